"""Metric scale of SfM from depth images (RGB-D captures without poses): the ratio fit, its refusals, and
an SfM run on a BOP scene without cam_R_w2c that comes out metric."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin import io
from splattwin.capture import load_dataset, load_depth
from splattwin.poses import PoseOptions, estimate_poses
from splattwin.poses.align import transform_camera
from splattwin.poses.depth import backproject_depth
from splattwin.poses.depth_scale import depth_ratios, scale_from_depth


def _views(scene: Path, n: int = 6):
    ds = load_dataset(scene)
    frames = [f for f in ds.frames if f.depth_path is not None][:n]
    cams = [f.camera for f in frames]
    depths = [load_depth(f.depth_path, ds.depth_scale, size=(c.width, c.height)) for f, c in zip(frames, cams)]
    return cams, depths


def _sfm_frame(s: float) -> np.ndarray:
    """A similarity like SfM's arbitrary frame: lengths x s, rotated and moved."""
    S = np.eye(4)
    S[:3, :3] = s * Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    S[:3, 3] = [0.3, -1.2, 2.0]
    return S


def _to(S: np.ndarray, cams, pts):
    return [transform_camera(S, c) for c in cams], pts @ S[:3, :3].T + S[:3, 3]


def test_scale_is_sensor_over_sfm_depth_and_robust_to_outliers(scene_small: Path):
    cams, depths = _views(scene_small)
    rng = np.random.default_rng(0)
    pts = np.concatenate([backproject_depth(d, c, stride=9)[0] for c, d in zip(cams, depths)])
    pts = pts[rng.choice(len(pts), 800, replace=False)]
    pts += rng.normal(0, 0.001, pts.shape)                               # SfM point noise (1 mm)
    pts[:80] += rng.normal(0, 0.2, (80, 3))                              # 10 % mismatched points
    s = 0.37
    sfm_cams, sfm_pts = _to(_sfm_frame(s), cams, pts)
    fit, note = scale_from_depth(sfm_cams, depths, sfm_pts)
    assert fit is not None, note
    assert fit.scale == pytest.approx(1 / s, rel=0.005)
    assert fit.readings > 300 and fit.views == len(cams) and fit.spread < 0.02
    assert 0.01 <= fit.uncertainty_rel < 0.02                           # the sensor-bias floor dominates
    # a single view's ratios: the same, read where the camera sees each point
    r = depth_ratios(sfm_cams[0], depths[0], sfm_pts)
    assert np.median(r) == pytest.approx(1 / s, rel=0.005)


def test_depth_that_disagrees_or_too_few_points_gives_no_scale(scene_small: Path):
    cams, depths = _views(scene_small)
    rng = np.random.default_rng(1)
    pts = np.concatenate([backproject_depth(d, c, stride=9)[0] for c, d in zip(cams, depths)])
    sfm_cams, sfm_pts = _to(_sfm_frame(2.0), cams, pts)
    # depth from another camera (not registered to the colour one): each map shifted by a third of the image
    shifted = [np.roll(d, d.shape[1] // 3, axis=1) * rng.uniform(0.6, 1.4) for d in depths]
    fit, note = scale_from_depth(sfm_cams, shifted, sfm_pts)
    assert fit is None and "disagree" in note
    fit, note = scale_from_depth(sfm_cams, depths, sfm_pts[:5])
    assert fit is None and "only" in note
    holes = [np.zeros_like(d) for d in depths]                          # a sensor that read nothing
    assert scale_from_depth(sfm_cams, holes, sfm_pts)[0] is None


def _bop_without_poses(scene: Path, out: Path) -> Path:
    """The embedded scene as a BOP scene with intrinsics and depth (mm) but no cam_R_w2c/cam_t_w2c: what an
    RGB-D sensor without robot poses gives."""
    ds = load_dataset(scene)
    cam_json = {}
    (out / "rgb").mkdir(parents=True)
    for i, f in enumerate(ds.frames):
        c = f.camera
        shutil.copy(f.image_path, out / "rgb" / f"{i:06d}.png")
        d = load_depth(f.depth_path, ds.depth_scale, size=(c.width, c.height))
        io.write_image(out / "depth" / f"{i:06d}.png", np.round(np.nan_to_num(d) * 1000.0).astype(np.uint16))
        K = c.K.copy()
        K[:2, 2] -= 0.5          # BOP's pixel centres are at integer coordinates, ours at +0.5
        cam_json[str(i)] = {"cam_K": K.reshape(-1).tolist(), "depth_scale": 1.0}
    io.write_json(out / "scene_camera.json", cam_json)
    return out


def test_sfm_on_rgbd_without_poses_is_metric(scene_default: Path, tmp_path: Path):
    src = _bop_without_poses(scene_default, tmp_path / "bop")
    ds = load_dataset(src)
    assert not ds.has_poses
    res = estimate_poses(ds, PoseOptions(progress=False, work_dir=tmp_path / "sfm"))
    assert res.frame.scaled and res.frame.source == "table_plane+depth"
    assert res.frame.units == "m" and res.frame.scale_uncertainty_rel < 0.02
    # lengths match the true metric cameras: every distance between two camera centres
    gt = {f"{i:06d}": f.camera.center for i, f in enumerate(load_dataset(scene_default).frames)}
    got = {f.image_path.stem: f.camera.center for f in res.frames}
    ks = sorted(set(gt) & set(got))
    assert len(ks) >= 15
    A, B = np.array([got[k] for k in ks]), np.array([gt[k] for k in ks])
    da, db = (np.linalg.norm(X[:, None] - X[None], axis=-1) for X in (A, B))
    far = db > 0.05
    assert np.median(da[far] / db[far]) == pytest.approx(1.0, abs=0.01)
    # the table frame: table top at z = 0, cameras at their true height above it
    assert np.mean(A[:, 2]) == pytest.approx(np.mean(B[:, 2]), rel=0.02)
    # without the option: the unscaled table frame, as before
    off = estimate_poses(load_dataset(src), PoseOptions(progress=False, scale_from_depth=False,
                                                        work_dir=tmp_path / "sfm"))
    assert not off.frame.scaled and off.frame.source == "unscaled"


def test_depth_in_wrong_units_gives_no_scale(scene_small: Path):
    """Depth read x10 (a wrong depth_scale) keeps the ratios' spread: only the scene's implied distance from
    the cameras shows it (it gave a twin 9.7 times too large, marked metric)."""
    cams, depths = _views(scene_small)
    pts = np.concatenate([backproject_depth(d, c, stride=9)[0] for c, d in zip(cams, depths)])
    sfm_cams, sfm_pts = _to(_sfm_frame(0.5), cams, pts)
    assert scale_from_depth(sfm_cams, depths, sfm_pts)[0] is not None
    for factor in (10.0, 1000.0, 0.01):
        fit, note = scale_from_depth(sfm_cams, [d * factor for d in depths], sfm_pts)
        assert fit is None and "units" in note
