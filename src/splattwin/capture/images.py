"""A plain image folder: frames without poses.

Intrinsics are a guess until poses are estimated: focal length from a field-of-view prior (default 60°
horizontal) unless given; the poses stage (SfM) refines them. Images may differ in size (internet photos
from several cameras): each frame has its own camera, and SfM gives one camera model per size/EXIF camera.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame, find_images, image_size, image_subfolders
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


ALPHA_DIR = "alpha_masks"
NOT_PHOTO_FOLDERS = ("depth", "mask", "label", "seg")   # sub-folder names (prefixes) that hold no photos
# PIL modes that carry an alpha channel (a palette image may carry one as its transparency entry)
_ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")


def transparent_pixels(path: Path) -> np.ndarray | None:
    """bool [h, w], True where the photo at `path` is fully transparent (alpha 0), or None when it has no
    alpha channel or no such pixel. The mode is read from the header; only photos with alpha are decoded."""
    from splattwin.limits import open_image

    with open_image(path) as im:
        if im.mode not in _ALPHA_MODES and not (im.mode == "P" and "transparency" in im.info):
            return None
        im.load()
        alpha = np.asarray(im.convert("RGBA") if im.mode in ("P", "PA", "RGBa", "La") else im)[..., -1]
    clear = alpha == 0
    return clear if clear.any() else None


def alpha_loss_masks(files: list[Path], out_dir: Path | None) -> dict[Path, Path]:
    """{photo: loss mask} for the photos of `files` with fully transparent pixels (a background removed by an
    app, a render with a transparent film): the colour stored under alpha 0 is no observation (often black),
    yet alpha was dropped and it was trained on as a black backdrop. Each mask (out_dir/alpha_masks/<stem>.png,
    255 = keep, 0 = transparent) makes the pixels ignored in training and evaluation as a nerfstudio
    `mask_path` does. out_dir None (nowhere to write): the photos are named in a warning instead."""
    from splattwin.io import write_image

    clear = {}
    for p in files:
        m = transparent_pixels(p)
        if m is not None:
            clear[p] = m
    if not clear:
        return {}
    share = ", ".join(f"{p.name} ({100 * float(m.mean()):.0f} %)" for p, m in list(clear.items())[:5])
    more = ", ..." if len(clear) > 5 else ""
    if out_dir is None:
        log.warning("%d of %d photos have transparent pixels (%s%s); nowhere to write their loss masks, so the "
                    "colours stored under them are used as they are", len(clear), len(files), share, more)
        return {}
    folder = Path(out_dir) / ALPHA_DIR
    out = {}
    for p, m in clear.items():
        dst, keep = folder / f"{p.stem}.png", np.where(m, 0, 255).astype(np.uint8)
        if not (dst.is_file() and np.array_equal(_read_mask(dst), keep)):   # unchanged: not rewritten
            write_image(dst, keep)
        out[p] = dst
    if folder not in _ANNOUNCED:   # once per folder and run: pre-flight, scene and poses all read the photos
        _ANNOUNCED.add(folder)
        log.info("%d of %d photos have transparent pixels (%s%s): those pixels are left out of training and "
                 "evaluation (loss masks in %s)", len(clear), len(files), share, more, folder)
    return out


_ANNOUNCED: set[Path] = set()


def _read_mask(path: Path) -> np.ndarray | None:
    """An earlier run's alpha loss mask, or None when it cannot be read (then it is written again)."""
    from splattwin.capture.dataset import load_mask

    try:
        return load_mask(path)
    except InputError:
        return None


def read(path: str | Path, fov_x_deg: float = 60.0, out_dir: str | Path | None = None) -> Dataset:
    """The images of `path` (or of path/images) as frames without poses. out_dir: where upright copies of
    photos stored rotated (EXIF Orientation) go (`capture.orientation`); needed only when there are any."""
    path = Path(path)
    folder = path / "images" if (path / "images").is_dir() and not find_images(path) else path
    files = find_images(folder)
    if not files:
        raise InputError("no images found (png/jpg/...)", folder)
    # masks/, depth/ ... beside the photos are no photos
    nested = [(n, k) for n, k in image_subfolders(folder) if not n.lower().startswith(NOT_PHOTO_FOLDERS)]
    if nested and folder not in _ANNOUNCED:   # photos split over sub-folders lost the rest without a word
        _ANNOUNCED.add(folder)
        log.warning("%s: using its %d images; sub-folders are not searched, so the images of %s are left out (give "
                    "a folder that holds all the photos)", folder, len(files),
                    ", ".join(f"{n}/ ({k})" for n, k in nested[:5]) + (", ..." if len(nested) > 5 else ""))
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
    # the upright copies are RGB: an EXIF-rotated photo's alpha is not looked at
    alpha = alpha_loss_masks([p for p in files if p not in upright], None if out_dir is None else Path(out_dir))
    frames = []
    for p in files:
        q = upright.get(p, p)
        w, h = image_size(q)
        frames.append(Frame(image_path=q, camera=Camera.from_fov(math.radians(fov_x_deg), w, h, name=p.stem),
                            mask_path=alpha.get(p)))
    meta = {"format": "images", "path": str(folder)}
    if upright:
        meta["exif_rotated"] = sorted(p.name for p in upright)
    return Dataset(root=Path(root), frames=frames, has_poses=False, meta=meta)
