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


def fit_height(image: np.ndarray, height: int) -> np.ndarray:
    """HxWx3 float/uint8 image shrunk (area-averaged, aspect kept) to at most `height` px tall; a smaller one
    unchanged. Returns float32 in [0, 1]. For report thumbnails: a 4032x3024 photo embedded as it is makes a
    picture of megabytes that the page shows a few hundred pixels wide anyway."""
    from PIL import Image

    im = np.asarray(image)
    im = im.astype(np.float32) / 255.0 if im.dtype == np.uint8 else im.astype(np.float32)
    if im.shape[0] <= height:
        return im
    w = max(1, round(im.shape[1] * height / im.shape[0]))
    u8 = (np.clip(im[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.asarray(Image.fromarray(u8).resize((w, height), Image.BOX), np.float32) / 255.0


def legend_strip(rows: Sequence[tuple[str, Sequence[int]]], height: int, width: int = 140) -> np.ndarray:
    """A white HxWx3 uint8 strip listing `rows` [(text, rgb 0..255)] as colour swatches with their text,
    at least `height` px tall (taller when the rows need it): the key of a picture coloured by object."""
    from PIL import Image, ImageDraw

    canvas = Image.new("RGB", (width, max(height, 16 * len(rows) + 8)), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (text, rgb) in enumerate(rows):
        y = 4 + 16 * i
        draw.rectangle([6, y, 18, y + 12], fill=tuple(int(c) for c in rgb))
        draw.text((24, y), str(text)[:18], fill=(0, 0, 0))
    return np.asarray(canvas)
