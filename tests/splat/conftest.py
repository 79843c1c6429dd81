"""`gsplat_on_cpu`: run our "cuda" backend through gsplat's real Python front end on a machine with no GPU.

gsplat's `rasterization()` is Python that calls five CUDA primitives (projection, tile intersection, offset
encoding, SH evaluation, compositing). This fixture replaces those five names in `gsplat.rendering` with
plain-PyTorch emulations written from the CUDA kernels of gsplat 1.5 (csrc/ProjectionEWA3DGSFused.cu,
IntersectTile.cu, RasterizeToPixels3DGSFwd.cu; gsplat's own `_torch_impl` helpers where they match the
kernels), declares CUDA available, and points our "cuda" backend's device at the CPU. Everything else -
gsplat's argument handling, SH layout, render modes, backgrounds, and our adapter, trainer and CLI - runs
for real, and autograd provides the gradients the CUDA backward kernels would. The fixture's `dtypes`
records the tensor dtypes the kernels were given (gsplat's CUDA kernels take float32 only).

Kernel semantics emulated (gsplat 1.5), where they differ from our reference:
- per-axis radii ceil(extend * sqrt(cov2d_ii)) with the opacity-aware extend
  min(3.33, sqrt(2 ln(255 o))), and Gaussians with o < 1/255 culled;
- each pixel composites every Gaussian listed for its 16x16 tile (no per-pixel box), alpha clamp 0.999.
"""

from __future__ import annotations

import importlib

import math
from types import SimpleNamespace

import pytest
import torch

ALPHA_THRESHOLD = 1.0 / 255.0
_DTYPES: set = set()  # float dtypes the emulated kernels received (the real ones take float32 only)


def _fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3,
                            near_plane=0.01, far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False,
                            calc_compensations=False, camera_model="pinhole", opacities=None):
    from gsplat.cuda import _torch_impl as ti

    assert not packed and camera_model == "pinhole" and means.ndim == 2, "emulation: unpacked pinhole only"
    _DTYPES.update(t.dtype for t in (means, covars, quats, scales, viewmats, Ks, opacities) if t is not None)
    if covars is None:
        covars, _ = ti._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    else:  # [N,6] upper triangle -> [N,3,3]
        a, b, c, d, e, f = covars.unbind(-1)
        covars = torch.stack([a, b, c, b, d, e, c, e, f], -1).reshape(-1, 3, 3)
    _, means2d, depths, conics, comp = ti._fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations, camera_model)
    with torch.no_grad():  # radii as the CUDA kernel computes them (not differentiable there either)
        ca, cb, cc = conics.unbind(-1)
        det_inv = ca * cc - cb * cb  # 1 / det(cov2d + eps2d I)
        valid = (det_inv > 0) & (depths > near_plane) & (depths < far_plane)
        det = torch.where(valid, 1.0 / det_inv.clamp_min(1e-30), torch.zeros_like(det_inv))
        var_x, var_y = cc * det, ca * det
        extend = torch.full_like(depths, 3.33)
        if opacities is not None:
            o = opacities[None, :].expand_as(depths)
            if comp is not None:
                o = o * comp
            valid &= o >= ALPHA_THRESHOLD
            extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log(o.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)))
        rx = torch.ceil(extend * torch.sqrt(var_x.clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(var_y.clamp_min(0)))
        valid &= (rx > radius_clip) | (ry > radius_clip)
        mx, my = means2d[..., 0], means2d[..., 1]
        valid &= ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
        radii = torch.stack([rx, ry], -1) * valid[..., None]
    return radii.to(torch.int32), means2d, depths, conics, comp


@torch.no_grad()
def _isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, segmented=False,
                 packed=False, n_images=None, image_ids=None, gaussian_ids=None):
    """Vectorised IntersectTile.cu: one key (image, tile, float32 depth bits) per (Gaussian, tile) pair."""
    assert not packed
    I, N = math.prod(means2d.shape[:-2]), means2d.shape[-2]
    m = means2d.detach().reshape(I * N, 2).double() / tile_size
    r = radii.reshape(I * N, 2).double() / tile_size
    lim = torch.tensor([tile_width, tile_height], dtype=torch.float64)
    tmin = torch.minimum(torch.floor(m - r).clamp_min(0), lim).long()
    tmax = torch.minimum(torch.ceil(m + r).clamp_min(0), lim).long()
    ext = tmax - tmin
    cnt = ext.prod(-1) * (radii.reshape(I * N, 2) > 0).all(-1)
    src = torch.repeat_interleave(torch.arange(I * N), cnt)
    k = torch.arange(src.numel()) - (torch.cumsum(cnt, 0) - cnt)[src]
    w = ext[src, 0]
    tile = (tmin[src, 1] + k // w) * tile_width + tmin[src, 0] + k % w
    tile_bits = (tile_width * tile_height).bit_length()
    depth_bits = depths.detach().reshape(-1).float().view(torch.int32).long()[src] & 0xFFFFFFFF
    isect_ids = ((((src // N) << tile_bits) | tile) << 32) | depth_bits
    flatten_ids = src.to(torch.int32)
    if sort:  # stable: equal depths keep index order (CUB's radix sort is stable too)
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return cnt.reshape(means2d.shape[:-1]).to(torch.int32), isect_ids, flatten_ids


def _spherical_harmonics(degrees_to_use, dirs, coeffs, masks=None):
    from gsplat.cuda import _torch_impl as ti

    out = ti._spherical_harmonics(degrees_to_use, dirs, coeffs)
    return out if masks is None else out * masks[..., None]  # the kernel writes 0 for masked entries


def _rasterize_to_pixels(means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets,
                         flatten_ids, backgrounds=None, masks=None, packed=False, absgrad=False):
    """RasterizeToPixels3DGSFwd.cu per tile, vectorised over (pixel, listed Gaussian); autograd = backward."""
    assert not packed and masks is None
    _DTYPES.update(t.dtype for t in (means2d, conics, colors, opacities, backgrounds) if t is not None)
    dims, N, D = means2d.shape[:-2], means2d.shape[-2], colors.shape[-1]
    I = math.prod(dims)
    m2, con = means2d.reshape(I * N, 2), conics.reshape(I * N, 3)
    col, op = colors.reshape(I * N, D), opacities.reshape(I * N)
    th, tw = isect_offsets.shape[-2:]
    offs = isect_offsets.reshape(-1).tolist() + [flatten_ids.numel()]
    imgs, accs = [], []
    for i in range(I):
        rows_c, rows_a = [], []
        for ty in range(th):
            tiles_c, tiles_a = [], []
            y = torch.arange(ty * tile_size, min((ty + 1) * tile_size, image_height), dtype=m2.dtype) + 0.5
            for tx in range(tw):
                x = torch.arange(tx * tile_size, min((tx + 1) * tile_size, image_width), dtype=m2.dtype) + 0.5
                px = torch.stack(torch.meshgrid(y, x, indexing="ij")[::-1], -1).reshape(-1, 2)  # (u, v)
                t = (i * th + ty) * tw + tx
                ids = flatten_ids[offs[t]:offs[t + 1]].long()
                d = px[:, None, :] - m2[ids][None]  # [P,L,2]
                c = con[ids]
                sigma = 0.5 * (c[:, 0] * d[..., 0] ** 2 + c[:, 2] * d[..., 1] ** 2) + c[:, 1] * d[..., 0] * d[..., 1]
                alpha = torch.clamp_max(op[ids] * torch.exp(-sigma), 0.999)
                alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_THRESHOLD), alpha, torch.zeros_like(alpha))
                T_after = torch.cumprod(1.0 - alpha, dim=1)
                T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], dim=1)
                # a pixel stops at the first Gaussian that would take T to <= 1e-4, excluding it
                w = alpha * T_before * (T_after > 1e-4)
                tiles_c.append((w @ col[ids]).reshape(len(y), len(x), D))
                tiles_a.append(w.sum(1).reshape(len(y), len(x), 1))
            rows_c.append(torch.cat(tiles_c, 1))
            rows_a.append(torch.cat(tiles_a, 1))
        imgs.append(torch.cat(rows_c, 0))
        accs.append(torch.cat(rows_a, 0))
    render = torch.stack(imgs).reshape(dims + (image_height, image_width, D))
    alphas = torch.stack(accs).reshape(dims + (image_height, image_width, 1))
    if backgrounds is not None:
        render = render + backgrounds[..., None, None, :] * (1.0 - alphas)
    return render, alphas


@pytest.fixture
def gsplat_on_cpu(monkeypatch):
    """gsplat's front end with emulated CUDA primitives; our "cuda" backend available, on the CPU."""
    import gsplat.cuda._torch_impl as ti
    import gsplat.rendering as gr

    r = importlib.import_module("splattwin.splat.rasterize")

    monkeypatch.setattr(gr, "fully_fused_projection", _fully_fused_projection)
    monkeypatch.setattr(gr, "isect_tiles", _isect_tiles)
    monkeypatch.setattr(gr, "isect_offset_encode", ti._isect_offset_encode)
    monkeypatch.setattr(gr, "spherical_harmonics", _spherical_harmonics)
    monkeypatch.setattr(gr, "rasterize_to_pixels", _rasterize_to_pixels)
    monkeypatch.setattr(r, "cuda_unavailable_reason", lambda: None)
    monkeypatch.setattr(r, "CUDA_DEVICE", "cpu")
    _DTYPES.clear()
    return SimpleNamespace(module=gr, dtypes=_DTYPES)
