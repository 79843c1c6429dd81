"""Numba kernels of the CPU rasterizer: projection, SH, tile binning, compositing, each with its backward.

Why our own kernels: no differentiable CPU Gaussian rasterizer exists on PyPI (gsplat and taichi-splatting
are GPU-only) and a dense PyTorch version is O(H W N) in time and memory. These follow the published
tile-based CUDA rasterizers (3DGS, gsplat) re-organised for a CPU:

* one camera per call; float32 arrays; per-Gaussian and per-pair terms in float64 scalars (free on a CPU,
  and they keep the 2x2 inversions and the per-row terms well conditioned), per-pixel work in float32 SIMD;
* every drawn Gaussian gets one float32 record (2D mean, conic, opacity, its opacity-aware pixel box,
  log-levels, colours); binning is a counting sort by tile of the Gaussians taken in global depth order
  that copies each record into every tile list it reaches (box tiles the ellipse misses are left out), so
  every tile's list is depth-sorted without a per-tile sort and is streamed from consecutive memory;
* tiles of 16x16 pixels are the unit of parallel work (`prange`); inside a tile the loop runs over the
  tile's Gaussians and, for each, over the rows of its box that hold pixels with alpha >= 1/255, a whole
  tile row at a time as 16 float32 SIMD lanes (see "compositing" below);
* the backward pass writes one gradient row per (tile, Gaussian) pair - each row is owned by one tile, so
  threads never write to the same memory (numba has no atomics) - then a parallel reduction per Gaussian
  sums its rows in a fixed order: results are deterministic for any thread count;
* per-camera gradients of the view matrix are reduced over fixed chunks of Gaussians.

Exact semantics (culling, extents, thresholds) are those of `splattwin.splat.reference`.
"""

from __future__ import annotations

import math

import llvmlite.ir as _ir
import numpy as np
from numba import carray, njit, prange
from numba import types as _nbt
from numba.core import cgutils as _cgutils
from numba.extending import intrinsic as _intrinsic

from splattwin.splat.reference import RADIUS_MAX  # box half-sizes saturate there (int32 extents)

TILE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
EXTENT = 3.0
FOV_CLAMP = 1.3
CHUNK = 1024  # Gaussians per work item in the per-Gaussian kernels
# Quaternion norms are clamped to at least this before normalising, as the reference backend and gsplat's
# PyTorch implementation do (torch.nn.functional.normalize's eps): a zero quaternion gives the identity
# rotation, and its gradient is that of q / QUAT_EPS (no normalising projection below the clamp).
QUAT_EPS = np.float32(1e-12)

_JIT = dict(parallel=True, fastmath=False, cache=True, nogil=True)
_JIT1 = dict(parallel=False, fastmath=False, cache=True, nogil=True)
# The two compositing kernels (most of a training step) with fastmath flags: only finite values reach them
# (culled Gaussians are never binned), and fused multiply-adds only make the float32 lanes more accurate.
_FAST = {"nnan", "ninf", "nsz", "arcp", "contract", "afn"}  # not "reassoc": it would undo compensated sums
_JITF = dict(parallel=True, fastmath=_FAST, cache=True, nogil=True)
_JIT1F = dict(parallel=False, fastmath=_FAST, cache=True, nogil=True)  # helpers inlined into the _JITF kernels

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2_0, SH_C2_1, SH_C2_2, SH_C2_3, SH_C2_4 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                               -1.0925484305920792, 0.5462742152960396)
SH_C3_0, SH_C3_1, SH_C3_2, SH_C3_3, SH_C3_4, SH_C3_5, SH_C3_6 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
    1.445305721320277, -0.5900435899266435)


# --------------------------------------------------------------------------------------------------------
# projection
# --------------------------------------------------------------------------------------------------------
@njit(**_JIT1)
def _quat_rotmat(q0, q1, q2, q3, Rq):
    """Unit-normalised wxyz quaternion -> Rq [3,3] (in place). Returns the norm, clamped to >= QUAT_EPS
    (a zero quaternion gives the identity)."""
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    if n < QUAT_EPS:
        n = QUAT_EPS
    w, x, y, z = q0 / n, q1 / n, q2 / n, q3 / n
    Rq[0, 0] = 1 - 2 * (y * y + z * z)
    Rq[0, 1] = 2 * (x * y - w * z)
    Rq[0, 2] = 2 * (x * z + w * y)
    Rq[1, 0] = 2 * (x * y + w * z)
    Rq[1, 1] = 1 - 2 * (x * x + z * z)
    Rq[1, 2] = 2 * (y * z - w * x)
    Rq[2, 0] = 2 * (x * z - w * y)
    Rq[2, 1] = 2 * (y * z + w * x)
    Rq[2, 2] = 1 - 2 * (x * x + y * y)
    return n


@njit(**_JIT)
def project_fwd(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, eps2d, near, far,
                means2d, conics, depths, extents):
    """EWA projection for one camera.

    means [N,3], quats [N,4] wxyz, scales [N,3], viewmat [4,4] world->cam (float32);
    writes means2d [N,2], conics [N,3], depths [N] (float32) and extents [N,2] int32 (0 = culled).
    """
    N = means.shape[0]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lxp = (width - cx) / fx + (FOV_CLAMP - 1.0) * tan_x
    lxn = cx / fx + (FOV_CLAMP - 1.0) * tan_x
    lyp = (height - cy) / fy + (FOV_CLAMP - 1.0) * tan_y
    lyn = cy / fy + (FOV_CLAMP - 1.0) * tan_y
    R = viewmat.astype(np.float64)
    nch = (N + CHUNK - 1) // CHUNK
    for ch in prange(nch):
        Rq = np.empty((3, 3))
        A = np.empty((3, 3))
        for i in range(ch * CHUNK, min(N, (ch + 1) * CHUNK)):
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            x = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + R[0, 3]
            y = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + R[1, 3]
            z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + R[2, 3]
            depths[i] = z
            extents[i, 0] = 0
            extents[i, 1] = 0
            valid = z > near and z < far
            zs = z if valid else 1.0
            means2d[i, 0] = fx * x / zs + cx
            means2d[i, 1] = fy * y / zs + cy
            if not valid:
                conics[i, 0] = 0.0
                conics[i, 1] = 0.0
                conics[i, 2] = 0.0
                continue
            _quat_rotmat(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], Rq)
            s0, s1, s2 = np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2])
            # A = R_view Rq S  (Sigma_cam = A A^T)
            for r in range(3):
                a0 = R[r, 0] * Rq[0, 0] + R[r, 1] * Rq[1, 0] + R[r, 2] * Rq[2, 0]
                a1 = R[r, 0] * Rq[0, 1] + R[r, 1] * Rq[1, 1] + R[r, 2] * Rq[2, 1]
                a2 = R[r, 0] * Rq[0, 2] + R[r, 1] * Rq[1, 2] + R[r, 2] * Rq[2, 2]
                A[r, 0] = a0 * s0
                A[r, 1] = a1 * s1
                A[r, 2] = a2 * s2
            tx = z * min(max(x / z, -lxn), lxp)
            ty = z * min(max(y / z, -lyn), lyp)
            J00, J02 = fx / z, -fx * tx / (z * z)
            J11, J12 = fy / z, -fy * ty / (z * z)
            # B = J A  [2,3]
            b00 = J00 * A[0, 0] + J02 * A[2, 0]
            b01 = J00 * A[0, 1] + J02 * A[2, 1]
            b02 = J00 * A[0, 2] + J02 * A[2, 2]
            b10 = J11 * A[1, 0] + J12 * A[2, 0]
            b11 = J11 * A[1, 1] + J12 * A[2, 1]
            b12 = J11 * A[1, 2] + J12 * A[2, 2]
            ca = b00 * b00 + b01 * b01 + b02 * b02 + eps2d
            cb = b00 * b10 + b01 * b11 + b02 * b12
            cc = b10 * b10 + b11 * b11 + b12 * b12 + eps2d
            det = ca * cc - cb * cb
            if not det > 0:
                conics[i, 0] = 0.0
                conics[i, 1] = 0.0
                conics[i, 2] = 0.0
                continue
            conics[i, 0] = cc / det
            conics[i, 1] = -cb / det
            conics[i, 2] = ca / det
            rx = min(math.ceil(EXTENT * math.sqrt(ca)), RADIUS_MAX)  # saturated: int32 extents
            ry = min(math.ceil(EXTENT * math.sqrt(cc)), RADIUS_MAX)
            u, v = means2d[i, 0], means2d[i, 1]
            if u + rx > 0 and u - rx < width and v + ry > 0 and v - ry < height and rx > 0 and ry > 0:
                extents[i, 0] = rx
                extents[i, 1] = ry


@njit(**_JIT)
def project_bwd(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, eps2d, extents,
                v_means2d, v_conics, v_depths, v_means, v_quats, v_scales, v_viewmat_chunks):
    """Backward of `project_fwd` for one camera.

    v_means2d [N,2], v_conics [N,3], v_depths [N] in; writes v_means [N,3], v_quats [N,4], v_scales [N,3]
    and per-chunk view-matrix gradients v_viewmat_chunks [nchunks,3,4] (summed by the caller).
    Culled Gaussians (extent 0) get zero gradients except through the depth output, which the caller
    never uses for them (their depth does not reach any pixel).
    """
    N = means.shape[0]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lxp = (width - cx) / fx + (FOV_CLAMP - 1.0) * tan_x
    lxn = cx / fx + (FOV_CLAMP - 1.0) * tan_x
    lyp = (height - cy) / fy + (FOV_CLAMP - 1.0) * tan_y
    lyn = cy / fy + (FOV_CLAMP - 1.0) * tan_y
    R = viewmat.astype(np.float64)
    nch = (N + CHUNK - 1) // CHUNK
    for ch in prange(nch):
        Rq = np.empty((3, 3))
        M = np.empty((3, 3))
        A = np.empty((3, 3))
        GA = np.empty((3, 3))
        GM = np.empty((3, 3))
        GR = np.zeros((3, 4))
        for i in range(ch * CHUNK, min(N, (ch + 1) * CHUNK)):
            for k in range(3):
                v_means[i, k] = 0.0
                v_scales[i, k] = 0.0
            for k in range(4):
                v_quats[i, k] = 0.0
            if extents[i, 0] == 0:
                continue
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            x = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + R[0, 3]
            y = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + R[1, 3]
            z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + R[2, 3]
            qn = _quat_rotmat(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], Rq)
            s = (np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2]))
            for r in range(3):
                for c in range(3):
                    M[r, c] = Rq[r, c] * s[c]
            for r in range(3):
                for c in range(3):
                    A[r, c] = R[r, 0] * M[0, c] + R[r, 1] * M[1, c] + R[r, 2] * M[2, c]
            xr, yr = x / z, y / z
            x_clip = xr < -lxn or xr > lxp
            y_clip = yr < -lyn or yr > lyp
            tx = z * min(max(xr, -lxn), lxp)
            ty = z * min(max(yr, -lyn), lyp)
            J00, J02 = fx / z, -fx * tx / (z * z)
            J11, J12 = fy / z, -fy * ty / (z * z)
            b00 = J00 * A[0, 0] + J02 * A[2, 0]
            b01 = J00 * A[0, 1] + J02 * A[2, 1]
            b02 = J00 * A[0, 2] + J02 * A[2, 2]
            b10 = J11 * A[1, 0] + J12 * A[2, 0]
            b11 = J11 * A[1, 1] + J12 * A[2, 1]
            b12 = J11 * A[1, 2] + J12 * A[2, 2]
            ca = b00 * b00 + b01 * b01 + b02 * b02 + eps2d
            cb = b00 * b10 + b01 * b11 + b02 * b12
            cc = b10 * b10 + b11 * b11 + b12 * b12 + eps2d
            det = ca * cc - cb * cb
            qa, qb, qc = cc / det, -cb / det, ca / det  # conic Q
            # dL/dQ as a symmetric matrix (off-diagonal entries share the b gradient)
            ga, gb, gc = np.float64(v_conics[i, 0]), 0.5 * np.float64(v_conics[i, 1]), np.float64(v_conics[i, 2])
            # G_cov = -Q G_Q Q
            t00 = qa * ga + qb * gb
            t01 = qa * gb + qb * gc
            t10 = qb * ga + qc * gb
            t11 = qb * gb + qc * gc
            G00 = -(t00 * qa + t01 * qb)
            G01 = -(t00 * qb + t01 * qc)
            G11 = -(t10 * qb + t11 * qc)
            # cov2d = B B^T  ->  G_B = 2 G_cov B
            gb00 = 2 * (G00 * b00 + G01 * b10)
            gb01 = 2 * (G00 * b01 + G01 * b11)
            gb02 = 2 * (G00 * b02 + G01 * b12)
            gb10 = 2 * (G01 * b00 + G11 * b10)
            gb11 = 2 * (G01 * b01 + G11 * b11)
            gb12 = 2 * (G01 * b02 + G11 * b12)
            # B = J A: G_J = G_B A^T, G_A = J^T G_B
            gJ00 = gb00 * A[0, 0] + gb01 * A[0, 1] + gb02 * A[0, 2]
            gJ02 = gb00 * A[2, 0] + gb01 * A[2, 1] + gb02 * A[2, 2]
            gJ11 = gb10 * A[1, 0] + gb11 * A[1, 1] + gb12 * A[1, 2]
            gJ12 = gb10 * A[2, 0] + gb11 * A[2, 1] + gb12 * A[2, 2]
            GA[0, 0], GA[0, 1], GA[0, 2] = J00 * gb00, J00 * gb01, J00 * gb02
            GA[1, 0], GA[1, 1], GA[1, 2] = J11 * gb10, J11 * gb11, J11 * gb12
            GA[2, 0] = J02 * gb00 + J12 * gb10
            GA[2, 1] = J02 * gb01 + J12 * gb11
            GA[2, 2] = J02 * gb02 + J12 * gb12
            # camera-frame point gradient: means2d, depth, Jacobian
            vu, vv = np.float64(v_means2d[i, 0]), np.float64(v_means2d[i, 1])
            iz = 1.0 / z
            iz2 = iz * iz
            gx = fx * iz * vu
            gy = fy * iz * vv
            gz = -fx * x * iz2 * vu - fy * y * iz2 * vv + np.float64(v_depths[i])
            gz += -fx * iz2 * gJ00 - fy * iz2 * gJ11 + 2 * fx * tx * iz2 * iz * gJ02 + 2 * fy * ty * iz2 * iz * gJ12
            gtx = -fx * iz2 * gJ02
            gty = -fy * iz2 * gJ12
            if x_clip:
                gz += min(max(xr, -lxn), lxp) * gtx
            else:
                gx += gtx
            if y_clip:
                gz += min(max(yr, -lyn), lyp) * gty
            else:
                gy += gty
            # A = R_view M:  G_R += G_A M^T,  G_M = R^T G_A
            for r in range(3):
                for c in range(3):
                    GR[r, c] += GA[r, 0] * M[c, 0] + GA[r, 1] * M[c, 1] + GA[r, 2] * M[c, 2]
                    GM[r, c] = R[0, r] * GA[0, c] + R[1, r] * GA[1, c] + R[2, r] * GA[2, c]
            # p = R m + t
            GR[0, 0] += gx * mx
            GR[0, 1] += gx * my
            GR[0, 2] += gx * mz
            GR[1, 0] += gy * mx
            GR[1, 1] += gy * my
            GR[1, 2] += gy * mz
            GR[2, 0] += gz * mx
            GR[2, 1] += gz * my
            GR[2, 2] += gz * mz
            GR[0, 3] += gx
            GR[1, 3] += gy
            GR[2, 3] += gz
            v_means[i, 0] = R[0, 0] * gx + R[1, 0] * gy + R[2, 0] * gz
            v_means[i, 1] = R[0, 1] * gx + R[1, 1] * gy + R[2, 1] * gz
            v_means[i, 2] = R[0, 2] * gx + R[1, 2] * gy + R[2, 2] * gz
            # M = Rq S
            for c in range(3):
                v_scales[i, c] = GM[0, c] * Rq[0, c] + GM[1, c] * Rq[1, c] + GM[2, c] * Rq[2, c]
                for r in range(3):
                    GM[r, c] *= s[c]  # now G_Rq
            w, qx, qy, qz = quats[i, 0] / qn, quats[i, 1] / qn, quats[i, 2] / qn, quats[i, 3] / qn
            G = GM
            vw = 2 * (qx * (G[2, 1] - G[1, 2]) + qy * (G[0, 2] - G[2, 0]) + qz * (G[1, 0] - G[0, 1]))
            vx = 2 * (-2 * qx * (G[1, 1] + G[2, 2]) + qy * (G[1, 0] + G[0, 1]) + qz * (G[2, 0] + G[0, 2])
                      + w * (G[2, 1] - G[1, 2]))
            vy = 2 * (qx * (G[1, 0] + G[0, 1]) - 2 * qy * (G[0, 0] + G[2, 2]) + qz * (G[2, 1] + G[1, 2])
                      + w * (G[0, 2] - G[2, 0]))
            vz = 2 * (qx * (G[2, 0] + G[0, 2]) + qy * (G[2, 1] + G[1, 2]) - 2 * qz * (G[0, 0] + G[1, 1])
                      + w * (G[1, 0] - G[0, 1]))
            dot = w * vw + qx * vx + qy * vy + qz * vz
            if qn <= QUAT_EPS:  # the norm was clamped: q / eps, no normalising projection (as the reference)
                dot = dot * 0
            v_quats[i, 0] = (vw - w * dot) / qn
            v_quats[i, 1] = (vx - qx * dot) / qn
            v_quats[i, 2] = (vy - qy * dot) / qn
            v_quats[i, 3] = (vz - qz * dot) / qn
        for r in range(3):
            for c in range(4):
                v_viewmat_chunks[ch, r, c] = GR[r, c]


# --------------------------------------------------------------------------------------------------------
# spherical harmonics
# --------------------------------------------------------------------------------------------------------
@njit(**_JIT1)
def _sh_basis(x, y, z, degree, Y, dY):
    """Basis Y [16] and its gradient dY [16,3] w.r.t. the unit direction (x, y, z), up to `degree`.

    Entries of dY that are structurally zero are never written: callers pass zero-initialised arrays."""
    Y[0] = SH_C0
    if degree < 1:
        return
    Y[1], dY[1, 1] = -SH_C1 * y, -SH_C1
    Y[2], dY[2, 2] = SH_C1 * z, SH_C1
    Y[3], dY[3, 0] = -SH_C1 * x, -SH_C1
    if degree < 2:
        return
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    Y[4], dY[4, 0], dY[4, 1] = SH_C2_0 * xy, SH_C2_0 * y, SH_C2_0 * x
    Y[5], dY[5, 1], dY[5, 2] = SH_C2_1 * yz, SH_C2_1 * z, SH_C2_1 * y
    Y[6] = SH_C2_2 * (2 * zz - xx - yy)
    dY[6, 0], dY[6, 1], dY[6, 2] = -2 * SH_C2_2 * x, -2 * SH_C2_2 * y, 4 * SH_C2_2 * z
    Y[7], dY[7, 0], dY[7, 2] = SH_C2_3 * xz, SH_C2_3 * z, SH_C2_3 * x
    Y[8], dY[8, 0], dY[8, 1] = SH_C2_4 * (xx - yy), 2 * SH_C2_4 * x, -2 * SH_C2_4 * y
    if degree < 3:
        return
    Y[9] = SH_C3_0 * y * (3 * xx - yy)
    dY[9, 0], dY[9, 1] = 6 * SH_C3_0 * xy, SH_C3_0 * (3 * xx - 3 * yy)
    Y[10] = SH_C3_1 * xy * z
    dY[10, 0], dY[10, 1], dY[10, 2] = SH_C3_1 * yz, SH_C3_1 * xz, SH_C3_1 * xy
    Y[11] = SH_C3_2 * y * (4 * zz - xx - yy)
    dY[11, 0], dY[11, 1], dY[11, 2] = -2 * SH_C3_2 * xy, SH_C3_2 * (4 * zz - xx - 3 * yy), 8 * SH_C3_2 * yz
    Y[12] = SH_C3_3 * z * (2 * zz - 3 * xx - 3 * yy)
    dY[12, 0], dY[12, 1], dY[12, 2] = -6 * SH_C3_3 * xz, -6 * SH_C3_3 * yz, SH_C3_3 * (6 * zz - 3 * xx - 3 * yy)
    Y[13] = SH_C3_4 * x * (4 * zz - xx - yy)
    dY[13, 0], dY[13, 1], dY[13, 2] = SH_C3_4 * (4 * zz - 3 * xx - yy), -2 * SH_C3_4 * xy, 8 * SH_C3_4 * xz
    Y[14] = SH_C3_5 * z * (xx - yy)
    dY[14, 0], dY[14, 1], dY[14, 2] = 2 * SH_C3_5 * xz, -2 * SH_C3_5 * yz, SH_C3_5 * (xx - yy)
    Y[15] = SH_C3_6 * x * (xx - 3 * yy)
    dY[15, 0], dY[15, 1] = SH_C3_6 * (3 * xx - 3 * yy), -6 * SH_C3_6 * xy


@njit(**_JIT)
def sh_fwd(dirs, coeffs, degree, colors):
    """colors [N,3] = max(0, 0.5 + sum_k Y_k(dirs/|dirs|) coeffs[:,k]). dirs [N,3], coeffs [N,K,3]."""
    N = dirs.shape[0]
    nb = (degree + 1) * (degree + 1)
    nch = (N + CHUNK - 1) // CHUNK
    for ch in prange(nch):
        Y = np.zeros(16)
        dY = np.zeros((16, 3))
        for i in range(ch * CHUNK, min(N, (ch + 1) * CHUNK)):
            dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
            n = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            _sh_basis(dx / n, dy / n, dz / n, degree, Y, dY)
            r, g, b = 0.5, 0.5, 0.5
            for k in range(nb):
                r += Y[k] * coeffs[i, k, 0]
                g += Y[k] * coeffs[i, k, 1]
                b += Y[k] * coeffs[i, k, 2]
            colors[i, 0] = max(r, 0.0)
            colors[i, 1] = max(g, 0.0)
            colors[i, 2] = max(b, 0.0)


@njit(**_JIT)
def sh_bwd(dirs, coeffs, degree, v_colors, v_coeffs, v_dirs, accumulate):
    """Backward of `sh_fwd`: writes (or adds to, if `accumulate`) v_coeffs [N,K,3] (entries beyond the
    degree get zero) and writes v_dirs [N,3]."""
    N = dirs.shape[0]
    K = coeffs.shape[1]
    nb = (degree + 1) * (degree + 1)
    nch = (N + CHUNK - 1) // CHUNK
    for ch in prange(nch):
        Y = np.zeros(16)
        dY = np.zeros((16, 3))
        gcl = np.zeros(3)
        for i in range(ch * CHUNK, min(N, (ch + 1) * CHUNK)):
            if v_colors[i, 0] == 0.0 and v_colors[i, 1] == 0.0 and v_colors[i, 2] == 0.0:
                # not drawn in this camera (or no gradient): zero gradients, no basis to evaluate
                if not accumulate:
                    for k in range(K):
                        for c in range(3):
                            v_coeffs[i, k, c] = 0.0
                v_dirs[i, 0] = 0.0
                v_dirs[i, 1] = 0.0
                v_dirs[i, 2] = 0.0
                continue
            dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
            n = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            ux, uy, uz = dx / n, dy / n, dz / n
            _sh_basis(ux, uy, uz, degree, Y, dY)
            for c in range(3):
                acc = 0.5
                for k in range(nb):
                    acc += Y[k] * coeffs[i, k, c]
                gcl[c] = np.float64(v_colors[i, c]) if acc >= 0.0 else 0.0
            gux, guy, guz = 0.0, 0.0, 0.0
            for k in range(nb):
                gc = coeffs[i, k, 0] * gcl[0] + coeffs[i, k, 1] * gcl[1] + coeffs[i, k, 2] * gcl[2]
                gux += dY[k, 0] * gc
                guy += dY[k, 1] * gc
                guz += dY[k, 2] * gc
                if accumulate:
                    for c in range(3):
                        v_coeffs[i, k, c] += Y[k] * gcl[c]
                else:
                    for c in range(3):
                        v_coeffs[i, k, c] = Y[k] * gcl[c]
            if not accumulate:
                for k in range(nb, K):
                    for c in range(3):
                        v_coeffs[i, k, c] = 0.0
            dot = ux * gux + uy * guy + uz * guz
            v_dirs[i, 0] = (gux - ux * dot) / n
            v_dirs[i, 1] = (guy - uy * dot) / n
            v_dirs[i, 2] = (guz - uz * dot) / n


# --------------------------------------------------------------------------------------------------------
# tile binning
# --------------------------------------------------------------------------------------------------------
# record layout of one (Gaussian, camera): float32 columns
R_U, R_V, R_A, R_B, R_C, R_OP, R_X0, R_X1, R_Y0, R_Y1, R_LEVEL, R_LOP = range(12)
R_COL = 12  # colour channels from here (D of them)


@njit(**_JIT1)
def _levels(op):
    """(log(255 op), log(op)) of an opacity, guarded for op <= 0 (those are never drawn)."""
    if op * 255.0 < 1.0:
        return 0.0, -1e30
    return math.log(op * 255.0), math.log(op)


@njit(**_JIT)
def make_records(means2d, conics, colors, opacities, extents, width, height, rec, ntiles):
    """Per Gaussian one float32 record rec [N, 12+D]: u, v, conic a, b, c, opacity, inclusive pixel box
    x0, x1, y0, y1 (integers, exact in float32), level = log(255 opacity) (sigma above it gives alpha <
    1/255) and log(opacity) (computed once here rather than per tile), colours [D]; and its number of touched tiles ntiles [N]
    (0: not drawn; an upper bound: `bin_tiles` leaves out the tiles of the box the ellipse misses, see
    `_touches`). One record = one cache line or two: binning copies it into every tile list it touches,
    so the compositing kernels stream each tile's Gaussians from consecutive memory.

    The box holds the pixel centres inside the 3-sigma box (`extents`) that are also inside the bounding
    box of the ellipse sigma <= log(255 opacity), outside which alpha < 1/255 and the compositing kernels
    skip the pixel anyway: the same image from fewer tiles and rows for faint Gaussians (a 0.01 px margin
    absorbs rounding, as in `_row_spans`)."""
    N = means2d.shape[0]
    D = colors.shape[1]
    for i in prange(N):
        rx, ry = np.float64(extents[i, 0]), np.float64(extents[i, 1])
        ntiles[i] = 0
        op = np.float64(opacities[i])
        u, v = np.float64(means2d[i, 0]), np.float64(means2d[i, 1])
        ca, cb, cc = np.float64(conics[i, 0]), np.float64(conics[i, 1]), np.float64(conics[i, 2])
        rec[i, R_U] = means2d[i, 0]
        rec[i, R_V] = means2d[i, 1]
        rec[i, R_A] = conics[i, 0]
        rec[i, R_B] = conics[i, 1]
        rec[i, R_C] = conics[i, 2]
        rec[i, R_OP] = opacities[i]
        rec[i, R_LEVEL], rec[i, R_LOP] = _levels(op)
        for d in range(D):
            rec[i, R_COL + d] = colors[i, d]
        rec[i, R_X0] = 0.0
        rec[i, R_X1] = -1.0
        rec[i, R_Y0] = 0.0
        rec[i, R_Y1] = -1.0
        det = ca * cc - cb * cb
        # alpha < 1/255 everywhere, a NaN or infinite opacity (never drawn, as the reference: binned, a NaN one
        # sent NaN into the fastmath kernels and came back as a NaN opacity gradient), or a conic that is not
        # positive definite: never drawn
        if rx == 0 or not (1.0 <= op * 255.0 < math.inf) or not (ca > 0.0 and det > 0.0):
            continue
        two_level = 2.0 * math.log(op * 255.0)
        rx = min(rx, math.sqrt(two_level * cc / det) + 0.01)  # sigma_xx = c / det of the conic
        ry = min(ry, math.sqrt(two_level * ca / det) + 0.01)
        x0 = max(int(math.ceil(u - rx - 0.5)), 0)
        x1 = min(int(math.floor(u + rx - 0.5)), width - 1)
        y0 = max(int(math.ceil(v - ry - 0.5)), 0)
        y1 = min(int(math.floor(v + ry - 0.5)), height - 1)
        if x0 > x1 or y0 > y1:
            continue
        rec[i, R_X0], rec[i, R_X1], rec[i, R_Y0], rec[i, R_Y1] = x0, x1, y0, y1
        ntiles[i] = (x1 // TILE - x0 // TILE + 1) * (y1 // TILE - y0 // TILE + 1)


@njit(**_JIT1)
def _touches(u, v, ca, cb, cc, level, x0, x1, y0, y1):
    """True if some point of the rectangle of pixel centres [x0 + 1/2, x1 + 1/2] x [y0 + 1/2, y1 + 1/2] has
    sigma <= level (+ 1e-3, for rounding): the exact test of a convex quadratic against a rectangle (the
    minimum is the centre, or on an edge: a clamped 1-D minimum per edge). Tiles of a Gaussian's box that
    fail it hold no pixel with alpha >= 1/255 (gsplat's and 3DGS's bounding boxes list them anyway: ~9 % of
    the pairs of a trained model)."""
    dxa, dxb = u - (x1 + 0.5), u - (x0 + 0.5)  # dx = u - pixel centre over the rectangle
    dya, dyb = v - (y1 + 0.5), v - (y0 + 0.5)
    if dxa <= 0.0 <= dxb and dya <= 0.0 <= dyb:
        return True
    best = math.inf
    b_c, b_a = cb / cc, cb / ca
    for X in (dxa, dxb):  # vertical edges
        dy = min(max(-b_c * X, dya), dyb)
        best = min(best, 0.5 * ca * X * X + cb * X * dy + 0.5 * cc * dy * dy)
    for Y in (dya, dyb):  # horizontal edges
        dx = min(max(-b_a * Y, dxa), dxb)
        best = min(best, 0.5 * ca * dx * dx + cb * dx * Y + 0.5 * cc * Y * Y)
    return best <= level + 1e-3


@njit(**_JIT1)
def _tile_hit(r, tx, ty):
    """Whether record r's ellipse reaches tile (tx, ty) of its box (the part of the tile inside the box).
    Always true when the box spans one tile row or column: an ellipse crosses every column (row) of its
    bounding box, and the box is that, clipped (most Gaussians: no test)."""
    bx0, bx1, by0, by1 = np.int64(r[R_X0]), np.int64(r[R_X1]), np.int64(r[R_Y0]), np.int64(r[R_Y1])
    if bx0 // TILE == bx1 // TILE or by0 // TILE == by1 // TILE:
        return True
    x0, x1 = max(np.int64(r[R_X0]), tx * TILE), min(np.int64(r[R_X1]), tx * TILE + TILE - 1)
    y0, y1 = max(np.int64(r[R_Y0]), ty * TILE), min(np.int64(r[R_Y1]), ty * TILE + TILE - 1)
    return _touches(np.float64(r[R_U]), np.float64(r[R_V]), np.float64(r[R_A]), np.float64(r[R_B]),
                    np.float64(r[R_C]), np.float64(r[R_LEVEL]), x0, x1, y0, y1)


BIN_CHUNKS = 16  # depth-order chunks binned in parallel (fixed: the output does not depend on threads)


@njit(**_JIT)
def bin_tiles(order, rec, width, height, tile_start, packed, rank_off, rank_isect):
    """Counting sort of (tile, Gaussian) pairs by tile, Gaussians taken in depth `order` [n] (drawn
    Gaussians only), each pair's record copied: packed [M, 10+D] holds tile t's Gaussians, depth-sorted, at
    rows tile_start[t]:tile_start[t+1] (tile_start [T+1], out), so a tile's compositing streams through
    consecutive memory (scattered reads made the 640x480 / 200k case 2x slower per pair than 320x240).
    rank_off [n+1] (out): prefix sum of the touched tiles in depth order; rank_isect [M] (out): the packed
    rows of the Gaussian of depth rank j are rank_isect[rank_off[j]:rank_off[j+1]] (to reduce gradients).
    packed and rank_isect may be longer than needed (sized by make_records' box counts): M = tile_start[T]
    rows are used (box tiles the ellipse misses, `_tile_hit`, are not listed).

    The records are first gathered in depth order (one random read per Gaussian), then binned in parallel
    over BIN_CHUNKS consecutive chunks of that order: each chunk counts its pairs per tile, a prefix sum over
    (tile, chunk) gives every chunk its own cursor in each tile's list, and the chunks scatter independently
    - the same output as one sequential pass.
    """
    tw = (width + TILE - 1) // TILE
    T = tile_start.shape[0] - 1
    n = order.shape[0]
    RW = rec.shape[1]
    P = BIN_CHUNKS
    size = (n + P - 1) // P
    srt = np.empty((n, RW), np.float32)
    nt = np.empty(n, np.int64)
    hits = np.empty(n, np.uint64)
    cursor = np.zeros((P, T), np.int64)
    for p in prange(P):
        for j in range(p * size, min(n, (p + 1) * size)):
            g = order[j]
            for c in range(RW):
                srt[j, c] = rec[g, c]
            x0, x1 = np.int64(srt[j, R_X0]) // TILE, np.int64(srt[j, R_X1]) // TILE
            y0, y1 = np.int64(srt[j, R_Y0]) // TILE, np.int64(srt[j, R_Y1]) // TILE
            test = x0 != x1 and y0 != y1  # a single row or column of tiles: all reached (`_tile_hit`)
            c = 0
            bits = np.uint64(0)  # which box tiles are reached (the first 64), for the scatter pass
            b = 0
            for ty in range(y0, y1 + 1):
                for tx in range(x0, x1 + 1):
                    if not test or _tile_hit(srt[j], tx, ty):
                        cursor[p, ty * tw + tx] += 1
                        c += 1
                        if b < 64:
                            bits |= np.uint64(1) << np.uint64(b)
                    b += 1
            nt[j] = c
            hits[j] = bits
    pos = 0
    for t in range(T):
        tile_start[t] = pos
        for p in range(P):
            c = cursor[p, t]
            cursor[p, t] = pos
            pos += c
    tile_start[T] = pos
    rank_off[0] = 0
    for j in range(n):
        rank_off[j + 1] = rank_off[j] + nt[j]
    for p in prange(P):
        for j in range(p * size, min(n, (p + 1) * size)):
            k = rank_off[j]
            x0, x1 = np.int64(srt[j, R_X0]) // TILE, np.int64(srt[j, R_X1]) // TILE
            y0, y1 = np.int64(srt[j, R_Y0]) // TILE, np.int64(srt[j, R_Y1]) // TILE
            test = x0 != x1 and y0 != y1
            bits = hits[j]
            b = -1
            for ty in range(y0, y1 + 1):
                for tx in range(x0, x1 + 1):
                    b += 1
                    if test:
                        hit = (bits >> np.uint64(b)) & np.uint64(1) if b < 64 else _tile_hit(srt[j], tx, ty)
                        if not hit:
                            continue
                    t = ty * tw + tx
                    q = cursor[p, t]
                    cursor[p, t] = q + 1
                    for c in range(RW):
                        packed[q, c] = srt[j, c]
                    rank_isect[k] = q
                    k += 1


@njit(**_JIT)
def reduce_isect_grads(isect_grad, order, rank_off, rank_isect, out):
    """out [N, 6+D] = sum of each Gaussian's pair rows (fixed order: deterministic); zero for Gaussians
    that were not drawn. isect_grad [M, 6+D] per packed pair; order, rank_off, rank_isect from bin_tiles."""
    N = out.shape[0]
    J = out.shape[1]
    n = order.shape[0]
    for g in prange(N):
        for j in range(J):
            out[g, j] = 0.0
    nch = (n + CHUNK - 1) // CHUNK
    for ch in prange(nch):
        acc = np.zeros(J)
        for r in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            for j in range(J):
                acc[j] = 0.0
            for k in range(rank_off[r], rank_off[r + 1]):
                pos = rank_isect[k]
                for j in range(J):
                    acc[j] += isect_grad[pos, j]
            g = order[r]
            for j in range(J):
                out[g, j] = acc[j]


# --------------------------------------------------------------------------------------------------------
# compositing
# --------------------------------------------------------------------------------------------------------
# The compositing kernels work on one tile row at a time, all 16 pixels of it as SIMD lanes in float32:
# every per-pixel update is a select, not a branch, so LLVM vectorises the lane loops (float32: twice the
# lanes of float64 per instruction). Per-tile state lives in stack buffers (`_stack`): LLVM knows distinct
# stack buffers never overlap, whereas for numba's heap arrays it must add run-time overlap checks to every
# vectorised loop (they cost as much as the loop).
#
# alpha of a lane is exp(log(opacity) - sigma) from a vectorisable float32 exp (`_exp32`), with sigma written
# about the row's minimum: sigma = a/2 t^2 + sigma_min(row), t = dx + (b/a) dy. The per-row terms are float64
# scalars, so no large terms cancel in float32 (as they would in a/2 dx^2 + b dx dy + c/2 dy^2 for a thin
# Gaussian far from its centre); float32 alphas are within a few 1e-7 of float64 ones (tested).
assert TILE == 16  # the stack buffers below are sized by literals (16 lanes, 256 pixels)


def _stack_intrinsic(nbtype):
    @_intrinsic
    def _stack(typingctx, n):
        """Pointer to a stack buffer of n (an integer literal) elements, for `carray`."""
        if not isinstance(n, _nbt.IntegerLiteral):
            return None
        size = n.literal_value

        def codegen(context, builder, signature, args):
            ty = context.get_value_type(nbtype)
            buf = _cgutils.alloca_once(builder, _ir.ArrayType(ty, size))  # in the entry block: no stack growth
            return builder.bitcast(buf, ty.as_pointer())
        return _nbt.CPointer(nbtype)(n), codegen
    return _stack


_stack_f32 = _stack_intrinsic(_nbt.float32)
_stack_i32 = _stack_intrinsic(_nbt.int32)


@_intrinsic
def _bits_to_f32(typingctx, x):
    """The float32 whose bit pattern is the int32 x (a free register move, and vectorisable)."""
    if x != _nbt.int32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], _ir.FloatType())
    return _nbt.float32(_nbt.int32), codegen


_F0, _F1, _HALF = np.float32(0.0), np.float32(1.0), np.float32(0.5)
_A_MAX, _A_MIN, _T_MIN = np.float32(ALPHA_MAX), np.float32(ALPHA_MIN), np.float32(T_MIN)
EXP_LO = np.float32(-30.0)  # exp(-30) ~ 1e-13 << 1/255: lanes below are masked off, and never denormal
_LOG2E, _LN2_HI, _LN2_LO = np.float32(1.4426950408889634), np.float32(0.693359375), np.float32(-2.12194440e-4)
_E0, _E1, _E2 = np.float32(1.9875691500e-4), np.float32(1.3981999507e-3), np.float32(8.3334519073e-3)
_E3, _E4, _E5 = np.float32(4.1665795894e-2), np.float32(1.6666665459e-1), np.float32(5.0000001201e-1)
_EXP_BIAS, _EXP_SHIFT = np.float32(127.0), np.float32(8388608.0)  # 2^k as bits: (k + 127) << 23


@njit(**_JIT1F)
def _exp32(x):
    """exp(x) for a float32 x in [-87, 0], within 2 ulp (Cephes' expf: x = k ln2 + r, |r| <= ln2/2, a degree-6
    polynomial for exp(r), 2^k assembled from its bits). Plain arithmetic, so LLVM vectorises it in the lane
    loops (numba's math.exp stays a scalar libm call per lane)."""
    fk = np.floor(x * _LOG2E + _HALF)
    r = x - fk * _LN2_HI - fk * _LN2_LO
    p = ((((_E0 * r + _E1) * r + _E2) * r + _E3) * r + _E4) * r + _E5
    y = p * r * r + r + _F1
    return y * _bits_to_f32(np.int32((fk + _EXP_BIAS) * _EXP_SHIFT))


@njit(**_JIT1)
def _pair_consts(ca, cb, cc):
    """Per-(tile, Gaussian) constants of the conic (a, b, c): b/a, det/(2a), a/2, 2/a."""
    ia = 1.0 / ca
    return cb * ia, 0.5 * (ca * cc - cb * cb) * ia, 0.5 * ca, 2.0 * ia


@njit(**_JIT1)
def _fold16(A, n):
    """A[j, 0] = sum of A[j, :16] for j < n, by halving (vector adds; float32 sums of 16 per-lane sums)."""
    for w in (8, 4, 2, 1):
        for j in range(n):
            for i in range(w):
                A[j, i] += A[j, i + w]


@njit(**_JIT1)
def _rows(v, ty0, ry0, ry1, dx0, b_a, hdet_a, inv_ha, level, lop, bx0, bx1, nrows, IA, IB, EF, EL, CF, DY):
    """The rows of a (tile, Gaussian) pair, all 16 in one loop LLVM vectorises (row by row, the sqrt-round
    chain of each row stalls the lane loops). Row j (pixel row ty0 + j) gets lanes [IA[j], IB[j]] (tile-
    relative, inside the pair's box columns bx0..bx1 and rows ry0..ry1) that may hold alpha >= 1/255 (IA >
    IB: none; a 0.01 px margin absorbs rounding, every lane is still tested); lane i there has
    t = (EF[j] - i) + EL[j] (EF + EL = e in float64) and log(op) - sigma = CF[j] - a/2 t^2; DY[j] = v -
    the row's pixel centre. nrows = 16 (a run-time value: see raster_fwd)."""
    for j in range(nrows):
        dy = v - (ty0 + j + 0.5)
        smin = hdet_a * dy * dy
        e = dx0 + b_a * dy
        w = math.sqrt(max(level - smin, 0.0) * inv_ha) + 0.01
        ia = max(np.float64(bx0), math.ceil(min(max(e - w, -1.0), 17.0)))
        ib = min(np.float64(bx1), math.floor(min(max(e + w, -1.0), 17.0)))
        full = (smin <= level + 0.01) & (j >= ry0) & (j <= ry1)
        IA[j] = np.float32(ia)
        IB[j] = np.float32(ib if full else ia - 1.0)
        ef = np.float32(e)
        EF[j] = ef
        EL[j] = np.float32(e - np.float64(ef))  # t = (EF - i) + EL: the first difference is exact
        CF[j] = np.float32(lop - smin)
        DY[j] = np.float32(dy)


@njit(**_JIT1)
def _window(ia, ib):
    """Lanes [l0, l0 + n) to compute for a row span [ia, ib] (float lane indices): 8 lanes from min(ia, 8)
    when the span fits in 8 (most rows of most Gaussians: one SIMD vector of float32 instead of two), else
    all 16."""
    if ib - ia < 8.0:
        return max(min(np.int64(ia), 8), 0), 8  # (max: provably >= 0, or numba's negative-index wrap stops
    return 0, TILE  # vectorisation)


@njit(**_JITF)
def raster_fwd(packed, tile_start, tile_perm, width, height, render, final_T, last):
    """Front-to-back compositing per 16x16 tile.

    packed [M, 10+D] from `bin_tiles`; tile_perm [T] a permutation of the tiles (work order); writes render
    [H,W,D] (no background), final_T [H,W] and last [H,W] int32 (position in its tile's list of the last
    Gaussian that contributed to the pixel, -1 if none).
    """
    D = packed.shape[1] - R_COL
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    for it in prange(tw * th):
        t = tile_perm[it]  # shuffled: numba splits the range statically, this balances the threads
        tx0, ty0 = (t % tw) * TILE, (t // tw) * TILE
        tx1, ty1 = min(tx0 + TILE, width) - 1, min(ty0 + TILE, height) - 1
        npix = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
        Tl = carray(_stack_f32(256), (TILE, TILE))  # transmittance
        live = carray(_stack_f32(256), (TILE, TILE))  # 1: not terminated
        lastl = carray(_stack_i32(256), (TILE, TILE))  # last contributing list position
        lane = carray(_stack_f32(16), TILE)  # 0, 1, ..., 15
        wb = carray(_stack_f32(16), TILE)  # blending weight alpha T per lane
        IA, IB = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)  # per row of a pair (`_rows`)
        EF, EL = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)
        CF, DY = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)
        # 16, but not a compile-time constant: LLVM fully unrolls a constant 16-iteration loop and then fails
        # to re-vectorise it
        nrows = TILE if width > 0 else 0
        for i in range(TILE):
            lane[i] = i
        for r in range(TILE):
            for i in range(TILE):
                Tl[r, i] = 1.0
                live[r, i] = 1.0
                lastl[r, i] = -1
        acc = np.zeros((D, TILE, TILE), np.float32)
        cg = np.zeros(D, np.float32)
        ndone = 0
        k0 = tile_start[t]
        for k in range(k0, tile_start[t + 1]):
            u, v = np.float64(packed[k, R_U]), np.float64(packed[k, R_V])
            ca, cb, cc = np.float64(packed[k, R_A]), np.float64(packed[k, R_B]), np.float64(packed[k, R_C])
            op = np.float64(packed[k, R_OP])
            if op * 255.0 < 1.0 or not (ca > 0.0 and ca * cc - cb * cb > 0.0):  # never drawn
                continue
            bx0, bx1 = max(np.int64(packed[k, R_X0]), tx0) - tx0, min(np.int64(packed[k, R_X1]), tx1) - tx0
            ry0, ry1 = max(np.int64(packed[k, R_Y0]), ty0) - ty0, min(np.int64(packed[k, R_Y1]), ty1) - ty0
            level, lop = np.float64(packed[k, R_LEVEL]), np.float64(packed[k, R_LOP])
            b_a, hdet_a, ha, inv_ha = _pair_consts(ca, cb, cc)
            haf = np.float32(ha)
            for d in range(D):
                cg[d] = packed[k, R_COL + d]
            kk = np.int32(k - k0)
            _rows(v, ty0, ry0, ry1, u - (tx0 + 0.5), b_a, hdet_a, inv_ha, level, lop, bx0, bx1, nrows, IA, IB, EF, EL,
                  CF, DY)
            for r in range(ry0, ry1 + 1):
                iaf, ibf = IA[r], IB[r]
                if iaf > ibf:
                    continue
                ef, el, cf = EF[r], EL[r], CF[r]
                l0, nl = _window(iaf, ibf)
                nfin = 0
                for i in range(l0, l0 + nl):
                    tt = (ef - lane[i]) + el
                    a_raw = _exp32(max(cf - haf * tt * tt, EXP_LO))
                    alpha = min(_A_MAX, a_raw)
                    T = Tl[r, i]
                    nT = T * (_F1 - alpha)
                    on = (lane[i] >= iaf) & (lane[i] <= ibf) & (a_raw >= _A_MIN) & (live[r, i] > _F0)
                    fin = on & (nT < _T_MIN)  # would drop below T_MIN: the pixel ends before this Gaussian
                    draw = on & (nT >= _T_MIN)
                    wb[i] = alpha * T if draw else _F0
                    Tl[r, i] = nT if draw else T
                    live[r, i] = _F0 if fin else live[r, i]
                    lastl[r, i] = kk if draw else lastl[r, i]
                    nfin += 1 if fin else 0
                for d in range(D):
                    c = cg[d]
                    for i in range(l0, l0 + nl):
                        acc[d, r, i] += wb[i] * c
                ndone += nfin
            if ndone == npix:
                break
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
                r, i = py - ty0, px - tx0
                for d in range(D):
                    render[py, px, d] = acc[d, r, i]
                final_T[py, px] = Tl[r, i]
                last[py, px] = lastl[r, i]


@njit(**_JITF)
def raster_bwd(packed, tile_start, tile_perm, width, height, final_T, last, v_render, v_alpha, isect_grad):
    """Back-to-front gradient of `raster_fwd` per tile (as in 3DGS), the same lanes and alphas.

    packed [M, 10+D]; final_T [H,W], last [H,W] from raster_fwd (the backward pass starts at the last
    contributor of any pixel of the tile); v_render [H,W,D], v_alpha [H,W] (gradient of the alpha image).
    Writes isect_grad [M, 6+D]: per list position the gradient w.r.t. (u, v, conic a, b, c, opacity,
    colour[D]) of that Gaussian from that tile's pixels. Rows of positions no pixel reached are zeroed.
    """
    D = packed.shape[1] - R_COL
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    for it in prange(tw * th):
        t = tile_perm[it]  # shuffled: numba splits the range statically, this balances the threads
        tx0, ty0 = (t % tw) * TILE, (t // tw) * TILE
        tx1, ty1 = min(tx0 + TILE, width) - 1, min(ty0 + TILE, height) - 1
        Tl = carray(_stack_f32(256), (TILE, TILE))  # transmittance behind the current Gaussian
        Tf = carray(_stack_f32(256), (TILE, TILE))  # final transmittance
        lastl = carray(_stack_i32(256), (TILE, TILE))
        va = carray(_stack_f32(256), (TILE, TILE))
        lane = carray(_stack_f32(16), TILE)  # 0, 1, ..., 15
        alb = carray(_stack_f32(16), TILE)  # per lane of the current row: alpha, 1 - alpha, 1 / (1 - alpha),
        omb = carray(_stack_f32(16), TILE)  # T in front, blending weight, dL/dalpha (colour part), and
        ivb = carray(_stack_f32(16), TILE)  # unclamped alpha where alpha depends on sigma and opacity
        Tb = carray(_stack_f32(16), TILE)
        wb = carray(_stack_f32(16), TILE)
        dlb = carray(_stack_f32(16), TILE)
        qb = carray(_stack_f32(16), TILE)
        # per-lane sums over the pair's pixels of q = alpha_raw dL/dalpha times dx, dx^2, dy, dx dy, dy^2, 1
        P = carray(_stack_f32(96), (6, TILE))
        IA, IB = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)  # per row of a pair (`_rows`)
        EF, EL = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)
        CF, DY = carray(_stack_f32(16), TILE), carray(_stack_f32(16), TILE)
        S = np.zeros((D, TILE, TILE), np.float32)  # colour accumulated behind the current Gaussian
        vr = np.zeros((D, TILE, TILE), np.float32)
        gcl = np.zeros((D, TILE), np.float32)
        cg = np.zeros(D, np.float32)
        kmax = -1
        # 16, but not a compile-time constant: LLVM fully unrolls a constant 16-iteration loop and then fails
        # to re-vectorise it (the colour loop became 16 scalar lanes per channel)
        nlanes = TILE if width > 0 else 0
        for i in range(TILE):
            lane[i] = i
        for r in range(TILE):
            for i in range(TILE):
                Tl[r, i] = 1.0
                Tf[r, i] = 1.0
                lastl[r, i] = -1
                va[r, i] = 0.0
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
                r, i = py - ty0, px - tx0
                Tl[r, i] = final_T[py, px]
                Tf[r, i] = final_T[py, px]
                lastl[r, i] = last[py, px]
                kmax = max(kmax, np.int64(last[py, px]))
                for d in range(D):
                    vr[d, r, i] = v_render[py, px, d]
                va[r, i] = v_alpha[py, px]
        k0 = tile_start[t]
        for k in range(k0 + kmax + 1, tile_start[t + 1]):
            for j in range(6 + D):
                isect_grad[k, j] = 0.0
        for k in range(k0 + kmax, k0 - 1, -1):
            for j in range(6 + D):
                isect_grad[k, j] = 0.0
            u, v = np.float64(packed[k, R_U]), np.float64(packed[k, R_V])
            ca, cb, cc = np.float64(packed[k, R_A]), np.float64(packed[k, R_B]), np.float64(packed[k, R_C])
            op = np.float64(packed[k, R_OP])
            if op * 255.0 < 1.0 or not (ca > 0.0 and ca * cc - cb * cb > 0.0):  # never drawn
                continue
            bx0, bx1 = max(np.int64(packed[k, R_X0]), tx0) - tx0, min(np.int64(packed[k, R_X1]), tx1) - tx0
            ry0, ry1 = max(np.int64(packed[k, R_Y0]), ty0) - ty0, min(np.int64(packed[k, R_Y1]), ty1) - ty0
            level, lop = np.float64(packed[k, R_LEVEL]), np.float64(packed[k, R_LOP])
            b_a, hdet_a, ha, inv_ha = _pair_consts(ca, cb, cc)
            haf = np.float32(ha)
            for d in range(D):
                cg[d] = packed[k, R_COL + d]
            for j in range(6):
                for i in range(TILE):
                    P[j, i] = 0.0
            kkf = np.int32(k - k0)
            dx0 = u - (tx0 + 0.5)
            dx0f = np.float32(dx0)
            _rows(v, ty0, ry0, ry1, dx0, b_a, hdet_a, inv_ha, level, lop, bx0, bx1, nlanes, IA, IB, EF, EL, CF, DY)
            for r in range(ry0, ry1 + 1):
                iaf, ibf = IA[r], IB[r]
                if iaf > ibf:
                    continue
                ef, el, cf = EF[r], EL[r], CF[r]
                for i in range(nlanes):
                    tt = (ef - lane[i]) + el
                    a_raw = _exp32(max(cf - haf * tt * tt, EXP_LO))
                    on = (lane[i] >= iaf) & (lane[i] <= ibf) & (kkf <= lastl[r, i]) & (a_raw >= _A_MIN)
                    alpha = min(_A_MAX, a_raw) if on else _F0
                    om = _F1 - alpha
                    inv = _F1 / om  # the one division per lane (vector divisions are slow)
                    T = Tl[r, i] * inv  # transmittance in front of this Gaussian (unchanged where off)
                    Tl[r, i] = T
                    alb[i] = alpha
                    omb[i] = om
                    ivb[i] = inv
                    Tb[i] = T
                    wb[i] = alpha * T
                    dlb[i] = _F0
                    qb[i] = a_raw if (on & (a_raw < _A_MAX)) else _F0  # alpha not clamped: it has gradients
                for d in range(D):
                    c = cg[d]
                    for i in range(nlanes):
                        s = S[d, r, i]
                        rd = vr[d, r, i]
                        gcl[d, i] += wb[i] * rd
                        dlb[i] += (c - s) * rd
                        S[d, r, i] = alb[i] * c + omb[i] * s
                dyf = DY[r]
                dy2f = dyf * dyf
                for i in range(nlanes):
                    dl = dlb[i] * Tb[i] + va[r, i] * Tf[r, i] * ivb[i]  # dL/dalpha
                    q = qb[i] * dl
                    dx = dx0f - lane[i]
                    qx = dx * q
                    P[0, i] += qx
                    P[1, i] += dx * qx
                    P[2, i] += dyf * q
                    P[3, i] += dyf * qx
                    P[4, i] += dy2f * q
                    P[5, i] += q
            _fold16(P, 6)
            _fold16(gcl, D)
            sx, sxx, sy = np.float64(P[0, 0]), np.float64(P[1, 0]), np.float64(P[2, 0])
            sxy, syy, sq = np.float64(P[3, 0]), np.float64(P[4, 0]), np.float64(P[5, 0])
            # dalpha/dsigma = -alpha_raw, sigma = a/2 dx^2 + b dx dy + c/2 dy^2 (dx = u - px, dy = v - py)
            isect_grad[k, 0] = -(ca * sx + cb * sy)
            isect_grad[k, 1] = -(cb * sx + cc * sy)
            isect_grad[k, 2] = -0.5 * sxx
            isect_grad[k, 3] = -sxy
            isect_grad[k, 4] = -0.5 * syy
            isect_grad[k, 5] = sq / op  # dalpha/dopacity = alpha_raw / opacity
            for d in range(D):
                isect_grad[k, 6 + d] = gcl[d, 0]
                for i in range(TILE):
                    gcl[d, i] = 0.0
