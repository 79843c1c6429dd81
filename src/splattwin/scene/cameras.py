"""Scan trajectory of the embedded scene: an eye-in-hand-like arc over the table.

Views lie on a 240-degree arc centred on the robot's side (-x), with elevation oscillating between ~35 and
~65 degrees and distance from the table centre between 0.55 and 0.8 m, all looking at the objects.
Held-out views are taken *between* training views along the same arc (interpolation, not extrapolation).
"""

from __future__ import annotations

import math

import numpy as np

from splattwin.capture.camera import Camera, look_at

ARC_CENTER = math.pi      # azimuth of the arc's middle: the robot's side of the table
ARC_SPAN = math.radians(240.0)
ELEVATION = (math.radians(35.0), math.radians(65.0))
DISTANCE = (0.55, 0.80)   # metres from the table centre


def heldout_indices(views: int, heldout: int) -> list[int]:
    """Positions (along the arc of views + heldout cameras) of the held-out views: evenly spread and never
    the first or last position, so every held-out view lies between training views."""
    n = views + heldout
    idx: list[int] = []
    for k in range(heldout):
        i = min(n - 2, max(1, int(math.floor((k + 0.5) * n / heldout))))
        if idx and i <= idx[-1]:
            i = idx[-1] + 1
        idx.append(i)
    # too many held-out views for the gaps: shift the tail back inside [1, n-2]
    for k in range(heldout - 1, -1, -1):
        limit = n - 2 - (heldout - 1 - k)
        if idx[k] > limit:
            idx[k] = limit
    return idx


def scan_cameras(views: int, heldout: int, width: int, height: int, fov_x: float, look_target: np.ndarray,
                 seed: int) -> list[Camera]:
    """Cameras along the arc in scan order, named train_XXX / heldout_XXX. Intrinsics: principal point
    at the image centre, square pixels, no distortion."""
    rng = np.random.default_rng([seed, 2])
    n = views + heldout
    held = set(heldout_indices(views, heldout))
    cams: list[Camera] = []
    it = ih = 0
    for i in range(n):
        s = (i + 0.5) / n
        az = ARC_CENTER - ARC_SPAN / 2 + ARC_SPAN * s + rng.normal(0, math.radians(2.0))
        el = (ELEVATION[0] + ELEVATION[1]) / 2 + (ELEVATION[1] - ELEVATION[0]) / 2 * math.sin(2 * math.pi * 3 * s)
        r = (DISTANCE[0] + DISTANCE[1]) / 2 + (DISTANCE[1] - DISTANCE[0]) / 2 * math.sin(2 * math.pi * 2 * s + 0.7)
        eye = r * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        target = np.asarray(look_target, dtype=np.float64) + rng.normal(0, 0.015, 3)
        T = look_at(eye, target)
        if i in held:
            name, ih = f"heldout_{ih:03d}", ih + 1
        else:
            name, it = f"train_{it:03d}", it + 1
        cams.append(Camera.from_fov(fov_x, width, height, T_world_cam=T, name=name))
    return cams
