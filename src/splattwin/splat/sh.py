"""Real spherical harmonics (degree 0-3) as used by 3DGS / gsplat, in plain PyTorch.

The basis, constants and sign conventions are those of the original 3DGS code (and gsplat), so PLY files
from other tools render with the same colours. A colour is `max(0, 0.5 + sum_k Y_k(d) * sh_k)` where `d`
is the unit view direction from the camera centre to the Gaussian (world frame).

This module is the reference (autograd) implementation; the CPU backend has its own numba kernels with a
hand-written backward in `splattwin.splat._cpu.sh_kernels`, tested against this one.
"""

from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients K = (degree + 1)^2 for degree 0..3."""
    if not 0 <= int(degree) <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (int(degree) + 1) ** 2


def sh_degree_from_bases(K: int) -> int:
    """Inverse of `num_sh_bases` (K must be 1, 4, 9 or 16)."""
    for d in range(4):
        if (d + 1) ** 2 == K:
            return d
    raise ValueError(f"number of SH coefficients must be 1, 4, 9 or 16, got {K}")


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """SH basis values Y_k(d) for unit directions.

    Args:
        degree: 0..3.
        dirs: [..., 3] unit vectors.
    Returns:
        [..., (degree+1)^2]
    """
    out = [torch.full_like(dirs[..., 0], C0)]
    if degree > 0:
        x, y, z = dirs.unbind(-1)
        out += [-C1 * y, C1 * z, -C1 * x]
        if degree > 1:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
            if degree > 2:
                out += [C3[0] * y * (3.0 * xx - yy), C3[1] * xy * z, C3[2] * y * (4.0 * zz - xx - yy),
                        C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), C3[4] * x * (4.0 * zz - xx - yy),
                        C3[5] * z * (xx - yy), C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Raw SH sum (no +0.5 offset).

    Args:
        degree: SH degree to use (0..3); only the first (degree+1)^2 of the K coefficients are used.
        dirs: [..., 3] view directions (need not be normalised; zero vectors give the DC term only).
        coeffs: [..., K, 3] with K >= (degree+1)^2.
    Returns:
        [..., 3]
    """
    nb = num_sh_bases(degree)
    if coeffs.shape[-2] < nb:
        raise ValueError(f"SH degree {degree} needs {nb} coefficients, got {coeffs.shape[-2]}")
    n = torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    d = dirs / torch.clamp(n, min=1e-12)
    basis = sh_basis(degree, d)
    return (basis[..., None] * coeffs[..., :nb, :]).sum(dim=-2)


def sh_to_color(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Colour from SH as rendered by 3DGS/gsplat: clamp_min(eval_sh + 0.5, 0). [..., 3]"""
    return torch.clamp_min(eval_sh(degree, dirs, coeffs) + 0.5, 0.0)


def rgb_to_sh(rgb):
    """DC coefficient that reproduces `rgb` in [0,1] (works on numpy arrays and tensors)."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh0):
    """Colour of a DC coefficient (inverse of `rgb_to_sh`)."""
    return sh0 * C0 + 0.5
