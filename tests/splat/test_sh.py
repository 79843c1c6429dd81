"""SH evaluation: analytic values, orthonormality of the basis and the colour convention."""

from __future__ import annotations

import math

import torch

from splattwin.splat import sh


def test_dc_colour_convention():
    c = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    coeffs = sh.rgb_to_sh(c)[:, None, :]
    out = sh.sh_to_color(0, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), coeffs)
    assert torch.allclose(out, c)
    assert torch.allclose(sh.sh_to_rgb(sh.rgb_to_sh(c)), c)


def test_basis_is_orthonormal_on_the_sphere():
    # Monte-Carlo integral over the unit sphere of Y_i Y_j = delta_ij (4 pi * mean)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    Y = sh.sh_basis(3, d)
    gram = 4 * math.pi * (Y.T @ Y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)


def test_degree_one_sign_convention_matches_3dgs():
    # 3DGS: result -= C1 * y * sh[1]; += C1 * z * sh[2]; -= C1 * x * sh[3]
    coeffs = torch.zeros(1, 4, 3, dtype=torch.float64)
    coeffs[0, 1] = 1.0
    out = sh.eval_sh(1, torch.tensor([[0.0, 2.0, 0.0]], dtype=torch.float64), coeffs)  # unnormalised dir
    assert torch.allclose(out, torch.full((1, 3), -sh.C1, dtype=torch.float64))


def test_lower_degree_ignores_higher_coefficients_and_clamps():
    g = torch.Generator().manual_seed(1)
    coeffs = torch.randn(5, 16, 3, generator=g, dtype=torch.float64)
    d = torch.randn(5, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(sh.eval_sh(1, d, coeffs), sh.eval_sh(1, d, coeffs[:, :4]))
    assert (sh.sh_to_color(3, d, coeffs * 10) >= 0).all()
    assert sh.sh_degree_from_bases(9) == 2 and sh.num_sh_bases(3) == 16
