from __future__ import annotations

from splattwin.pipeline.cli import _print_headline
from splattwin.pipeline.runner import Context


def test_headline_names_the_twin_only_when_there_is_one(tmp_path, capsys, monkeypatch):
    """`build --until splats` stops before the twin stage: the last line names the folder, not a twin.json."""
    monkeypatch.setenv("COLUMNS", "1000")   # rich: no wrapping inside the long tmp paths
    ctx = Context(out=tmp_path, options={}, timings={"poses": 8.0, "splats": 25.0},
                  results={"splats": {"gaussians": 7080, "split": "heldout", "psnr": 14.3, "ssim": 0.49}})
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert "7080 Gaussians, heldout PSNR 14.30 dB" in out and "total 33 s" in out
    assert "twin.json" in out and "no twin.json" in out and "twin: " not in out
    (tmp_path / "twin.json").write_text("{}")
    _print_headline(ctx)
    out = capsys.readouterr().out
    assert f"twin: {tmp_path / 'twin.json'}" in out and "no twin.json" not in out
