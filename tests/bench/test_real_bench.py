"""bench/real.py helpers that turn figures into conclusions, checked on analytic cases."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image


def test_misplacement_bound_of_a_ramp(tmp_path: Path, load_bench):
    """A horizontal ramp of slope s per pixel: shifted by d px along x it differs by d*s at each of the
    h*(w-d) overlapping pixels, along y not at all at (h-d)*w pixels; the pooled MSE follows exactly."""
    twin, w, h, s = tmp_path / "twin", 64, 48, 3
    (twin / "poses" / "images").mkdir(parents=True)
    ramp = np.repeat((np.arange(w) * s).astype(np.uint8)[None, :, None], h, 0).repeat(3, 2)
    frames = []
    for i in range(2):
        Image.fromarray(ramp).save(twin / "poses" / "images" / f"{i}.png")
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": T.tolist(),
                       "split": "heldout" if i == 0 else "train"})
    (twin / "poses" / "transforms.json").write_text(json.dumps(
        {"camera_model": "PINHOLE", "fl_x": 50.0, "fl_y": 50.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h,
         "frames": frames}))
    (twin / "splat").mkdir()
    (twin / "splat" / "train.json").write_text(json.dumps({"resolution": {"resolution": 1, "max_side": None}}))
    got = load_bench("real")._misplacement_bound(twin)
    for d in (1, 2):
        mse = (d * s / 255) ** 2 * h * (w - d) / (h * (w - d) + (h - d) * w)
        assert got[f"statue_self_shift_{d}px_db"] == round(-10 * math.log10(mse), 2)
