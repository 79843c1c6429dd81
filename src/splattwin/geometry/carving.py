"""Free-space carving of an object's splat-extent samples against the object's own rendered depth.

The mesh of an object encloses its splats' half-opaque ellipsoids (`meshing.ellipsoid_samples`). A
splat seen face-on is barely constrained along the viewing ray: the photos fix its footprint, not its
thickness. Such splats on a box top seen from above (a robot's sweep) stand 2-6 mm thick, and the
ellipsoids' envelope then lies several millimetres above the surface the splats render (cardboard box
of the robot-style capture: mesh top 8.6 mm too high, F1@5 mm 0.91).

The cure is classic space carving (Kutulakos & Seitz, "A theory of shape by space carving", 2000),
with the splats' own rendering as the observation: from each capture camera, render the object's
splats alone (expected depth where alpha >= 0.5) and drop every sample that lies more than `tol` in
front of that depth: the camera looked through that point at the rendered surface. Samples behind
the surface (unseen sides, the inside) and outside the object's silhouette are never touched, so what
no camera saw keeps the ellipsoids' envelope. The object is rendered without the rest of the scene, so
occluders (the robot, another object) carve nothing. The rendered surface is the splats', not the
photos': this makes the mesh agree with what the twin renders, it does not second-guess training.

A capture with measured depth (RGB-D: a robot's D435 sweep) gives a second, independent observation
of free space: a sample that a camera's *sensor* sees clearly in front of the measured surface is not
part of the object either (`sensor_views`, `free_space_mask` with a depth-dependent tolerance and a
vote). This corrects what the splats' own rendering cannot: at short training the splats over a box top
are scattered a centimetre up and down, their rendered surface is itself a dome, and carving against it
leaves the mesh top 5-12 mm high (docs/BENCHMARKS.md, robot-style capture). The sensor is only trusted
where it looks at the object: inside the object's own visible 2D mask, eroded by `erode_px` pixels
(depth bleeding and colour/depth misregistration at silhouettes read the background there), as far from
any depth edge (a segmenter's mask may overshoot the object, and a pixel on a silhouette reads the
background behind a point it half covers), where the reading is valid (finite, > 0), and after a small
median filter over those pixels (a D4xx reading's noise is nearly white from pixel to pixel). An occluder in front of the object is outside the object's
visible mask, and would in any case read nearer than the object, so it carves nothing.

Noise model of the tolerance: a stereo camera's axial error grows with the square of the depth
(sigma_z = z^2 * sigma_disparity / (f * baseline); Intel quotes < 2 % at 2 m for a D435, i.e. about
1 cm RMS at 1 m), so a sample at depth z is free space only when it lies more than
`tol + noise_1m * z^2` in front of the measured (filtered) depth, in at least `min_share` of the views
that see it on or in front of the measured surface (views that see it behind the surface say nothing).

Frames: points and cameras in the twin frame; depth is camera z (the frame's units; metres for measured
depth, which is only used in a metric twin).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians


def depth_views(gaussians: "Gaussians", cameras: list["Camera"], max_views: int = 32, max_side: int = 640,
                min_alpha: float = 0.5) -> list[tuple["Camera", np.ndarray]]:
    """[(camera, depth [H,W])]: the splats' expected depth (camera z) from each camera, inf where their
    accumulated alpha is below `min_alpha`. At most `max_views` cameras, spread evenly over the list (a
    video's hundreds of frames add nothing but time). Cameras are used as ideal pinholes (the rasterizer's
    model) and scaled so their longest side is at most `max_side` pixels (the carving needs the surface,
    not the photo's detail)."""
    from splattwin.splat.rendering import render_depth

    cameras = [cameras[i] for i in pick_views(len(cameras), max_views)]
    out = []
    for cam in cameras:
        cam = dataclasses.replace(cam, dist=None)
        if max(cam.width, cam.height) > max_side:
            cam = cam.scaled(max_side / max(cam.width, cam.height))
        out.append((cam, render_depth(gaussians, cam, min_alpha=min_alpha)))
    return out


def free_space_mask(points: np.ndarray, views: list[tuple["Camera", np.ndarray]], tol: float,
                    noise_1m: float = 0.0, min_share: float = 0.0) -> np.ndarray:
    """[M] bool: True for the points [M,3] that the views see as empty. A view sees a point as empty when
    the point projects inside its image, in front of the camera, onto a pixel with a finite depth d, at a
    depth below d - (tol + noise_1m * d^2) (noise_1m: the depth error at 1 m, growing with d^2; 0: a fixed
    tol). min_share 0: one such view is enough (rendered depth: no noise); above 0: also at least this
    share of the views that see the point on or in front of their surface (z < d + tolerance), a vote
    that keeps a point on the surface where one noisy reading dips below it."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n_free = np.zeros(len(points), dtype=np.int32)
    n_seen = np.zeros(len(points), dtype=np.int32)
    for cam, depth in views:
        uv, z = cam.project(points)
        ok = cam.in_image(uv) & (z > 0)
        if min_share <= 0:
            ok &= n_free == 0
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            continue
        u = np.floor(uv[idx, 0]).astype(np.int64)
        v = np.floor(uv[idx, 1]).astype(np.int64)
        d = depth[v, u].astype(np.float64)
        fin = np.isfinite(d)
        t = tol + noise_1m * np.where(fin, d, 0.0) ** 2
        n_free[idx[fin & (z[idx] < d - t)]] += 1
        n_seen[idx[fin & (z[idx] < d + t)]] += 1
    if min_share <= 0:
        return n_free > 0
    return (n_free > 0) & (n_free >= min_share * n_seen)


DEPTH_EDGE = 0.01  # m: a 3x3 window of valid readings spanning more than this holds a depth edge


def sensor_views(depth_m: np.ndarray, mask: np.ndarray, erode_px: int = 2, median_px: int = 5) -> np.ndarray:
    """[H,W] float32: a measured depth map (m, camera z; 0, negative or non-finite = no reading) kept
    only where it sees this object: inside its visible mask [H,W] eroded by `erode_px` pixels, with a
    valid reading, and more than `erode_px` pixels from a depth edge (a 3x3 window of the filtered depth
    spanning more than DEPTH_EDGE); there the median of such readings in a `median_px` square around it
    (1: none), inf elsewhere. Why: see the module docstring (edges bleed, a pixel on a silhouette reads
    the background behind a point it half covers, a segmenter's mask overshoots the object, readings are
    noisy: the edges are found on the filtered depth, or the noise would make every pixel one)."""
    import warnings

    from scipy import ndimage

    depth = np.asarray(depth_m, dtype=np.float32)
    mask = np.asarray(mask, dtype=bool)
    if depth.shape != mask.shape:
        raise ValueError(f"depth map {depth.shape} and mask {mask.shape} differ in size")
    st = np.ones((3, 3), bool)
    if erode_px > 0:
        mask = ndimage.binary_erosion(mask, st, iterations=int(erode_px), border_value=0)
    out = np.full(depth.shape, np.inf, dtype=np.float32)
    if not mask.any():
        return out
    # only the object's box and a margin (window, edge distance): an object is a small part of a robot's view
    r = max(int(median_px), 1) // 2
    m = r + max(int(erode_px), 0) + 2
    vs, us = np.nonzero(mask)
    v0, v1 = max(vs.min() - m, 0), min(vs.max() + 1 + m, depth.shape[0])
    u0, u1 = max(us.min() - m, 0), min(us.max() + 1 + m, depth.shape[1])
    d = depth[v0:v1, u0:u1]
    valid = np.isfinite(d) & (d > 0)
    if r > 0:
        win = np.lib.stride_tricks.sliding_window_view(np.pad(np.where(valid, d, np.nan), r, constant_values=np.nan),
                                                       (2 * r + 1, 2 * r + 1))
        with warnings.catch_warnings():   # windows without a reading: nan, as they should
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(win.reshape(*d.shape, -1), axis=-1)
    else:
        med = np.where(valid, d, np.nan)
    ok = np.isfinite(med)
    hi = ndimage.maximum_filter(np.where(ok, med, -np.inf), 3)
    lo = ndimage.minimum_filter(np.where(ok, med, np.inf), 3)
    with np.errstate(invalid="ignore"):
        edge = ok & (hi - lo > DEPTH_EDGE)
    if erode_px > 0:
        edge = ndimage.binary_dilation(edge, st, iterations=int(erode_px))
    good = mask[v0:v1, u0:u1] & valid & ~edge
    if r > 0:  # the value: the median of the trusted readings alone (the object's, away from edges)
        win = np.lib.stride_tricks.sliding_window_view(np.pad(np.where(good, d, np.nan), r, constant_values=np.nan),
                                                       (2 * r + 1, 2 * r + 1))
        med = np.nanmedian(win[good].reshape(int(good.sum()), -1), axis=1) if good.any() else med[good]
        out[v0:v1, u0:u1][good] = med
    else:
        out[v0:v1, u0:u1][good] = d[good]
    return out


def pick_views(n: int, max_views: int) -> np.ndarray:
    """Indices of at most `max_views` of n views, spread evenly (a video's hundreds of frames add only time)."""
    if n <= max_views:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max(max_views, 1)).round().astype(int))


def measured_views(views: list, depth_of, has_depth=None, max_views: int = 32, erode_px: int = 2,
                   median_px: int = 5) -> list[tuple["Camera", np.ndarray]]:
    """[(camera, sensor depth)] of one object for carving against measured depth: at most `max_views` of
    its views with a 2D mask (views: [(camera, mask)], as `completeness.mask_views` gives per object) whose
    camera has a depth map, spread evenly, each as `sensor_views` of that map under its mask. depth_of:
    camera -> [H,W] measured depth (m, z, the camera's size), called once per chosen view; has_depth:
    camera -> bool, whether it has one (None: all). Views whose object pixels hold no valid reading are
    left out. One object at a time, so that only its views' maps are held (a 720p map is 3.7 MB)."""
    views = [(cam, mask) for cam, mask in views if has_depth is None or has_depth(cam)]
    out = []
    for i in pick_views(len(views), max_views):
        cam, mask = views[i]
        d = sensor_views(depth_of(cam), mask, erode_px, median_px)
        if np.isfinite(d).any():
            out.append((cam, d))
    return out
