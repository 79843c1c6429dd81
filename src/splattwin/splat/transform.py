"""Moving Gaussians into another frame by a similarity (rigid, or with a uniform scale): means, orientations,
scales *and* the view-dependent colour. The SH coefficients of each degree l mix under rotation; the
(2l+1)x(2l+1) mixing matrix is found by least squares from the basis evaluated at sample directions (exact:
each degree's span is rotation-invariant), which avoids hand-deriving Wigner matrices for the 3DGS basis
signs. A uniform scale s leaves colours and opacities as they are (each Gaussian covers the same pixels
seen from the camera moved by the same similarity), so a trained splat and its cameras moved together
render the same images (`splattwin.splat.rescale`: a twin given its metric scale after training).

(Here, not in `twin.splats`, so that the splat stage may use it; `twin.splats` re-exports these names.)
"""

from __future__ import annotations

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


def similarity_scale(T_new_old: np.ndarray) -> float:
    """The uniform scale s of a similarity [4,4] [[s R, t], [0, 1]] (1 for a rigid transform); ValueError when
    its 3x3 part is not s times a rotation (a reflection, a shear, unequal axis scales)."""
    A = np.asarray(T_new_old, dtype=np.float64)[:3, :3]
    det = float(np.linalg.det(A))
    if not (np.isfinite(det) and det > 0):
        raise ValueError(f"not a similarity: the 3x3 part has determinant {det:.6g} (must be > 0)")
    s = float(np.cbrt(det))
    if abs(s - 1.0) < 1e-9:   # rigid (up to rounding): exactly 1, so a rigid move keeps the scales' bits
        s = 1.0
    R = A / s
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise ValueError("not a similarity: the 3x3 part is not a uniform scale times a rotation")
    return s


def transform_gaussians(g: Gaussians, T_new_old: np.ndarray) -> Gaussians:
    """Gaussians expressed in a new frame: means moved, orientations and SH colour rotated, scales times s.

    T_new_old [4,4] maps old-frame points to the new frame: rigid, or a similarity [[s R, t], [0, 1]]
    (s > 0, uniform): positions s R p + t, rotations R q, standard deviations s * scales (log-scales + log s),
    opacities and colours unchanged, SH of degree >= 1 rotated with R."""
    T_new_old = np.asarray(T_new_old, dtype=np.float64)
    s = similarity_scale(T_new_old)
    R, t = T_new_old[:3, :3] / s, T_new_old[:3, 3]
    means = g.means @ T_new_old[:3, :3].T + t
    quats = quat_mul_wxyz(quat_wxyz_from_matrix(R, canonical=False), g.quats)
    # colour seen along d_new equals old colour along R^T d_new  ->  f_new(d) = f_old(R^T d)
    D = sh_rotation(R.T, g.sh_degree)
    sh = np.einsum("kj,njc->nkc", D, g.sh)
    scales = g.scales * s if s != 1.0 else g.scales.copy()
    return Gaussians(means, quats, scales, g.opacities.copy(), sh)
