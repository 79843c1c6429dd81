"""`splat.rescale.similarity_between`: the one similarity that moved every camera, or None when the cameras
moved otherwise (then the splats are trained again, never moved by a wrong transform)."""

import numpy as np
from scipy.spatial.transform import Rotation

from splattwin.capture.camera import look_at
from splattwin.poses.align import transform_pose
from splattwin.splat.rescale import similarity_between


def _poses(n=6):
    rng = np.random.default_rng(0)
    return [look_at(rng.normal(size=3) + np.array([0, 0, 2.0]), np.zeros(3)) for _ in range(n)]


def _similarity(s=0.0873):
    S = np.eye(4)
    S[:3, :3] = s * Rotation.from_euler("z", 30, degrees=True).as_matrix()
    S[:3, 3] = [0.1, 0.2, -0.05]
    return S


def test_the_similarity_that_moved_every_camera_is_found():
    old = _poses()
    S = _similarity()
    found = similarity_between(old, [transform_pose(S, T) for T in old])
    np.testing.assert_allclose(found, S, atol=1e-9)


def test_cameras_moved_otherwise_give_none():
    old = _poses()
    S = _similarity()
    new = [transform_pose(S, T) for T in old]
    shifted = [T.copy() for T in new]
    shifted[2][:3, 3] += 1e-3          # one camera re-estimated elsewhere (another SfM run)
    assert similarity_between(old, shifted) is None
    turned = [T.copy() for T in new]
    turned[4][:3, :3] = turned[4][:3, :3] @ Rotation.from_euler("x", 0.01, degrees=True).as_matrix()
    assert similarity_between(old, turned) is None
    assert similarity_between(old[:2], new[:2]) is None   # two centres: the rotation is undetermined
