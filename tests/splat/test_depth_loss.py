from __future__ import annotations

import pytest
import torch

from splattwin.splat.depth_loss import depth_loss, valid_depth_mask

NAN, INF = float("nan"), float("inf")


def test_holes_and_low_alpha_are_masked():
    # D435-style holes: 0, NaN and inf all mean "no reading"
    gt = torch.tensor([[1.0, 0.0, NAN], [INF, 2.0, 4.0]])
    alpha = torch.tensor([[0.9, 0.9, 0.9], [0.9, 0.9, 0.3]])
    ok = valid_depth_mask(gt, alpha)
    assert ok.tolist() == [[True, False, False], [False, True, False]]
    depth = torch.tensor([[1.25, 5.0, 5.0], [5.0, 2.5, 9.0]], requires_grad=True)
    inv = depth_loss(depth, alpha, gt, "inverse")
    assert float(inv) == pytest.approx((abs(1 / 1.25 - 1) + abs(1 / 2.5 - 1 / 2)) / 2)
    rel = depth_loss(depth, alpha, gt, "relative")
    assert float(rel) == pytest.approx((0.25 / 1 + 0.5 / 2) / 2)
    inv.backward()
    g = depth.grad
    assert torch.isfinite(g).all()
    assert (g[~ok] == 0).all()  # no gradient through holes or faint pixels


def test_no_valid_pixel_gives_zero_with_graph():
    depth = torch.ones(2, 2, requires_grad=True)
    loss = depth_loss(depth, torch.ones(2, 2), torch.zeros(2, 2), "inverse")
    assert float(loss) == 0.0
    loss.backward()
    assert (depth.grad == 0).all()


@pytest.mark.parametrize("mode", ["relative", "inverse"])
def test_gradient_matches_finite_differences(mode):
    g = torch.Generator().manual_seed(0)
    gt = 0.5 + 2 * torch.rand(5, 6, generator=g, dtype=torch.float64)
    gt[0, :3] = 0.0       # holes
    gt[2, 2] = INF
    alpha = torch.rand(5, 6, generator=g, dtype=torch.float64)
    alpha[alpha < 0.5] += 0.5  # all drawn ...
    alpha[4, 0] = 0.1          # ... but one
    depth = (gt.nan_to_num(1.0, posinf=1.0).clamp_min(0.3) * (1 + 0.3 * torch.randn(5, 6, generator=g,
             dtype=torch.float64))).abs().clamp_min(0.2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: depth_loss(d, alpha, gt, mode), (depth,), eps=1e-7, atol=1e-6)


def test_unknown_mode():
    with pytest.raises(ValueError):
        depth_loss(torch.ones(1, 1), torch.ones(1, 1), torch.ones(1, 1), "log")
