"""A plain image folder: frames without poses.

Intrinsics are a guess until poses are estimated: focal length from a field-of-view prior (default 60°
horizontal) unless given; the poses stage (SfM) refines them.
"""

from __future__ import annotations

import math
from pathlib import Path

from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame, find_images, image_size
from splattwin.errors import InputError


def read(path: str | Path, fov_x_deg: float = 60.0) -> Dataset:
    path = Path(path)
    folder = path / "images" if (path / "images").is_dir() and not find_images(path) else path
    files = find_images(folder)
    if not files:
        raise InputError("no images found (png/jpg/...)", folder)
    frames = []
    size0 = None
    for p in files:
        w, h = image_size(p)
        if size0 is None:
            size0 = (w, h)
        elif (w, h) != size0:
            raise InputError(f"image is {w}x{h} but the first image ({files[0].name}) is {size0[0]}x{size0[1]}; "
                             "all images of one capture must share a size", p)
        frames.append(Frame(image_path=p, camera=Camera.from_fov(math.radians(fov_x_deg), w, h, name=p.stem)))
    return Dataset(root=path, frames=frames, has_poses=False, meta={"format": "images", "path": str(folder)})
