"""Depth units: 16-bit PNG in mm -> metres exactly (nearest float32), explicit scales per format."""

from __future__ import annotations

import json
from fractions import Fraction

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import load_dataset, load_depth, nerfstudio
from splattwin.errors import InputError


def _nearest_f32(q: Fraction) -> np.float32:
    """The float32 nearest to the rational q (ties away are irrelevant here), computed exactly."""
    f = np.float32(float(q))
    cands = [np.nextafter(f, np.float32(-np.inf)), f, np.nextafter(f, np.float32(np.inf))]
    return min(cands, key=lambda c: abs(Fraction(float(c)) - q))


@pytest.mark.parametrize("units_per_m", [1000, 5000, 10000])
def test_integer_depth_is_the_nearest_float32_of_raw_over_units(tmp_path, units_per_m):
    raw = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    io.write_image(tmp_path / "d.png", raw)
    d = load_depth(tmp_path / "d.png", 1.0 / units_per_m)
    assert d.dtype == np.float32 and d.shape == raw.shape
    sample = np.r_[0:40, 999:1003, 4999:5003, 65500:65536, np.random.default_rng(0).integers(0, 65536, 300)]
    for r in sample:
        assert d.reshape(-1)[r] == _nearest_f32(Fraction(int(r), units_per_m)), r
    assert d.reshape(-1)[1234] == np.float32(1234 / units_per_m)


def test_defaults_by_file_type_and_explicit_scale(tmp_path):
    io.write_image(tmp_path / "d.png", np.full((4, 5), 1500, np.uint16))
    io.write_npy(tmp_path / "d.npy", np.full((4, 5), 1.5, np.float32))
    assert np.all(load_depth(tmp_path / "d.png") == np.float32(1.5))      # PNG: millimetres by default
    assert np.all(load_depth(tmp_path / "d.npy") == np.float32(1.5))      # float: metres by default
    assert np.all(load_depth(tmp_path / "d.npy", 0.1) == np.float32(0.15))  # an explicit scale applies to all
    # a scale of exactly 1.0 is honoured (it no longer means "guess millimetres")
    assert np.all(load_depth(tmp_path / "d.png", 1.0) == np.float32(1500.0))
    for bad in (0.0, -1e-3, float("nan")):
        with pytest.raises(InputError, match="depth scale must be a positive"):
            load_depth(tmp_path / "d.png", bad)


def test_nerfstudio_depth_unit_scale_factor_round_trip(tmp_path, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    assert "depth_unit_scale_factor" not in json.loads(out.read_text())
    assert load_dataset(out).depth_scale is None          # absent: the file type's default
    ds.depth_scale = 2e-4
    nerfstudio.write(ds, out)
    assert json.loads(out.read_text())["depth_unit_scale_factor"] == 2e-4
    assert load_dataset(out).depth_scale == 2e-4
    meta = json.loads(out.read_text())
    meta["depth_unit_scale_factor"] = "mm"
    out.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="depth_unit_scale_factor must be a number") as e:
        load_dataset(out)
    assert e.value.path == out


def test_nerfstudio_write_states_the_depth_unit(tmp_path, make_dataset):
    """nerfstudio multiplies every depth file (.npy too) by depth_unit_scale_factor, 0.001 when absent: our
    metre .npy was read 1000x too near. The factor is now always written with depth."""
    ds = make_dataset(tmp_path, with_points=False, with_depth=True)   # float .npy in metres
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    assert json.loads(out.read_text())["depth_unit_scale_factor"] == 1.0
    back = load_dataset(out)
    assert back.depth_scale == 1.0
    f = back.frames[0]
    assert np.array_equal(load_depth(f.depth_path, back.depth_scale), np.load(ds.frames[0].depth_path))
    for fr in ds.frames:                                               # 16-bit PNG in millimetres
        fr.depth_path = fr.depth_path.with_suffix(".png")
        io.write_image(fr.depth_path, np.full((fr.camera.height, fr.camera.width), 750, np.uint16))
    nerfstudio.write(ds, out)
    assert json.loads(out.read_text())["depth_unit_scale_factor"] == 0.001
    assert np.all(load_depth(ds.frames[0].depth_path, load_dataset(out).depth_scale) == np.float32(0.75))


def test_nerfstudio_read_warns_of_millimetre_npy_without_factor(tmp_path, make_dataset, caplog):
    ds = make_dataset(tmp_path, with_points=False, with_depth=True)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    meta = json.loads(out.read_text())
    del meta["depth_unit_scale_factor"]
    out.write_text(json.dumps(meta))
    with caplog.at_level("WARNING"):
        assert load_dataset(out).depth_scale is None                 # metres .npy as before: no warning
    assert "millimetres" not in caplog.text
    for fr in ds.frames:
        io.write_npy(fr.depth_path, np.load(fr.depth_path) * 1000)     # now in mm
    with caplog.at_level("WARNING"):
        assert load_dataset(out).depth_scale is None
    assert "millimetres?" in caplog.text and "img_000.npy" in caplog.text and "depth_unit_scale_factor" in caplog.text


def test_nerfstudio_lower_resolution_depth_is_resized_nearest(tmp_path, make_dataset):
    """Phone captures (Polycam, Record3D) ship 256x192 depth with 1024x768 photos; nerfstudio resizes it
    (nearest). It was refused. A smaller map of another aspect ratio is still refused (not registered)."""
    ds = make_dataset(tmp_path, with_points=False, with_depth=True)   # 64x48 images
    low = np.arange(32 * 24, dtype=np.uint16).reshape(24, 32) + 500   # 32x24 mm, every value distinct
    for fr in ds.frames:
        fr.depth_path = fr.depth_path.with_suffix(".png")
        io.write_image(fr.depth_path, low)
    out = nerfstudio.write(ds, tmp_path / "transforms.json")
    back = load_dataset(out)                                           # validate accepts it
    f = back.frames[0]
    d = load_depth(f.depth_path, back.depth_scale, size=(f.camera.width, f.camera.height))
    assert d.shape == (48, 64)
    np.testing.assert_array_equal(d, np.repeat(np.repeat(low, 2, 0), 2, 1).astype(np.float32) / 1000)  # no blend
    for fr in ds.frames:
        io.write_image(fr.depth_path, np.full((20, 32), 500, np.uint16))   # 32x20: another aspect ratio
    with pytest.raises(InputError, match="depth map is 32x20 but its camera is 64x48: depth must be registered") as e:
        load_dataset(out)
    assert e.value.path == ds.frames[0].depth_path
