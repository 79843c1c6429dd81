from pathlib import Path

import numpy as np
from PIL import Image

from splattwin.pictures import side_by_side
from splattwin.report.html import Report, png_bytes
from splattwin.splat.metrics import error_heatmap
from splattwin.report.screenshot import screenshot


def _report(tmp_path):
    rep = Report("test report", "subtitle")
    sec = rep.section("Reconstruction")
    sec.kpis({"PSNR (dB)": 31.2, "success": True})
    sec.table(["view", "PSNR"], [["v0", 30.1234567], ["v1", 29.0]])
    img = np.zeros((60, 80, 3), np.float32)
    img[:, :40, 0] = 1.0  # left half red
    sec.image(img, caption="red | black")
    return rep.save(tmp_path / "report" / "index.html")


def test_report_is_self_contained(tmp_path):
    html = _report(tmp_path).read_text()
    assert "data:image/png;base64," in html
    assert "http://" not in html and "https://" not in html  # opens offline
    assert "30.12" in html and "<th>PSNR</th>" in html


def test_report_renders_in_chromium(tmp_path):
    path = _report(tmp_path)
    png = screenshot(path.as_uri(), tmp_path / "shot.png", width=900, height=700, budget_ms=2000)
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    # the page is not blank: the dark header and the red embedded image are drawn
    assert (shot.sum(axis=2) < 150).mean() > 0.01
    red = (shot[..., 0] > 200) & (shot[..., 1] < 60) & (shot[..., 2] < 60)
    assert red.sum() > 500


def test_side_by_side_and_heatmap():
    a = np.zeros((10, 12, 3), np.float32)
    b = np.ones((10, 12, 3), np.float32)
    sbs = side_by_side([a, b, error_heatmap(a, b)], gap=2)
    assert sbs.shape == (10, 12 * 3 + 4, 3)
    assert error_heatmap(a, a).max() == 0 and error_heatmap(a, b)[..., 0].min() == 255
    assert png_bytes(a)[:4] == b"\x89PNG"
    tall = side_by_side([a, np.zeros((14, 5, 3), np.float32)], gap=1)
    assert tall.shape == (14, 18, 3) and tall[10:, :12].min() == 1.0  # short image padded white


def test_screenshot_waits_longer_for_a_page_that_draws_late(tmp_path):
    # The page stays blank white until its script draws, 1.5 s of (virtual) time after load: a 1 s
    # budget catches it blank, the retry with a longer budget sees the drawing.
    page = tmp_path / "late.html"
    page.write_text("<html><body style='margin:0;background:#fff'><script>setTimeout(function(){"
                    "var d=document.createElement('div');d.style.cssText='width:300px;height:200px;background:#f00';"
                    "document.body.appendChild(d);},1500);</script></body></html>")
    png = screenshot(page.as_uri(), tmp_path / "late.png", width=400, height=300, budget_ms=1000)
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    red = (shot[..., 0] > 200) & (shot[..., 1] < 60) & (shot[..., 2] < 60)
    assert red.sum() > 10000


def _fake_chromium(tmp_path, monkeypatch, picture: bool):
    """A stand-in for Chromium that records where it was told to write and, if `picture`, writes a
    two-colour PNG there (the real one writes its --screenshot file itself)."""
    import sys

    import splattwin.report.screenshot as shot

    log = tmp_path / "told.txt"
    script = tmp_path / "fake-chromium"
    script.write_text(
        f"#!{sys.executable}\n"
        "import sys\n"
        "from PIL import Image\n"
        "path = next(a.split('=', 1)[1] for a in sys.argv if a.startswith('--screenshot='))\n"
        f"open({str(log)!r}, 'a').write(path + '\\n')\n"
        + ("im = Image.new('RGB', (8, 8), (255, 0, 0)); im.putpixel((0, 0), (0, 0, 255)); im.save(path)\n"
           if picture else ""))
    script.chmod(0o755)
    monkeypatch.setattr(shot, "find_chromium", lambda: str(script))
    return log


def test_screenshot_is_written_atomically(tmp_path, monkeypatch):
    """Chromium writes into a temporary file beside the target, renamed onto it when it is done: a killed
    run never leaves a half-written PNG under the artifact's name, and no temporary file is left."""
    log = _fake_chromium(tmp_path, monkeypatch, picture=True)
    out = tmp_path / "shots" / "view.png"
    out.parent.mkdir()
    out.write_bytes(b"old")
    assert screenshot("file:///nothing.html", out, budget_ms=1000) == out.resolve()
    told = [Path(p) for p in log.read_text().split()]
    assert len(told) == 1 and told[0] != out.resolve() and told[0].parent == out.resolve().parent
    assert told[0].suffix == ".png"   # Chromium picks the format by the extension
    with Image.open(out) as im:
        assert im.size == (8, 8)
    assert sorted(p.name for p in out.parent.iterdir()) == ["view.png"]


def test_screenshot_without_a_picture_leaves_nothing(tmp_path, monkeypatch):
    import pytest

    _fake_chromium(tmp_path, monkeypatch, picture=False)
    out = tmp_path / "shots" / "view.png"
    with pytest.raises(RuntimeError, match="no screenshot"):
        screenshot("file:///nothing.html", out, budget_ms=1000)
    assert list(out.parent.iterdir()) == []
