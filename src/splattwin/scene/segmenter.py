"""Simulated open-vocabulary segmenter: turns a clean GT instance mask into what GroundingDINO + SAM
would plausibly return for the object's text prompt.

Error modes (probabilities and sizes in `MaskNoise`, recorded in scene.json):
- boundary wobble: every detected mask follows the silhouette only up to a smooth random offset;
- bleeding: the mask spreads a few pixels across the boundary, onto what lies *behind* the object (the
  table, a box behind it) -- the typical "mask loosely covers object + adjacent background" failure
  that depth-aware semantic fusion must reject;
- partial detection: only the part of the object on one side of a random line is segmented;
- missed detection: empty mask;
- spurious blob: a false-positive region somewhere else in the image.

Hand-written (no library simulates segmenter failures); morphology and distance transforms are OpenCV's,
smooth random fields scipy's.

Each (view, object) pair uses its own generator seeded by (scene seed, view index, label), so results do
not depend on which other views or objects are generated.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from splattwin.scene.options import MaskNoise


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field [H,W] float32."""
    f = gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma, mode="wrap")
    sd = float(f.std())
    return f / sd if sd > 0 else f


def _signed_distance(mask: np.ndarray) -> np.ndarray:
    """Approximate signed distance to the mask boundary in pixels (> 0 inside). [H,W] float32"""
    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    return np.where(mask, inside - 0.5, 0.5 - outside).astype(np.float32)


def segment(labels: np.ndarray, depth: np.ndarray, label: int, noise: MaskNoise,
            rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Simulated segmenter output for one object in one view.

    Args:
        labels: [H,W] uint8 GT label image. depth: [H,W] float32 z-depth, metres (inf = no surface).
        label: the object's label id. noise: error model. rng: this (view, object)'s generator.
    Returns:
        mask [H,W] bool, events {"visible_px", "missed", "partial_keep", "bleed_px", "blob"}.
    """
    H, W = labels.shape
    scale = W / 320.0
    gt = labels == label
    area = int(gt.sum())
    # draw every random number up front, in a fixed order: events are independent of each other
    u_miss, u_partial, u_bleed, u_blob = rng.random(4)
    keep = rng.uniform(*noise.partial_keep)
    angle = rng.uniform(0, 2 * np.pi)
    bleed_r = int(rng.integers(noise.bleed_px[0], noise.bleed_px[1] + 1))
    blob_r = rng.uniform(*noise.blob_radius_px) * scale
    blob_pick = rng.random()
    blob_aspect, blob_angle = rng.uniform(0.5, 1.0), rng.uniform(0, np.pi)
    field = _smooth_field(rng, (H, W), sigma=3.0 * scale)
    events = {"visible_px": area, "missed": False, "partial_keep": None, "bleed_px": 0, "blob": False}

    mask = np.zeros((H, W), dtype=bool)
    detected = area >= max(1, noise.min_visible_px)
    if detected and u_miss < noise.p_miss:
        events["missed"] = True
        detected = False
    if detected:
        mask = gt.copy()
        if u_partial < noise.p_partial:
            ys, xs = np.nonzero(gt)
            d = (xs - xs.mean()) * np.cos(angle) + (ys - ys.mean()) * np.sin(angle)
            thr = np.quantile(d, keep)
            mask[ys[d > thr], xs[d > thr]] = False
            events["partial_keep"] = float(mask.sum() / area)
        if u_bleed < noise.p_bleed and bleed_r > 0:
            ring = cv2.dilate(mask.astype(np.uint8), _disk(bleed_r)).astype(bool) & ~mask
            if noise.bleed_behind_only:
                obj_depth = np.where(mask, depth, np.inf).astype(np.float32)
                near = cv2.erode(obj_depth, _disk(bleed_r), borderValue=np.inf)  # min object depth nearby
                ring &= depth > near + noise.bleed_depth_margin
            ring &= field > -0.6  # uneven: the bleed comes and goes along the boundary
            mask |= ring
            events["bleed_px"] = bleed_r
        if noise.boundary_jitter_px > 0:
            sd = _signed_distance(mask)
            mask = (sd + noise.boundary_jitter_px * field) > 0
    if u_blob < noise.p_blob:
        # a false positive on some other visible surface, away from the object
        away = np.isfinite(depth) & ~cv2.dilate(gt.astype(np.uint8), _disk(max(1, int(6 * scale)))).astype(bool)
        ys, xs = np.nonzero(away)
        if len(ys):
            k = min(int(blob_pick * len(ys)), len(ys) - 1)
            yy, xx = np.mgrid[0:H, 0:W]
            dx, dy = xx - xs[k], yy - ys[k]
            c, s = np.cos(blob_angle), np.sin(blob_angle)
            a, b = blob_r, blob_r * blob_aspect
            r2 = ((dx * c + dy * s) / a) ** 2 + ((-dx * s + dy * c) / b) ** 2
            mask |= r2 + 0.25 * field < 1.0
            events["blob"] = True
    return mask, events
