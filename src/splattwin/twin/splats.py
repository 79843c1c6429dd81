"""Per-object Gaussian splat PLYs (Unity Gaussian Splatting, SuperSplat), in the object frame.

Moving Gaussians into another frame rotates means, orientations *and* the view-dependent colour: the
SH coefficients of each degree l mix under rotation. The (2l+1)x(2l+1) mixing matrix is found by least
squares from the basis evaluated at sample directions (exact: each degree's span is rotation-invariant),
which avoids hand-deriving Wigner matrices for the 3DGS basis signs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin.splat.gaussians import Gaussians
from splattwin.transforms import quat_mul_wxyz, quat_wxyz_from_matrix

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
       1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """[M,(degree+1)^2] real SH basis of the 3DGS/gsplat convention at unit directions [M,3]."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    cols = [np.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                 _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy), _C3[5] * z * (xx - yy),
                 _C3[6] * x * (xx - 3 * yy)]
    return np.stack(cols, axis=1)


def eval_sh(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Colour [N,3] (before the +0.5 offset) of SH coefficients [N,K,3] seen along unit directions [N,3]."""
    deg = int(round(np.sqrt(sh.shape[1]))) - 1
    return np.einsum("nk,nkc->nc", sh_basis(dirs, deg), sh)


def sh_rotation(R: np.ndarray, degree: int) -> np.ndarray:
    """[K,K] matrix D with coefficients_new = D @ coefficients such that f_new(d) = f_old(R d).

    Use R = R_world_obj to express world-frame SH in the object frame."""
    rng = np.random.default_rng(0)
    d = rng.standard_normal((64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    B = sh_basis(d, degree)
    BR = sh_basis(d @ R.T, degree)  # rows: basis at R d
    D = np.zeros((B.shape[1], B.shape[1]))
    for l in range(degree + 1):  # degrees do not mix: solve each block
        s = slice(l * l, (l + 1) ** 2)
        X, *_ = np.linalg.lstsq(B[:, s], BR[:, s], rcond=None)  # B X = B(R d)
        D[s, s] = X
    return D


def transform_gaussians(g: Gaussians, T_new_old: np.ndarray) -> Gaussians:
    """Gaussians expressed in a new frame: means, orientations and SH colour rotated, scales kept.

    T_new_old [4,4] rigid, maps old-frame points to the new frame."""
    R, t = T_new_old[:3, :3], T_new_old[:3, 3]
    means = g.means @ R.T + t
    quats = quat_mul_wxyz(quat_wxyz_from_matrix(R, canonical=False), g.quats)
    # colour seen along d_new equals old colour along R^T d_new  ->  f_new(d) = f_old(R^T d)
    D = sh_rotation(R.T, g.sh_degree)
    sh = np.einsum("kj,njc->nkc", D, g.sh)
    return Gaussians(means, quats, g.scales.copy(), g.opacities.copy(), sh)


def write_object_splats(path: str | Path, g: Gaussians, T_world_obj: np.ndarray, comments=()) -> Path:
    """Write Gaussians (world frame) as a standard 3DGS PLY in the object frame, atomically.
    comments: PLY comment lines (units, frame; see `splat.ply.write_gaussians_ply`)."""
    from splattwin.splat.ply import write_gaussians_ply

    return write_gaussians_ply(path, transform_gaussians(g, np.linalg.inv(T_world_obj)), comments)
