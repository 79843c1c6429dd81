"""Umeyama similarity: exact recovery, agreement with pycolmap, camera transforms keep projections."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.capture import Camera, look_at
from splattwin.poses.align import sim3_inverse, transform_camera, transform_points, umeyama


def _random_sim3(rng) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = 2.7 * Rotation.random(random_state=1).as_matrix()
    S[:3, 3] = rng.normal(size=3)
    return S


def test_umeyama_recovers_exact_similarity():
    rng = np.random.default_rng(0)
    S = _random_sim3(rng)
    src = rng.normal(size=(12, 3))
    fit = umeyama(src, transform_points(S, src))
    np.testing.assert_allclose(fit.S, S, atol=1e-10)
    assert fit.rms < 1e-10 and fit.scale_uncertainty_rel < 1e-9
    np.testing.assert_allclose(sim3_inverse(S) @ S, np.eye(4), atol=1e-12)


def test_umeyama_matches_pycolmap_with_noise():
    import pycolmap

    rng = np.random.default_rng(1)
    S = _random_sim3(rng)
    src = rng.normal(size=(30, 3))
    tgt = transform_points(S, src) + rng.normal(0, 0.01, (30, 3))
    fit = umeyama(src, tgt)
    ref = pycolmap.estimate_sim3d(src, tgt).matrix()
    np.testing.assert_allclose(fit.S[:3, :], ref, atol=1e-8)
    assert 0.005 < fit.rms < 0.03
    # scale uncertainty is of the order of the empirical scatter of the scale over noise draws
    scales = [umeyama(src, transform_points(S, src) + rng.normal(0, 0.01, (30, 3))).scale for _ in range(200)]
    emp = np.std(scales) / 2.7
    assert 0.3 * emp < fit.scale_uncertainty_rel < 3 * emp


def test_umeyama_rejects_degenerate_input():
    with pytest.raises(ValueError):
        umeyama(np.zeros((5, 3)), np.ones((5, 3)))
    line = np.outer(np.arange(5.0), [1, 2, 3])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line)


def test_transformed_camera_sees_transformed_points_at_same_pixels():
    rng = np.random.default_rng(2)
    cam = Camera(K=np.array([[300.0, 0, 160], [0, 310, 120], [0, 0, 1]]), width=320, height=240,
                 T_world_cam=look_at(np.array([0.5, -0.4, 0.6]), np.zeros(3)), dist=np.array([-0.05, 0.01, 0.001, 0.0]))
    pts = rng.uniform(-0.2, 0.2, (50, 3))
    S = _random_sim3(rng)
    uv0, z0 = cam.project(pts)
    cam2 = transform_camera(S, cam)
    uv1, z1 = cam2.project(transform_points(S, pts))
    np.testing.assert_allclose(uv1, uv0, atol=1e-9)
    np.testing.assert_allclose(z1, 2.7 * z0, rtol=1e-12)
