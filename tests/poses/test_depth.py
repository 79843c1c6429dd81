"""Depth back-projection: analytic plane and a distortion round trip."""

from __future__ import annotations

import numpy as np

from splattwin.capture import Camera, look_at
from splattwin.poses.depth import backproject_depth


def _plane_depth(cam: Camera) -> np.ndarray:
    """Analytic z-depth of the plane z = 0 seen by an undistorted camera."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    d_cam = np.stack([(u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    R, c = cam.T_world_cam[:3, :3], cam.center
    dz_world = d_cam @ R.T                       # ray direction per unit z-depth, world frame
    with np.errstate(divide="ignore"):
        t = -c[2] / dz_world[..., 2]
    t[t <= 0] = np.inf
    return t


def test_plane_backprojects_onto_plane():
    cam = Camera.from_fov(np.radians(60), 64, 48, T_world_cam=look_at(np.array([0.4, -0.3, 0.5]), np.zeros(3)))
    depth = _plane_depth(cam)
    img = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    xyz, rgb = backproject_depth(depth, cam, img)
    assert len(xyz) == np.isfinite(depth).sum() > 1000
    np.testing.assert_allclose(xyz[:, 2], 0.0, atol=1e-9)
    assert rgb.dtype == np.uint8 and rgb.shape == xyz.shape
    xs, _ = backproject_depth(depth, cam, stride=4, max_depth=0.7)
    assert len(xs) < len(xyz) / 10


def test_distorted_camera_round_trip():
    cam = Camera(K=np.array([[200.0, 0, 40], [0, 205, 30], [0, 0, 1]]), width=80, height=60,
                 T_world_cam=look_at(np.array([0.1, 0.2, 0.8]), np.zeros(3)), dist=np.array([-0.2, 0.05, 0.001, -0.002]))
    depth = np.random.default_rng(1).uniform(0.5, 1.0, (60, 80))
    depth[5, 7] = np.inf
    depth[6, 7] = 0.0
    xyz, _ = backproject_depth(depth, cam)
    assert len(xyz) == 60 * 80 - 2
    uv, z = cam.project(xyz)
    v, u = np.mgrid[0:60, 0:80]
    ok = np.isfinite(depth) & (depth > 0)
    np.testing.assert_allclose(uv, np.stack([u[ok] + 0.5, v[ok] + 0.5], 1), atol=1e-3)
    np.testing.assert_allclose(z, depth[ok], rtol=1e-9)


def test_a_wrong_size_depth_map_among_many_is_named(tmp_path):
    """One 200x160 depth map among 14 of 160x120: the up check samples 12 frames and missed it, then the
    back-projection raised ValueError (exit 1). Every depth map is now checked where it is read."""
    import pytest

    from splattwin import io
    from splattwin.capture import Frame
    from splattwin.errors import InputError
    from splattwin.poses.depth import backproject_frames
    from splattwin.poses.up import depth_points

    frames = []
    for i in range(14):
        cam = Camera.from_fov(1.0, 16, 12, T_world_cam=look_at(np.array([0.5, 0.1 * i, 0.5]), np.zeros(3)), name=f"{i}")
        io.write_image(tmp_path / f"{i}.png", np.zeros((12, 16, 3), np.uint8))
        d = tmp_path / f"{i}_d.png"
        io.write_image(d, np.full((14, 16) if i == 3 else (12, 16), 500, np.uint16))
        frames.append(Frame(image_path=tmp_path / f"{i}.png", camera=cam, depth_path=d))
    with pytest.raises(InputError, match="depth map is 16x14 but its camera is 16x12") as e:
        backproject_frames(frames, stride=1)
    assert e.value.path == tmp_path / "3_d.png"
    with pytest.raises(InputError, match="depth map is 16x14") as e:
        depth_points(frames, None, max_frames=14)
    assert e.value.path == tmp_path / "3_d.png"


def test_merge_with_depth_keeps_the_sparse_points_one_per_voxel_and_bounded():
    from splattwin.poses.depth import merge_with_depth

    rng = np.random.default_rng(0)
    sparse = rng.uniform(0, 0.1, (50, 3))
    dense = np.concatenate([rng.uniform(0, 0.3, (5000, 3)), sparse + 1e-4])   # some in the sparse voxels
    xyz, rgb = merge_with_depth(sparse, np.full((50, 3), 7, np.uint8), dense, np.zeros((len(dense), 3), np.uint8),
                                voxel=0.002)
    assert np.array_equal(xyz[:50], sparse) and (rgb[:50] == 7).all()      # the sparse points first, kept
    keys = np.floor((xyz - xyz.min(axis=0)) / 0.002).astype(int)
    assert len(np.unique(keys, axis=0)) == len(xyz)                          # one per voxel
    assert len(xyz) < len(sparse) + len(dense)
    xyz, rgb = merge_with_depth(sparse, None, dense, np.zeros((len(dense), 3), np.uint8), max_points=1000)
    assert len(xyz) == 1000 and rgb.dtype == np.uint8
    assert np.array_equal(xyz[:50], sparse) and (rgb[:50] == 128).all()    # all sparse kept under the bound


def test_the_depth_seed_cloud_comes_from_training_views_only(scene_small):
    """The back-projected cloud seeds the splats' positions and colours: a held-out view's pixels in it
    would leak into the model that view scores."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.poses.depth import backproject_frames

    ds = load_dataset(scene_small)
    assert any(f.depth_path is not None for f in ds.frames)
    res = estimate_poses(ds, PoseOptions(method="known", progress=False, triangulate=False))
    train = [f for f in res.frames if f.split == "train"]
    held = [f for f in res.frames if f.split == "heldout"]
    assert train and held and res.stats["depth_points_views"] == len(train)
    xyz, _ = backproject_frames(train, depth_scale=res.depth_scale)
    every, _ = backproject_frames(res.frames, depth_scale=res.depth_scale)
    assert len(res.depth_xyz) == len(xyz) < len(every)
    np.testing.assert_allclose(res.depth_xyz, xyz)


def test_the_log_names_the_real_source_of_the_initial_points(scene_small, tmp_path, caplog):
    """Audit 8c L3: "initialised ... Gaussians from sfm" when no SfM ran and the points were back-projected
    from the depth images. The poses stage records what made its cloud (poses_report.json points_source),
    and the splat initialisation names it."""
    import logging

    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.splat.init import initial_gaussians, poses_points_source

    res = estimate_poses(load_dataset(scene_small), PoseOptions(method="known", progress=False, triangulate=False))
    assert res.stats["points_source"] == "depth back-projection"
    res.save(tmp_path / "poses")
    ds = load_dataset(tmp_path / "poses" / "transforms.json")
    assert poses_points_source(ds) == "depth back-projection"
    with caplog.at_level(logging.INFO, logger="splattwin.splat.init"):
        _, method = initial_gaussians("auto", ds.train(), ds.points_xyz, ds.points_rgb, max_points=500,
                                      points_source=poses_points_source(ds), progress=False)
    assert method == "sfm"   # the recorded method keeps its name (the posed dataset's points)
    assert "from depth back-projection" in caplog.text and "from sfm" not in caplog.text
    # a report written before points_source: read from its depth figures
    import json

    rep = json.loads((tmp_path / "poses" / "poses_report.json").read_text())
    del rep["points_source"]
    for stats, want in (({**rep, "method": "robot"}, "depth back-projection"),
                        ({**rep, "method": "sfm", "initial_points": {"sparse": 10}}, "SfM points + depth back-projection"),
                        ({"method": "sfm"}, None)):
        (tmp_path / "poses" / "poses_report.json").write_text(json.dumps(stats))
        assert poses_points_source(ds) == want
