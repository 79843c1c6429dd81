"""Depth and label-map renderers used by the semantic fusion.

Two depth backends behind one call signature `(keep [N] bool | None, cameras) -> list of [H,W] float32`
(z-depth in metres along the camera axis, inf where nothing is rendered):
- `SplatDepth`: expected depth ("ED") of the 3DGS model through `splattwin.splat.rasterize`
  (alpha < `min_alpha` -> inf). Faithful to large/transparent splats but ~1 s per 200k-Gaussian view on
  2 CPU cores, and the fusion re-renders every view in each refinement round.
- `PointDepth`: a z-buffer of the Gaussian centres (a numba min-depth scatter, then occlusion-aware hole
  filling, `_fill_holes`). Written here because no library offers a point z-buffer with a per-point keep
  mask at this speed (~30 ms per 200k-point view); the default for the fusion (labels agree with the
  rasterizer-depth fusion on ~96 % of the Gaussians, see bench/semantics.py).

Label maps: one-hot label channels rendered through `rasterization()` (`sh_degree=None`, any number of
channels), the largest accumulated weight wins with the unlabelled weight as background; or, with the
point backend, the label of the nearest centre (the "projected" labels).

Cameras with lens distortion (SfM's SIMPLE_RADIAL): the rasterizer draws at the pinhole camera that covers
the photo (`capture.undistort.covering_pinhole`) and the map is resampled to the photo's pixel grid, where
the masks are and where `project_to_pixels` puts the centres.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numba
import numpy as np

from splattwin.capture.camera import Camera
from splattwin.capture.dataset import resize_nearest
from splattwin.capture.undistort import covering_pinhole, distort_image

DepthRenderer = Callable[[np.ndarray | None, Sequence[Camera]], list[np.ndarray]]


def project_to_pixels(means: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Project centres into the image: (pixel index v*W+u [N] int64, -1 when outside / behind; z [N] m).

    Pinhole cameras are projected with column-wise arithmetic (an [N,3] @ [3,3] matmul is ~50x slower
    here under BLAS thread contention); distorted cameras go through `Camera.project`.
    """
    means = np.asarray(means, dtype=np.float64)
    if camera.dist is not None:
        uv, z = camera.project(means)
        u, v = uv[:, 0], uv[:, 1]
    else:
        T = camera.T_cam_world
        x, y, zz = means[:, 0], means[:, 1], means[:, 2]
        pc = [T[r, 0] * x + T[r, 1] * y + T[r, 2] * zz + T[r, 3] for r in range(3)]
        z = pc[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = camera.fx * (pc[0] / z) + camera.cx
            v = camera.fy * (pc[1] / z) + camera.cy
    with np.errstate(invalid="ignore"):
        inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    pix = np.full(len(means), -1, dtype=np.int64)
    pix[inside] = v[inside].astype(np.int64) * camera.width + u[inside].astype(np.int64)
    return pix, z.astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _min_depth(pix: np.ndarray, z: np.ndarray, keep: np.ndarray, depth: np.ndarray, owner: np.ndarray) -> None:
    """depth[p] = min z over kept points with pix == p; owner[p] = index of that point (-1 none)."""
    for i in range(pix.shape[0]):
        p = pix[i]
        if p >= 0 and keep[i] and z[i] < depth[p]:
            depth[p] = z[i]
            owner[p] = i


def zbuffer(pix: np.ndarray, z: np.ndarray, values: np.ndarray | None, width: int, height: int,
            radius: int = 1, keep: np.ndarray | None = None, gap: float = 0.02) -> tuple[np.ndarray, np.ndarray | None]:
    """Nearest-point z-buffer. pix [N] (-1 = skip), z [N] -> depth [H,W] (inf where empty).

    values [N] (optional, e.g. labels): returned as [H,W] from the nearest point (-1 where empty).
    radius: passes of occlusion-aware hole filling (`_fill_holes`), closing the holes between centres
    of a surface without growing silhouettes. gap: depth step (m) that separates surfaces there.
    keep [N] bool: points to use (default all).
    """
    keep = np.ones(len(pix), dtype=np.bool_) if keep is None else np.ascontiguousarray(keep, dtype=np.bool_)
    depth = np.full(width * height, np.inf, dtype=np.float32)
    owner = np.full(width * height, -1, dtype=np.int64)
    _min_depth(np.ascontiguousarray(pix, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float32), keep, depth, owner)
    depth = depth.reshape(height, width)
    vals = None
    if values is not None:
        vals = np.where(owner >= 0, np.asarray(values)[np.maximum(owner, 0)], -1).reshape(height, width)
    for _ in range(radius):
        depth, vals = _fill_holes(depth, vals, gap)
    return depth, vals


def _fill_holes(depth: np.ndarray, vals: np.ndarray | None, gap: float) -> tuple[np.ndarray, np.ndarray | None]:
    """One pass of occlusion-aware hole filling on a point z-buffer [H,W].

    A pixel that is empty, or that shows a point more than `gap` metres behind the nearest point of its
    3x3 window, while at least 5 of the 9 window pixels hold that near surface, is a hole in the near
    surface (the far point shines through between centres): it takes the window's nearest depth and
    value. Requiring a majority keeps silhouettes from growing (outside a straight edge only 3 of 9).
    """
    H, W = depth.shape
    pad = np.pad(depth, 1, constant_values=np.inf)
    win = np.lib.stride_tricks.sliding_window_view(pad, (3, 3)).reshape(H, W, 9)
    d_min = win.min(axis=2)
    near = (win <= (d_min + gap)[..., None]).sum(axis=2)
    hole = np.isfinite(d_min) & (~np.isfinite(depth) | (depth > d_min + gap)) & (near >= 5)
    if not hole.any():
        return depth, vals
    out_d = np.where(hole, d_min, depth)
    if vals is None:
        return out_d, None
    vpad = np.pad(vals, 1, constant_values=-1)
    vwin = np.lib.stride_tricks.sliding_window_view(vpad, (3, 3)).reshape(H, W, 9)
    arg = win.argmin(axis=2)
    nearest_val = np.take_along_axis(vwin, arg[..., None], axis=2)[..., 0]
    return out_d, np.where(hole, nearest_val, vals)


class PointDepth:
    """Depth of the nearest Gaussian centre per pixel (see module docstring). radius in pixels."""

    name = "points"

    def __init__(self, means: np.ndarray, radius: int = 1):
        self.means = np.asarray(means, dtype=np.float64)
        self.radius = radius
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def project(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        key = id(camera)
        if key not in self._cache:
            self._cache[key] = project_to_pixels(self.means, camera)
        return self._cache[key]

    def __call__(self, keep: np.ndarray | None, cameras: Sequence[Camera]) -> list[np.ndarray]:
        out = []
        for cam in cameras:
            pix, z = self.project(cam)
            out.append(zbuffer(pix, z, None, cam.width, cam.height, self.radius, keep)[0])
        return out


class SplatDepth:
    """Expected depth of the Gaussians through the splat stage's rasterizer ("ED"); inf where alpha < min_alpha."""

    name = "splat"

    def __init__(self, gaussians, min_alpha: float = 0.5, backend: str = "auto", scale: float = 1.0,
                 raster: tuple[str, float | None] = ("classic", None)):
        from splattwin.splat.rasterize import rasterization  # noqa: F401  (fail early if missing)

        self.gaussians = gaussians
        self.raster = raster  # (rasterize_mode, eps2d): as the splats were trained
        self.min_alpha = min_alpha
        self.backend = backend
        self.scale = scale  # render at scale x resolution, upsample (nearest) to the camera's size

    def __call__(self, keep: np.ndarray | None, cameras: Sequence[Camera]) -> list[np.ndarray]:
        g = self.gaussians if keep is None else self.gaussians.subset(keep)
        out = []
        for cam in cameras:
            pin = covering_pinhole(cam)  # the rasterizer draws pinholes: a distorted photo's is resampled
            c = pin if self.scale == 1.0 else pin.scaled(self.scale)
            colors, alphas = _rasterize(g, np.zeros((len(g.means), 1), np.float32), c, "ED", self.backend,
                                        self.raster)
            d = colors[..., -1].astype(np.float32)
            d[alphas < self.min_alpha] = np.inf
            if cam.dist is not None:
                d = distort_image(d, c, cam, nearest=True)
            elif c is not cam:
                d = resize_nearest(d, cam.width, cam.height)
            out.append(d)
        return out


def _rasterize(g, colors: np.ndarray, cam: Camera, mode: str, backend: str,
               raster: tuple[str, float | None] = ("classic", None)) -> tuple[np.ndarray, np.ndarray]:
    """One camera through the splat stage's `render()`. colors [N,C] -> (render [H,W,ch], alpha [H,W]).
    raster: (rasterize_mode, eps2d) the splats were trained with (`splat.config.trained_filter`): their
    footprints and opacities are those the training fitted."""
    from splattwin.splat.rendering import render

    return render(g, cam, mode=mode, colors=colors, backend=backend, rasterize_mode=raster[0], eps2d=raster[1])


def default_depth_renderer(gaussians, prefer: str = "splat") -> DepthRenderer:
    """`SplatDepth` when the splat stage's rasterizer is importable (and preferred), else `PointDepth`."""
    if prefer == "splat":
        try:
            return SplatDepth(gaussians)
        except ImportError:
            pass
    return PointDepth(gaussians.means)


def render_label_maps(gaussians, labels: np.ndarray, cameras: Sequence[Camera], n_labels: int,
                      renderer: str = "splat", threshold: float = 0.5, backend: str = "auto",
                      raster: tuple[str, float | None] = ("classic", None)) -> list[np.ndarray]:
    """Per-camera label image [H,W] int32 (0 background) of the labelled Gaussians. raster: the splats'
    trained (rasterize_mode, eps2d), for the "splat" renderer.

    renderer "splat": one-hot channels for labels 1..n_labels rendered with `rasterization`; a pixel
    takes the label with the largest accumulated weight, the unlabelled Gaussians' weight (alpha minus
    the object channels) competing as background; pixels with alpha < threshold are background.
    renderer "points": label of the nearest centre (z-buffer, 1-px min filter); background where the
    nearest centre is unlabelled.
    """
    labels = np.asarray(labels)
    out = []
    if renderer == "splat":
        onehot = np.zeros((len(labels), max(n_labels, 1)), dtype=np.float32)
        fg = labels > 0
        onehot[np.flatnonzero(fg), labels[fg] - 1] = 1.0
        for cam in cameras:
            pin = covering_pinhole(cam)
            rc, alpha = _rasterize(gaussians, onehot, pin, "RGB", backend, raster)
            bg = alpha - rc.sum(axis=-1)  # weight of unlabelled Gaussians
            lab = np.concatenate([bg[..., None], rc], axis=-1).argmax(axis=-1).astype(np.int32)
            lab[alpha < threshold] = 0
            if cam.dist is not None:  # labels < 2^24 pass through float32 exactly
                lab = distort_image(lab.astype(np.float32), pin, cam, nearest=True).astype(np.int32)
            out.append(lab)
        return out
    for cam in cameras:
        pix, z = project_to_pixels(np.asarray(gaussians.means if hasattr(gaussians, "means") else gaussians), cam)
        _, vals = zbuffer(pix, z, labels.astype(np.int64), cam.width, cam.height, radius=1)
        out.append(np.maximum(vals, 0).astype(np.int32))
    return out


# -- pictures ---------------------------------------------------------------------------------

def palette(n: int) -> np.ndarray:
    """[n+1,3] uint8 colours: index 0 (background) dark grey, then well-separated hues."""
    base = np.array([[60, 60, 60], [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                     [140, 86, 75], [227, 119, 194], [188, 189, 34], [23, 190, 207], [174, 199, 232]], dtype=np.uint8)
    if n + 1 <= len(base):
        return base[: n + 1]
    rng = np.random.default_rng(0)
    return np.concatenate([base, rng.integers(40, 255, size=(n + 1 - len(base), 3), dtype=np.uint8)])


def colorize(label_map: np.ndarray, names: dict[int, str], image: np.ndarray | None = None,
             legend: bool = True) -> np.ndarray:
    """Label image [H,W] -> RGB uint8 with a colour legend strip (label names) on the right.

    image: optional float [H,W,3] in [0,1] (or uint8) blended under the labels.
    """
    from splattwin.pictures import legend_strip

    n = max(max(names, default=0), int(label_map.max(initial=0)))
    pal = palette(n)
    rgb = pal[np.clip(label_map, 0, n)]
    if image is not None:
        img = np.asarray(image)
        img = (img * 255).astype(np.uint8) if img.dtype != np.uint8 else img
        a = np.where(label_map[..., None] > 0, 0.6, 0.25)
        rgb = (a * rgb + (1 - a) * img[..., :3]).astype(np.uint8)
    if not legend:
        return rgb
    H, W = label_map.shape
    rows = [(0, "background")] + sorted(names.items())
    strip = legend_strip([(f"{k} {name}", pal[min(k, n)]) for k, name in rows], H)
    out = np.full((strip.shape[0], W + strip.shape[1], 3), 255, np.uint8)
    out[:H, :W] = rgb
    out[:, W:] = strip
    return out
