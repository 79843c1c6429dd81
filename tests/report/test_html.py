import os
from pathlib import Path

import numpy as np
from PIL import Image

from splattwin.pictures import side_by_side
from splattwin.report.html import Report, picture_bytes, png_bytes
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
    rng = np.random.default_rng(1)
    green = np.clip(np.array([0.1, 0.8, 0.15]) + rng.normal(0, 0.03, (60, 80, 3)), 0, 1)   # a noisy "photo"
    sec.image(green, caption="green photo", photo=True)
    return rep.save(tmp_path / "report" / "index.html")


def test_report_is_self_contained(tmp_path):
    import re

    rep = Report("test report")
    sec = rep.section("pictures")
    sec.image(np.repeat(np.repeat(np.eye(2, dtype=np.float32), 30, 0), 40, 1), caption="flat")
    sec.image(_photo(), caption="photo", photo=True)
    html = _report(tmp_path).read_text() + rep.to_html()
    assert "data:image/png;base64," in html and "data:image/jpeg;base64," in html   # the flat ones, the photo
    assert "http://" not in html and "https://" not in html  # opens offline
    assert all(src.startswith("data:") for src in re.findall(r'src="([^"]*)"', html))
    assert "30.12" in html and "<th>PSNR</th>" in html


def _photo(h: int = 120, w: int = 160) -> np.ndarray:
    """A photo-like HxWx3 uint8 picture: smooth shading, fine texture and sensor noise (thousands of
    colours), with a 1-px red line across it (an outline drawn over a render)."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.5 + 0.3 * np.sin(6 * x + 2 * y), 0.45 + 0.25 * np.cos(5 * y), 0.4 + 0.2 * x], -1)
    texture = 0.05 * np.sin(40 * x)[..., None] * np.cos(30 * y)[..., None]
    img = np.clip(base + texture + rng.normal(0, 0.01, base.shape), 0, 1)
    img[h // 2] = (1.0, 0.0, 0.0)
    return (img * 255 + 0.5).astype(np.uint8)


def _decode(data: bytes) -> np.ndarray:
    import io

    return np.asarray(Image.open(io.BytesIO(data)))


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


def test_pictures_are_embedded_as_jpeg_or_png_by_their_kind(tmp_path):
    """Every picture was a PNG (a 15-view 320x240 twin's report: 5.7 MB): photographic ones are JPEG now,
    flat-colour ones, plots and pictures with alpha stay PNG."""
    from splattwin.io import write_image

    photo = _photo()
    flat = np.zeros((120, 160, 3), np.uint8)
    flat[20:80, 30:90] = (200, 40, 40)      # a label map / mask: a few flat colours, 1-px edges
    flat[:, 100] = (0, 0, 255)
    rgba = np.dstack([photo, np.full(photo.shape[:2], 128, np.uint8)])
    assert picture_bytes(photo, photo=True)[0] == "image/jpeg"
    assert picture_bytes(photo)[0] == "image/jpeg"                  # decided from the content
    assert picture_bytes(photo, photo=False)[0] == "image/png"      # the caller knows: a plot
    assert picture_bytes(flat)[0] == "image/png"
    assert picture_bytes(rgba, photo=True)[0] == "image/png"        # JPEG has no alpha
    assert picture_bytes(photo.astype(np.float32) / 255)[0] == "image/jpeg"   # float in [0, 1]
    # files: a photo PNG on disk, a flat PNG (its own bytes embedded) and an RGBA one
    p_photo = write_image(tmp_path / "render.png", photo)
    p_flat = write_image(tmp_path / "labels.png", flat)
    p_rgba = write_image(tmp_path / "rgba.png", rgba)
    assert picture_bytes(p_photo)[0] == "image/jpeg"
    assert picture_bytes(p_flat) == ("image/png", p_flat.read_bytes())
    assert picture_bytes(p_rgba, photo=True) == ("image/png", p_rgba.read_bytes())
    assert picture_bytes(p_photo, photo=False) == ("image/png", p_photo.read_bytes())


def test_a_jpeg_picture_is_close_to_its_source_and_a_flat_png_is_exact(tmp_path):
    from PIL import JpegImagePlugin

    photo = _photo()
    mime, data = picture_bytes(photo, photo=True)
    assert mime == "image/jpeg" and len(data) < 0.5 * len(png_bytes(photo))
    back = _decode(data)
    assert back.shape == photo.shape and _psnr(back, photo) > 35
    with Image.open(__import__("io").BytesIO(data)) as im:
        assert JpegImagePlugin.get_sampling(im) == 0     # 4:4:4: the colour is not halved in resolution
    line = back[photo.shape[0] // 2].astype(int)         # the 1-px red line keeps its colour
    assert line[:, 0].min() > 200 and line[:, 1].max() < 60 and line[:, 2].max() < 60
    flat = np.zeros((50, 70, 3), np.uint8)
    flat[10:30, 5:40] = (10, 200, 30)
    flat[:, 50] = (255, 0, 255)
    mime, data = picture_bytes(flat)
    assert mime == "image/png" and np.array_equal(_decode(data), flat)


def test_report_renders_in_chromium(tmp_path):
    path = _report(tmp_path)
    png = screenshot(path.as_uri(), tmp_path / "shot.png", width=900, height=700)
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    # the page is not blank: the dark header and the red embedded image are drawn
    assert (shot.sum(axis=2) < 150).mean() > 0.01
    red = (shot[..., 0] > 200) & (shot[..., 1] < 60) & (shot[..., 2] < 60)
    assert red.sum() > 500
    green = (shot[..., 1] > 150) & (shot[..., 0] < 80) & (shot[..., 2] < 90)   # the JPEG one is drawn too
    assert "data:image/jpeg;base64," in path.read_text() and green.sum() > 500


def test_side_by_side_and_heatmap():
    a = np.zeros((10, 12, 3), np.float32)
    b = np.ones((10, 12, 3), np.float32)
    sbs = side_by_side([a, b, error_heatmap(a, b)], gap=2)
    assert sbs.shape == (10, 12 * 3 + 4, 3)
    assert error_heatmap(a, a).max() == 0 and error_heatmap(a, b)[..., 0].min() == 255
    assert png_bytes(a)[:4] == b"\x89PNG"
    tall = side_by_side([a, np.zeros((14, 5, 3), np.float32)], gap=1)
    assert tall.shape == (14, 18, 3) and tall[10:, :12].min() == 1.0  # short image padded white


def test_screenshot_waits_for_a_page_that_draws_late(tmp_path):
    # The page stays blank white until its script draws, 1.5 s after load: the first picture (0.3 s after
    # load) is blank, the later ones see the drawing.
    page = tmp_path / "late.html"
    page.write_text("<html><body style='margin:0;background:#fff'><script>setTimeout(function(){"
                    "var d=document.createElement('div');d.style.cssText='width:300px;height:200px;background:#f00';"
                    "document.body.appendChild(d);},1500);</script></body></html>")
    png = screenshot(page.as_uri(), tmp_path / "late.png", width=400, height=300, settle_ms=300)
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert shot.shape == (300, 400, 3)
    red = (shot[..., 0] > 200) & (shot[..., 1] < 60) & (shot[..., 2] < 60)
    assert red.sum() == 300 * 200


def test_screenshot_waits_until_the_caller_calls_the_picture_ready(tmp_path):
    """`ready` decides: a page that turns its square from red to green after 2 s is pictured green when the
    caller waits for green, and the last (red) picture comes back when it never gets ready in time (a page
    that stays red: with the turning page and a 1 s budget, Chromium's start-up alone, 0.3-0.8 s with the
    machine loaded, could use up the budget and leave no picture at all)."""
    square = ("<html><body style='margin:0;background:#fff'><div id=d style='width:100px;height:100px;"
              "background:#f00'></div>{}</body></html>")
    page, stays_red = tmp_path / "turns.html", tmp_path / "red.html"
    page.write_text(square.format("<script>setTimeout(function(){document.getElementById('d')"
                                  ".style.background='#0f0';},2000);</script>"))
    stays_red.write_text(square.format(""))

    def green(rgb):
        return bool(rgb[50, 50, 1] > 200 and rgb[50, 50, 0] < 60)

    png = screenshot(page.as_uri(), tmp_path / "green.png", width=200, height=200, settle_ms=0, ready=green)
    assert green(np.asarray(Image.open(png).convert("RGB")))
    png = screenshot(stays_red.as_uri(), tmp_path / "red.png", width=200, height=200, settle_ms=0, ready=green,
                     timeout_s=8.0)
    shot = np.asarray(Image.open(png).convert("RGB"))
    assert tuple(shot[50, 50]) == (255, 0, 0)


def _fake_chromium(tmp_path, monkeypatch, behaviour: str):
    """A stand-in for Chromium that logs its pid and then either hangs without opening its DevTools port
    ("hang") or exits with code 3 at once ("exit"), printing a line to stderr first."""
    import sys

    import splattwin.report.screenshot as shot

    log = tmp_path / "pids.txt"
    script = tmp_path / "fake-chromium"
    script.write_text(
        f"#!{sys.executable}\n"
        "import os, sys, time\n"
        f"open({str(log)!r}, 'a').write(str(os.getpid()) + '\\n')\n"
        "print('fake chromium: GPU process isn\\'t usable', file=sys.stderr, flush=True)\n"
        + ("time.sleep(1000)\n" if behaviour == "hang" else "sys.exit(3)\n"))
    script.chmod(0o755)
    monkeypatch.setattr(shot, "find_chromium", lambda: str(script))
    return log


def test_screenshot_kills_a_chromium_that_hangs_and_says_what_it_printed(tmp_path, monkeypatch):
    import time

    import pytest

    log = _fake_chromium(tmp_path, monkeypatch, "hang")
    out = tmp_path / "shots" / "view.png"
    out.parent.mkdir()
    out.write_bytes(b"old")
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="no screenshot.*did not open its DevTools port.*GPU process isn't usable"):
        screenshot("file:///nothing.html", out, timeout_s=3.0)
    assert time.monotonic() - t0 < 10
    pids = [int(p) for p in log.read_text().split()]
    assert len(pids) == 1
    with pytest.raises(ProcessLookupError):   # killed, not left running
        os.kill(pids[0], 0)
    assert list(out.parent.iterdir()) == []   # the old picture is gone, nothing half-written


def test_screenshot_starts_chromium_again_when_it_dies(tmp_path, monkeypatch):
    import pytest

    import splattwin.report.screenshot as shot

    log = _fake_chromium(tmp_path, monkeypatch, "exit")
    with pytest.raises(RuntimeError, match="exited with code 3 at start-up"):
        screenshot("file:///nothing.html", tmp_path / "view.png", timeout_s=60.0)
    assert len(log.read_text().split()) == shot.MAX_TRIES


def test_screenshot_is_written_atomically(tmp_path, monkeypatch):
    """The picture goes to a temporary file beside the target, renamed onto it: no temporary file is left,
    and a failed picture leaves neither a new nor the old file."""
    import pytest

    import splattwin.report.screenshot as shot

    buf = __import__("io").BytesIO()
    Image.new("RGB", (8, 6), (255, 0, 0)).save(buf, format="PNG")
    monkeypatch.setattr(shot, "_capture", lambda *a: buf.getvalue())
    out = tmp_path / "shots" / "view.png"
    out.parent.mkdir()
    out.write_bytes(b"old")
    assert screenshot("file:///nothing.html", out) == out.resolve()
    with Image.open(out) as im:
        assert im.size == (8, 6)
    assert sorted(p.name for p in out.parent.iterdir()) == ["view.png"]

    def fail(*a):
        raise RuntimeError("chromium produced no screenshot")

    monkeypatch.setattr(shot, "_capture", fail)
    with pytest.raises(RuntimeError):
        screenshot("file:///nothing.html", out)
    assert list(out.parent.iterdir()) == []