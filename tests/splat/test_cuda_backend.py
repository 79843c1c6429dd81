"""The "cuda" backend (gsplat adapter) through gsplat's real front end with CPU-emulated kernels.

See tests/splat/conftest.py (`gsplat_on_cpu`) for what is emulated. These tests check our side of the
contract: argument conventions (wxyz quaternions, linear scales, opacities in [0,1], world->camera
viewmats, SH [N,K,3]), render modes, backgrounds, the meta dict (radii [C,N] int32, visibility, means2d
with its gradient) and every parameter gradient, against our reference rasterizer.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from splattwin.splat.rasterize import rasterization, resolve_backend

_spec = importlib.util.spec_from_file_location("_splat_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)
_spec = importlib.util.spec_from_file_location("_splat_raster_tests", Path(__file__).with_name("test_raster.py"))
raster_tests = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(raster_tests)

DT = raster_tests.DT
NAMES = raster_tests.NAMES


def _scene(n=120, seed=0, opac=(0.05, 0.35), **kw):
    # principal point off-centre and fx != fy: catch a swapped cx/cy or a transposed K
    return raster_tests._scene(n=n, seed=seed, opac_min=opac[0], opac_span=opac[1] - opac[0], th=0.15,
                               pp=(0.45, 0.55), fy_scale=1.1, **kw)


def _se3_grad(grad_viewmats: torch.Tensor, viewmats: torch.Tensor) -> torch.Tensor:
    """[C,6] derivative along the rigid motions exp(xi) @ viewmat (xi = translation, rotation) of a loss
    whose gradient w.r.t. the [C,4,4] matrices is `grad_viewmats`."""
    E = torch.zeros(6, 4, 4, dtype=viewmats.dtype)
    for k in range(3):
        E[k, k, 3] = 1.0
    for k, (i, j) in enumerate([(2, 1), (0, 2), (1, 0)]):
        E[3 + k, i, j], E[3 + k, j, i] = 1.0, -1.0
    return torch.einsum("cil,kij,cjl->ck", grad_viewmats, E, viewmats)


def _run(backend, inputs, K, W, H, use_bg=True, loss_seed=1, **kw):
    xs = [t.clone().requires_grad_(True) for t in inputs]
    img, alpha, meta = rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], K, W, H,
                                     backgrounds=xs[6] if use_bg else None, backend=backend, **kw)
    g = torch.Generator().manual_seed(loss_seed)
    loss = (img * torch.randn(img.shape, generator=g, dtype=img.dtype)).sum() \
        + (alpha * torch.randn(alpha.shape, generator=g, dtype=alpha.dtype)).sum()
    loss.backward()
    return img.detach(), alpha.detach(), meta, {n: x.grad for n, x in zip(NAMES, xs)}


@pytest.mark.parametrize("render_mode,sh_degree,use_bg", [("RGB", 2, True), ("RGB+ED", 3, True), ("D", None, False),
                                                          ("RGB", None, False)])
def test_matches_reference_images_and_gradients(gsplat_on_cpu, render_mode, sh_degree, use_bg):
    """With opacities <= 0.35 gsplat's opacity-aware extent and our 3-sigma box admit the same pixels and
    neither alpha clamp is reached, so the two backends must agree to rounding."""
    inputs, K = _scene(K_sh=16 if sh_degree == 3 else 9)
    if sh_degree is None:
        inputs[4] = torch.rand(inputs[0].shape[0], 3, dtype=DT, generator=torch.Generator().manual_seed(3))
    W, H = 40, 30
    cu = _run("cuda", inputs, K, W, H, use_bg=use_bg, render_mode=render_mode, sh_degree=sh_degree)
    ref = _run("reference", inputs, K, W, H, use_bg=use_bg, render_mode=render_mode, sh_degree=sh_degree)
    assert cu[2]["backend"] == "cuda" and ref[2]["backend"] == "reference"
    assert cu[0].shape == ref[0].shape and cu[1].shape == ref[1].shape
    assert ref[1].max() > 0.5  # a scene with real coverage, not an empty image
    torch.testing.assert_close(cu[0], ref[0], rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(cu[1], ref[1], rtol=1e-6, atol=1e-7)
    for name in NAMES:
        a, b = cu[3][name], ref[3][name]
        if (not use_bg and name == "backgrounds") or (render_mode == "D" and name == "colors"):
            assert a is None or a.abs().max() == 0, name  # not an input of this render
            continue
        assert b is not None and b.abs().max() > 0, name
        if name == "viewmats":  # gsplat differentiates campos = inverse(viewmat), we -R^T t: equal along
            a, b = _se3_grad(a, inputs[5]), _se3_grad(b, inputs[5])  # rigid motions, which is what poses use
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * b.abs().max().item(), msg=name)


def test_meta_contract(gsplat_on_cpu):
    inputs, K = _scene(seed=4)
    inputs[0][:5, 2] = -1.0  # behind the camera
    inputs[0][5:10, 0] = 40.0  # far off-screen
    cu = _run("cuda", inputs, K, 40, 30, sh_degree=2)
    ref = _run("reference", inputs, K, 40, 30, sh_degree=2)
    mc, mr = cu[2], ref[2]
    C, N = 2, inputs[0].shape[0]
    assert mc["radii"].shape == (C, N) and mc["radii"].dtype == torch.int32
    assert mc["visibility"].dtype == torch.bool and torch.equal(mc["visibility"], mc["radii"] > 0)
    assert not mc["visibility"][:, :10].any()
    # gsplat's opacity-aware extent is at most our 3 sigma: everything it draws, we draw
    assert (mr["visibility"] | ~mc["visibility"]).all() and mc["visibility"].sum() > 0.8 * mr["visibility"].sum()
    assert (mc["radii"] <= mr["radii"] + 1).all()
    # radii [C,N] = the larger of gsplat's per-axis radii ceil(extend sqrt(cov2d_ii)), opacity-aware extend
    a, b, c = mr["conics"].detach().unbind(-1)
    o = inputs[3][None].expand(C, N)
    ext = torch.clamp(torch.sqrt(2 * torch.log(o * 255)), max=3.33)
    r_axes = torch.ceil(ext[..., None] * torch.sqrt(torch.stack([c, a], -1) / (a * c - b * b)[..., None]))
    vis = mc["visibility"]
    torch.testing.assert_close(mc["radii"][vis].double(), r_axes.amax(-1)[vis], rtol=0, atol=0)
    both = mc["visibility"] & mr["visibility"]
    torch.testing.assert_close(mc["means2d"].detach()[both], mr["means2d"].detach()[both])
    torch.testing.assert_close(mc["depths"].detach()[both], mr["depths"].detach()[both])
    torch.testing.assert_close(mc["conics"].detach()[both], mr["conics"].detach()[both])
    # the densification gradient: dL/d(means2d) in pixels, retained on the returned tensor
    gc, gr = mc["means2d"].grad, mr["means2d"].grad
    assert gc is not None and gc.shape == (C, N, 2) and gc[both].abs().max() > 0
    torch.testing.assert_close(gc[both], gr[both], rtol=1e-5, atol=1e-9)
    assert mc["width"] == 40 and mc["height"] == 30 and mc["n_cameras"] == C


def test_typical_opacities_differ_only_by_gsplat_extent_and_clamp(gsplat_on_cpu):
    """High opacities: gsplat's documented differences (alpha clamp 0.999, opacity-aware extent) are small."""
    inputs, K = _scene(n=200, seed=5, opac=(0.2, 1.0))
    cu = _run("cuda", inputs, K, 40, 30, sh_degree=2)
    ref = _run("reference", inputs, K, 40, 30, sh_degree=2)
    diff = (cu[0] - ref[0]).abs()
    assert 0 < diff.max() < 0.02 and diff.mean() < 5e-4, (diff.mean().item(), diff.max().item())  # measured 4e-3, 3e-5
    for name in NAMES[:5]:
        cos = torch.nn.functional.cosine_similarity(cu[3][name].flatten(), ref[3][name].flatten(), dim=0)
        assert cos > 0.995, (name, cos.item())  # measured >= 0.9996


def test_antialiased_mode(gsplat_on_cpu):
    inputs, K = _scene(seed=6)
    inputs[2] = inputs[2] * 0.1  # sub-pixel Gaussians, where the compensation matters
    cu = _run("cuda", inputs, K, 40, 30, sh_degree=1, rasterize_mode="antialiased")
    ref = _run("reference", inputs, K, 40, 30, sh_degree=1, rasterize_mode="antialiased")
    classic = _run("reference", inputs, K, 40, 30, sh_degree=1)
    torch.testing.assert_close(cu[0], ref[0], rtol=1e-6, atol=1e-7)
    assert (classic[0] - ref[0]).abs().max() > 1e-2  # the mode changes the image, and both agree on how
    torch.testing.assert_close(cu[3]["scales"], ref[3]["scales"], rtol=1e-5,
                               atol=1e-6 * ref[3]["scales"].abs().max().item())


def test_gpu_without_gsplat_kernels_falls_back_with_reason(monkeypatch):
    """A CUDA device but gsplat's kernels unbuildable (this machine: gsplat installed, CPU-only torch):
    "auto" stays on the CPU and "cuda" says why, as a user error."""
    from splattwin.errors import InputError
    r = importlib.import_module("splattwin.splat.rasterize")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    reason = r.cuda_unavailable_reason()
    assert reason is not None and "gsplat's CUDA kernels" in reason
    assert resolve_backend("auto") == "cpu"
    with pytest.raises(InputError, match="gsplat's CUDA kernels"):
        resolve_backend("cuda")


def test_auto_picks_cuda_when_available(gsplat_on_cpu):
    assert resolve_backend("auto") == "cuda"
    inputs, K = _scene(n=20, C=1)
    img, alpha, meta = rasterization(*inputs[:6], K[:1], 40, 30, sh_degree=0)
    assert meta["backend"] == "cuda" and img.shape == (1, 30, 40, 3)
    _, _, meta = rasterization(*inputs[:6], K[:1], 40, 30, sh_degree=0, backend="cpu")  # overridable
    assert meta["backend"] == "cpu"


@pytest.mark.slow
def test_train_resume_and_eval_on_cuda_backend(gsplat_on_cpu, tmp_path):
    """`splattwin train/eval --device cuda`: the trainer's CUDA path (device placement, densification from
    gsplat's means2d gradients, checkpoints and resume, PLY) runs end to end and learns the scene about as
    well as the CPU backend."""
    from splattwin.cli import main
    from splattwin.splat.gaussians import Gaussians

    ds = helpers.make_dataset(tmp_path / "ds", n_train=6, n_heldout=2)
    args = ["--iters", "100", "--sh-degree", "1", "--init", "random", "--init-points", "300", "--checkpoint-every",
            "50", "--no-progress"]
    summaries = {}
    for dev in ("cuda", "cpu"):
        assert main(["train", str(ds), str(tmp_path / dev), "--device", dev, *args]) == 0
        summaries[dev] = json.loads((tmp_path / dev / "train.json").read_text())
        assert main(["eval", str(tmp_path / dev), "--dataset", str(ds), "--device", dev, "--no-progress"]) == 0
    cu, cpu = summaries["cuda"], summaries["cpu"]
    assert cu["backend"] == "cuda" and cpu["backend"] == "cpu"
    counts = [e["n"] for e in cu["history"]]
    assert max(counts) > 300 or min(counts) < 300  # densification ran on gsplat's gradients
    assert cu["train_psnr"] > cu["history"][0]["psnr"] + 5
    m = {d: json.loads((tmp_path / d / "eval" / "metrics.json").read_text())["mean_psnr"] for d in summaries}
    assert m["cuda"] > m["cpu"] - 2.0, m
    g = Gaussians.load_ply(tmp_path / "cuda" / "point_cloud.ply")
    assert len(g) == cu["gaussians"] and np.isfinite(g.means).all()
    # a finished run resumed from its checkpoint rewrites the same result
    assert main(["train", str(ds), str(tmp_path / "cuda"), "--device", "cuda", "--resume", *args]) == 0
    np.testing.assert_array_equal(Gaussians.load_ply(tmp_path / "cuda" / "point_cloud.ply").means, g.means)
    # joint pose refinement and test-time pose alignment (gradients w.r.t. viewmats through gsplat)
    assert main(["train", str(ds), str(tmp_path / "poses"), "--device", "cuda", "--refine-poses", "--iters", "40",
                 "--sh-degree", "0", "--checkpoint-every", "0", "--no-progress"]) == 0
    poses = json.loads((tmp_path / "poses" / "refined_poses.json").read_text())["poses"]
    assert len(poses) == 6
    assert main(["eval", str(tmp_path / "poses"), "--dataset", str(ds), "--device", "cuda", "--align-poses",
                 "--no-progress"]) == 0
    ma = json.loads((tmp_path / "poses" / "eval" / "metrics.json").read_text())
    assert "pose_correction_deg" in ma["views"][0]
    assert gsplat_on_cpu.dtypes == {torch.float32}  # what gsplat's CUDA kernels accept


def _spy_projection(gsplat_on_cpu, monkeypatch):
    """Record, for each projection gsplat runs, whether its view matrices carry a gradient."""
    seen = []
    project = gsplat_on_cpu.module.fully_fused_projection

    def spy(means, covars, quats, scales, viewmats, *a, **kw):
        seen.append(viewmats.requires_grad)
        return project(means, covars, quats, scales, viewmats, *a, **kw)

    monkeypatch.setattr(gsplat_on_cpu.module, "fully_fused_projection", spy)
    return seen


def test_pose_gradient_is_exact_not_gsplats_approximation(gsplat_on_cpu, monkeypatch):
    """gsplat's view-matrix gradient leaves out the rotation's term through the covariance (0.6 % off the
    float64 reference on an H200, bench/cuda.py). A one-camera render whose pose needs a gradient (pose
    refinement) moves the Gaussians into the camera frame by torch: gsplat's projection never sees a view
    matrix that requires grad, and images, screen positions and every gradient match the reference."""
    seen = _spy_projection(gsplat_on_cpu, monkeypatch)
    inputs, K = _scene(seed=7, C=1)
    cu = _run("cuda", inputs, K, 40, 30, sh_degree=2)
    assert seen == [False]
    ref = _run("reference", inputs, K, 40, 30, sh_degree=2)
    torch.testing.assert_close(cu[0], ref[0], rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(cu[1], ref[1], rtol=1e-6, atol=1e-7)
    for name in NAMES:
        a, b = cu[3][name], ref[3][name]
        assert b is not None and b.abs().max() > 0, name
        if name == "viewmats":
            a, b = _se3_grad(a, inputs[5]), _se3_grad(b, inputs[5])
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * b.abs().max().item(), msg=name)
    mc, mr = cu[2], ref[2]
    both = mc["visibility"] & mr["visibility"]
    assert mc["radii"].shape == (1, inputs[0].shape[0]) and both.sum() > 0
    torch.testing.assert_close(mc["means2d"].detach()[both], mr["means2d"].detach()[both])
    torch.testing.assert_close(mc["depths"].detach()[both], mr["depths"].detach()[both])
    gc = mc["means2d"].grad   # the densification gradient, retained on the returned tensor
    assert gc is not None and gc.shape == (1, inputs[0].shape[0], 2)
    torch.testing.assert_close(gc[both], mr["means2d"].grad[both], rtol=1e-5, atol=1e-9)


def test_without_pose_gradient_gsplat_gets_the_world_frame(gsplat_on_cpu, monkeypatch):
    seen = _spy_projection(gsplat_on_cpu, monkeypatch)
    inputs, K = _scene(seed=7, C=1)
    xs = [t.clone().requires_grad_(i != 5) for i, t in enumerate(inputs)]
    img, _, _ = rasterization(*xs[:6], K, 40, 30, backgrounds=xs[6], sh_degree=2, backend="cuda")
    img.sum().backward()
    assert seen == [False] and xs[0].grad is not None
    ref = _run("reference", inputs, K, 40, 30, sh_degree=2)
    torch.testing.assert_close(img.detach(), ref[0], rtol=1e-6, atol=1e-7)
