from __future__ import annotations

import math

import numpy as np
import pytest

from splattwin.capture import Camera, Frame, look_at
from splattwin.errors import InputError
from splattwin.io import write_image, write_npy
from splattwin.splat.init import (backproject_depth, initial_gaussians, knn_scales, points_from_depth,
                                  scene_center_and_scale)


def test_knn_scales_on_grid():
    g = np.stack(np.meshgrid(np.arange(5), np.arange(5), [0.0]), -1).reshape(-1, 3) * 0.1
    s = knn_scales(g)
    # interior points: 4 neighbours at 0.1 -> the 3 nearest average 0.1
    assert s[12] == pytest.approx(0.1)
    assert np.all(s >= 0.1 - 1e-12)


def _cam(w=40, h=30):
    T = look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3), up=np.array([0.0, 1.0, 0.0]))
    return Camera.from_fov(math.radians(60), w, h, T, name="c")


def test_backproject_plane_and_missing_pixels():
    cam = _cam()
    depth = np.full((30, 40), 1.0, np.float32)
    depth[0, :] = np.inf
    xyz, rgb = backproject_depth(depth, cam, stride=1)
    assert len(xyz) == 40 * 29 and np.allclose(xyz[:, 2], 0.0, atol=1e-9)  # the z=0 plane 1 m ahead
    uv, z = cam.project(xyz)
    assert np.allclose(z, 1.0)
    v, u = np.mgrid[1:30, 0:40]
    np.testing.assert_allclose(uv, np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1), atol=1e-9)
    assert np.allclose(rgb, 0.5)


def test_backproject_through_a_distorted_lens():
    """With lens distortion (TUM's Freiburg cameras, SfM's SIMPLE_RADIAL) each pixel's point lies on the
    ray the lens model sends through that pixel: projected back with the model it lands on the pixel
    centre at the measured z-depth."""
    import dataclasses

    cam = dataclasses.replace(_cam(), dist=np.array([0.2, -0.1, 0.001, -0.002]))
    depth = np.full((30, 40), 1.5, np.float32)
    xyz, _ = backproject_depth(depth, cam, stride=1)
    uv, z = cam.project(xyz)
    np.testing.assert_allclose(z, 1.5, atol=1e-9)
    v, u = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1), atol=1e-6)
    # rays that hit nothing go to the background sphere along the same lens rays
    from splattwin.splat.init import _rays_to_sphere

    sel = np.zeros(30 * 40, bool)
    sel[::7] = True
    pts, _ = _rays_to_sphere(cam, np.zeros((30, 40, 3)), 1, sel, np.zeros(3), 5.0)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 5.0, rtol=1e-9)
    uv, _ = cam.project(pts)
    np.testing.assert_allclose(uv, np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)[sel], atol=1e-6)


def test_points_from_depth_with_background(tmp_path):
    cam = _cam()
    depth = np.full((30, 40), 1.0, np.float32)
    depth[:5] = np.inf  # rays that miss: become far-sphere background points
    img = np.zeros((30, 40, 3), np.uint8)
    img[:5] = 200
    f = Frame(image_path=write_image(tmp_path / "i.png", img), camera=cam,
              depth_path=write_npy(tmp_path / "d.npy", depth))
    xyz, rgb = points_from_depth([f], max_points=500, background_fraction=0.2)
    assert len(xyz) <= 500
    far = np.linalg.norm(xyz - cam.center, axis=1) > 1.5
    assert 0 < far.sum() <= 100 and np.allclose(rgb[far], 200 / 255, atol=1e-6)
    assert np.allclose(xyz[~far, 2], 0.0, atol=1e-6)
    with pytest.raises(InputError, match="depth"):
        points_from_depth([Frame(image_path=tmp_path / "i.png", camera=cam)])


def test_initial_gaussians_methods():
    cams = [_cam(), Camera.from_fov(1.0, 40, 30, look_at(np.array([1.0, 0, 1]), np.zeros(3)))]
    frames = [Frame(image_path=None, camera=c) for c in cams]  # type: ignore[arg-type]
    c, s = scene_center_and_scale(cams)
    assert s == pytest.approx(1.1 * 0.5)
    pts = np.random.default_rng(0).normal(size=(50, 3))
    g, m = initial_gaussians("auto", frames, pts, None, sh_degree=2)
    assert m == "sfm" and len(g) == 50 and g.sh_degree == 2
    np.testing.assert_allclose(g.opacities, 0.1)
    np.testing.assert_allclose(g.colors, 0.5)
    g, m = initial_gaussians("auto", frames, None, None, max_points=100)  # no images: nothing to triangulate
    assert m == "random" and len(g) == 100
    # inside the common view: in front of and inside the image of both cameras, not around the cameras
    for cam in cams:
        uv, z = cam.project(g.means)
        assert np.all(cam.in_image(uv)) and np.all(z > 0)
    with pytest.raises(InputError, match="sfm"):
        initial_gaussians("sfm", frames, None, None)
    with pytest.raises(InputError, match="unknown"):
        initial_gaussians("magic", frames, pts, None)


def test_random_init_stays_in_the_common_view_of_a_ring():
    from splattwin.splat.init import random_points_in_view

    cams = []
    for i in range(12):  # a ring 1 m around the origin, 0.5 m up, looking at the table centre
        a = 2 * math.pi * i / 12
        cams.append(Camera.from_fov(math.radians(50), 64, 48, look_at(np.array([math.cos(a), math.sin(a), 0.5]),
                                                                      np.zeros(3))))
    xyz, rgb = random_points_in_view(cams, 2000, seed=1)
    assert xyz.shape == (2000, 3) and rgb.shape == (2000, 3)
    seen = np.zeros(len(xyz), int)
    for c in cams:
        uv, z = c.project(xyz)
        seen += c.in_image(uv) & (z > 0)
    assert np.all(seen >= 6)  # at least half of the cameras see each point
    # nothing around the cameras (where random points become per-view floaters)
    d = np.min(np.linalg.norm(xyz[:, None] - np.array([c.center for c in cams])[None], axis=2), axis=1)
    assert d.min() > 0.3
