"""Procedural solid textures of the tabletop scene, evaluated at surface points in each object's frame.

Solid (3D) textures need no UV unwrapping and are multi-view consistent by construction: the colour of a
surface point depends only on where the point is on the object. Every object gets a distinct pattern
(wood grain, corrugated cardboard with printed text, stripes, dots, glyph-like marks, a label band) plus
fine value noise, so SIFT matching and photometric reconstruction have something to lock onto.

Hand-written because no library in the stack offers vectorised 3D value noise; it is a few lines of
integer hashing (no state, no randomness beyond the seed), fully deterministic across runs and machines.

Functions take `p [N,3]` object-frame points (metres) and `n [N,3]` object-frame unit normals and return
linear-ish RGB albedo `[N,3]` float32 in [0, 1].
"""

from __future__ import annotations

from typing import Callable

import numba
import numpy as np

Albedo = Callable[[np.ndarray, np.ndarray], np.ndarray]


# -- noise primitives --------------------------------------------------------------------------------
def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice hash -> float32 in [0, 1). Inputs int64 arrays (any shape)."""
    h = (ix.astype(np.uint32) * np.uint32(374761393) + iy.astype(np.uint32) * np.uint32(668265263)
         + iz.astype(np.uint32) * np.uint32(2246822519) + np.uint32((seed * 3266489917) & 0xFFFFFFFF))
    h = (h ^ (h >> np.uint32(13))) * np.uint32(1274126177)
    h = h ^ (h >> np.uint32(16))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise_reference(p: np.ndarray, freq: float | np.ndarray, seed: int) -> np.ndarray:
    """Plain-numpy value noise (reference for the numba kernel `value_noise`). -> [N] float32 in [0, 1]"""
    q = np.asarray(p, dtype=np.float64) * np.asarray(freq, dtype=np.float64)
    i0 = np.floor(q)
    f = (q - i0).astype(np.float32)
    i0 = i0.astype(np.int64)
    w = f * f * (3.0 - 2.0 * f)  # smoothstep fade
    out = np.zeros(q.shape[0], dtype=np.float32)
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz, seed)
    return out


_M32 = np.uint64(0xFFFFFFFF)


@numba.njit(cache=True, inline="always")
def _hash1(ix: int, iy: int, iz: int, s: np.uint64) -> np.float32:
    # numba promotes uint32 products to 64 bits: do the arithmetic in uint64 and wrap explicitly
    h = (np.uint64(ix & 0xFFFFFFFF) * np.uint64(374761393) + np.uint64(iy & 0xFFFFFFFF) * np.uint64(668265263)
         + np.uint64(iz & 0xFFFFFFFF) * np.uint64(2246822519) + s) & _M32
    h = ((h ^ (h >> np.uint64(13))) * np.uint64(1274126177)) & _M32
    h = h ^ (h >> np.uint64(16))
    return np.float32(h >> np.uint64(8)) * np.float32(1.0 / (1 << 24))


@numba.njit(cache=True, nogil=True)  # nogil: the renderer shades row bands in threads
def _value_noise_kernel(q: np.ndarray, s: np.uint64, out: np.ndarray) -> None:
    for i in range(q.shape[0]):
        fx0, fy0, fz0 = np.floor(q[i, 0]), np.floor(q[i, 1]), np.floor(q[i, 2])
        ix, iy, iz = np.int64(fx0), np.int64(fy0), np.int64(fz0)
        fx, fy, fz = np.float32(q[i, 0] - fx0), np.float32(q[i, 1] - fy0), np.float32(q[i, 2] - fz0)
        wx = fx * fx * (np.float32(3.0) - np.float32(2.0) * fx)
        wy = fy * fy * (np.float32(3.0) - np.float32(2.0) * fy)
        wz = fz * fz * (np.float32(3.0) - np.float32(2.0) * fz)
        acc = np.float32(0.0)
        for dx in range(2):
            ax = wx if dx else np.float32(1.0) - wx
            for dy in range(2):
                ay = wy if dy else np.float32(1.0) - wy
                for dz in range(2):
                    az = wz if dz else np.float32(1.0) - wz
                    acc += ax * ay * az * _hash1(ix + dx, iy + dy, iz + dz, s)
        out[i] = acc


def value_noise(p: np.ndarray, freq: float | np.ndarray, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] (numba kernel; same values as `value_noise_reference` up to float
    rounding). p [N,3] metres, freq cycles per metre (scalar or [3]). -> [N] float32"""
    q = np.ascontiguousarray(np.asarray(p, dtype=np.float64) * np.asarray(freq, dtype=np.float64)).reshape(-1, 3)
    out = np.empty(q.shape[0], dtype=np.float32)
    _value_noise_kernel(q, np.uint64((seed * 3266489917) & 0xFFFFFFFF), out)
    return out


def fbm(p: np.ndarray, freq: float | np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of `octaves` value-noise octaves (lacunarity 2, gain 0.5), normalised to [0, 1]. -> [N]"""
    out = np.zeros(len(p), dtype=np.float32)
    amp, total = 1.0, 0.0
    freq = np.asarray(freq, dtype=np.float64)
    for o in range(octaves):
        out += amp * value_noise(p, freq * (2.0 ** o), seed + 101 * o)
        total += amp
        amp *= 0.5
    return out / total


def cell_hash(u: np.ndarray, v: np.ndarray, cell: tuple[float, float], seed: int) -> np.ndarray:
    """Per-cell random number in [0,1) on a 2D grid of `cell` (du, dv) metres. -> [N]"""
    iu = np.floor(u / cell[0]).astype(np.int64)
    iv = np.floor(v / cell[1]).astype(np.int64)
    return _hash(iu, iv, np.zeros_like(iu), seed)


def text_marks(u: np.ndarray, v: np.ndarray, glyph: float, seed: int, density: float = 0.5) -> np.ndarray:
    """Glyph-like printed marks ("text") on a 2D surface parametrisation (u, v) in metres. -> bool [N]

    Lines of pitch 1.8 glyph heights; each glyph is a 3x5 bitmap of random strokes; ~15 % of glyphs are
    spaces so the lines break into words.
    """
    gw, gh = 0.65 * glyph, glyph
    line = np.floor(v / (1.8 * gh))
    vv = v - line * 1.8 * gh
    col = np.floor(u / gw)
    uu = u - col * gw
    in_line = vv < gh
    space = _hash(col.astype(np.int64), line.astype(np.int64), np.full(len(u), 7, np.int64), seed) < 0.15
    bx = np.clip(np.floor(uu / gw * 4.0), 0, 3).astype(np.int64)  # 3 stroke columns + 1 gap
    by = np.clip(np.floor(vv / gh * 5.0), 0, 4).astype(np.int64)
    bit = _hash(col.astype(np.int64) * 8 + bx, line.astype(np.int64) * 8 + by, np.full(len(u), 3, np.int64), seed)
    return in_line & ~space & (bx < 3) & (bit < density)


def _face_uv(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D coordinates on the box face a point lies on (dominant normal axis) + that axis index [N]."""
    ax = np.argmax(np.abs(n), axis=1)
    u = np.where(ax == 0, p[:, 1], p[:, 0])
    v = np.where(ax == 2, p[:, 1], p[:, 2])
    return u, v, ax


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Lerp colours a [3] or [N,3] -> b by t [N]."""
    t = np.asarray(t, dtype=np.float32)[:, None]
    return (np.asarray(a, np.float32) * (1 - t) + np.asarray(b, np.float32) * t).astype(np.float32)


def _grain(p: np.ndarray, seed: int, amp: float = 0.12) -> np.ndarray:
    """Fine multiplicative speckle (~2 mm) shared by every material: gives SIFT corners everywhere. -> [N]"""
    return (1.0 - amp / 2 + amp * value_noise(p, 450.0, seed + 9)).astype(np.float32)


# -- materials ---------------------------------------------------------------------------------------
def table_albedo(seed: int, target_center: np.ndarray, target_size: float, tape_width: float = 0.018,
                 marker: Callable[[np.ndarray], np.ndarray] | None = None) -> Albedo:
    """Wooden planks along x, with a taped square outline (the hammer's target frame) and, optionally, a
    printed fiducial (`marker(p) -> [N] float in {0,1} or nan outside`)."""
    tc = np.asarray(target_center, dtype=np.float64)

    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        plank = np.floor(p[:, 1] / 0.11)
        shade = _hash(plank.astype(np.int64), np.zeros(len(p), np.int64), np.ones(len(p), np.int64), seed)
        warp = fbm(p * np.array([1.0, 1.0, 1.0]), np.array([3.0, 25.0, 25.0]), seed + 1, 3)
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (p[:, 1] * 140.0 + 6.0 * warp + 3.0 * shade))
        rgb = _mix([0.78, 0.60, 0.40], [0.52, 0.34, 0.19], rings ** 3)
        rgb *= (0.85 + 0.3 * shade)[:, None]
        seam = np.abs(p[:, 1] / 0.11 - np.round(p[:, 1] / 0.11)) * 0.11 < 0.0015
        rgb[seam] *= 0.45
        # knots: darker blotches
        knot = value_noise(p, np.array([18.0, 40.0, 40.0]), seed + 5) > 0.82
        rgb[knot] *= 0.7
        # target frame: coloured tape outline on the top surface
        d = np.maximum(np.abs(p[:, 0] - tc[0]), np.abs(p[:, 1] - tc[1]))
        tape = (np.abs(d - target_size / 2) < tape_width / 2) & (n[:, 2] > 0.5)
        if tape.any():
            tn = value_noise(p[tape], 300.0, seed + 6)
            rgb[tape] = _mix([0.92, 0.42, 0.10], [0.80, 0.30, 0.06], tn)
        if marker is not None:
            m = marker(p)
            on = np.isfinite(m) & (n[:, 2] > 0.5)
            rgb[on] = np.where(m[on, None] > 0.5, 0.92, 0.04).astype(np.float32)
            rgb[~on] *= _grain(p[~on], seed)[:, None]
            return np.clip(rgb, 0, 1)
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def cardboard_albedo(seed: int, extent: np.ndarray) -> Albedo:
    """Brown corrugated cardboard: fibre noise, printed text blocks on every face, a packing-tape strip."""
    hx, hy, hz = np.asarray(extent) / 2

    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        base = fbm(p, 60.0, seed, 3)
        rgb = _mix([0.70, 0.53, 0.34], [0.58, 0.42, 0.25], base)
        corr = 0.5 + 0.5 * np.sin(2 * np.pi * p[:, 0] / 0.008)  # faint flutes
        rgb *= (0.96 + 0.04 * corr)[:, None]
        u, v, ax = _face_uv(p, n)
        txt = text_marks(u + 1.0, v + 1.0, 0.009, seed + 2, 0.55)
        # text only in two blocks per face
        block = ((np.abs(u) < 0.06) & (v > (np.where(ax == 2, 0.0, 0.0))) & (np.abs(v) < 0.035)) | \
                ((u > 0.02) & (u < 0.09) & (v < -0.04) & (v > -0.065))
        rgb[txt & block] = [0.12, 0.10, 0.09]
        # a printed ring logo
        r = np.hypot(u - (-0.06), v - (-0.045))
        rgb[(np.abs(r - 0.012) < 0.0022)] = [0.55, 0.08, 0.06]
        # tape strip across the top face
        tape = (n[:, 2] > 0.5) & (np.abs(p[:, 1]) < 0.024)
        rgb[tape] = _mix([0.80, 0.70, 0.52], [0.72, 0.62, 0.45], value_noise(p[tape], 200.0, seed + 3))
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def blue_box_albedo(seed: int) -> Albedo:
    """Blue printed carton: diagonal white stripes, a dot grid, glyph marks."""
    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        rgb = _mix([0.10, 0.24, 0.78], [0.06, 0.15, 0.55], fbm(p, 80.0, seed, 2))
        u, v, ax = _face_uv(p, n)
        stripe = np.abs(((u + v) / 0.022) % 1.0 - 0.5) < 0.09
        rgb[stripe] = _mix([0.85, 0.88, 0.95], [0.7, 0.75, 0.9], value_noise(p[stripe], 300.0, seed + 1))
        du = (u / 0.008) % 1.0 - 0.5
        dv = (v / 0.008) % 1.0 - 0.5
        dots = (du * du + dv * dv < 0.06) & (v < -0.005)
        rgb[dots] = [0.95, 0.80, 0.15]
        txt = text_marks(u + 1.0, v + 1.0, 0.006, seed + 4, 0.5) & (v > 0.008)
        rgb[txt] = [0.97, 0.97, 0.97]
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def yellow_cube_albedo(seed: int) -> Albedo:
    """Yellow toy block: a different glyph on each face, speckle."""
    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        rgb = _mix([0.96, 0.82, 0.12], [0.85, 0.66, 0.05], fbm(p, 200.0, seed, 2))
        u, v, ax = _face_uv(p, n)
        sign = np.sign(np.take_along_axis(n, ax[:, None], 1)[:, 0]).astype(np.int64)
        face = ax * 2 + (sign > 0)
        iu = np.floor((u + 0.0125) / 0.025 * 5).astype(np.int64)
        iv = np.floor((v + 0.0125) / 0.025 * 5).astype(np.int64)
        inner = (iu >= 1) & (iu <= 3) & (iv >= 1) & (iv <= 3)
        bit = _hash(iu, iv, face, seed + 1) < 0.55
        rgb[inner & bit] = [0.75, 0.18, 0.08]
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def hammer_albedo(seed: int, head_x: float) -> Albedo:
    """Toy hammer: orange wooden handle with black rings (x < head_x), red speckled head."""
    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        head = p[:, 0] >= head_x
        handle_rgb = _mix([0.92, 0.52, 0.16], [0.76, 0.38, 0.10], fbm(p, np.array([40.0, 300.0, 300.0]), seed, 2))
        ring = ((p[:, 0] / 0.02) % 1.0) < 0.18
        handle_rgb[ring] = [0.08, 0.08, 0.08]
        head_rgb = _mix([0.80, 0.12, 0.10], [0.55, 0.06, 0.05], fbm(p, 150.0, seed + 1, 2))
        spots = value_noise(p, 260.0, seed + 2) > 0.7
        head_rgb[spots] = [0.95, 0.90, 0.85]
        rgb = np.where(head[:, None], head_rgb, handle_rgb)
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def bottle_albedo(seed: int, radius: float, height: float) -> Albedo:
    """Green bottle (frame origin at the centre): printed label band with text, white cap."""
    def f(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        z = p[:, 2] + height / 2
        rgb = _mix([0.10, 0.45, 0.22], [0.05, 0.30, 0.15], fbm(p, 90.0, seed, 2))
        theta = np.arctan2(p[:, 1], p[:, 0])
        s = (theta + np.pi) * radius  # arc length, m
        band = (z > 0.05) & (z < 0.11) & (n[:, 2] < 0.5)
        label = _mix([0.92, 0.92, 0.88], [0.80, 0.80, 0.76], value_noise(p, 300.0, seed + 1))
        red = (z > 0.094) & (z < 0.106)
        label[red] = [0.78, 0.08, 0.10]
        txt = text_marks(s + 1.0, z, 0.007, seed + 2, 0.55) & (z > 0.058) & (z < 0.09)
        label[txt] = [0.1, 0.1, 0.12]
        rgb = np.where(band[:, None], label, rgb)
        stripes = (~band) & (z < 0.05) & (((s / 0.012) % 1.0) < 0.2)
        rgb[stripes] *= 0.6
        cap = z > height - 0.018
        rgb[cap] = [0.93, 0.93, 0.93]
        return np.clip(rgb * _grain(p, seed)[:, None], 0, 1)

    return f


def background_rgb(dirs_world: np.ndarray) -> np.ndarray:
    """Colour of rays that miss everything: a dim, smooth room gradient (no texture). [N,3] -> [N,3]"""
    t = np.clip(0.5 + 0.5 * dirs_world[:, 2], 0, 1).astype(np.float32)
    return _mix([0.30, 0.30, 0.32], [0.62, 0.64, 0.68], t)
