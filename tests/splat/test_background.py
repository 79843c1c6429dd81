from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splattwin.capture import Camera, look_at
from splattwin.splat.background import (BackgroundModel, equirect_lookup, ray_directions, sphere_points,
                                        sphere_radius)


def _cam(w=8, h=6, eye=(0.0, 0.0, 0.0), target=(1.0, 0.0, 0.0)):
    return Camera.from_fov(math.radians(60), w, h, look_at(np.array(eye), np.array(target)))


def test_ray_directions_match_the_projection():
    cam = _cam(eye=(0.3, -0.2, 0.5), target=(1.0, 1.0, 0.0))
    d = ray_directions(torch.tensor(cam.K, dtype=torch.float64), torch.tensor(cam.T_world_cam), cam.width, cam.height)
    assert d.shape == (6, 8, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(6, 8, dtype=torch.float64))
    # a point along the ray of pixel (u, v) projects to the pixel centre (u + 0.5, v + 0.5)
    p = cam.center + 2.0 * d[4, 5].numpy()
    q = cam.T_cam_world[:3, :3] @ p + cam.T_cam_world[:3, 3]
    uv = (cam.K @ q)[:2] / q[2]
    np.testing.assert_allclose(uv, [5.5, 4.5], atol=1e-9)


def test_equirect_lookup_directions_and_wrap():
    env = torch.zeros(3, 4, 8)
    env[0, :2] = 1.0   # red in the upper hemisphere rows
    env[2, 2:] = 1.0   # blue below
    up = equirect_lookup(env, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    torch.testing.assert_close(up, torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    # longitude wraps: directions just either side of -x (lon = +-pi) see the same texels
    e = torch.rand(3, 4, 8)
    a = equirect_lookup(e, torch.tensor([[-1.0, 1e-4, 0.3]]))
    b = equirect_lookup(e, torch.tensor([[-1.0, -1e-4, 0.3]]))
    torch.testing.assert_close(a, b, atol=1e-3, rtol=0)
    # a constant map returns the constant everywhere
    c = equirect_lookup(torch.full((3, 4, 8), 0.25), torch.nn.functional.normalize(torch.randn(50, 3), dim=1))
    torch.testing.assert_close(c, torch.full((50, 3), 0.25))


def test_composite_and_gradient_reach_the_background():
    cam = _cam()
    K, T_wc = torch.tensor(cam.K, dtype=torch.float32), torch.tensor(cam.T_world_cam, dtype=torch.float32)
    m = BackgroundModel("color", init_rgb=(0.2, 0.4, 0.6))
    img = torch.rand(6, 8, 3)
    alpha = torch.rand(6, 8, 1)
    out = m.composite(img * alpha, alpha, K, T_wc, rendered_bg=torch.zeros(3))
    torch.testing.assert_close(out, img * alpha + (1 - alpha) * torch.tensor([0.2, 0.4, 0.6]))
    # rendered over white: the white is replaced by the learnt colour
    white = img * alpha + (1 - alpha) * 1.0
    torch.testing.assert_close(m.composite(white, alpha, K, T_wc, torch.ones(3)), out)
    out.sum().backward()
    torch.testing.assert_close(m.param.grad[:, 0, 0], (1 - alpha).sum().expand(3))


def test_env_map_learns_a_sky_and_generalises_to_a_new_view():
    """Empty views (alpha 0) of a world whose far field is bright above and dark below: the env map
    learnt from views looking one way predicts a view looking another way (the same directions seen)."""
    def truth(d):
        return torch.where(d[..., 2:3] > 0, torch.tensor([0.9, 0.9, 1.0]), torch.tensor([0.2, 0.15, 0.1]))

    train = [_cam(16, 12, target=(math.cos(a), math.sin(a), 0.0)) for a in np.linspace(0, 2 * math.pi, 8, endpoint=False)]
    new = _cam(16, 12, target=(math.cos(0.4), math.sin(0.4), 0.1))
    m = BackgroundModel("env", init_rgb=(0.5, 0.5, 0.5), env_size=(8, 16), lr=0.05)
    zero, a0 = torch.zeros(12, 16, 3), torch.zeros(12, 16, 1)

    def view(c):
        K, T = torch.tensor(c.K, dtype=torch.float32), torch.tensor(c.T_world_cam, dtype=torch.float32)
        return K, T, truth(ray_directions(K, T, 16, 12))

    err0 = float((m.composite(zero, a0, *view(new)[:2]) - view(new)[2]).abs().mean())
    for it in range(300):
        K, T, gt = view(train[it % len(train)])
        ((m.composite(zero, a0, K, T) - gt) ** 2).mean().backward()
        m.step()
    K, T, gt = view(new)
    err = float((m.composite(zero, a0, K, T) - gt).abs().mean())
    assert err < 0.3 * err0, (err0, err)


def test_state_round_trip(tmp_path):
    from splattwin.splat import checkpoint as ckpt_io

    m = BackgroundModel("env", env_size=(4, 8))
    with torch.no_grad():
        m.param.uniform_()
    ckpt_io.save(tmp_path / "b.safetensors", {"bg": m.state_dict()})
    sd = ckpt_io.load(tmp_path / "b.safetensors")["bg"]
    m2 = BackgroundModel("env", env_size=(4, 8))
    m2.load_state_dict(sd)
    torch.testing.assert_close(m2.param, m.param)
    torch.testing.assert_close(BackgroundModel.from_state(sd).param, m.param)
    with pytest.raises(ValueError):
        BackgroundModel("color").load_state_dict(sd)


def test_sphere_points_take_colours_from_the_views_that_see_them():
    cams = [_cam(20, 20, target=(1.0, 0.0, 0.0)), _cam(20, 20, target=(-1.0, 0.0, 0.0))]
    imgs = [np.full((10, 10, 3), [1.0, 0.0, 0.0]), np.full((10, 10, 3), [0.0, 0.0, 1.0])]  # half size: scaled
    xyz, rgb = sphere_points(cams, imgs, np.zeros(3), 5.0, 400)
    np.testing.assert_allclose(np.linalg.norm(xyz, axis=1), 5.0)
    front = xyz[:, 0] > 4.6   # well inside camera 0's view cone (+x)
    back = xyz[:, 0] < -4.6
    assert front.any() and back.any()
    np.testing.assert_allclose(rgb[front], [[1.0, 0.0, 0.0]] * int(front.sum()))
    np.testing.assert_allclose(rgb[back], [[0.0, 0.0, 1.0]] * int(back.sum()))
    side = np.abs(xyz[:, 2]) > 4.8  # straight up/down: no camera sees it -> the mean colour
    np.testing.assert_allclose(rgb[side], [[0.5, 0.0, 0.5]] * int(side.sum()))


def test_sphere_radius_lies_beyond_the_points():
    pts = np.random.default_rng(0).normal(size=(1000, 3)) * 10
    r = sphere_radius(pts, np.zeros(3), 1.0, 3.0)
    assert r > np.quantile(np.linalg.norm(pts, axis=1), 0.98)
    assert sphere_radius(None, np.zeros(3), 2.0, 3.0) == 6.0
