from __future__ import annotations

import numpy as np
import torch

from splattwin.splat import densify
from splattwin.splat.gaussians import Gaussians
from splattwin.splat.model import PARAM_NAMES, GaussianModel


def make_model(n: int = 6, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    g = Gaussians(means=rng.normal(size=(n, 3)), quats=q / np.linalg.norm(q, axis=1, keepdims=True),
                  scales=np.full((n, 3), 0.005), opacities=np.full(n, 0.5), sh=rng.normal(size=(n, 1, 3)))
    g.scales[3:] = 0.05  # three large ones (scene scale 1 -> grow_scale3d 0.01 m)
    m = GaussianModel.from_gaussians(g, max_sh_degree=1, scene_scale=1.0)
    # one optimizer step so that Adam has per-row moments to keep consistent
    loss = sum((v.float() ** 2).sum() * (i + 1) for i, v in enumerate(m.activated().values()))
    loss.backward()
    m.step()
    return m


def moments(m: GaussianModel, name: str) -> torch.Tensor:
    return m.optimizers[name].state[m.params[name]]["exp_avg"]


def test_remove_and_duplicate_keep_optimizer_rows():
    m = make_model()
    before = {k: (m.params[k].detach().clone(), moments(m, k).clone()) for k in PARAM_NAMES}
    keep = torch.tensor([True, False, True, True, False, True])
    densify.remove(m, keep)
    assert len(m) == 4
    for k in PARAM_NAMES:
        assert torch.equal(m.params[k].detach(), before[k][0][keep])
        assert torch.equal(moments(m, k), before[k][1][keep])
        assert m.optimizers[k].param_groups[0]["params"][0] is m.params[k]
    sel = torch.tensor([False, True, False, True])
    densify.duplicate(m, sel)
    assert len(m) == 6
    for k in PARAM_NAMES:
        assert torch.equal(m.params[k].detach()[4:], m.params[k].detach()[:4][sel])
        assert torch.all(moments(m, k)[4:] == 0) and moments(m, k).shape == m.params[k].shape
    # optimizer still steps on the new tensors
    m.zero_grad()
    m.activated()["means"].sum().backward()
    m.step()


def test_split_samples_and_scales():
    m = make_model()
    g = torch.Generator().manual_seed(0)
    old_scales = m.params["scales"].detach().clone()
    sel = torch.tensor([False, False, False, True, False, False])
    old_mean = m.params["means"].detach()[3].clone()
    densify.split(m, sel, g, factor=1.6)
    assert len(m) == 7
    torch.testing.assert_close(m.params["scales"].detach()[-2:], (old_scales[3] - np.log(1.6)).expand(2, 3))
    d = (m.params["means"].detach()[-2:] - old_mean).norm(dim=1)
    assert torch.all(d > 0) and torch.all(d < 0.05 * 5)  # within 5 sigma of the parent (sigma 0.05)
    assert moments(m, "means").shape == (7, 3)


def test_refine_clones_small_splits_large_prunes_transparent():
    m = make_model()
    st = densify.new_state(6)
    # grads: Gaussians 0 (small) and 3 (large) above threshold
    grad = torch.zeros(1, 6, 2)
    grad[0, 0] = torch.tensor([1e-3, 0.0])
    grad[0, 3] = torch.tensor([0.0, 1e-3])
    densify.accumulate(st, grad, torch.ones(1, 6, dtype=torch.int32), width=4, height=4)
    np.testing.assert_allclose(st["grad2d"][0].item(), 2e-3 * 1.0, rtol=1e-6)  # x * W/2
    assert st["count"].tolist() == [1.0] * 6
    with torch.no_grad():
        m.params["opacities"][5] = -10.0  # will be pruned
    cfg = densify.DensifyConfig(grad_threshold=5e-4, grow_scale3d=0.01, reset_every=10_000)
    res = densify.refine(m, st, cfg, step=100, generator=torch.Generator().manual_seed(0))
    assert (res.cloned, res.split, res.pruned) == (1, 1, 1)
    assert len(m) == 6 + 1 + 1 - 1
    assert st["grad2d"].shape == (7,) and float(st["grad2d"].sum()) == 0 and float(st["count"].sum()) == 0
    for k in PARAM_NAMES:
        assert moments(m, k).shape == m.params[k].shape


def test_refine_respects_cap_and_opacity_reset():
    m = make_model()
    st = densify.new_state(6)
    densify.accumulate(st, torch.full((1, 6, 2), 1e-2), torch.ones(1, 6, dtype=torch.int32), 10, 10)
    cfg = densify.DensifyConfig(max_gaussians=8, reset_every=10_000)
    densify.refine(m, st, cfg, step=1)
    assert len(m) == 8
    densify.reset_opacity(m, 0.01)
    assert float(torch.sigmoid(m.params["opacities"].detach()).max()) <= 0.01 + 1e-6
    assert torch.all(moments(m, "opacities") == 0)


def test_schedule_scales_with_iterations():
    c = densify.DensifyConfig.for_iterations(3000)
    assert c.refine_start < c.refine_stop < 3000 and c.refine_every == 100
    assert c.reset_every == 0  # no opacity reset in short runs (see for_iterations)
    c = densify.DensifyConfig.for_iterations(200)
    assert 0 < c.refine_start < c.refine_stop < 200


def test_size_prune_spares_far_background():
    m = make_model()
    with torch.no_grad():
        m.params["scales"][:] = np.log(0.005)
        m.params["scales"][0] = np.log(0.5)    # big and near the centre: pruned
        m.params["means"][0] = 0.0
        m.params["scales"][1] = np.log(0.5)    # equally big but 20 scene radii away: background, kept
        m.params["means"][1] = torch.tensor([20.0, 0.0, 0.0])
    st = densify.new_state(6)
    # without opacity resets (reset_every=0) there is no size pruning either, as in 3DGS before the first
    assert densify.refine(m, st, densify.DensifyConfig(reset_every=0, prune_scale3d=0.1), step=100).pruned == 0
    cfg = densify.DensifyConfig(reset_every=10, prune_scale3d=0.1)
    res = densify.refine(m, st, cfg, step=100)
    assert res.pruned == 1 and len(m) == 5
    assert torch.any((m.params["means"].detach() - torch.tensor([20.0, 0, 0])).norm(dim=1) < 1e-6)
