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


def _fake_sfm(monkeypatch, gt_frames, S: np.ndarray, n_points: int = 300):
    """run_sfm replaced by the true cameras and a few hundred points in an SfM-like frame (similarity S):
    the points only where the objects are (near the scene centre), as SfM's features sit on their textured
    edges while the plain table gives none. Returns the points' true (metric) positions."""
    import splattwin.poses.sfm as sfm_mod
    from splattwin.poses.sfm import SfmResult, image_layout

    ds_depth = load_dataset(gt_frames)
    frames = [f for f in ds_depth.frames if f.depth_path is not None]
    pts = np.concatenate([backproject_depth(load_depth(f.depth_path, ds_depth.depth_scale,
                                                       size=(f.camera.width, f.camera.height)),
                                            f.camera, stride=3)[0] for f in frames])
    centre = np.median(pts, axis=0)
    near = pts[np.linalg.norm(pts[:, :2] - centre[:2], axis=1) < 0.08]
    rng = np.random.default_rng(0)
    true_pts = near[rng.choice(len(near), n_points, replace=False)]
    # a table plane for the table frame: SfM finds some points on the table too
    table = pts[np.abs(pts[:, 2] - np.median(pts[:, 2])) < 0.002]
    true_pts = np.concatenate([true_pts, table[rng.choice(len(table), 60, replace=False)]])

    def run_sfm(paths, work, sopts, progress=True, masks=None):
        _, rel = image_layout(list(paths))
        by_path = {Path(f.image_path).name: f.camera for f in ds_depth.frames}
        cams = {r: transform_camera(S, by_path[Path(p).name]) for r, p in zip(rel, paths)}
        n = len(true_pts)
        return SfmResult(cameras=cams, unregistered=[], points_xyz=true_pts @ S[:3, :3].T + S[:3, 3],
                         points_rgb=np.full((n, 3), 200, np.uint8), points_error=np.full(n, 0.3),
                         points_track_len=np.full(n, 3), mean_reproj_error=0.3)

    monkeypatch.setattr(sfm_mod, "run_sfm", run_sfm)
    return true_pts, pts


def test_sfm_on_rgbd_seeds_the_splats_from_the_depth(scene_small: Path, tmp_path: Path, monkeypatch):
    """SfM scaled by the depth images: the initial cloud (points3D.ply, what training starts from) is the SfM
    points joined by the back-projected depth, not the SfM points alone (314 points seeded the embedded scene
    as a BOP capture without poses: the table stopped at the objects' edges and the yellow cube vanished)."""
    from tests.poses.conftest import stripped

    true_pts, depth_pts = _fake_sfm(monkeypatch, scene_small, _sfm_frame(0.37))
    ds = stripped(load_dataset(scene_small), depth=True)
    res = estimate_poses(ds, PoseOptions(progress=False, work_dir=tmp_path / "sfm"))
    assert res.frame.scaled and res.frame.source == "table_plane+depth"
    assert res.depth_xyz is not None and len(res.depth_xyz) > 1000
    n_sfm = len(true_pts)
    assert len(res.points_xyz) > 5 * n_sfm                            # the depth joined the SfM points
    assert res.stats["initial_points"]["sparse"] == n_sfm
    # every depth point has an initial point within 2 voxels (the whole table, not just the objects)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(res.points_xyz).query(res.depth_xyz)
    assert np.quantile(d, 0.99) < 0.004
    # one frame: the SfM points (first, kept) lie on the depth cloud, in metres
    d_sfm, _ = cKDTree(res.depth_xyz).query(res.points_xyz[:n_sfm])
    assert np.median(d_sfm) < 0.01
    # unscaled (no depth scale): the depth is not in SfM units, so the SfM points alone
    off = estimate_poses(stripped(load_dataset(scene_small), depth=True),
                         PoseOptions(progress=False, scale_from_depth=False, work_dir=tmp_path / "sfm2"))
    assert not off.frame.scaled and len(off.points_xyz) == n_sfm


def test_depth_that_disagrees_with_the_points_is_not_merged(scene_small: Path, tmp_path: Path, monkeypatch):
    """A frame scaled by something else (here a known length): the depth joins the SfM points when it
    agrees with them, and stays out when it does not (the length given x2: a second, misplaced copy)."""
    from splattwin.poses.table import KnownLength
    from tests.poses.conftest import stripped

    true_pts, _ = _fake_sfm(monkeypatch, scene_small, _sfm_frame(0.37))
    gt = load_dataset(scene_small)
    a, b = gt.frames[0], gt.frames[1]
    L = float(np.linalg.norm(a.camera.center - b.camera.center))
    for factor, merged in ((1.0, True), (2.0, False)):
        kl = KnownLength.parse(f"baseline@{Path(a.image_path).stem},{Path(b.image_path).stem}={L * factor}")
        res = estimate_poses(stripped(gt, depth=True), PoseOptions(progress=False, known_length=kl,
                                                                   work_dir=tmp_path / f"sfm{factor}"))
        assert res.frame.scaled and res.frame.source == "table_plane+known_length"
        assert res.stats["depth_fits_points"]["ok"] is merged
        assert (len(res.points_xyz) > 5 * len(true_pts)) is merged
