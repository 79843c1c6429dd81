"""CPU backend of `rasterization()`: numba kernels (`kernels.py`) wrapped in `torch.autograd.Function`s.

Three differentiable steps, like gsplat: `project` (EWA projection; gradients to means, quats, scales and
view matrices), `sh_colors` (SH evaluation; gradients to the coefficients and, through the view
direction, to means and view matrices) and `rasterize` (tile compositing; gradients to 2D means,
conics, colours and opacities). All backward passes are hand-written kernels; the only autograd glue is
O(N) tensor arithmetic (camera centres, view directions, background blending).

Kernels run in float32 storage (float32 SIMD lanes per pixel, float64 per-Gaussian scalars) whatever the
input dtype; outputs and gradients are cast back to the input dtype.
"""

from __future__ import annotations

# Thread count and OpenMP wait policy (passive: numba's workers must not spin between kernels) are set
# by `splattwin.runtime.configure()`, not at import.
import numba
import numpy as np
import torch

from splattwin.splat._cpu import kernels as K_
from splattwin.splat._cpu.first_run import announce_first_compile

announce_first_compile()   # their first compile after install (~40 s) is said, not silent

TILE = K_.TILE


def _np32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def _intr(Ks: np.ndarray, c: int) -> tuple[float, float, float, float]:
    return float(Ks[c, 0, 0]), float(Ks[c, 1, 1]), float(Ks[c, 0, 2]), float(Ks[c, 1, 2])


_TILE_ORDERS: dict[tuple[int, int, int], np.ndarray] = {}


def _tile_order(tw: int, th: int) -> np.ndarray:
    """Work order of a tw x th tile grid: tile rows interleaved over the threads, raster order inside.

    numba's prange hands each thread one contiguous block of iterations, and image rows differ a lot in
    work (background vs objects): thread j of n gets the tile rows r with r % n == j, which spreads every
    thread over the whole image. Inside a block the tiles stay in raster order, so consecutive tiles read
    and write neighbouring image memory (a random shuffle, which balanced as well, made the per-tile image
    loads and stores cache misses: ~10 % of the backward pass at 640x480). Tiles are independent: the order
    does not change results."""
    n = max(1, numba.get_num_threads())
    key = (tw, th, n)
    p = _TILE_ORDERS.get(key)
    if p is None:
        rows = sorted(range(th), key=lambda r: (r % n, r))
        p = _TILE_ORDERS[key] = (np.array(rows, np.int64)[:, None] * tw + np.arange(tw)).reshape(-1)
    return p


def depth_order(depths: np.ndarray, ntiles: np.ndarray) -> np.ndarray:
    """Indices of the drawn Gaussians (ntiles > 0) by ascending float32 depth, ties by index (= a stable
    argsort; numpy's SIMD sort of int64 keys is ~15x faster than a stable argsort or numba's sort).

    Positive float32 values order like their int32 bit patterns (drawn Gaussians have z > near > 0)."""
    vis = np.flatnonzero(ntiles)
    key = (depths[vis].view(np.int32).astype(np.int64) << 32) | vis
    key.sort()
    return (key & 0xFFFFFFFF).astype(np.int32)


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, Ks, width, height, eps2d, near, far):
        m, q, s, vm = _np32(means), _np32(quats), _np32(scales), _np32(viewmats)
        Kn = Ks.detach().to("cpu", torch.float64).numpy()
        C, N = vm.shape[0], m.shape[0]
        means2d = np.empty((C, N, 2), np.float32)
        conics = np.empty((C, N, 3), np.float32)
        depths = np.empty((C, N), np.float32)
        extents = np.empty((C, N, 2), np.int32)
        for c in range(C):
            K_.project_fwd(m, q, s, vm[c], *_intr(Kn, c), int(width), int(height), float(eps2d), float(near),
                           float(far), means2d[c], conics[c], depths[c], extents[c])
        ctx.np = (m, q, s, vm, Kn, extents)
        ctx.cfg = (int(width), int(height), float(eps2d))
        ctx.dtype = means.dtype
        dt = means.dtype
        ext = torch.from_numpy(extents)
        ctx.mark_non_differentiable(ext)
        return (torch.from_numpy(means2d).to(dt), torch.from_numpy(conics).to(dt), torch.from_numpy(depths).to(dt),
                ext)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_ext):
        m, q, s, vm, Kn, extents = ctx.np
        width, height, eps2d = ctx.cfg
        C, N = vm.shape[0], m.shape[0]
        z2 = lambda t, shape: np.zeros(shape, np.float32) if t is None else _np32(t)  # noqa: E731
        g2, gc, gd = z2(v_means2d, (C, N, 2)), z2(v_conics, (C, N, 3)), z2(v_depths, (C, N))
        v_means = np.zeros((N, 3), np.float32)
        v_quats = np.zeros((N, 4), np.float32)
        v_scales = np.zeros((N, 3), np.float32)
        v_vm = np.zeros((C, 4, 4), np.float64)
        bm, bq, bs = np.empty((N, 3), np.float32), np.empty((N, 4), np.float32), np.empty((N, 3), np.float32)
        nch = (N + K_.CHUNK - 1) // K_.CHUNK
        vch = np.empty((nch, 3, 4), np.float64)
        for c in range(C):
            if C == 1:
                bm, bq, bs = v_means, v_quats, v_scales
            K_.project_bwd(m, q, s, vm[c], *_intr(Kn, c), width, height, eps2d, extents[c], g2[c], gc[c], gd[c],
                           bm, bq, bs, vch)
            if C > 1:
                v_means += bm
                v_quats += bq
                v_scales += bs
            v_vm[c, :3, :] = vch.sum(0)
        dt = ctx.dtype
        f = lambda a: torch.from_numpy(a).to(dt)  # noqa: E731
        return f(v_means), f(v_quats), f(v_scales), f(v_vm), None, None, None, None, None, None


class _SH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, dirs, coeffs, degree):
        d, co = _np32(dirs), _np32(coeffs)
        C, N = d.shape[:2]
        out = np.empty((C, N, 3), np.float32)
        for c in range(C):
            K_.sh_fwd(d[c], co, int(degree), out[c])
        ctx.np = (d, co)
        ctx.degree = int(degree)
        ctx.dtype = dirs.dtype
        return torch.from_numpy(out).to(dirs.dtype)

    @staticmethod
    def backward(ctx, v_colors):
        d, co = ctx.np
        C, N = d.shape[:2]
        vc = _np32(v_colors)
        v_co = np.empty(co.shape, np.float32)
        v_d = np.empty((C, N, 3), np.float32)
        for c in range(C):
            K_.sh_bwd(d[c], co, ctx.degree, vc[c], v_co, v_d[c], c > 0)
        return torch.from_numpy(v_d).to(ctx.dtype), torch.from_numpy(v_co).to(ctx.dtype), None


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, extents, width, height):
        m2, co, cl, op = _np32(means2d), _np32(conics), _np32(colors), _np32(opacities)
        D_in = cl.shape[2]
        dep = _np32(depths)
        ext = np.ascontiguousarray(extents.detach().cpu().numpy().astype(np.int32))
        C, N, D = cl.shape
        W, H = int(width), int(height)
        tw, th = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
        render = np.empty((C, H, W, D), np.float32)
        final_T = np.empty((C, H, W), np.float32)
        last = np.empty((C, H, W), np.int32)
        saved = []
        rec = np.empty((N, K_.R_COL + D), np.float32)
        ntiles = np.empty(N, np.int64)
        for c in range(C):
            opc = op if op.ndim == 1 else op[c]
            K_.make_records(m2[c], co[c], cl[c], opc, ext[c], W, H, rec, ntiles)
            order = depth_order(dep[c], ntiles)
            M = int(ntiles.sum())
            tile_start = np.empty(tw * th + 1, np.int64)
            packed = np.empty((M, rec.shape[1]), np.float32)
            rank_off = np.empty(order.shape[0] + 1, np.int64)
            rank_isect = np.empty(M, np.int64)
            K_.bin_tiles(order, rec, W, H, tile_start, packed, rank_off, rank_isect)
            M = int(tile_start[-1])  # <= the box count: tiles the ellipses miss are not listed
            packed, rank_isect = packed[:M], rank_isect[:M]
            K_.raster_fwd(packed, tile_start, _tile_order(tw, th), W, H, render[c], final_T[c], last[c])
            saved.append((packed, tile_start, order, rank_off, rank_isect))
        ctx.np = (cl.shape, final_T, last, saved)
        ctx.op_ndim = op.ndim
        ctx.cfg = (W, H, D_in)
        ctx.dtype = means2d.dtype
        dt = means2d.dtype
        return (torch.from_numpy(render[..., :D_in]).to(dt),
                torch.from_numpy(1.0 - final_T[..., None]).to(dt))

    @staticmethod
    def backward(ctx, v_render, v_alphas):
        (C, N, D), final_T, last, saved = ctx.np
        W, H, D_in = ctx.cfg
        if v_render is not None and D_in == D:
            vr = _np32(v_render)
        else:
            vr = np.zeros((C, H, W, D), np.float32)
            if v_render is not None:
                vr[..., :D_in] = _np32(v_render)
        va = np.zeros((C, H, W), np.float32) if v_alphas is None else _np32(v_alphas[..., 0])
        v_m2 = np.empty((C, N, 2), np.float32)
        v_co = np.empty((C, N, 3), np.float32)
        v_cl = np.empty((C, N, D), np.float32)
        per_cam_op = ctx.op_ndim == 2
        v_op = np.zeros((C, N) if per_cam_op else N, np.float32)
        out = np.empty((N, 6 + D), np.float32)
        for c in range(C):
            packed, tile_start, order, rank_off, rank_isect = saved[c]
            isect_grad = np.empty((packed.shape[0], 6 + D), np.float32)  # summed in float64
            K_.raster_bwd(packed, tile_start, _tile_order((W + TILE - 1) // TILE, (H + TILE - 1) // TILE), W, H, final_T[c], last[c], vr[c], va[c],
                          isect_grad)
            K_.reduce_isect_grads(isect_grad, order, rank_off, rank_isect, out)
            v_m2[c] = out[:, 0:2]
            v_co[c] = out[:, 2:5]
            if per_cam_op:
                v_op[c] = out[:, 5]
            else:
                v_op += out[:, 5]
            v_cl[c] = out[:, 6:]
        dt = ctx.dtype
        f = lambda a: torch.from_numpy(a).to(dt)  # noqa: E731
        return f(v_m2), f(v_co), f(np.ascontiguousarray(v_cl[..., :D_in])), f(v_op), None, None, None, None


def project(means, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01, far_plane=1e10):
    """Same contract as `splattwin.splat.reference.project` (CPU kernels)."""
    means2d, conics, depths, extents = _Project.apply(means, quats, scales, viewmats, Ks, width, height, eps2d,
                                                      near_plane, far_plane)
    radii = torch.maximum(extents[..., 0], extents[..., 1])
    return {"means2d": means2d, "conics": conics, "depths": depths, "radii": radii, "extents": extents}


def sh_colors(means, coeffs, viewmats, degree):
    """Same contract as `splattwin.splat.reference.sh_colors`: [C,N,3] colours from SH [N,K,3]."""
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    campos = -torch.einsum("cji,cj->ci", R, t)
    dirs = means[None, :, :] - campos[:, None, :]
    return _SH.apply(dirs, coeffs, int(degree))


def rasterize(means2d, conics, colors, opacities, depths, extents, width, height, backgrounds=None, **_):
    """Same contract as `splattwin.splat.reference.rasterize` (tile kernels)."""
    render, alphas = _Rasterize.apply(means2d, conics, colors, opacities, depths.detach(), extents, width, height)
    if backgrounds is not None:
        render = render + (1 - alphas) * backgrounds[:, None, None, :]
    return render, alphas
