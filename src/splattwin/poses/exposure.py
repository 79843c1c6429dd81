"""Do the photos differ in exposure or white balance? Per-image colour gains measured from the capture.

Auto-exposure and auto white balance (a robot's RealSense sweep, a phone walk-around) change each photo's
gain and colour; the splats then absorb the differences as view-dependent colour or floaters, and the
per-image appearance correction (`--splat.appearance`, `splattwin.splat.appearance`) is what handles
them. This check runs after the poses are known, on the poses stage's own sparse points (SfM points,
points triangulated from known poses, or the depth back-projection: no second matcher): each point is
projected into every posed image (`Camera.project`, lens distortion applied), kept where it is the
nearest point in its pixel cell (a z-buffer of the points themselves, so a point hidden behind another
surface is not sampled), and its colour read from the image reduced to `MAX_SIDE` px (an area average:
a point a pixel off on a texture edge reads a blend, not the other side).

The model, per image i and channel c, in the images' own 8-bit encoding (the space the appearance
correction acts on): colour_ipc = gain_ic * albedo_pc. `fit_log_gains` solves it in log space by
alternating medians (median polish: robust to occlusion misses, specular highlights and wrong points),
relative to the median image (its gains are 1). Samples within `DARK`/`BRIGHT` of the ends are left
out: a clipped or black pixel holds no ratio.

Per image: `gain` (exposure: the geometric mean of the three channel gains) and `rgb_gain` (the channel
gains); for the capture: `spread_pct` = the largest channel gain's distance from 1 over all images, in
percent (100 * (exp(max |log gain|) - 1)), and `images_off`, the images beyond `THRESHOLD_PCT`.
Measured (bench/exposure.py, embedded scene as a 24-view robot capture, 320x240): the unperturbed capture
reads 0.0 %; per-view gains of 0.7..1.3 x white balance 0.9..1.1 are recovered within 0.8 % (spread 56 %),
0.9..1.1 x 0.97..1.03 within 0.5 % (spread 14 %); 1.0-2.4 s for 24 PNGs on a shared machine. Real photos
(SfM points; JPEGs decoded at a reduced scale, 0.1-0.25 s for 8-10 photos): cake 7.8 %, statue 8.0 %,
british_museum (internet photos of many cameras) 79 %.

The splat stage reads the record (`splat.appearance.decide`): with the default `--splat.appearance off` it
warns when `varies`, suggesting the correction; `--splat.appearance auto` trains a per-image gain then, and
any trained correction starts at these gains (`splat.appearance.initial_gains`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera

log = logging.getLogger(__name__)

MAX_SIDE = 320          # px: images are read reduced to this longest side (an area average)
MAX_POINTS = 20000      # points sampled (fixed seed) from the sparse cloud
MAX_SAMPLES = 4_000_000  # points x images held at once (float32 x 3: 48 MB)
CELL_PX = 3             # z-buffer cell, px at the reduced size
DEPTH_TOL_REL = 0.03    # a point this much (relative) behind its cell's nearest point is hidden
DARK, BRIGHT = 8 / 255, 247 / 255   # samples outside (a channel) are left out: clipped or black
MIN_POINTS = 30         # samples an image needs for a gain
MIN_VIEWS = 2           # images a point must be seen in
# spread above which the capture is said to vary. Measured: unperturbed embedded robot capture 0.0 %, real
# phone captures 7.8 % (cake) and 8.0 % (statue; per-image appearance there: seed noise, README), per-view gain
# 0.9..1.1 x white balance 0.97..1.03 14.1 % (appearance gain: +0.4 dB held-out, +0.8 dB on the
# right-half protocol), 0.7..1.3 x 0.9..1.1 56 %, british_museum (internet photos) 79 %
THRESHOLD_PCT = 10.0
ITERATIONS = 8          # median-polish rounds


def fit_log_gains(log_rgb: np.ndarray, min_points: int = MIN_POINTS, min_views: int = MIN_VIEWS,
                  iterations: int = ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Per-image log gains from log colours of shared points.

    log_rgb: [V,N,3] log colour of point n in image v (NaN: not seen, hidden or clipped there).
    Returns (log_gain [V,3], samples [V]): log_gain relative to the median image (its row is ~0); NaN
    for images with fewer than `min_points` samples on points seen in >= `min_views` images."""
    L = np.asarray(log_rgb, np.float64)
    if L.ndim != 3 or L.shape[2] != 3:
        raise ValueError(f"log_rgb must be [V,N,3], got {L.shape}")
    V = L.shape[0]
    seen = np.isfinite(L).all(axis=2)                                  # [V,N]
    shared = seen.sum(axis=0) >= min_views
    L, seen = L[:, shared], seen[:, shared]
    samples = seen.sum(axis=1)
    ok = samples >= min_points
    g = np.zeros((V, 3))
    if ok.sum() < 2:
        return np.full((V, 3), np.nan), samples
    L = np.where(ok[:, None, None], L, np.nan)                          # unmeasurable images: left out
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)                 # all-NaN slices: points seen once
        for _ in range(iterations):
            ref = np.nanmedian(L - g[:, None, :], axis=0)              # [N,3] each point's albedo (log)
            g = np.nanmedian(L - ref[None], axis=1)                    # [V,3]
            g = np.where(ok[:, None], g, 0.0)
            g -= np.median(g[ok], axis=0)                              # relative to the median image
    g[~ok] = np.nan
    return g, samples


def _reduced(path: Path, cam: Camera, max_side: int) -> tuple[np.ndarray, float, float]:
    """The image as float32 [h,w,3] in [0,1], reduced (box filter) so that its longest side is at most
    `max_side`, and the factors (x, y) from the camera's pixels to it. A JPEG is decoded at a reduced scale
    (PIL's draft: 12 MP photos would otherwise cost ~0.1 s each to decode in full)."""
    from PIL import Image

    from splattwin.capture import load_image
    from splattwin.limits import open_image

    s = min(1.0, max_side / max(cam.width, cam.height))
    w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
    if Path(path).suffix.lower() in (".jpg", ".jpeg"):
        with open_image(path) as im:
            im.draft("RGB", (w, h))
            u8 = im.convert("RGB")
            u8 = u8.resize((w, h), Image.BOX) if u8.size != (w, h) else u8
            img = np.asarray(u8, np.float32) / 255.0
    else:
        img = load_image(path)
        if img.shape[:2] != (h, w):
            u8 = Image.fromarray(np.round(img * 255).astype(np.uint8)).resize((w, h), Image.BOX)
            img = np.asarray(u8, np.float32) / 255.0
    return img, w / cam.width, h / cam.height


def _visible_colours(cam: Camera, img: np.ndarray, sx: float, sy: float, xyz: np.ndarray) -> np.ndarray:
    """[N,3] colours of the points in this image (NaN where out of view, hidden or clipped)."""
    out = np.full((len(xyz), 3), np.nan, np.float32)
    uv, z = cam.project(xyz)
    inside = cam.in_image(uv) & (z > 0)
    if not inside.any():
        return out
    idx = np.flatnonzero(inside)
    h, w = img.shape[:2]
    px = np.clip((uv[idx] * [sx, sy]).astype(np.int64), 0, [w - 1, h - 1])
    zi = z[idx]
    # z-buffer of the points themselves: keep the ones near their cell's nearest point
    cw, ch = -(-w // CELL_PX), -(-h // CELL_PX)
    cell = (px[:, 1] // CELL_PX) * cw + px[:, 0] // CELL_PX
    zmin = np.full(cw * ch, np.inf)
    np.minimum.at(zmin, cell, zi)
    front = zi <= zmin[cell] * (1.0 + DEPTH_TOL_REL)
    idx, px = idx[front], px[front]
    c = img[px[:, 1], px[:, 0]]
    good = ((c > DARK) & (c < BRIGHT)).all(axis=1)
    out[idx[good]] = c[good]
    return out


def measure_exposure(cameras: list[Camera], image_paths: list[Path], names: list[str],
                     points_xyz: np.ndarray | None, seed: int = 0, threshold_pct: float = THRESHOLD_PCT,
                     max_side: int = MAX_SIDE) -> dict:
    """Per-image exposure / white-balance gains of posed images from their shared sparse points.

    cameras: posed cameras (T_world_cam, metres or the poses' units) in the frame of points_xyz [N,3].
    Returns the record the poses report keeps under "exposure" (module docstring): {"images": {name:
    {"gain", "rgb_gain": [r,g,b], "samples"}}, "spread_pct", "threshold_pct", "varies", "images_off",
    "unmeasured", "points", "seconds", "method"}, or {"error": why, ...} when it cannot be measured (no
    points, fewer than two images sharing enough points)."""
    t0 = time.perf_counter()
    base = {"threshold_pct": threshold_pct, "method": "median log colour ratio of the poses' sparse points "
                                                      "seen in several images, relative to the median image"}
    if len(cameras) != len(image_paths) or len(cameras) != len(names):
        raise ValueError("cameras, image_paths and names must have the same length")
    if points_xyz is None or len(points_xyz) == 0:
        return {**base, "error": "no sparse points to compare the images on"}
    if len(cameras) < 2:
        return {**base, "error": "fewer than two posed images"}
    xyz = np.asarray(points_xyz, np.float64).reshape(-1, 3)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    n = min(len(xyz), MAX_POINTS, max(MIN_POINTS, MAX_SAMPLES // len(cameras)))
    if n < len(xyz):
        xyz = xyz[np.sort(np.random.default_rng(seed).choice(len(xyz), n, replace=False))]
    cols = np.full((len(cameras), len(xyz), 3), np.nan, np.float32)
    for i, (cam, path) in enumerate(zip(cameras, image_paths)):
        img, sx, sy = _reduced(Path(path), cam, max_side)
        cols[i] = _visible_colours(cam, img, sx, sy, xyz)
    with np.errstate(divide="ignore", invalid="ignore"):
        g, samples = fit_log_gains(np.log(cols))
    ok = np.isfinite(g).all(axis=1)
    rec = {**base, "points": int(len(xyz)), "seconds": round(time.perf_counter() - t0, 3)}
    if ok.sum() < 2:
        return {**rec, "error": f"fewer than two images share >= {MIN_POINTS} unclipped points seen in "
                                f">= {MIN_VIEWS} images ({int(ok.sum())} of {len(names)} do)",
                "unmeasured": [n for n, o in zip(names, ok) if not o]}
    images = {}
    for name, gi, k, o in zip(names, g, samples, ok):
        images[name] = ({"gain": round(float(np.exp(gi.mean())), 4), "rgb_gain": [round(float(v), 4) for v in np.exp(gi)],
                         "samples": int(k)} if o else {"gain": None, "rgb_gain": None, "samples": int(k)})
    dev = np.abs(g[ok]).max(axis=1)                                    # [V_ok] largest channel |log gain|
    off = [nm for nm, d in zip([n for n, o in zip(names, ok) if o], dev) if 100 * np.expm1(d) > threshold_pct]
    spread = float(100 * np.expm1(dev.max()))
    return {**rec, "spread_pct": round(spread, 2), "varies": bool(spread > threshold_pct), "images_off": off,
            "unmeasured": [n for n, o in zip(names, ok) if not o], "images": images}


def describe(rec: dict, max_names: int = 6) -> str:
    """One line for the log: the spread and the images beyond the threshold."""
    if "error" in rec:
        return f"exposure check: not measured ({rec['error']})"
    off = rec.get("images_off") or []
    named = ", ".join(f"{n} (x{rec['images'][n]['gain']:.2f})" for n in off[:max_names])
    more = f" and {len(off) - max_names} more" if len(off) > max_names else ""
    return (f"exposure check: images differ in gain / white balance by up to {rec['spread_pct']:.1f} % "
            f"(threshold {rec['threshold_pct']:g} %)" + (f": {named}{more}" if off else ""))
