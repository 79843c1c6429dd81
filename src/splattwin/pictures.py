"""Composing pictures from numpy images (shared by the stages that write figures and by the report)."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def side_by_side(images: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    """Concatenate HxWx3 float/uint8 images horizontally with a white gap; shorter ones are padded
    with white at the bottom. Returns float32 HxWx3 in [0, 1]."""
    ims = [np.asarray(im, dtype=np.float32) / (255.0 if np.asarray(im).dtype == np.uint8 else 1.0) for im in images]
    h = max(im.shape[0] for im in ims)
    out = []
    for i, im in enumerate(ims):
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        im = im[..., :3]
        if im.shape[0] < h:
            im = np.concatenate([im, np.ones((h - im.shape[0], im.shape[1], 3), np.float32)], axis=0)
        out.append(im)
        if i < len(ims) - 1:
            out.append(np.ones((h, gap, 3), np.float32))
    return np.concatenate(out, axis=1)
