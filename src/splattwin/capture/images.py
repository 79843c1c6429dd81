"""A plain image folder: frames without poses.

Intrinsics are a guess until poses are estimated: focal length from a field-of-view prior (default 60°
horizontal) unless given; the poses stage (SfM) refines them. Images may differ in size (internet photos
from several cameras): each frame has its own camera, and SfM gives one camera model per size/EXIF camera.
"""

from __future__ import annotations

import math
from pathlib import Path

from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame, find_images, image_size
from splattwin.capture.orientation import upright_copies
from splattwin.errors import InputError


def read(path: str | Path, fov_x_deg: float = 60.0, out_dir: str | Path | None = None) -> Dataset:
    """The images of `path` (or of path/images) as frames without poses. out_dir: where upright copies of
    photos stored rotated (EXIF Orientation) go (`capture.orientation`); needed only when there are any."""
    path = Path(path)
    folder = path / "images" if (path / "images").is_dir() and not find_images(path) else path
    files = find_images(folder)
    if not files:
        raise InputError("no images found (png/jpg/...)", folder)
    upright = upright_copies(files, None if out_dir is None else Path(out_dir), folder)
    frames = []
    for p in files:
        q = upright.get(p, p)
        w, h = image_size(q)
        frames.append(Frame(image_path=q, camera=Camera.from_fov(math.radians(fov_x_deg), w, h, name=p.stem)))
    meta = {"format": "images", "path": str(folder)}
    if upright:
        meta["exif_rotated"] = sorted(p.name for p in upright)
    return Dataset(root=path, frames=frames, has_poses=False, meta=meta)
