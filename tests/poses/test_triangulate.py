"""Points from known poses (COLMAP's point triangulator) on the embedded scene: they lie on the true surfaces."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import Camera, Dataset, load_dataset, load_depth, look_at
from splattwin.poses.triangulate import colmap_camera, known_camera_groups, pairs_from_poses


def _depth_residuals(xyz: np.ndarray, frames) -> np.ndarray:
    """[N] distance (along the ray) of each point to the true surface, in the view and the 3x3 pixels where
    it is closest: a point on a surface lies on the depth map of the views that see it (others may see an
    occluder), and at an object's outline its pixel may hold the surface behind."""
    best = np.full(len(xyz), np.inf)
    for f in frames:
        d = load_depth(f.depth_path)
        h, w = d.shape
        uv, z = f.camera.project(xyz)
        ok = f.camera.in_image(uv) & (z > 0)
        u = uv[ok].astype(int)
        idx = np.flatnonzero(ok)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                r = np.abs(d[np.clip(u[:, 1] + dv, 0, h - 1), np.clip(u[:, 0] + du, 0, w - 1)] - z[ok])
                best[idx] = np.minimum(best[idx], np.where(np.isfinite(r), r, np.inf))
    return best


@pytest.fixture(scope="module")
def known_no_points(scene_default: Path) -> tuple[Dataset, Dataset]:
    """(ground truth, the same capture with its poses but without point cloud or depth)."""
    gt = load_dataset(scene_default)
    frames = [dataclasses.replace(f, depth_path=None) for f in gt.frames]
    return gt, Dataset(root=gt.root, frames=frames, has_poses=True, meta={"format": "nerfstudio", "path": str(gt.root)})


def test_triangulated_points_lie_on_the_true_surfaces(known_no_points, tmp_path: Path):
    from splattwin.poses.triangulate import triangulate_known_poses

    gt, bare = known_no_points
    train = bare.train()
    res = triangulate_known_poses([f.image_path for f in train], [f.camera for f in train], tmp_path / "w",
                                  progress=False)
    assert len(res.points_xyz) > 300 and res.points_rgb.shape == res.points_xyz.shape
    assert res.stats["mean_reproj_error"] < 1.0
    r = _depth_residuals(res.points_xyz, [f for f in gt.frames if f.split == "train"][:8])
    # 320x240 views ~0.7 m from a ~0.6 m table: a pixel is ~2-3 mm there
    assert np.median(r) < 0.001 and np.mean(r < 0.01) > 0.85
    # resume: the finished result is re-used, not recomputed
    again = triangulate_known_poses([f.image_path for f in train], [f.camera for f in train], tmp_path / "w",
                                    progress=False)
    np.testing.assert_array_equal(again.points_xyz, res.points_xyz)


def test_known_poses_without_points_get_triangulated_points(known_no_points, tmp_path: Path):
    from splattwin.poses import PoseOptions, estimate_poses

    gt, bare = known_no_points
    res = estimate_poses(bare, PoseOptions(method="known", work_dir=tmp_path / "w", progress=False))
    assert res.frame.source == "known_poses" and res.points_xyz is not None and len(res.points_xyz) > 300
    assert res.stats["triangulation"]["points"] == len(res.points_xyz)
    for f, g in zip(res.frames, gt.frames):  # poses untouched
        np.testing.assert_allclose(f.camera.T_world_cam, g.camera.T_world_cam, atol=1e-12)
    r = _depth_residuals(res.points_xyz, gt.frames)
    assert np.median(r) < 0.001 and np.mean(r < 0.01) > 0.85
    # written with the posed dataset: training starts from them
    out = res.save(tmp_path / "out")
    assert load_dataset(out).points_xyz.shape == res.points_xyz.shape


def test_trainer_init_triangulates_when_only_poses_are_known(known_no_points):
    from splattwin.splat.init import initial_gaussians

    gt, bare = known_no_points
    g, method = initial_gaussians("auto", bare.train(), None, None, max_points=5000)
    assert method == "triangulate" and 300 < len(g) <= 5000
    r = _depth_residuals(g.means, gt.frames)
    assert np.median(r) < 0.001 and np.mean(r < 0.01) > 0.85


def test_colmap_camera_models():
    K = np.array([[100.0, 0, 32], [0, 110.0, 24], [0, 0, 1]])
    assert colmap_camera(Camera(K=K, width=64, height=48)) == ("PINHOLE", [100.0, 110.0, 32.0, 24.0])
    m, p = colmap_camera(Camera(K=K, width=64, height=48, dist=np.array([0.1, -0.01, 0.001, 0.002])))
    assert m == "OPENCV" and p[4:] == [0.1, -0.01, 0.001, 0.002]
    m, p = colmap_camera(Camera(K=K, width=64, height=48, dist=np.array([0.1, -0.01, 0.001, 0.002, 0.05])))
    assert m == "FULL_OPENCV" and p[8] == 0.05 and len(p) == 12
    cams = [Camera(K=K, width=64, height=48), Camera(K=K, width=64, height=48), Camera(K=K * [[2], [2], [1]], width=128, height=96)]
    groups = known_camera_groups(cams, ["a", "b", "c"])
    assert sorted(g.names for g in groups) == [["a", "b"], ["c"]]


def test_pairs_from_poses_pair_neighbours_that_see_the_same_side():
    cams = []
    for i in range(24):  # a ring looking inwards
        a = 2 * math.pi * i / 24
        eye = np.array([math.cos(a), math.sin(a), 0.5])
        cams.append(Camera.from_fov(1.0, 64, 48, look_at(eye, np.zeros(3))))
    pairs = pairs_from_poses(cams, neighbours=4)
    assert (0, 1) in pairs and (0, 23) in pairs
    assert (0, 12) not in pairs  # opposite side, facing the other way
    assert all(i < j for i, j in pairs)
    deg = np.bincount(np.array(pairs).ravel(), minlength=24)
    assert deg.min() >= 4


def test_outlier_mask_drops_isolated_and_badly_reprojected_points():
    from splattwin.poses.triangulate import outlier_mask

    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 0.1, (500, 3))
    err = rng.uniform(0.1, 0.5, 500)
    xyz[:5] += 2.0            # far from everything
    err[5:10] = 4.0           # reprojects badly
    keep = outlier_mask(xyz, err)
    assert not keep[:10].any() and keep[10:].mean() > 0.97
