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


def mask_transparent_pixels(frames: list[Frame], out_dir: Path | None) -> None:
    """Leave the fully transparent pixels (alpha 0) of the frames' photos out of training, evaluation and SfM
    feature extraction, for every dataset format (`load_dataset`: an image folder, a transforms.json such as
    Blender's synthetic sets, COLMAP, BOP, TUM): the colour stored under alpha 0 (often black) is no
    observation, yet alpha was dropped on reading and it was trained on as a black backdrop. A frame whose
    photo has such pixels gets a loss mask (out_dir/alpha_masks/<view name>.png, 255 = keep, 0 = ignore, the
    photo's size) in `Frame.mask_path`, as a nerfstudio `mask_path`; a frame that already has a mask_path
    gets the AND of the pixels both keep (the mask is read at the photo's size, enlarged when reduced). A
    mask that already leaves out every transparent pixel (an earlier run's, bundled into TWIN/poses) is kept
    as it is. Partial alpha (an anti-aliased edge) is no mask: those pixels are observations. out_dir None
    (nowhere to write): the photos are named in a warning and their colours are used as stored."""
    from splattwin.capture.dataset import load_loss_mask
    from splattwin.io import write_image

    clear = {}
    for f in frames:
        m = transparent_pixels(f.image_path)
        if m is None:
            continue
        keep = np.ones_like(m) if f.mask_path is None else load_loss_mask(f.mask_path, (m.shape[1], m.shape[0]))
        if (keep & m).any():   # some transparent pixel is still trained on
            clear[id(f)] = (f, keep & ~m, m)
    if not clear:
        return
    share = ", ".join(f"{f.image_path.name} ({100 * float(m.mean()):.0f} %)" for f, _, m in list(clear.values())[:5])
    more = ", ..." if len(clear) > 5 else ""
    if out_dir is None:
        log.warning("%d of %d photos have transparent pixels (%s%s); nowhere to write their loss masks, so the "
                    "colours stored under them are used as they are", len(clear), len(frames), share, more)
        return
    folder = Path(out_dir) / ALPHA_DIR
    for f, keep, _ in clear.values():
        # named by the view (unique and a plain file name, `_check_frame_names`): stems repeat in a COLMAP rig
        dst, keep8 = folder / f"{f.name}.png", np.where(keep, 255, 0).astype(np.uint8)
        if not (dst.is_file() and np.array_equal(_read_mask(dst), keep8)):   # unchanged: not rewritten
            write_image(dst, keep8)
        f.mask_path = dst
    if folder not in _ANNOUNCED:   # once per folder and run: pre-flight, scene and poses all read the photos
        _ANNOUNCED.add(folder)
        log.info("%d of %d photos have transparent pixels (%s%s): those pixels are left out of training and "
                 "evaluation (loss masks in %s)", len(clear), len(frames), share, more, folder)


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
    frames = []
    for p in files:
        q = upright.get(p, p)
        w, h = image_size(q)
        frames.append(Frame(image_path=q, camera=Camera.from_fov(math.radians(fov_x_deg), w, h, name=p.stem)))
    meta = {"format": "images", "path": str(folder)}
    if upright:
        meta["exif_rotated"] = sorted(p.name for p in upright)
    return Dataset(root=Path(root), frames=frames, has_poses=False, meta=meta)
