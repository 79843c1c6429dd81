"""CPU rasterizer (numba kernels, hand-written backward) against the plain-PyTorch reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from splattwin.errors import InputError
from splattwin.splat.rasterize import rasterization, resolve_backend

DT = torch.float64
NAMES = ["means", "quats", "scales", "opacities", "colors", "viewmats", "backgrounds"]


def _scene(n=150, C=2, seed=0, W=40, H=30, K_sh=9, f=40.0, opac_min=0.2, opac_span=0.79, th=0.1, pp=(0.5, 0.5),
           fy_scale=1.0):
    """Random Gaussians in front of C cameras (the second rotated by th rad), float64. Opacities uniform in
    [opac_min, opac_min + opac_span]; principal point at pp * (W, H); fy = fy_scale * f."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=DT) - 0.5) * torch.tensor([1.6, 1.2, 0.6], dtype=DT)
    means[:, 2] += 2.0
    quats = torch.randn(n, 4, generator=g, dtype=DT)
    scales = 0.02 + 0.08 * torch.rand(n, 3, generator=g, dtype=DT)
    opac = opac_min + opac_span * torch.rand(n, generator=g, dtype=DT)
    sh = 0.3 * torch.randn(n, K_sh, 3, generator=g, dtype=DT)
    vms = torch.eye(4, dtype=DT).repeat(C, 1, 1)
    if C > 1:
        vms[1, :3, :3] = torch.tensor([[math.cos(th), 0, math.sin(th)], [0, 1, 0], [-math.sin(th), 0, math.cos(th)]],
                                      dtype=DT)
        vms[1, :3, 3] = torch.tensor([0.1, -0.05, 0.1], dtype=DT)
    K = torch.tensor([[f, 0, pp[0] * W], [0, fy_scale * f, pp[1] * H], [0, 0, 1]], dtype=DT).repeat(C, 1, 1)
    bg = torch.rand(C, 3, generator=g, dtype=DT)
    return [means, quats, scales, opac, sh, vms, bg], K


def _run(backend, inputs, K, W, H, **kw):
    xs = [t.clone().requires_grad_(True) for t in inputs]
    bg = xs[6] if kw.pop("use_bg", True) else None
    img, alpha, meta = rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], K, W, H, backgrounds=bg,
                                     backend=backend, **kw)
    w = torch.sin(torch.arange(img.numel(), dtype=DT) * 0.37).reshape(img.shape)
    loss = (img * w).sum() + 0.3 * (alpha * torch.cos(torch.arange(alpha.numel(), dtype=DT)).reshape(alpha.shape)).sum()
    loss.backward()
    grads = {n: x.grad for n, x in zip(NAMES, xs)}
    grads["means2d"] = meta["means2d"].grad
    return img.detach(), alpha.detach(), meta, grads


def _assert_close_grads(gr, gc, rtol=3e-4):
    for name, a in gr.items():
        b = gc[name]
        if a is None:
            assert b is None or b.abs().max() == 0, name
            continue
        scale = a.abs().max().item()
        err = (a - b).abs().max().item()
        assert err <= rtol * scale + 1e-5, f"{name}: max err {err:.3g} vs scale {scale:.3g}"


@pytest.mark.parametrize("mode,deg", [("RGB+ED", 2), ("RGB", 3)])
def test_cpu_matches_reference_images_and_all_gradients(mode, deg):
    inputs, K = _scene(K_sh=(deg + 1) ** 2, seed=deg)
    ir, ar, mr, gr = _run("reference", inputs, K, 40, 30, sh_degree=deg, render_mode=mode)
    ic, ac, mc, gc = _run("cpu", inputs, K, 40, 30, sh_degree=deg, render_mode=mode)
    assert ic.shape == ir.shape == (2, 30, 40, 4 if mode == "RGB+ED" else 3)
    assert (mr["radii"] == mc["radii"]).all() and mc["radii"].dtype == torch.int32
    assert torch.allclose(mr["depths"], mc["depths"], atol=1e-5)
    assert torch.allclose(ir, ic, atol=5e-5) and torch.allclose(ar, ac, atol=5e-6)
    assert ar.max() > 0.9  # the scene is not trivially empty
    _assert_close_grads(gr, gc)
    for name in NAMES:  # every parameter actually receives gradient
        assert gc[name].abs().max() > 0, name


def test_cpu_edge_cases_behind_offscreen_degenerate_and_empty_tiles():
    # A large image where the Gaussians sit in one corner (most tiles empty), plus Gaussians behind the
    # camera, inside the near plane, partly off-screen and with degenerate (near-zero) scales.
    inputs, K = _scene(n=40, C=1, seed=3, W=96, H=64, K_sh=1, f=60.0)
    means, quats, scales = inputs[0], inputs[1], inputs[2]
    means[:, :2] = means[:, :2] * 0.3 - 0.4  # corner cluster
    means[0] = torch.tensor([0.0, 0.0, -1.0])  # behind
    means[1] = torch.tensor([0.0, 0.0, 0.005])  # inside the near plane
    means[2] = torch.tensor([1.55, 0.0, 2.0])  # partly off the right edge
    means[3] = torch.tensor([-0.2, -0.2, 1.9])
    scales[3] = torch.tensor([1e-9, 1e-9, 1e-9])  # degenerate: only the 0.3 px low-pass remains
    scales[4] = torch.tensor([0.05, 1e-9, 0.05])  # flat
    ir, ar, mr, gr = _run("reference", inputs, K, 96, 64, sh_degree=0)
    ic, ac, mc, gc = _run("cpu", inputs, K, 96, 64, sh_degree=0)
    vis = mc["visibility"][0]
    assert not vis[0] and not vis[1] and vis[2] and vis[3]
    assert (mr["radii"] == mc["radii"]).all()
    assert torch.allclose(ir, ic, atol=5e-5) and torch.allclose(ar, ac, atol=5e-6)
    assert ac[0, 40:, 60:].max() == 0  # far corner: empty tiles
    assert ac[0, :, 90:].max() > 0.05  # off-screen Gaussian still draws its visible part
    _assert_close_grads(gr, gc)
    assert torch.all(gc["means"][:2] == 0) and torch.all(gc["opacities"][:2] == 0)
    assert torch.isfinite(gc["scales"]).all() and torch.isfinite(gc["quats"]).all()


def test_huge_gaussians_saturate_their_radius_and_still_cover_the_image():
    # 3-sigma radii beyond int32 (2.4e10 px here: a 1e8 m scale, as in an untrusted PLY, or a Gaussian at the
    # near plane) used to wrap round (reference -2147483648, CPU -1769801390): neither backend drew the
    # Gaussian covering the image, and visibility said it was off-screen.
    W, H = 40, 30
    K = torch.tensor([[[40.0, 0, 20.0], [0, 40.0, 15.0], [0, 0, 1.0]]], dtype=DT)
    means = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.6]], dtype=DT)
    scales = torch.tensor([[1e8, 1e8, 1e8], [1e6, 1e6, 1e6]], dtype=DT)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=DT)
    opac = torch.tensor([0.5, 0.8], dtype=DT)
    cols = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=DT)
    out = {}
    for be in ("reference", "cpu"):
        img, alpha, meta = rasterization(means, quats, scales, opac, cols, torch.eye(4, dtype=DT)[None], K, W, H,
                                         backend=be)
        r = meta["radii"][0].tolist()  # the first saturates at reference.RADIUS_MAX
        assert r[0] == 2 ** 30 and abs(r[1] - 2e8) <= 20, (be, r)  # saturated; the other (2e8: float32 on the CPU) as is
        assert meta["visibility"][0].all(), be
        out[be] = img
        # front (z 0.5, opacity 0.5) over the back (0.8): alpha 1 - 0.5 * 0.2 = 0.9 on every pixel
        assert torch.allclose(alpha, torch.full_like(alpha, 0.9), atol=1e-6), be
        assert torch.allclose(img[0], torch.tensor([0.5, 0.4, 0.0], dtype=DT).expand(H, W, 3), atol=1e-6), be
    assert torch.allclose(out["reference"], out["cpu"], atol=1e-6)


def test_non_finite_opacities_are_never_drawn_on_either_backend():
    # A NaN opacity was binned on the CPU (its alpha tests all fail, so it drew nothing) and came back as a NaN
    # opacity gradient; on the reference it made the gradients of every Gaussian NaN. An infinite one drew
    # alpha 0.99 over its whole box on the reference and nothing on the CPU. Now both: not drawn, zero
    # gradients - the same render and gradients as without that Gaussian.
    inputs, K = _scene(n=40, C=1, seed=5, K_sh=4)
    inputs[0][:, :2] *= 0.3  # overlapping: the Gaussian sits among the others
    keep = torch.arange(40) >= 2
    without = [t[keep] if i < 5 else t for i, t in enumerate(inputs)]
    for be in ("reference", "cpu"):
        i0, a0, _, g0 = _run(be, without, K, 40, 30, sh_degree=1)
        bad = [t.clone() for t in inputs]
        bad[3][:2] = torch.tensor([math.nan, math.inf], dtype=DT)
        i1, a1, m1, g1 = _run(be, bad, K, 40, 30, sh_degree=1)
        assert torch.allclose(i1, i0, atol=1e-6) and torch.allclose(a1, a0, atol=1e-6), be
        for n in NAMES:
            assert torch.isfinite(g1[n]).all(), (be, n)
            g = g1[n][keep] if n not in ("viewmats", "backgrounds") else g1[n]
            assert torch.allclose(g, g0[n], rtol=1e-5, atol=1e-5), (be, n)
        assert torch.all(g1["opacities"][:2] == 0) and torch.all(g1["colors"][:2] == 0), be
    assert i0.max() > 0.3  # the scene is not empty


def test_zero_quaternions_render_as_identity_on_both_backends():
    # A zero quaternion is normalised with the norm clamped at 1e-12 (torch's F.normalize, as gsplat's
    # PyTorch implementation): the identity rotation, on both backends, forward and backward.
    inputs, K = _scene(n=40, C=2, seed=4, K_sh=1)
    inputs[1][:3] = 0.0
    ir, ar, mr, gr = _run("reference", inputs, K, 40, 30, sh_degree=0)
    ic, ac, mc, gc = _run("cpu", inputs, K, 40, 30, sh_degree=0)
    assert mc["visibility"][:, :3].all() and (mr["radii"] == mc["radii"]).all()
    assert torch.allclose(ir, ic, atol=5e-5) and torch.allclose(ar, ac, atol=5e-6)
    ident = inputs[1].clone()
    ident[:3] = torch.tensor([1.0, 0, 0, 0], dtype=DT)
    i1, a1, _, _ = _run("reference", [ident if i == 1 else t for i, t in enumerate(inputs)], K, 40, 30, sh_degree=0)
    assert torch.allclose(i1, ir, atol=1e-12)  # zero quaternion == identity
    _assert_close_grads(gr, gc)
    # R(q / eps) is quadratic in q: at q = 0 its gradient is exactly zero (finite, not NaN)
    assert torch.all(gc["quats"][:3] == 0) and torch.all(gr["quats"][:3] == 0)
    assert torch.isfinite(gc["quats"]).all() and gc["quats"][3:].abs().max() > 0


def test_cpu_single_gaussian_analytic_centre_value():
    W, H, f = 32, 32, 100.0
    K = torch.tensor([[[f, 0, 16.5], [0, f, 16.5], [0, 0, 1.0]]])  # mean projects onto pixel (16,16) centre
    means = torch.tensor([[0.0, 0.0, 2.0]])
    img, alpha, meta = rasterization(means, torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[0.04, 0.04, 0.04]]),
                                     torch.tensor([0.7]), torch.tensor([[0.2, 0.4, 0.6]]), torch.eye(4)[None], K,
                                     W, H, backend="cpu")
    assert abs(alpha[0, 16, 16, 0].item() - 0.7) < 1e-6
    assert torch.allclose(img[0, 16, 16], torch.tensor([0.14, 0.28, 0.42]), atol=1e-6)
    var = (f * 0.04 / 2) ** 2 + 0.3
    assert abs(alpha[0, 16, 17, 0].item() - 0.7 * math.exp(-0.5 / var)) < 1e-6
    assert meta["radii"][0, 0].item() == math.ceil(3 * math.sqrt(var))


def test_antialiased_mode_cpu_matches_reference_and_gradients():
    # Per-camera opacities (opacity x compensation) through both backends, two cameras, every gradient.
    inputs, K = _scene(K_sh=4, seed=5)
    inputs[2] = inputs[2] * 0.2  # small Gaussians: compensation well below 1
    ir, ar, _, gr = _run("reference", inputs, K, 40, 30, sh_degree=1, rasterize_mode="antialiased")
    ic, ac, _, gc = _run("cpu", inputs, K, 40, 30, sh_degree=1, rasterize_mode="antialiased")
    assert torch.allclose(ir, ic, atol=5e-5) and torch.allclose(ar, ac, atol=5e-6)
    _assert_close_grads(gr, gc)
    ic0, ac0, _, _ = _run("cpu", inputs, K, 40, 30, sh_degree=1)
    assert ac.sum() < 0.9 * ac0.sum()  # the classic mode over-draws sub-pixel Gaussians


def test_antialiased_mode_preserves_a_small_gaussians_footprint():
    # Integrated alpha of an isotropic Gaussian of screen std s px: op * 2 pi s^2 (the true footprint)
    # with "antialiased"; op * 2 pi (s^2 + eps2d) with "classic" (the low-pass widens it at full opacity).
    W = H = 48
    f, z = 100.0, 2.0
    K = torch.tensor([[[f, 0, 24.0], [0, f, 24.0], [0, 0, 1.0]]], dtype=DT)
    op = 0.5  # alpha stays far from the 0.99 clamp; the 1/255 cut-off loses < 2 % of the mass
    for s_px in (0.3, 0.6, 1.5):
        sc = torch.full((1, 3), s_px * z / f, dtype=DT)
        args = (torch.tensor([[0.0, 0.0, z]], dtype=DT), torch.tensor([[1.0, 0, 0, 0]], dtype=DT), sc,
                torch.tensor([op], dtype=DT), torch.ones(1, 1, dtype=DT), torch.eye(4, dtype=DT)[None], K, W, H)
        # eps2d 0.3 in both: sampled at pixel centres, a narrower filtered Gaussian would alias the sum
        _, a_aa, _ = rasterization(*args, backend="cpu", rasterize_mode="antialiased", eps2d=0.3)
        _, a_cl, _ = rasterization(*args, backend="cpu")
        # 3-sigma truncation and pixel sampling: within a few per cent
        assert a_aa.sum().item() == pytest.approx(op * 2 * math.pi * s_px**2, rel=0.04)
        assert a_cl.sum().item() == pytest.approx(op * 2 * math.pi * (s_px**2 + 0.3), rel=0.04)


def test_default_low_pass_follows_the_mode():
    """eps2d None: 3DGS's 0.3 dilation for classic, Mip-Splatting's 0.1 (about one pixel's box filter,
    variance 1/12 px^2) for antialiased; an explicit eps2d is used as given. A Gaussian of screen std
    1.5 px (well sampled): its rendered peak is op * s^2 / (s^2 + eps2d) antialiased."""
    from splattwin.splat.rasterize import DEFAULT_EPS2D

    assert DEFAULT_EPS2D == {"classic": 0.3, "antialiased": 0.1}
    W = H = 32
    f, z, s_px, op = 100.0, 2.0, 1.5, 0.5
    K = torch.tensor([[[f, 0, 16.0], [0, f, 16.0], [0, 0, 1.0]]], dtype=DT)
    args = (torch.tensor([[0.0, 0.0, z]], dtype=DT), torch.tensor([[1.0, 0, 0, 0]], dtype=DT),
            torch.full((1, 3), s_px * z / f, dtype=DT), torch.tensor([op], dtype=DT), torch.ones(1, 1, dtype=DT),
            torch.eye(4, dtype=DT)[None], K, W, H)
    for mode in ("classic", "antialiased"):
        _, a_def, _ = rasterization(*args, backend="cpu", rasterize_mode=mode)
        for eps in (0.1, 0.3):
            _, a_eps, _ = rasterization(*args, backend="cpu", rasterize_mode=mode, eps2d=eps)
            same = torch.equal(a_def, a_eps)
            assert same == (eps == DEFAULT_EPS2D[mode]), (mode, eps)
    _, a_aa, _ = rasterization(*args, backend="cpu", rasterize_mode="antialiased")
    peak = a_aa.max().item()  # the pixel at the centre (16, 16) is 0.5 px from the mean: exp(-0.25 / 2v)
    v = s_px**2 + 0.1
    assert peak == pytest.approx(op * math.sqrt(s_px**4 / v**2) * math.exp(-0.25 / (2 * v)) ** 2, rel=1e-3)


def test_antialias_compensation_formula():
    from splattwin.splat.rasterize import antialias_compensation

    g = torch.Generator().manual_seed(0)
    A = torch.randn(20, 2, 2, generator=g, dtype=DT)
    S = A @ A.transpose(1, 2)
    Sd = S + 0.3 * torch.eye(2, dtype=DT)
    Q = torch.linalg.inv(Sd)
    conics = torch.stack([Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 1]], -1)
    want = torch.sqrt(torch.linalg.det(S) / torch.linalg.det(Sd))
    assert torch.allclose(antialias_compensation(conics, 0.3), want, atol=1e-6)
    assert antialias_compensation(torch.zeros(1, 3, dtype=DT), 0.3).item() == 1.0  # culled


def test_cpu_multichannel_features_per_camera_and_depth_modes():
    inputs, K = _scene(n=80, C=2, seed=5, K_sh=1)
    means, quats, scales, opac, _, vms, _ = inputs
    feats = torch.rand(2, 80, 7, generator=torch.Generator().manual_seed(0), dtype=DT)  # [C,N,D], D = 7
    args = (means, quats, scales, opac, feats, vms, K, 40, 30)
    for mode in ("RGB", "D", "ED", "RGB+D"):
        r, a, _ = rasterization(*args, render_mode=mode, backend="reference")
        c, ac, _ = rasterization(*args, render_mode=mode, backend="cpu")
        assert c.shape == r.shape and c.shape[-1] == {"RGB": 7, "D": 1, "ED": 1, "RGB+D": 8}[mode]
        assert torch.allclose(r, c, atol=5e-5), mode
    # gradients of per-camera features and opacities through the D-channel path
    grads = []
    for be in ("reference", "cpu"):
        f = feats.clone().requires_grad_(True)
        o = opac.clone().requires_grad_(True)
        img, a, _ = rasterization(means, quats, scales, o, f, vms, K, 40, 30, render_mode="RGB+D", backend=be)
        (img * torch.cos(torch.arange(img.numel(), dtype=DT)).reshape(img.shape)).sum().backward()
        grads.append({"colors": f.grad, "opacities": o.grad})
    _assert_close_grads(*grads)
    # one-hot labels: channel sums equal alpha
    onehot = torch.nn.functional.one_hot(torch.arange(80) % 5, 5).to(DT)
    lab, a, _ = rasterization(means, quats, scales, opac, onehot, vms, K, 40, 30, backend="cpu")
    assert torch.allclose(lab.sum(-1, keepdim=True), a, atol=1e-6)


def test_cpu_is_deterministic():
    inputs, K = _scene(n=100, C=1, seed=7, K_sh=4)
    a = _run("cpu", inputs, K, 40, 30, sh_degree=1)
    b = _run("cpu", inputs, K, 40, 30, sh_degree=1)
    assert torch.equal(a[0], b[0])
    for n in NAMES:
        assert torch.equal(a[3][n], b[3][n]), n


def test_float32_inputs_and_empty_scene():
    inputs, K = _scene(n=30, C=1, seed=8, K_sh=1)
    xs = [t.float() for t in inputs]
    img, alpha, meta = rasterization(*xs[:6], K.float(), 40, 30, sh_degree=0, backend="cpu")
    assert img.dtype == torch.float32 and meta["means2d"].dtype == torch.float32
    z = torch.zeros(0, 3)
    img, alpha, meta = rasterization(z, torch.zeros(0, 4), z, torch.zeros(0), torch.zeros(0, 3), xs[5], K.float(),
                                     40, 30, backend="cpu")
    assert img.shape == (1, 30, 40, 3) and alpha.abs().max() == 0


def test_mixed_dtypes_are_cast_to_the_means_dtype_on_every_backend():
    # float64 Ks / viewmats / backgrounds with float32 Gaussians: the same float32 render on both backends
    # (the reference used to raise "expected scalar type Double but found Float"), gradients in each
    # input's own dtype.
    inputs, K = _scene(n=30, C=1, seed=9, K_sh=1)
    xs = [t.float() if i not in (5, 6) else t for i, t in enumerate(inputs)]  # viewmats, bg stay float64
    out = {}
    for be in ("reference", "cpu"):
        leaves = [t.clone().requires_grad_(True) for t in xs]
        img, alpha, meta = rasterization(*leaves[:6], K, 40, 30, sh_degree=0, backgrounds=leaves[6], backend=be)
        assert img.dtype == alpha.dtype == meta["means2d"].dtype == torch.float32, be
        img.sum().backward()
        assert leaves[5].grad.dtype == torch.float64 and leaves[0].grad.dtype == torch.float32, be
        out[be] = (img.detach(), leaves[5].grad)
    assert torch.allclose(out["reference"][0], out["cpu"][0], atol=5e-5)
    assert torch.allclose(out["reference"][1], out["cpu"][1], rtol=1e-3, atol=1e-3)
    img64, _, _ = rasterization(*[t.double() for t in xs[:6]], K.float(), 40, 30, sh_degree=0, backend="reference")
    assert img64.dtype == torch.float64


def test_near_and_far_planes_are_checked():
    # A near plane <= 0 let Gaussians behind the camera through: projected mirrored, and ordered by the CPU's
    # float32-bit-pattern depth sort (valid for positive depths only) differently from the reference
    # (0.04 apart on this scene); near >= far silently rendered nothing.
    inputs, K = _scene(n=30, C=1, seed=50, K_sh=1)
    inputs[0][:15, 2] -= 2.6  # behind the camera
    args = (*inputs[:6], K, 40, 30)
    for near, far, what in [(-5.0, 1e10, "near_plane"), (0.0, 1e10, "near_plane"), (math.nan, 1e10, "near_plane"),
                            (math.inf, math.inf, "near_plane"), (3.0, 1.0, "far_plane"), (0.5, 0.5, "far_plane"),
                            (0.5, math.nan, "far_plane")]:
        for be in ("reference", "cpu"):
            with pytest.raises(ValueError, match=what):
                rasterization(*args, sh_degree=0, backend=be, near_plane=near, far_plane=far)
    img_r, _, _ = rasterization(*args, sh_degree=0, backend="reference", near_plane=1e-6, far_plane=math.inf)
    img_c, _, _ = rasterization(*args, sh_degree=0, backend="cpu", near_plane=1e-6, far_plane=math.inf)
    assert torch.allclose(img_r, img_c, atol=5e-5) and img_r.max() > 0.3


def test_rasterization_docstring_states_the_cpu_precision():
    doc = " ".join(rasterization.__doc__.split())
    assert "float32 whatever the input dtype" in doc and 'backend="reference"' in doc and "gradcheck" in doc


def test_backend_dispatch():
    if not torch.cuda.is_available():
        assert resolve_backend("auto") == "cpu"
        with pytest.raises(InputError, match="cuda"):
            resolve_backend("cuda")
        inputs, K = _scene(n=5, C=1)
        with pytest.raises(InputError, match="CUDA"):
            rasterization(*inputs[:6], K, 40, 30, sh_degree=2, backend="cuda")
    with pytest.raises(InputError, match="unknown rasterizer backend"):
        resolve_backend("metal")
    assert resolve_backend("reference") == "reference"


def test_bad_shapes_raise_clear_errors():
    inputs, K = _scene(n=5, C=1)
    with pytest.raises(ValueError, match="quats"):
        rasterization(inputs[0], inputs[1][:3], *inputs[2:6], K, 40, 30, sh_degree=2)
    with pytest.raises(ValueError, match="sh_degree"):
        rasterization(*inputs[:6], K, 40, 30, sh_degree=3)  # K = 9 coefficients: degree 2 at most
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(*inputs[:6], K, 40, 30, sh_degree=2, render_mode="XYZ")


def test_render_helpers_depth_and_rgb():
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.rendering import render_depth, render_features, render_rgb

    # a dense opaque sheet of Gaussians at z = 1.5 in front of a camera at the origin
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, 25), np.linspace(-0.2, 0.2, 17))
    n = xs.size
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n, 1.5)], 1)
    sh = np.zeros((n, 1, 3))
    sh[:, 0, :] = (np.array([0.9, 0.0, 0.0]) - 0.5) / 0.28209479177387814  # red 0.9
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.02),
                  opacities=np.full(n, 0.95), sh=sh)
    cam = Camera.from_fov(0.6, 48, 32)
    d = render_depth(g, cam)
    assert d.shape == (32, 48)
    centre = d[8:24, 12:36]
    assert np.all(np.isfinite(centre)) and np.allclose(centre, 1.5, atol=1e-3)
    assert np.isinf(d[0, 0]) or d[0, 0] == pytest.approx(1.5, abs=1e-3)
    far = Camera.from_fov(0.6, 48, 32, T_world_cam=np.array([[1, 0, 0, 5.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    assert np.all(np.isinf(render_depth(g, far)))  # nothing in view
    rgb = render_rgb(g, cam, background=(0.0, 0.0, 1.0))
    assert rgb.shape == (32, 48, 3) and abs(rgb[16, 24, 0] - 0.9) < 0.01 and rgb[16, 24, 2] < 0.01
    feats, alpha = render_features(g, cam, np.ones((n, 2)))
    assert np.allclose(feats[..., 0], alpha, atol=1e-6)


def _sheet(n_side=(25, 17), z=1.5, scale=0.02):
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians

    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, n_side[0]), np.linspace(-0.2, 0.2, n_side[1]))
    n = xs.size
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n, z)], 1)
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), scale),
                  opacities=np.full(n, 0.95), sh=np.full((n, 1, 3), 0.5))
    return g, Camera.from_fov(0.6, 48, 32)


def test_render_helper_takes_every_rasterizer_mode_and_refuses_others():
    from splattwin.splat.rendering import render

    g, cam = _sheet()
    ed, alpha = render(g, cam, mode="ED")
    d, _ = render(g, cam, mode="D")
    rgbd, _ = render(g, cam, mode="RGB+D")
    rgb, _ = render(g, cam, mode="RGB")
    assert d.shape == ed.shape == (32, 48, 1) and rgbd.shape == (32, 48, 4)
    np.testing.assert_allclose(d[..., 0], ed[..., 0] * alpha, atol=1e-5)  # D = sum w z = ED * alpha
    np.testing.assert_allclose(rgbd[..., 3], d[..., 0], atol=1e-6)
    np.testing.assert_array_equal(rgbd[..., :3], rgb)
    for bad in ("ed", "depth", "RGBD"):
        with pytest.raises(ValueError, match=r"render mode must be one of RGB, D, ED, RGB\+D, RGB\+ED"):
            render(g, cam, mode=bad)


def test_render_background_must_be_a_0_1_colour():
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.rendering import render, render_rgb

    g, cam = _sheet()
    for bad in ((255, 255, 255), (0.0, 0.0, 1.5), (-0.1, 0, 0)):
        with pytest.raises(ValueError, match=r"background colour must be in \[0, 1\]"):
            render(g, cam, background=bad)
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            render_rgb(g, cam, background=bad)
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            render(Gaussians.empty(), cam, background=bad)
    with pytest.raises(ValueError, match="3 values"):
        render(g, cam, background=(0.0, 1.0))
    img, _ = render(Gaussians.empty(), cam, background=(0.0, 0.5, 1.0))
    assert np.all(img[5, 5] == np.float32([0.0, 0.5, 1.0]))
    # features are not colours: any background value
    f, _ = render(g, cam, colors=np.full((len(g), 2), 7.0), background=(-3.0, 40.0))
    assert f.shape == (32, 48, 2) and np.isfinite(f).all()


def test_render_helpers_pass_the_raster_mode_through():
    from splattwin.splat.rendering import render, render_depth, render_features, render_rgbd

    g, cam = _sheet(n_side=(9, 7), scale=0.002)  # sub-pixel splats: antialiased draws them fainter
    kw = dict(rasterize_mode="antialiased", eps2d=0.2)
    img_aa, a_aa = render(g, cam, mode="RGB+ED", **kw)
    img_cl, a_cl = render(g, cam, mode="RGB+ED")
    assert a_aa.sum() < 0.9 * a_cl.sum()
    rgb, dep, a = render_rgbd(g, cam, **kw)
    np.testing.assert_array_equal(a, a_aa)
    np.testing.assert_array_equal(rgb, img_aa[..., :3])
    feats, fa = render_features(g, cam, np.ones((len(g), 2)), **kw)
    np.testing.assert_array_equal(fa, a_aa)
    d_aa = render_depth(g, cam, min_alpha=0.0, **kw)
    d_ed, _ = render(g, cam, mode="ED", **kw)
    np.testing.assert_array_equal(d_aa, d_ed[..., 0])
    assert not np.array_equal(render_features(g, cam, np.ones((len(g), 2)))[1], fa)  # classic by default


def test_pixel_boxes_shrink_to_the_visible_ellipse_of_faint_gaussians():
    # A faint Gaussian (alpha >= 1/255 only within ~1.4 sigma) is binned to fewer tiles than its
    # 3-sigma box, and draws the same image as the reference (which uses the full box).
    from splattwin.splat._cpu import kernels as K_

    W = H = 96
    K = torch.tensor([[[80.0, 0, 48.0], [0, 80.0, 48.0], [0, 0, 1.0]]], dtype=DT)
    args = (torch.tensor([[0.0, 0.0, 2.0]], dtype=DT), torch.tensor([[1.0, 0, 0, 0]], dtype=DT),
            torch.tensor([[0.3, 0.3, 0.3]], dtype=DT), torch.tensor([0.02], dtype=DT),
            torch.ones(1, 1, dtype=DT), torch.eye(4, dtype=DT)[None], K, W, H)
    img_c, a_c, meta = rasterization(*args, backend="cpu")
    img_r, a_r, _ = rasterization(*args, backend="reference")
    assert torch.allclose(a_c, a_r, atol=1e-7) and a_c.max() > 0.015
    m2 = meta["means2d"][0].detach().numpy().astype(np.float32)
    co = meta["conics"][0].detach().numpy().astype(np.float32)
    ext = np.stack([meta["radii"][0].numpy()] * 2, -1).astype(np.int32)
    rec, nt = np.empty((1, K_.R_COL + 1), np.float32), np.empty(1, np.int64)
    K_.make_records(m2, co, np.ones((1, 1), np.float32), np.array([0.02], np.float32), ext, W, H, rec, nt)
    faint_tiles, faint_box = int(nt[0]), rec[0, K_.R_X0:K_.R_Y1 + 1].copy()
    K_.make_records(m2, co, np.ones((1, 1), np.float32), np.array([0.99], np.float32), ext, W, H, rec, nt)
    assert faint_tiles < int(nt[0])
    assert faint_box[1] - faint_box[0] < rec[0, K_.R_X1] - rec[0, K_.R_X0]


def test_exp32_is_within_two_ulp_of_exp():
    # The compositing kernels' vectorisable float32 exp (kernels._exp32) over the range they use it on.
    from splattwin.splat._cpu import kernels as K_

    x = np.concatenate([np.linspace(float(K_.EXP_LO), 0.0, 20001), -np.geomspace(1e-8, 30, 2001)]).astype(np.float32)
    got = np.array([K_._exp32(v) for v in x], np.float64)
    want = np.exp(x.astype(np.float64))
    assert np.max(np.abs(got / want - 1)) < 2.5e-7  # float32 ulp: 6e-8 (relative, at worst 1.2e-7)
    assert K_._exp32(np.float32(0.0)) == 1.0


def test_lane_alphas_about_the_row_minimum_match_float64_for_thin_far_gaussians():
    # Lanes compute alpha in float32 as exp(log(op) - a/2 t^2 - sigma_min(row)) with float64 per-row terms
    # (kernels._row): no cancellation even for a needle whose a/2 dx^2, b dx dy, c/2 dy^2 are each ~1e4.
    from splattwin.splat._cpu import kernels as K_

    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(300):
        th = rng.uniform(0, np.pi)
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        cov = R @ np.diag([rng.uniform(0.3, 4e4), rng.uniform(0.3, 2.0)]) @ R.T  # up to 200 px long
        ca, cb, cc = np.linalg.inv(cov)[[0, 0, 1], [0, 1, 1]]
        op = rng.uniform(0.05, 1.0)
        u, v = rng.uniform(-200, 216, size=2)
        level, lop = K_._levels(op)
        b_a, hdet_a, ha, inv_ha = K_._pair_consts(ca, cb, cc)
        dx0 = u - 0.5
        IA, IB, EF, EL, CF, DY = (np.empty(16, np.float32) for _ in range(6))
        K_._rows(v, 0, 0, 15, dx0, b_a, hdet_a, inv_ha, level, lop, 0, 15, 16, IA, IB, EF, EL, CF, DY)
        for py in range(16):
            dx = dx0 - np.arange(16)
            dy = v - (py + 0.5)
            assert DY[py] == np.float32(dy)
            sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
            want = op * np.exp(-sigma)
            inside = want >= 1 / 255
            lanes = np.arange(16)
            assert np.all((lanes[inside] >= IA[py]) & (lanes[inside] <= IB[py]))  # the span holds every drawn lane
            if inside.any():
                tt = (EF[py] - lanes.astype(np.float32)) + EL[py]
                s = CF[py] - np.float32(ha) * tt * tt
                got = np.array([K_._exp32(np.float32(max(q, K_.EXP_LO))) for q in s], np.float64)
                worst = max(worst, float(np.max(np.abs(got[inside] / want[inside] - 1))))
    assert worst < 2e-5


def test_bin_tiles_lists_every_reached_tile_once_in_depth_order():
    # Random (often elongated) Gaussians on a 7 x 5 tile grid: each tile's packed list holds exactly the
    # Gaussians with a pixel centre of alpha >= 1/255 in that tile (up to the 1e-3 sigma margin of the
    # rectangle test), once each, in depth order (ties by index); box tiles the ellipse misses are skipped.
    from splattwin.splat._cpu import _tile_order, depth_order
    from splattwin.splat._cpu import kernels as K_

    rng = np.random.default_rng(3)
    N, W, H, D = 400, 100, 70, 2
    th_ = rng.uniform(0, np.pi, N)
    sd = np.stack([rng.uniform(0.5, 20, N), rng.uniform(0.5, 3, N)], 1)
    R = np.stack([np.cos(th_), -np.sin(th_), np.sin(th_), np.cos(th_)], 1).reshape(N, 2, 2)
    cov = R @ (sd[:, :, None] ** 2 * np.eye(2)) @ R.transpose(0, 2, 1)
    Q = np.linalg.inv(cov)
    conics = np.stack([Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 1]], 1).astype(np.float32)
    m2 = np.stack([rng.uniform(-10, W + 10, N), rng.uniform(-10, H + 10, N)], 1).astype(np.float32)
    op = rng.uniform(0.02, 1.0, N).astype(np.float32)
    ext = np.ceil(3 * np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1))).astype(np.int32)
    rec, ntiles = np.empty((N, K_.R_COL + D), np.float32), np.empty(N, np.int64)
    K_.make_records(m2, conics, rng.uniform(0, 1, (N, D)).astype(np.float32), op, ext, W, H, rec, ntiles)
    rec[:, K_.R_COL] = np.arange(N)  # a colour channel identifies the Gaussian in the packed copy
    depths = rng.uniform(0.5, 3.0, N).astype(np.float32)
    depths[1::50] = depths[0]  # ties: by index
    order = depth_order(depths, ntiles)
    assert len(order) == int((ntiles > 0).sum()) and np.all(np.diff(depths[order]) >= 0)
    tw, th = 7, 5
    M = int(ntiles.sum())
    tile_start, packed = np.empty(tw * th + 1, np.int64), np.empty((M, rec.shape[1]), np.float32)
    rank_off, rank_isect = np.empty(len(order) + 1, np.int64), np.empty(M, np.int64)
    K_.bin_tiles(order, rec, W, H, tile_start, packed, rank_off, rank_isect)
    assert tile_start[-1] < M  # box tiles the ellipses miss are left out
    # brute force: which tiles hold a pixel centre with sigma <= level (inside the pixel box), and which
    # hold any point of the box's continuous rectangle of pixel centres with sigma <= level + 0.05
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    fy, fx = np.mgrid[0:H * 4, 0:W * 4] / 4.0 + 0.5  # 1/4 px grid
    reached, near = {}, {}
    for g in range(N):
        x0, x1, y0, y1 = (int(rec[g, k]) for k in (K_.R_X0, K_.R_X1, K_.R_Y0, K_.R_Y1))
        a, b, c = (float(x) for x in conics[g])
        sigma = lambda px, py: (0.5 * (a * (m2[g, 0] - px) ** 2 + c * (m2[g, 1] - py) ** 2)  # noqa: E731
                                + b * (m2[g, 0] - px) * (m2[g, 1] - py))
        level = np.log(255 * op[g])
        inside = (sigma(xs, ys) <= level) & (xs >= x0) & (xs <= x1 + 1) & (ys >= y0) & (ys <= y1 + 1)
        reached[g] = {(int(y) // 16, int(x) // 16) for y, x in zip(*np.nonzero(inside))}
        box = (fx >= x0 + 0.5) & (fx <= x1 + 0.5) & (fy >= y0 + 0.5) & (fy <= y1 + 0.5)
        close = (sigma(fx, fy) <= level + 0.05) & box
        near[g] = {(int(y) // 16, int(x) // 16) for y, x in zip(fy[close], fx[close])}

    listed = {g: set() for g in range(N)}
    for t in range(tw * th):
        got = packed[tile_start[t]:tile_start[t + 1], K_.R_COL].astype(int)
        assert len(set(got)) == len(got)  # once each
        assert list(got) == [g for g in order if g in set(got)]  # depth order, ties by index
        for g in got:
            listed[g].add((t // tw, t % tw))
    for g in range(N):
        assert reached[g] <= listed[g]  # no tile with a drawn pixel is dropped
        x0, x1, y0, y1 = (int(rec[g, k]) // 16 for k in (K_.R_X0, K_.R_X1, K_.R_Y0, K_.R_Y1))
        if x0 != x1 and y0 != y1:  # boxes over several tile rows and columns: tested, within 0.05 of level
            assert listed[g] <= near[g], g
        elif ntiles[g]:  # one tile row or column: every tile of the box (an ellipse crosses them all)
            assert len(listed[g]) == ntiles[g]
    assert sum(ntiles[g] - len(listed[g]) for g in range(N)) > 50  # box tiles the ellipses miss: left out
    for j, g in enumerate(order):  # each Gaussian's pairs, for the gradient reduction
        rows = rank_isect[rank_off[j]:rank_off[j + 1]]
        assert len(rows) == len(listed[g]) and np.all(packed[rows, K_.R_COL] == g)
    assert sorted(_tile_order(7, 5)) == list(range(35))


def test_cpu_sharp_thin_gaussians_match_the_reference():
    # With a tiny low-pass (eps2d) thin needles have conics far sharper than one pixel: the float32 lanes must
    # still match the float64 reference. (Needles across the whole image are left out: their float32 conics
    # alone - as stored by every kernel, and by gsplat - put the alphas 1e-5 off the float64 reference.)
    g = torch.Generator().manual_seed(11)
    n, W, H = 60, 48, 40
    means = (torch.rand(n, 3, generator=g, dtype=DT) - 0.5) * torch.tensor([1.2, 1.0, 0.2], dtype=DT)
    means[:, 2] += 2.0
    quats = torch.randn(n, 4, generator=g, dtype=DT)
    scales = torch.stack([0.15 * torch.rand(n, generator=g, dtype=DT) + 0.02,
                          torch.full((n,), 2e-4, dtype=DT), torch.full((n,), 2e-4, dtype=DT)], -1)
    scales[::2, 1:] = 0.03  # every other one round and soft
    opac = 0.3 + 0.69 * torch.rand(n, generator=g, dtype=DT)
    cols = torch.rand(n, 3, generator=g, dtype=DT)
    K = torch.tensor([[[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]], dtype=DT)
    inputs = [means, quats, scales, opac, cols, torch.eye(4, dtype=DT)[None], torch.rand(1, 3, dtype=DT)]
    ir, ar, mr, gr = _run("reference", inputs, K, W, H, eps2d=0.01)
    ic, ac, mc, gc = _run("cpu", inputs, K, W, H, eps2d=0.01)
    co = mc["conics"][0].detach()
    lam_max = 0.5 * (co[:, 0] + co[:, 2]) + torch.sqrt(0.25 * (co[:, 0] - co[:, 2]) ** 2 + co[:, 1] ** 2)
    assert (lam_max > 20).sum() > 10  # needles far sharper than a pixel
    assert ac.max() > 0.3
    assert torch.allclose(ir, ic, atol=5e-5) and torch.allclose(ar, ac, atol=5e-6)
    _assert_close_grads(gr, gc)


def test_non_tensor_inputs_and_fractional_sizes_raise_type_errors_naming_the_argument():
    """numpy inputs failed deep inside ("'numpy.ndarray' object has no attribute 'is_floating_point'") and a
    width of 40.7 px rendered 40 px (audit 10A L8)."""
    inputs, K = _scene(n=5, C=1)
    args = [*inputs[:4], inputs[4][:, 0], inputs[5], K]
    for i, name in enumerate(["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks"]):
        bad = list(args)
        bad[i] = bad[i].numpy()
        with pytest.raises(TypeError, match=rf"^{name} must be a Tensor \(torch.as_tensor .*\), got ndarray$"):
            rasterization(*bad, 40, 30)
    with pytest.raises(TypeError, match="backgrounds must be a Tensor .*, got list"):
        rasterization(*args, 40, 30, backgrounds=[[0.0, 0.0, 0.0]])
    for w, h in ((40.7, 30), (40, "30"), (True, 30)):
        with pytest.raises(TypeError, match="must be a whole number of pixels"):
            rasterization(*args, w, h)
    img, _, _ = rasterization(*args, np.int64(40), 30.0)   # whole numbers of any type are sizes
    assert img.shape == (1, 30, 40, 3)


def test_render_helpers_refuse_a_path_or_a_matrix_naming_the_argument(tmp_path):
    """render(path, camera) failed with "'str' object has no attribute 'sh_degree'" and render_depth(g, K)
    with "'numpy.ndarray' object has no attribute 'height'" (audit 10A L19)."""
    from splattwin.capture.camera import Camera
    from splattwin.splat import Gaussians, render, render_depth

    cam = Camera(np.array([[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]]), 40, 30)
    g = Gaussians.empty()
    with pytest.raises(TypeError, match=r"^gaussians must be a Gaussians .*Gaussians\.load_ply.*, got str$"):
        render(str(tmp_path / "splats.ply"), cam)
    with pytest.raises(TypeError, match=r"^camera must be a Camera .*, got ndarray$"):
        render_depth(g, cam.K)
    img, alpha = render(g, cam)
    assert img.shape == (30, 40, 3) and alpha.shape == (30, 40)
