"""The D435-like depth sensor model (`splattwin.scene.depth_noise`) and its use by the robot capture:
noise statistics against the model, analytic occlusion shadows and fattening, holes written as 0 and
read back as holes, seeded determinism, the perfect-depth switch."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splattwin.capture import load_dataset, load_depth
from splattwin.cli import main
from splattwin.errors import InputError
from splattwin.scene import SceneOptions
from splattwin.scene.depth_noise import REF_WIDTH, depth_edges, occlusion_shadow, sensor_depth, view_rng
from splattwin.scene.options import DepthNoise
from splattwin.scene.robot_capture import RobotCaptureOptions, depth_mm, sweep_cameras, write_robot_capture

NOISE_ONLY = DepthNoise(fattening_px=0.0, baseline=0.0, edge_hole_prob=0.0, blob_fraction=0.0)


def _two_planes(w: int = 1280, h: int = 400) -> np.ndarray:
    """Left half at 0.5 m, right half at 1.0 m."""
    d = np.full((h, w), 0.5)
    d[:, w // 2:] = 1.0
    return d


@pytest.mark.parametrize("corr", [0.0, 1.0])
def test_axial_noise_grows_with_depth_squared(corr):
    d = _two_planes()
    noise = replace(NOISE_ONLY, rms_1m=0.01, noise_corr_px=corr)
    s = sensor_depth(d, 500.0, noise, view_rng(0, 0)).astype(np.float64)
    assert np.isfinite(s).all()                                  # no holes asked for: none made
    inner = np.zeros_like(d, bool)
    inner[:, 8:-8] = True
    inner[:, d.shape[1] // 2 - 8: d.shape[1] // 2 + 8] = False   # away from the step
    tol = 0.03 if corr == 0 else 0.08                            # correlated: fewer independent samples
    for z in (0.5, 1.0):
        e = (s - d)[inner & (d == z)]
        assert np.std(e) == pytest.approx(0.01 * z ** 2, rel=tol)
        assert abs(np.mean(e)) < 4 * 0.01 * z ** 2 / np.sqrt(e.size / (1 + 40 * corr ** 2))
    if corr:   # neighbours correlate (a matching window), white noise does not
        e = (s - d)[:, 8:600]
        r = np.corrcoef(e[:, :-1].ravel(), e[:, 1:].ravel())[0, 1]
        assert r > 0.5
    else:
        e = (s - d)[:, 8:600]
        assert abs(np.corrcoef(e[:, :-1].ravel(), e[:, 1:].ravel())[0, 1]) < 0.02


def test_occlusion_shadow_is_the_disparity_step_left_of_a_near_object():
    # plane at 1 m, a near bar at 0.5 m in columns 40..59: disparities fx B / z = 5 px (plane), 10 px (bar)
    d = np.full((10, 100), 1.0)
    d[:, 40:60] = 0.5
    sh = occlusion_shadow(d, fx=100.0, baseline=0.05)
    assert sh.any(axis=0).nonzero()[0].tolist() == [35, 36, 37, 38, 39]    # 10 - 5 = 5 px, on its left
    assert sh[:, 35:40].all()
    assert not occlusion_shadow(d, 100.0, 0.0).any()
    assert not occlusion_shadow(np.full((10, 100), 1.0), 100.0, 0.05).any()   # a plane shadows nothing


def test_fattening_spreads_the_near_surface_across_the_edge():
    d = np.full((20, REF_WIDTH), 1.0)
    d[:, 300:] = 0.5                     # near surface on the right
    noise = replace(NOISE_ONLY, rms_1m=0.0, fattening_px=3.0)
    s = sensor_depth(d, 500.0, noise, view_rng(0, 0))
    row = s[10]
    assert np.all(row[297:] == 0.5) and np.all(row[:296] == 1.0)   # 3 px of the far side read near
    assert depth_edges(d, 0.02)[10].nonzero()[0].tolist() == [299, 300]


def test_holes_concentrate_at_edges_and_blobs_have_their_fraction():
    d = np.full((240, 320), 0.8)
    d[80:160, 100:220] = 0.6   # a box top
    d[:10] = np.inf            # no return
    noise = DepthNoise(rms_1m=0.0, baseline=0.0, fattening_px=0.0)
    s = sensor_depth(d, 307.0, noise, view_rng(3, 1))
    lost = ~np.isfinite(s)
    assert lost[:10].all()                                          # no return stays a hole
    edges = depth_edges(d, noise.edge_jump)
    from scipy import ndimage
    dist = ndimage.distance_transform_edt(~edges)
    band = dist <= noise.edge_hole_px * 320 / REF_WIDTH
    interior = (dist > 10) & np.isfinite(d)
    assert 0.3 < lost[band & np.isfinite(d)].mean() < 0.8          # ~edge_hole_prob of the edge band
    assert lost[interior].mean() == pytest.approx(noise.blob_fraction, abs=0.006)   # blobs only
    # several separate blobs, not one
    n_blobs = ndimage.label(lost & interior)[1]
    assert n_blobs >= 3


def test_perfect_and_validation():
    d = _two_planes(64, 32)
    d[0, 0] = np.inf
    s = sensor_depth(d, 50.0, DepthNoise.perfect(), view_rng(0, 0))
    np.testing.assert_array_equal(s, d.astype(np.float32))
    for bad in ({"rms_1m": -0.01}, {"edge_hole_prob": 1.5}, {"blob_fraction": 0.9}, {"baseline": float("nan")}):
        with pytest.raises(InputError):
            RobotCaptureOptions(depth_noise=replace(DepthNoise(), **bad)).validate()


W, H = 96, 72
OPTS = SceneOptions(seed=0, width=W, height=H, supersample=1)


def _truth_depth(n: int, i: int, seed: int = 0) -> tuple[np.ndarray, float]:
    from splattwin.scene.generator import build_scene, look_target

    objects, _, _, renderer = build_scene(replace(OPTS, seed=seed))
    cam = sweep_cameras(RobotCaptureOptions(views=n, width=W, height=H), look_target(objects), seed)[i]
    return renderer.render(cam, 1)["depth"], float(cam.K[0, 0])


@pytest.mark.parametrize("fmt", ["bop", "tum"])
def test_capture_holes_are_zero_and_loaders_read_them_as_holes(tmp_path: Path, fmt: str):
    from splattwin.splat.trainer import load_views

    out = write_robot_capture(tmp_path / fmt, OPTS, RobotCaptureOptions(views=4, width=W, height=H, format=fmt),
                              progress=False)
    ds = load_dataset(out)
    truth, fx = _truth_depth(4, 2)
    f = ds.frames[2]
    raw = np.asarray(Image.open(f.depth_path))
    assert raw.dtype == np.uint16
    sensed = sensor_depth(truth, fx, DepthNoise(), view_rng(0, 2))
    np.testing.assert_array_equal(raw == 0, ~np.isfinite(sensed))   # every lost reading is a 0
    holes = (raw == 0) & np.isfinite(truth)
    assert holes.sum() > 0.01 * raw.size                           # the sensor lost readings the truth has
    ok = raw > 0
    err = load_depth(f.depth_path, ds.depth_scale)[ok] - truth[ok]
    assert 0.0005 < np.median(np.abs(err)) < 0.01                  # noisy (mm scale), not perfect, not wild
    views = load_views(ds.frames, 1, depth=True, depth_scale=ds.depth_scale)
    dv = views[2].depth.numpy()
    np.testing.assert_array_equal(np.isinf(dv), raw == 0)           # training sees holes as unknown (inf)


def test_capture_is_seeded_and_perfect_depth_switch(tmp_path: Path):
    cap = RobotCaptureOptions(views=3, width=W, height=H)
    a = write_robot_capture(tmp_path / "a", OPTS, cap, progress=False)
    b = write_robot_capture(tmp_path / "b", OPTS, cap, progress=False)
    c = write_robot_capture(tmp_path / "c", replace(OPTS, seed=1), cap, progress=False)
    p = write_robot_capture(tmp_path / "p", OPTS, replace(cap, depth_noise=DepthNoise.perfect()), progress=False)
    name = "depth/000001.png"
    da, db, dc, dp = (np.asarray(Image.open(x / name)) for x in (a, b, c, p))
    np.testing.assert_array_equal(da, db)                          # same seed: same readings
    assert (dc != da).mean() > 0.5                                 # another seed (and layout): other readings
    truth, _ = _truth_depth(3, 1)
    np.testing.assert_array_equal(dp, depth_mm(truth))             # perfect: the ray-cast depth in mm
    assert (da != dp).mean() > 0.3
    rec = json.loads((p / "scene.json").read_text())["robot_capture"]
    assert rec["depth_noise"]["enabled"] is False
    assert RobotCaptureOptions.from_dict(rec) == replace(cap, depth_noise=DepthNoise.perfect())
    rec_a = json.loads((a / "scene.json").read_text())["robot_capture"]
    assert RobotCaptureOptions.from_dict(rec_a) == cap                  # the record round-trips
    # the CLI switch, recorded in scene.json
    assert main(["scene", "generate", str(tmp_path / "cli"), "--robot-capture", "bop", "--width", "64", "--height",
                 "48", "--views", "3", "--supersample", "1", "--no-progress",
                 "--no-robot-capture.depth_noise.enabled"]) == 0
    assert json.loads((tmp_path / "cli" / "scene.json").read_text())["robot_capture"]["depth_noise"]["enabled"] is False
    assert main(["scene", "generate", str(tmp_path / "cli2"), "--robot-capture", "tum", "--width", "64", "--height",
                 "48", "--views", "3", "--supersample", "1", "--no-progress",
                 "--robot-capture.depth_noise.rms-1m", "0.004"]) == 0
    rec = json.loads((tmp_path / "cli2" / "scene.json").read_text())["robot_capture"]["depth_noise"]
    assert rec["enabled"] is True and rec["rms_1m"] == 0.004
