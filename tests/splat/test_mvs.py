"""Plane-sweep stereo (splat/mvs.py) against an analytic scene: a textured plane at a known depth."""

import numpy as np
import pytest
import torch

from splattwin.capture import Camera, Frame
from splattwin.errors import InputError
from splattwin.splat import mvs

W, H, F_PX = 96, 72, 80.0
PLANE_Z = 2.0


def _texture(x, y):
    """Smooth random-looking grey texture on the plane (world x, y in m), values in [0, 1]."""
    t = (np.sin(23 * x + 1.0) * np.cos(17 * y) + 0.6 * np.sin(41 * x - 29 * y + 0.5)
         + 0.4 * np.cos(53 * y + 11 * x))
    return 0.5 + 0.2 * t


def _camera(tx, name=""):
    T = np.eye(4)
    T[0, 3] = tx
    return Camera(K=[[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1]], width=W, height=H, T_world_cam=T, name=name)


def _image(cam, flat=False):
    """The plane z = PLANE_Z seen by `cam` (looking along +z), as an [H,W,3] float image."""
    v, u = np.mgrid[0:H, 0:W]
    x = cam.T_world_cam[0, 3] + (u + 0.5 - cam.cx) / cam.fx * PLANE_Z
    y = cam.T_world_cam[1, 3] + (v + 0.5 - cam.cy) / cam.fy * PLANE_Z
    g = np.full(x.shape, 0.5) if flat else _texture(x, y)
    return np.repeat(g[..., None], 3, axis=-1).astype(np.float32)


def test_zncc_known_values():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(20, 20, generator=g)
    src = torch.stack([ref, 2 * ref + 0.3, 1 - ref, torch.full((20, 20), 0.4)])
    n = mvs.zncc(ref, src, 5)
    inner = (slice(None), slice(3, -3), slice(3, -3))
    assert torch.allclose(n[0][inner[1:]], torch.ones(14, 14), atol=1e-3)   # identical
    assert torch.allclose(n[1][inner[1:]], torch.ones(14, 14), atol=1e-3)   # gain and bias invariant
    assert torch.allclose(n[2][inner[1:]], -torch.ones(14, 14), atol=1e-3)  # inverted
    assert torch.all(n[3] == 0)                                           # flat patch: no evidence


def test_plane_sweep_recovers_the_plane_depth():
    cams = [_camera(tx) for tx in (-0.1, 0.0, 0.1)]
    grays = [_image(c)[..., 0] for c in cams]
    depth, score = mvs.plane_sweep(grays[1], cams[1], [grays[0], grays[2]], [cams[0], cams[2]],
                                   1.0, 4.0, n_planes=128, window=7)
    assert depth.shape == (H, W) and score.shape == (H, W)
    # the middle of the image is seen by both sources; the plane step near z = 2 is ~1.3 %
    mid = (slice(10, -10), slice(20, -20))
    err = np.abs(depth[mid] - PLANE_Z) / PLANE_Z
    assert np.median(err) < 0.01
    assert np.mean(err < 0.03) > 0.95
    assert np.median(score[mid]) > 0.9


def test_plane_sweep_validates_its_arguments():
    cam = _camera(0.0)
    g = _image(cam)[..., 0]
    with pytest.raises(ValueError, match="depth_min"):
        mvs.plane_sweep(g, cam, [g], [_camera(0.1)], 2.0, 1.0)
    with pytest.raises(ValueError, match="window"):
        mvs.plane_sweep(g, cam, [g], [_camera(0.1)], 1.0, 2.0, window=4)


def _frames(tmp_path, flat=False):
    import imageio.v3 as iio

    frames = []
    for i, tx in enumerate((-0.16, -0.08, 0.0, 0.08, 0.16)):
        cam = _camera(tx, name=f"v{i}")
        p = tmp_path / f"v{i}.png"
        iio.imwrite(p, (np.clip(_image(cam, flat), 0, 1) * 255).round().astype(np.uint8))
        frames.append(Frame(image_path=p, camera=cam))
    return frames


def test_dense_points_lie_on_the_plane(tmp_path):
    frames = _frames(tmp_path)
    sparse = np.array([[x, y, PLANE_Z] for x in (-0.4, 0.0, 0.4) for y in (-0.3, 0.0, 0.3)])
    opts = mvs.StereoOptions(max_side=96, n_planes=128, n_src=2)
    xyz, rgb = mvs.dense_points(frames, sparse, max_points=100_000, opts=opts, progress=False)
    assert len(xyz) > 0.3 * 5 * W * H   # most pixels of a fully textured, fully overlapping plane
    assert np.percentile(np.abs(xyz[:, 2] - PLANE_Z), 95) < 0.03 * PLANE_Z
    # colours are the texture at the points (8-bit rounding and the window's blur aside)
    assert np.median(np.abs(rgb[:, 0] - _texture(xyz[:, 0], xyz[:, 1]))) < 0.05
    sub, _ = mvs.dense_points(frames, sparse, max_points=500, opts=opts, progress=False)
    assert len(sub) == 500


def test_textureless_views_give_no_points(tmp_path):
    frames = _frames(tmp_path, flat=True)
    sparse = np.array([[x, y, PLANE_Z] for x in (-0.4, 0.0, 0.4) for y in (-0.3, 0.0, 0.3)])
    xyz, _ = mvs.dense_points(frames, sparse, max_points=100_000,
                              opts=mvs.StereoOptions(max_side=96, n_planes=32, n_src=2), progress=False)
    assert len(xyz) == 0


def test_fusion_drops_depths_the_other_views_contradict():
    cams = [_camera(tx) for tx in (-0.1, 0.0, 0.1)]
    good = np.full((H, W), PLANE_Z)
    bad = good.copy()
    bad[:, : W // 2] = 3.0   # the left half of view 1 claims a wrong depth
    scores = [np.ones((H, W))] * 3
    imgs = [_image(c) for c in cams]
    xyz, _, kept = mvs.fuse(cams, [good, bad, good], scores, imgs, ncc_min=0.5, rel_tol=0.01, min_agree=1)
    assert kept[1] < 0.55 and kept[0] > 0.8 and kept[2] > 0.8
    assert np.all(np.abs(xyz[:, 2] - PLANE_Z) < 1e-6)


def test_needs_two_views(tmp_path):
    frames = _frames(tmp_path)[:1]
    with pytest.raises(InputError, match="at least 2"):
        mvs.dense_points(frames, np.zeros((10, 3)), max_points=10, progress=False)
    with pytest.raises(InputError, match="sparse point cloud"):
        mvs.dense_points(_frames(tmp_path), None, max_points=10, progress=False)


def test_initial_gaussians_add_stereo_points_within_the_budget(tmp_path):
    from splattwin.splat.init import initial_gaussians

    frames = _frames(tmp_path)
    sparse = np.array([[x, y, PLANE_Z] for x in (-0.4, 0.0, 0.4) for y in (-0.3, 0.0, 0.3)])
    g, m = initial_gaussians("sfm", frames, sparse, None, max_points=600, stereo_points=5000, progress=False)
    assert m == "sfm+stereo" and len(g) == 600          # 9 SfM points + 591 stereo points: the budget
    np.testing.assert_allclose(g.means[:9], sparse)        # the SfM points are all kept, first
    assert np.percentile(np.abs(g.means[9:, 2] - PLANE_Z), 95) < 0.03 * PLANE_Z
    g0, m0 = initial_gaussians("sfm", frames, sparse, None, max_points=600, progress=False)
    assert m0 == "sfm" and len(g0) == 9


def test_dense_points_match_the_embedded_scenes_true_depth(scene_small):
    """Rendered textures, shading and occlusions (8 training views at 160x120): the fused points lie on the
    true surfaces (measured: median 2.6 mm, 92 % within 1 cm, 31 % of the pixels fused)."""
    from splattwin.capture import load_dataset, load_depth
    from splattwin.splat.init import backproject_depth

    ds = load_dataset(scene_small)
    train = ds.train()
    depths = [load_depth(f.depth_path, ds.depth_scale) for f in train]
    sparse = np.concatenate([backproject_depth(d, f.camera, stride=16)[0] for d, f in zip(depths, train)])
    xyz, _ = mvs.dense_points(train, sparse, 10**7, progress=False)
    assert len(xyz) > 0.2 * len(train) * 160 * 120
    err = np.full(len(xyz), np.inf)   # distance along the ray to the true surface, best training view
    for d, f in zip(depths, train):
        uv, z = f.camera.project(xyz)
        u, v = np.floor(uv).astype(int).T
        ok = (z > 0) & (u >= 0) & (u < d.shape[1]) & (v >= 0) & (v < d.shape[0])
        e = np.full(len(xyz), np.inf)
        e[ok] = np.abs(d[v[ok], u[ok]] - z[ok])
        err = np.minimum(err, e)
    assert np.median(err) < 0.005
    assert np.mean(err < 0.01) > 0.8
