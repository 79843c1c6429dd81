"""A plain image folder: frames without poses.

Intrinsics are a guess until poses are estimated: focal length from a field-of-view prior (default 60°
horizontal) unless given; the poses stage (SfM) refines them. Images may differ in size (internet photos
from several cameras): each frame has its own camera, and SfM gives one camera model per size/EXIF camera.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame, find_images, image_size
from splattwin.capture.orientation import upright_copies
from splattwin.errors import InputError

log = logging.getLogger(__name__)


def _drop_copies(files: list[Path]) -> list[Path]:
    """`files` without byte-identical copies of an earlier file (a copy held out beside its original in
    training scored 19 dB against 13 dB for a real held-out view, inflating the mean, and SfM gains nothing
    from it); a warning names them."""
    from splattwin.hashing import sha256_file

    first: dict[str, Path] = {}
    keep, copies = [], []
    for p in files:
        d = sha256_file(p)
        if d in first:
            copies.append(f"{p.name} (= {first[d].name})")
        else:
            first[d] = p
            keep.append(p)
    if copies:
        log.warning("%d photo%s identical to another and left out: %s%s", len(copies),
                    "s are" if len(copies) > 1 else " is", ", ".join(copies[:5]), ", ..." if len(copies) > 5 else "")
    return keep


def read(path: str | Path, fov_x_deg: float = 60.0, out_dir: str | Path | None = None) -> Dataset:
    """The images of `path` (or of path/images) as frames without poses. out_dir: where upright copies of
    photos stored rotated (EXIF Orientation) go (`capture.orientation`); needed only when there are any."""
    path = Path(path)
    folder = path / "images" if (path / "images").is_dir() and not find_images(path) else path
    files = find_images(folder)
    if not files:
        raise InputError("no images found (png/jpg/...)", folder)
    return read_files(files, root=path, folder=folder, fov_x_deg=fov_x_deg, out_dir=out_dir)


def read_files(files: list[Path], root: Path, folder: Path | None = None, fov_x_deg: float = 60.0,
               out_dir: str | Path | None = None) -> Dataset:
    """These image files (in this order) as frames without poses (`read`; a video's frames, `video.read`:
    only the files of its extraction, not whatever else its folder holds)."""
    folder = Path(folder) if folder is not None else Path(root)
    if not files:
        raise InputError("no images found (png/jpg/...)", folder)
    files = _drop_copies(list(files))
    upright = upright_copies(files, None if out_dir is None else Path(out_dir), folder)
    frames = []
    for p in files:
        q = upright.get(p, p)
        w, h = image_size(q)
        frames.append(Frame(image_path=q, camera=Camera.from_fov(math.radians(fov_x_deg), w, h, name=p.stem)))
    meta = {"format": "images", "path": str(folder)}
    if upright:
        meta["exif_rotated"] = sorted(p.name for p in upright)
    return Dataset(root=Path(root), frames=frames, has_poses=False, meta=meta)
