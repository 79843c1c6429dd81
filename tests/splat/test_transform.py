"""`splat.transform.transform_gaussians` with a similarity (scale, rotation, translation): the moved splats
seen from the camera moved by the same similarity render the same image (what lets a twin given its metric
scale after training keep its trained splats, `splat.rescale`)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.capture import Camera
from splattwin.capture.camera import look_at
from splattwin.poses.align import transform_camera
from splattwin.splat.gaussians import Gaussians
from splattwin.splat.rendering import render_rgb
from splattwin.splat.transform import similarity_scale, transform_gaussians


def _blob(n=300, degree=2, seed=0) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    sh = rng.normal(size=(n, (degree + 1) ** 2, 3)) * 0.5
    return Gaussians(rng.normal(size=(n, 3)) * 0.3, q / np.linalg.norm(q, axis=1, keepdims=True),
                     np.abs(rng.normal(size=(n, 3))) * 0.04 + 0.01, rng.uniform(0.2, 0.9, n), sh)


def _similarity(s: float, seed: int = 1) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = s * Rotation.random(random_state=seed).as_matrix()
    S[:3, 3] = [0.4, -1.2, 0.3]
    return S


@pytest.mark.parametrize("s", [0.0873, 1.0, 7.5])
def test_moved_splats_render_the_same_from_the_moved_camera(s):
    g = _blob()
    cam = Camera(np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]]), 80, 60,
                 T_world_cam=look_at(np.array([1.5, -1.0, 1.2]), np.zeros(3)))
    S = _similarity(s)
    h = transform_gaussians(g, S)
    np.testing.assert_allclose(h.scales, s * g.scales, rtol=1e-12)
    np.testing.assert_allclose(h.means, g.means @ S[:3, :3].T + S[:3, 3], atol=1e-12)
    a = render_rgb(g, cam, backend="cpu")
    b = render_rgb(h, transform_camera(S, cam), backend="cpu")
    assert a.std() > 0.05   # something is drawn
    assert np.abs(a - b).max() < 2e-3
    if s != 1.0:   # the scale matters: unscaled splats from the moved camera are another picture
        rigid = S.copy()
        rigid[:3, :3] /= s
        c = render_rgb(transform_gaussians(g, rigid), transform_camera(S, cam), backend="cpu")
        assert np.abs(a - c).max() > 0.05


def test_similarity_scale_refuses_what_is_not_one():
    assert similarity_scale(_similarity(2.0)) == pytest.approx(2.0)
    assert similarity_scale(np.eye(4)) == 1.0
    with pytest.raises(ValueError, match="determinant"):
        similarity_scale(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="uniform scale"):
        similarity_scale(np.diag([1.0, 2.0, 1.0, 1.0]))
