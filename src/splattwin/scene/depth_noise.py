"""D435-like depth sensor model: turns a perfect ray-cast z-depth map into what a RealSense D4xx
stereo camera writes (axial noise growing with z^2, edge fattening, occlusion shadows, ragged holes at
depth edges, random blobs of lost readings). The model and its constants: `splattwin.scene.options.DepthNoise`.

`sensor_depth(depth_m, fx, noise, rng)`: [H,W] float z-depth in metres (inf = no return) -> [H,W]
float32 metres with inf where the sensor gives no reading (written as 0 by `robot_capture.depth_mm`).
`view_rng(seed, index)`: the generator of view `index`, independent of how many views a capture has.

Our own code (a few scipy.ndimage filters): the simulators that model RealSense noise (e.g. BlenderProc's
stereo matching, Isaac Sim sensors) are whole rendering stacks, not a function of a depth map.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.special import ndtri

from splattwin.scene.options import DepthNoise

REF_WIDTH = 640          # pixel sizes of DepthNoise are at the D435 colour stream's width
FAR = 1e3                # stands in for "no return" when looking for edges (m)

__all__ = ["REF_WIDTH", "depth_edges", "occlusion_shadow", "sensor_depth", "view_rng"]


def view_rng(seed: int, index: int) -> np.random.Generator:
    """Generator of view `index`'s depth errors (seeded by the scene seed and the view index)."""
    return np.random.default_rng([int(seed), 435, int(index)])


def _smooth_unit_field(shape: tuple[int, int], sigma: float, rng: np.random.Generator) -> np.ndarray:
    """[H,W] zero-mean, unit-variance Gaussian random field correlated over `sigma` px (white when 0)."""
    white = rng.standard_normal(shape)
    if sigma <= 0:
        return white
    f = ndimage.gaussian_filter(white, sigma, mode="reflect")
    # the filter's gain on white noise: sqrt(sum of squared kernel weights), measured on a delta
    n = int(2 * np.ceil(4 * sigma) + 1)
    delta = np.zeros((n, n))
    delta[n // 2, n // 2] = 1.0
    return f / np.sqrt((ndimage.gaussian_filter(delta, sigma, mode="constant") ** 2).sum())


def depth_edges(depth_m: np.ndarray, jump: float) -> np.ndarray:
    """[H,W] bool: pixels whose 3x3 neighbourhood spans a depth step > `jump` (m), or borders no return."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, FAR)
    return (ndimage.maximum_filter(d, 3) - ndimage.minimum_filter(d, 3)) > jump


def occlusion_shadow(depth_m: np.ndarray, fx: float, baseline: float, tol: float = 0.01) -> np.ndarray:
    """[H,W] bool: pixels the second imager, `baseline` m along the camera's +x, cannot see because a
    nearer surface covers them (a band on the left of near objects). A pixel (u, z) lands at
    u - fx * B / z in that imager; it is shadowed when something nearer than z - tol lands there too."""
    h, w = depth_m.shape
    ok = np.isfinite(depth_m) & (depth_m > 0)
    if baseline <= 0 or not ok.any():
        return np.zeros((h, w), bool)
    v, u = np.nonzero(ok)
    z = depth_m[v, u].astype(np.float64)
    u2 = u - fx * baseline / z
    zbuf = np.full(h * w, np.inf)
    for k in (np.floor(u2), np.ceil(u2)):   # both neighbours: no gaps between a surface's samples
        inside = (k >= 0) & (k < w)
        np.minimum.at(zbuf, v[inside] * w + k[inside].astype(np.int64), z[inside])
    k = np.rint(u2)
    inside = (k >= 0) & (k < w)
    out = np.zeros((h, w), bool)
    out[v[inside], u[inside]] = z[inside] > zbuf[v[inside] * w + k[inside].astype(np.int64)] + tol
    return out


def sensor_depth(depth_m: np.ndarray, fx: float, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """What a D435-like sensor reads for the true z-depth `depth_m` [H,W] (m, inf = no return), seen
    through a camera of focal length `fx` px. Returns [H,W] float32 metres, inf where no reading."""
    d = np.asarray(depth_m, np.float64)
    if not noise.enabled:
        return d.astype(np.float32)
    h, w = d.shape
    px = w / REF_WIDTH
    hit = np.isfinite(d) & (d > 0)
    edges = depth_edges(d, noise.edge_jump)
    far_from_edge = ndimage.distance_transform_edt(~edges) if edges.any() else np.full((h, w), np.inf)
    out = d.copy()
    r = noise.fattening_px * px
    if r > 0 and edges.any():   # the nearer surface (smaller depth) spreads across the edge
        size = 2 * int(np.ceil(r)) + 1
        near = ndimage.minimum_filter(np.where(hit, d, FAR), size=size)
        # only a real surface spreads: a window with no return holds the FAR stand-in, which spread into
        # no-return pixels became 1 km "readings" (then +-km noise, saturated at 65535 mm in the PNG)
        fat = (far_from_edge <= r) & (near < FAR) & (near < d - noise.edge_jump)
        out = np.where(fat, near, out)
        hit = hit | fat
    if noise.rms_1m > 0:
        n = _smooth_unit_field((h, w), noise.noise_corr_px * px, rng)
        out = np.where(hit, out + noise.rms_1m * np.where(hit, out, 0.0) ** 2 * n, out)
    lost = ~hit
    lost |= occlusion_shadow(d, fx, noise.baseline, tol=noise.edge_jump / 2)
    if noise.edge_hole_prob > 0 and noise.edge_hole_px > 0 and edges.any():
        band = far_from_edge <= noise.edge_hole_px * px
        ragged = _smooth_unit_field((h, w), max(1.0, px), rng) < ndtri(min(noise.edge_hole_prob, 1 - 1e-9))
        lost |= band & ragged
    if noise.blob_fraction > 0:
        field = _smooth_unit_field((h, w), max(1.0, noise.blob_radius_px * px), rng)
        lost |= field > np.quantile(field, 1.0 - noise.blob_fraction)
    return np.where(lost | ~(out > 0), np.inf, out).astype(np.float32)
