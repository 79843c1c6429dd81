"""Photos stored rotated (EXIF Orientation tag): upright copies for everything downstream.

Why: a phone stores a portrait shot sideways (landscape pixels) with an EXIF Orientation tag (6 or 8) that
photo viewers apply. COLMAP's feature extraction and our own pixel reads take the pixels as stored, so
such a capture was reconstructed lying on its side: the cameras' image-up axis horizontal, every render
and report picture sideways, and SfM's tabletop sanity checks (cameras looking down at the table) judged
on rotated cameras. Measured on the cake photos re-saved as a phone writes them (pixels turned 90°,
Orientation 6): 6/8 images registered instead of 8/8, and the cameras' image-up vector at world z
-0.01..0.52 instead of 0.76..0.86.

HEIC/HEIF (an iPhone's default format) takes the same path: PIL reads it through pillow-heif (libheif
applies the rotation the container records for a portrait shot), COLMAP cannot read it at all.

What: for a plain image folder (where the cameras come from the images), every photo whose tag is not 1,
and every HEIC/HEIF photo, is written upright (PIL's `ImageOps.exif_transpose`, lossless PNG) into a folder of the run's own
(`build`: TWIN/capture/frames/upright/), and the frames point at those copies; photos without a tag or
with Orientation 1 are used as they are. The copies are reused while the source's size and mtime are
unchanged (upright.json). Datasets that come with their own cameras (transforms.json, COLMAP, BOP, TUM)
are read as stored: their intrinsics and poses were computed by tools that ignore the tag (COLMAP does),
so rotating their pixels would break them.
"""

from __future__ import annotations

import logging
from pathlib import Path

from splattwin.errors import InputError
from splattwin.limits import read_json

log = logging.getLogger(__name__)

ORIENTATION_TAG = 0x0112
HEIF_SUFFIXES = (".heic", ".heif")
UPRIGHT_DIR = "upright"
INDEX = "upright.json"
_SWAPS = {5, 6, 7, 8}   # orientations that exchange width and height


def exif_orientation(path: str | Path) -> int:
    """The EXIF Orientation (1..8) of an image, from its header; 1 when it has none or an invalid one."""
    from splattwin.limits import open_image

    with open_image(path) as im:
        try:
            o = im.getexif().get(ORIENTATION_TAG, 1)
        except Exception:   # noqa: BLE001 - a malformed EXIF block: the pixels as stored
            return 1
    try:
        o = int(o)
    except (TypeError, ValueError):
        return 1
    return o if 1 <= o <= 8 else 1


def displayed_size(width: int, height: int, orientation: int) -> tuple[int, int]:
    """(width, height) of the image as a viewer shows it."""
    return (height, width) if orientation in _SWAPS else (width, height)


def write_upright(src: Path, dst: Path) -> Path:
    """The image at `src` turned as its EXIF Orientation says, written atomically to `dst` (PNG)."""
    import numpy as np
    from PIL import ImageOps

    from splattwin.io import write_image
    from splattwin.limits import open_image

    with open_image(src) as im:
        im.load()
        up = ImageOps.exif_transpose(im)
        arr = np.asarray(up.convert("RGB") if up.mode not in ("RGB", "L") else up)
    return write_image(dst, arr)


def needs_copy(path: Path) -> int | str | None:
    """Why `path` cannot be used as stored: its EXIF Orientation (2..8), "HEIF" (COLMAP cannot read HEIC/HEIF,
    an iPhone's default format), or None."""
    if path.suffix.lower() in HEIF_SUFFIXES:
        return "HEIF"
    o = exif_orientation(path)
    return o if o != 1 else None


def upright_copies(paths: list[Path], out_dir: Path | None, where: Path) -> dict[Path, Path]:
    """{source: upright PNG copy} for the images in `paths` stored rotated or as HEIC/HEIF (none: {}). The
    copies go to out_dir/upright/<stem>.png; out_dir None when some are needed: InputError."""
    rotated = {}
    for p in paths:
        why = needs_copy(p)
        if why is not None:
            rotated[p] = why
    if not rotated:
        return {}
    if out_dir is None:
        first = next(iter(rotated))
        raise InputError(f"{len(rotated)} of {len(paths)} photos are stored rotated (EXIF Orientation) or as "
                         f"HEIC/HEIF (e.g. {first.name}: {rotated[first]}) and need upright PNG copies, but no "
                         f"folder was given for them; run `splattwin build` or `splattwin poses`, or convert the "
                         f"files first (exiftran -ai, mogrify -auto-orient, heif-convert)", where)
    folder = Path(out_dir) / UPRIGHT_DIR
    index_path = folder / INDEX
    try:   # a stale or damaged index only costs a rewrite of the copies
        index = read_json(index_path, max_bytes=1 << 24) if index_path.is_file() else {}
    except InputError:
        index = {}
    if not isinstance(index, dict):
        index = {}
    out: dict[Path, Path] = {}
    written = 0
    for p, o in rotated.items():
        dst = folder / f"{p.stem}.png"
        st = p.stat()
        stamp = {"source": str(p.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns, "reason": o}
        if index.get(dst.name) != stamp or not dst.is_file():
            write_upright(p, dst)
            index[dst.name] = stamp
            written += 1
        out[p] = dst
    if written:
        from splattwin.io import write_json

        write_json(index_path, index)
    if written or folder not in _ANNOUNCED:   # once per folder and run: pre-flight, scene and poses all read it
        _ANNOUNCED.add(folder)
        log.info("%d of %d photos are stored rotated (EXIF Orientation) or as HEIC/HEIF: using upright PNG copies "
                 "in %s (%d written)", len(rotated), len(paths), folder, written)
    return out


_ANNOUNCED: set[Path] = set()
