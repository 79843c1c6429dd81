"""The robot in the picture: depth order against the splats (analytic cases) for both representations."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.capture.camera import Camera, look_at
from splattwin.playback.compositor import PlaybackRenderer
from splattwin.playback.robot import RobotPose, RobotSplats, composite_layers
from splattwin.playback.scene import DynamicScene
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0

HOME = np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])


def test_composite_layers_depth_order_analytic():
    H, W = 2, 3
    red, blue = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    s_rgb = np.broadcast_to(red, (H, W, 3)).astype(np.float32)
    s_d = np.full((H, W), 1.0, np.float32)
    s_a = np.ones((H, W), np.float32)
    l_rgb = np.broadcast_to(blue, (H, W, 3)).astype(np.float32)
    cov = np.ones((H, W), np.float32)
    out, a = composite_layers(s_rgb, s_d, s_a, l_rgb, np.full((H, W), 0.5, np.float32), cov)
    np.testing.assert_allclose(out, l_rgb)                        # layer in front
    out, a = composite_layers(s_rgb, s_d, s_a, l_rgb, np.full((H, W), 2.0, np.float32), cov)
    np.testing.assert_allclose(out, s_rgb)                        # layer behind an opaque splat
    out, a = composite_layers(s_rgb, s_d, s_a, l_rgb, np.full((H, W), 0.5, np.float32), cov * 0.25)
    np.testing.assert_allclose(out[0, 0], 0.25 * blue + 0.75 * red, atol=1e-6)   # antialiased edge
    half = s_a * 0.5
    out, a = composite_layers(s_rgb * 0.5, s_d, half, l_rgb, np.full((H, W), 2.0, np.float32), cov)
    np.testing.assert_allclose(out[0, 0], 0.5 * red + 0.5 * blue, atol=1e-6)     # through a translucent splat
    np.testing.assert_allclose(a, 1.0)
    out, a = composite_layers(s_rgb * 0, s_d, s_a * 0, l_rgb, np.full((H, W), np.inf, np.float32), cov * 0)
    np.testing.assert_allclose(a, 0.0)                            # nothing anywhere


def _wall(z: float, half: float = 0.6, spacing: float = 0.01) -> Gaussians:
    g = np.arange(-half, half + 1e-9, spacing)
    xx, yy = np.meshgrid(g + 0.3, g, indexing="ij")
    n = xx.size
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = rgb_to_sh0(np.array([0.9, 0.1, 0.1]))
    return Gaussians(np.stack([xx.ravel(), yy.ravel(), np.full(n, z)], 1), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.tile([spacing * 0.8, spacing * 0.8, 1e-4], (n, 1)), np.full(n, 0.99), sh)


@pytest.fixture(scope="module")
def panda_splats():
    return RobotSplats.panda(np.eye(4))


def test_robot_gaussians_depth_order_against_splats(panda_splats):
    rob = panda_splats
    pose = RobotPose(HOME, 0.08)
    rob.set_pose(pose)
    hand = rob.body_pose("hand")[:3, 3]
    cam = Camera.from_fov(np.radians(40), 64, 48, look_at(np.array([hand[0], hand[1], 1.5]), hand * [1, 1, 0]))
    uv, z_hand = cam.project(hand[None])
    u, v = np.round(uv[0]).astype(int)
    for z_wall, robot_in_front in ((hand[2] + 0.25, False), (0.05, True)):
        scene = DynamicScene(background=_wall(z_wall), objects={}, T_world_obj0={})
        f = PlaybackRenderer(scene, rob, backend="cpu").render(cam, {}, pose)
        red = f.rgb[v, u, 0] > 0.6 and f.rgb[v, u, 1] < 0.3
        assert red != robot_in_front, (z_wall, f.rgb[v, u])
        if robot_in_front:   # expected depth is the hand's, not the wall's
            assert f.depth[v, u] < 1.5 - 0.3
            assert abs(f.depth[v, u] - (1.5 - z_wall)) > 0.2
        else:
            assert f.depth[v, u] == pytest.approx(1.5 - z_wall, abs=0.01)
    # the robot is drawn at all: without it the centre is the wall
    scene = DynamicScene(background=_wall(0.05), objects={}, T_world_obj0={})
    bare = PlaybackRenderer(scene, None, backend="cpu").render(cam, {}, None)
    assert bare.rgb[v, u, 0] > 0.6


def test_robot_splats_follow_forward_kinematics(panda_splats):
    rob = panda_splats
    assert 20_000 < len(rob) < 200_000
    m0, _, _ = rob.posed(RobotPose(HOME, 0.08))
    q = HOME.copy()
    q[0] = 0.5   # base yaw: every point but the base link's turns by 0.5 rad about z
    m1, _, c1 = rob.posed(RobotPose(q, 0.08))
    moving = rob.body != rob.model.body("link0").id
    a0 = np.arctan2(m0[moving, 1], m0[moving, 0])
    a1 = np.arctan2(m1[moving, 1], m1[moving, 0])
    r = np.hypot(m0[moving, 0], m0[moving, 1]) > 0.05
    d = np.angle(np.exp(1j * (a1 - a0)))[r]
    np.testing.assert_allclose(d, 0.5, atol=1e-6)
    np.testing.assert_allclose(m1[~moving], m0[~moving])
    assert c1.min() >= 0 and c1.max() <= 1
