"""The plain-PyTorch reference rasterizer: analytic cases and finite-difference gradients (float64)."""

from __future__ import annotations

import math

import torch

from splattwin.splat import reference as ref
from splattwin.splat.rasterize import rasterization

DT = torch.float64


def _cam(W=32, H=24, f=40.0):
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]], dtype=DT)
    return torch.eye(4, dtype=DT)[None], K


def test_single_gaussian_matches_analytic_value_at_centre_pixel():
    vm, K = _cam(32, 24, 100.0)
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=DT)
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=DT)
    s = torch.tensor([[0.05, 0.05, 0.05]], dtype=DT)
    o = torch.tensor([0.8], dtype=DT)
    c = torch.tensor([[1.0, 0.5, 0.2]], dtype=DT)
    bg = torch.tensor([[0.0, 0.0, 1.0]], dtype=DT)
    img, alpha, meta = rasterization(means, q, s, o, c, vm, K, 32, 24, backgrounds=bg, backend="reference")
    var = (100 * 0.05 / 2.0) ** 2 + 0.3  # isotropic: (f s / z)^2 + eps2d
    a = 0.8 * math.exp(-0.5 * (0.5**2 + 0.5**2) / var)  # pixel (11, 15) centre is 0.5 px from the mean
    assert abs(alpha[0, 11, 15, 0].item() - a) < 1e-12
    assert torch.allclose(img[0, 11, 15], torch.tensor([a, 0.5 * a, 0.2 * a + (1 - a)], dtype=DT))
    assert meta["radii"][0, 0].item() == math.ceil(3 * math.sqrt(var))
    # outside the 3-sigma box nothing is drawn, not even a faint tail
    r = meta["radii"][0, 0].item()
    assert alpha[0, 11, 16 + r + 1, 0].item() == 0.0


def test_culling_behind_camera_and_off_screen():
    vm, K = _cam()
    means = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.005], [50.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=DT)
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=DT).repeat(4, 1)
    s = torch.full((4, 3), 0.02, dtype=DT)
    o = torch.full((4,), 0.9, dtype=DT, requires_grad=True)
    c = torch.ones(4, 3, dtype=DT)
    img, alpha, meta = rasterization(means, q, s, o, c, vm, K, 32, 24, backend="reference")
    assert meta["visibility"][0].tolist() == [False, False, False, True]
    img.sum().backward()
    assert torch.all(o.grad[:3] == 0) and o.grad[3] > 0


def test_early_stop_and_alpha_clamp():
    # 10 opaque layers in front of each other: alpha is clamped to 0.99 and compositing stops once T < 1e-4
    vm, K = _cam()
    n = 10
    means = torch.stack([torch.zeros(n), torch.zeros(n), torch.linspace(1, 2, n)], 1).to(DT)
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=DT).repeat(n, 1)
    s = torch.full((n, 3), 0.5, dtype=DT)
    o = torch.ones(n, dtype=DT)
    c = torch.eye(n, dtype=DT)  # one-hot channel per layer (D = 10 channels)
    img, alpha, _ = rasterization(means, q, s, o, c, vm, K, 32, 24, backend="reference")
    px = img[0, 12, 16]
    # layer 0: 0.99, layer 1: 0.01*0.99; layer 2 would take T to 1e-6 < 1e-4 -> stop
    assert torch.allclose(px[:2], torch.tensor([0.99, 0.0099], dtype=DT), atol=1e-6)
    assert torch.all(px[2:] == 0)
    assert abs(alpha[0, 12, 16, 0].item() - (1 - 1e-4)) < 1e-9


def _random_scene(n=8, C=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=DT) - 0.5) * torch.tensor([1.0, 0.8, 0.4], dtype=DT)
    means[:, 2] += 2.0
    quats = torch.randn(n, 4, generator=g, dtype=DT)
    scales = 0.04 + 0.08 * torch.rand(n, 3, generator=g, dtype=DT)
    opac = 0.2 + 0.6 * torch.rand(n, generator=g, dtype=DT)
    sh = 0.3 * torch.randn(n, 4, 3, generator=g, dtype=DT)
    vms = torch.eye(4, dtype=DT).repeat(C, 1, 1)
    vms[1, :3, 3] = torch.tensor([0.1, -0.05, 0.1], dtype=DT)
    th = 0.1
    vms[1, :3, :3] = torch.tensor([[math.cos(th), 0, math.sin(th)], [0, 1, 0], [-math.sin(th), 0, math.cos(th)]],
                                  dtype=DT)
    K = torch.tensor([[20.0, 0, 10], [0, 20.0, 8], [0, 0, 1]], dtype=DT).repeat(C, 1, 1)
    bg = torch.rand(C, 3, generator=g, dtype=DT)
    return means, quats, scales, opac, sh, vms, K, bg


def test_finite_difference_gradients_all_parameters():
    means, quats, scales, opac, sh, vms, K, bg = _random_scene()
    W, H = 20, 16

    def f(means, quats, scales, opac, sh, vms, bg):
        img, alpha, _ = rasterization(means, quats, scales, opac, sh, vms, K, W, H, sh_degree=1,
                                      backgrounds=bg, render_mode="RGB+ED", backend="reference")
        return img, alpha

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, sh, vms, bg)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_means2d_grad_is_retained():
    means, quats, scales, opac, sh, vms, K, bg = _random_scene()
    means.requires_grad_(True)
    img, _, meta = rasterization(means, quats, scales, opac, sh, vms, K, 20, 16, sh_degree=1, backend="reference")
    img.sum().backward()
    g = meta["means2d"].grad
    assert g is not None and g.shape == (2, 8, 2) and g.abs().sum() > 0


def test_depth_modes():
    means, quats, scales, opac, sh, vms, K, bg = _random_scene()
    d, a, _ = rasterization(means, quats, scales, opac, sh, vms, K, 20, 16, sh_degree=1, render_mode="D",
                            backend="reference")
    ed, _, _ = rasterization(means, quats, scales, opac, sh, vms, K, 20, 16, sh_degree=1, render_mode="ED",
                             backend="reference")
    rgbed, _, _ = rasterization(means, quats, scales, opac, sh, vms, K, 20, 16, sh_degree=1,
                                render_mode="RGB+ED", backend="reference")
    rgb, _, _ = rasterization(means, quats, scales, opac, sh, vms, K, 20, 16, sh_degree=1, backend="reference")
    assert d.shape[-1] == 1 and rgbed.shape[-1] == 4
    m = a[..., 0] > 0.5
    assert torch.allclose(ed[m], (d / a)[m])
    # expected depth lies within the depth range of the Gaussians where they are opaque
    assert ed[m].min() > 1.5 and ed[m].max() < 2.5
    assert torch.allclose(rgbed[..., :3], rgb) and torch.allclose(rgbed[..., 3:], ed)


def test_projection_matches_camera_projection():
    from splattwin.capture.camera import Camera, look_at

    cam = Camera.from_fov(1.0, 64, 48, T_world_cam=look_at([0.5, -0.4, 0.6], [0, 0, 0]))
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 0.02]], dtype=DT)
    out = ref.project(pts, torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=DT), torch.full((2, 3), 0.01, dtype=DT),
                      torch.tensor(cam.T_cam_world)[None], torch.tensor(cam.K)[None], 64, 48)
    uv, z = cam.project(pts.numpy())
    assert torch.allclose(out["means2d"][0], torch.tensor(uv)) and torch.allclose(out["depths"][0], torch.tensor(z))
