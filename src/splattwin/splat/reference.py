"""Plain-PyTorch reference rasterizer (differentiable through autograd). Small sizes only.

It is the ground truth the fast CPU kernels (`splattwin.splat._cpu`) are tested against, and it defines
the exact semantics every backend follows (those of 3DGS / gsplat):

* Projection (EWA splatting): camera-frame mean p = R m + t, 3D covariance Sigma = R_q S S^T R_q^T from the
  unit quaternion (wxyz) and scales, 2D covariance J R Sigma R^T J^T + eps2d * I with the Jacobian J of the
  perspective projection at p (its x/z, y/z clamped to 1.3x the field of view, as gsplat does, so
  Gaussians far off-screen do not blow up), conic = inverse 2D covariance.
* Culling: z outside (near, far), non-positive 2D determinant, or a 3-sigma box fully off-screen -> radius
  0 (invisible, no gradient). Screen extent: 3 sigma per axis, ceil'd to whole pixels and saturated at
  RADIUS_MAX (rx = min(ceil(3 sqrt(cov2d_xx)), RADIUS_MAX), ry likewise); `radii` reports max(rx, ry).
* A Gaussian touches pixel (i, j) only if the pixel centre (j + 0.5, i + 0.5) is within its box
  |u - mean_u| <= rx, |v - mean_v| <= ry; this makes the result independent of the tile size.
* Compositing front to back in depth order (camera z, ties by index):
  alpha = min(0.99, o * exp(-sigma)), sigma = 0.5 (a dx^2 + c dy^2) + b dx dy >= 0, skipped if alpha < 1/255
  (a NaN or infinite opacity o: never drawn);
  a pixel stops before the Gaussian that would bring its transmittance below 1e-4.
  colour = sum_i c_i alpha_i T_i + T_final * background, alpha = 1 - T_final.

The compositing is evaluated densely over (pixel, Gaussian) pairs in pixel chunks; each chunk is
gradient-checkpointed so memory stays bounded, but time is O(H W N): use it for tests and benchmarks.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from splattwin.splat import sh as _sh

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
SIGMA_EXTENT = 3.0
FOV_CLAMP = 1.3  # Jacobian evaluated with x/z, y/z clamped to 1.3x the half field of view (gsplat)
# Box half-sizes saturate here (pixels): extents and radii are int32, and a 3-sigma radius beyond 2^31 px
# (an untrusted PLY's huge scale, or a Gaussian at the near plane: J = f / z) wrapped round to a negative
# or arbitrary value, so a Gaussian covering the whole image was not drawn at all. gsplat's CUDA
# float->int conversion saturates likewise. 2^30: exact in float32 and float64; a saturated box still holds
# the whole image when the Gaussian's centre projects less than 2^30 - max(width, height) px from it.
RADIUS_MAX = 2 ** 30


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz quaternions (normalised here) -> [..., 3, 3] rotation matrices; differentiable.

    The one torch implementation (densification's split uses it too); numpy code goes through
    `splattwin.transforms`. A zero quaternion gives the identity (its norm is clamped at 1e-12)."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def quat_scale_to_covar(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World-frame 3D covariance R S S^T R^T. quats [N,4] wxyz, scales [N,3] m -> [N,3,3] m^2."""
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
            Ks: torch.Tensor, width: int, height: int, eps2d: float = 0.3, near_plane: float = 0.01,
            far_plane: float = 1e10) -> dict[str, torch.Tensor]:
    """EWA projection of N Gaussians into C cameras.

    Args:
        means [N,3] world m; quats [N,4] wxyz; scales [N,3] m; viewmats [C,4,4] world->camera;
        Ks [C,3,3] pixels.
    Returns dict:
        means2d [C,N,2] pixels, conics [C,N,3] (a, b, c of the inverse 2D covariance), depths [C,N] camera z
        (m), radii [C,N] int32 (0 = culled), extents [C,N,2] int32 (rx, ry pixel half-sizes of the box).
    """
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    p = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C,N,3]
    x, y, z = p.unbind(-1)
    valid = (z > near_plane) & (z < far_plane)
    z_s = torch.where(valid, z, torch.ones_like(z))  # keeps culled entries finite (no NaN gradients)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + (FOV_CLAMP - 1.0) * tan_x, cx / fx + (FOV_CLAMP - 1.0) * tan_x
    lim_yp, lim_yn = (height - cy) / fy + (FOV_CLAMP - 1.0) * tan_y, cy / fy + (FOV_CLAMP - 1.0) * tan_y
    tx = z_s * torch.minimum(torch.maximum(x / z_s, -lim_xn), lim_xp)
    ty = z_s * torch.minimum(torch.maximum(y / z_s, -lim_yn), lim_yp)
    zero = torch.zeros_like(z_s)
    J = torch.stack([fx / z_s, zero, -fx * tx / (z_s * z_s),
                     zero, fy / z_s, -fy * ty / (z_s * z_s)], dim=-1).reshape(p.shape[:-1] + (2, 3))
    cov = quat_scale_to_covar(quats, scales)  # [N,3,3]
    cov_c = R[:, None] @ cov[None] @ R.transpose(-1, -2)[:, None]  # [C,N,3,3]
    cov2d = J @ cov_c @ J.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    ok = valid & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([fx * x / z_s + cx, fy * y / z_s + cy], dim=-1)
    with torch.no_grad():
        rx = torch.ceil(SIGMA_EXTENT * torch.sqrt(torch.clamp_min(a, 0))).clamp_max(RADIUS_MAX)
        ry = torch.ceil(SIGMA_EXTENT * torch.sqrt(torch.clamp_min(c, 0))).clamp_max(RADIUS_MAX)
        u, v = means2d.unbind(-1)
        on = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        keep = ok & on & (rx > 0) & (ry > 0)
        rx = torch.where(keep, rx, torch.zeros_like(rx))
        ry = torch.where(keep, ry, torch.zeros_like(ry))
        extents = torch.stack([rx, ry], dim=-1).to(torch.int32)
        radii = torch.maximum(rx, ry).to(torch.int32)
    return {"means2d": means2d, "conics": conics, "depths": z, "radii": radii, "extents": extents}


def _composite_chunk(px: torch.Tensor, py: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor,
                     opacities: torch.Tensor, colors: torch.Tensor, ext: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite P pixels against M depth-sorted Gaussians. px, py [P] pixel centres; means2d [M,2];
    conics [M,3]; opacities [M]; colors [M,D]; ext [M,2] box half-sizes. -> (colour [P,D], T_final [P])."""
    dx = means2d[None, :, 0] - px[:, None]  # [P,M]
    dy = means2d[None, :, 1] - py[:, None]
    sigma = 0.5 * (conics[None, :, 0] * dx * dx + conics[None, :, 2] * dy * dy) + conics[None, :, 1] * dx * dy
    alpha = torch.clamp(opacities[None, :] * torch.exp(-sigma), max=ALPHA_MAX)
    with torch.no_grad():
        inside = (dx.abs() <= ext[None, :, 0]) & (dy.abs() <= ext[None, :, 1]) & (sigma >= 0)
        inside &= alpha >= ALPHA_MIN
        a0 = torch.where(inside, alpha, torch.zeros_like(alpha))
        # stop before the Gaussian that takes T below T_MIN (T is non-increasing: a prefix test)
        inside &= torch.cumprod(1 - a0, dim=1) >= T_MIN
    alpha = torch.where(inside, alpha, torch.zeros_like(alpha))
    one_minus = 1 - alpha
    T_incl = torch.cumprod(one_minus, dim=1)
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    w = alpha * T_excl
    return w @ colors, T_incl[:, -1] if T_incl.shape[1] else torch.ones_like(px)


def rasterize(means2d: torch.Tensor, conics: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
              depths: torch.Tensor, extents: torch.Tensor, width: int, height: int,
              backgrounds: torch.Tensor | None = None, chunk_pixels: int = 1024
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense per-pixel compositing (see module docstring for the exact rules).

    Args:
        means2d [C,N,2]; conics [C,N,3]; colors [C,N,D]; opacities [N] or [C,N]; depths [C,N] (sort key only);
        extents [C,N,2] int box half-sizes (0 = culled); backgrounds [C,D] or None.
    Returns:
        render [C,H,W,D], alphas [C,H,W,1].
    """
    C, N, D = colors.shape
    dev, dt = means2d.device, means2d.dtype
    jj, ii = torch.meshgrid(torch.arange(width, device=dev, dtype=dt), torch.arange(height, device=dev, dtype=dt),
                            indexing="xy")
    px_all, py_all = (jj + 0.5).reshape(-1), (ii + 0.5).reshape(-1)
    renders, alphas = [], []
    for ci in range(C):
        vis = torch.nonzero(extents[ci, :, 0] > 0).squeeze(1)
        order = vis[torch.argsort(depths[ci, vis].detach(), stable=True)]
        m2, co, cl = means2d[ci, order], conics[ci, order], colors[ci, order]
        op = (opacities if opacities.ndim == 1 else opacities[ci])[order]
        # a NaN or infinite opacity is never drawn (zero, not NaN, gradients): alpha would be NaN, or 0.99 over
        # the whole box for +inf
        op = torch.where(torch.isfinite(op), op, torch.zeros_like(op))
        ex = extents[ci, order].to(dt)
        outs, Ts = [], []
        for s in range(0, width * height, chunk_pixels):
            px, py = px_all[s:s + chunk_pixels], py_all[s:s + chunk_pixels]
            if torch.is_grad_enabled() and (m2.requires_grad or cl.requires_grad or op.requires_grad
                                            or co.requires_grad):
                o, T = checkpoint(_composite_chunk, px, py, m2, co, op, cl, ex, use_reentrant=False)
            else:
                o, T = _composite_chunk(px, py, m2, co, op, cl, ex)
            outs.append(o)
            Ts.append(T)
        out = torch.cat(outs, 0)
        T = torch.cat(Ts, 0)
        if backgrounds is not None:
            out = out + T[:, None] * backgrounds[ci][None, :]
        renders.append(out.reshape(height, width, D))
        alphas.append((1 - T).reshape(height, width, 1))
    return torch.stack(renders, 0), torch.stack(alphas, 0)


def sh_colors(means: torch.Tensor, coeffs: torch.Tensor, viewmats: torch.Tensor, degree: int) -> torch.Tensor:
    """View-dependent colours [C,N,3] from SH coeffs [N,K,3] for each camera (directions camera -> mean)."""
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    campos = -torch.einsum("cji,cj->ci", R, t)  # camera centre in world: -R^T t
    dirs = means[None, :, :] - campos[:, None, :]
    return _sh.sh_to_color(degree, dirs, coeffs[None].expand(dirs.shape[0], -1, -1, -1))

