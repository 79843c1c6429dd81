"""Metric scale of an SfM reconstruction from the capture's depth images (RGB-D without poses).

SfM recovers the cameras up to scale; a depth sensor measures metres. Where an SfM point projects into a
view, the sensor's depth there over the point's SfM depth is the scale (metres per SfM unit). The median
over every point seen with a valid depth reading is robust to the sensor's holes (0), flying pixels at
depth edges and mismatched SfM points; its spread tells whether the depth and the reconstruction agree
(a depth image not registered to the colour camera spreads widely and is not used). A uniform unit error
(a wrong depth_scale) leaves the spread alone; the median reading, the scene's distance from the cameras,
must then lie within VIEW_DEPTH_M of a tabletop capture (x10 or x1000 errors fall outside; x2 ones cannot
be told from a farther capture).

Sampling: the depth pixel under the projected point (distortion applied: depth registered to the colour
camera is sampled where that camera saw the point); a reading is kept only when its 3x3 neighbourhood is
complete and within 2 % of it, which drops depth edges, where a point's SfM depth and the reading may
belong to different surfaces.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from splattwin.capture.camera import Camera

log = logging.getLogger(__name__)

MIN_READINGS = 50        # fewer pairs of (SfM depth, sensor depth): no scale
MAX_SPREAD = 0.15        # robust relative spread (1.4826 MAD / median) above which depth and SfM disagree
EDGE_TOLERANCE = 0.02    # a reading's 3x3 neighbourhood must lie within 2 % of it
# a consumer depth camera's systematic depth error (a D435: ~1 % at 1 m), which no number of readings averages
# out: the floor of the reported uncertainty
SENSOR_BIAS_REL = 0.01
# the median depth reading of a tabletop capture (m): a consumer depth camera reads 0.1-10 m, a tabletop is
# seen from 0.2-2 m; beyond these bounds the depth's units are wrong (x10 or x1000), not the scene
VIEW_DEPTH_M = (0.1, 4.0)


@dataclass
class DepthScale:
    """scale: metres per SfM unit (median of sensor depth / SfM depth); spread: robust relative spread of the
    ratios (1.4826 MAD / median); uncertainty_rel: 1-sigma relative uncertainty of the scale (the median's
    standard error and SENSOR_BIAS_REL); readings:
    number of pairs; views: views that gave at least one."""

    scale: float
    spread: float
    uncertainty_rel: float
    readings: int
    views: int

    def to_dict(self) -> dict:
        return {"scale": self.scale, "spread_rel": round(self.spread, 5), "uncertainty_rel": self.uncertainty_rel,
                "readings": self.readings, "views": self.views}


def depth_ratios(camera: Camera, depth_m: np.ndarray, points_xyz: np.ndarray) -> np.ndarray:
    """[K] sensor depth / SfM depth for the points [N,3] (SfM frame) that `camera` (SfM frame) sees where
    `depth_m` [H,W] (metres, 0 = no reading, registered to this camera's pixels) has a clean reading."""
    sensor, sfm = depth_pairs(camera, depth_m, points_xyz)
    return sensor / sfm


def depth_pairs(camera: Camera, depth_m: np.ndarray, points_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """([K] sensor depth m, [K] SfM depth) of the points that have a clean reading (`depth_ratios`)."""
    uv, z = camera.project(points_xyz)
    ok = camera.in_image(uv) & (z > 0)
    if not ok.any():
        return np.zeros(0), np.ones(0)
    # pixel (i, j) covers [j, j+1) x [i, i+1) (centres at +0.5, splattwin.capture.camera)
    j = np.floor(uv[ok, 0]).astype(int)
    i = np.floor(uv[ok, 1]).astype(int)
    z = z[ok]
    H, W = depth_m.shape
    inner = (i >= 1) & (i < H - 1) & (j >= 1) & (j < W - 1)
    i, j, z = i[inner], j[inner], z[inner]
    d = np.nan_to_num(depth_m.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    centre = d[i, j]
    good = centre > 0
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            nb = d[i + di, j + dj]
            good &= (nb > 0) & (np.abs(nb - centre) <= EDGE_TOLERANCE * centre)
    return centre[good], z[good]


def scale_from_depth(cameras: Sequence[Camera], depths_m: Sequence[np.ndarray], points_xyz: np.ndarray
                     ) -> tuple[DepthScale | None, str]:
    """Metres per SfM unit from views (`cameras`, SfM frame) and their depth maps (metres), or None and why.

    points_xyz: [N,3] SfM points. Returns (fit, note): None when fewer than MIN_READINGS readings or when
    the ratios spread more than MAX_SPREAD (the note says which)."""
    ratios, readings, views = [], [], 0
    for cam, d in zip(cameras, depths_m):
        sensor, sfm = depth_pairs(cam, d, points_xyz)
        if len(sensor):
            ratios.append(sensor / sfm)
            readings.append(sensor)
            views += 1
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    metres = np.concatenate(readings) if readings else np.zeros(0)
    keep = np.isfinite(r) & (r > 0)
    r, metres = r[keep], metres[keep]
    if len(r) < MIN_READINGS:
        return None, f"only {len(r)} SfM points have a clean depth reading (need {MIN_READINGS})"
    # A uniform unit error (mm read as cm, a wrong depth_scale) scales every ratio alike, so the spread
    # cannot see it; the distances it implies can: a tabletop capture sees its scene from arm's length.
    view_m = float(np.median(metres))
    if not (VIEW_DEPTH_M[0] <= view_m <= VIEW_DEPTH_M[1]):
        return None, (f"the depth images put the scene {view_m:.3g} m from the cameras (median reading), outside "
                      f"the {VIEW_DEPTH_M[0]:g}-{VIEW_DEPTH_M[1]:g} m of a tabletop capture: are their units right "
                      f"(BOP depth_scale, the intrinsics file's depth factor, nerfstudio depth_unit_scale_factor)?")
    med = float(np.median(r))
    spread = float(1.4826 * np.median(np.abs(r - med)) / med)
    if spread > MAX_SPREAD:
        return None, (f"the depth images disagree with the SfM points (sensor/SfM depth ratios spread "
                      f"{100 * spread:.0f} % around their median, over {len(r)} readings): depth not registered "
                      f"to the colour camera, or in other units than declared?")
    # the median's standard error (1.2533 sigma / sqrt(n), sigma from the MAD) and the sensor's own bias
    unc = float(np.hypot(1.2533 * spread / np.sqrt(len(r)), SENSOR_BIAS_REL))
    return DepthScale(scale=med, spread=spread, uncertainty_rel=unc, readings=int(len(r)), views=views), \
        f"median of {len(r)} sensor/SfM depth ratios over {views} views (spread {100 * spread:.1f} %)"
