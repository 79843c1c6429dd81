"""Bring a dataset's files into an output folder, so the folder is a self-contained dataset.

The poses stage writes `transforms.json` into the twin folder. If its image paths pointed back at the
input capture (`../../scan/img.png`), the twin could not be moved or copied (the paths would break, or
point at other files), and reading it would have to follow paths out of its folder, which
`splattwin.paths` refuses for untrusted files. So the frames' images, depth maps, loss masks and label
images are hard-linked into `OUT/images/`, `OUT/depth/`, `OUT/masks/`, `OUT/labels/` (copied when a
hard link is impossible, e.g. across file systems), keeping their paths relative to the common folder
of each kind. Hard links cost no space; a copy costs the capture's size once. Where the capture was is
recorded by the caller (twin.json `config.build.input`), not needed afterwards.

A capture file that is a symbolic link keeps its own name (not its target's) and is bundled as the
file it points at: OUT never holds a link, which would lead out of OUT (and be refused when read).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import posixpath
import shutil
from pathlib import Path

from splattwin import io
from splattwin.capture.dataset import Frame
from splattwin.errors import InputError
from splattwin.paths import confined, unfollowed

log = logging.getLogger(__name__)

KINDS = {"image_path": "images", "depth_path": "depth", "mask_path": "masks", "label_path": "labels"}


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or os.path.samefile(a, b)
    except OSError:
        return False


def place_file(src: Path, dst: Path) -> Path:
    """Make `dst` a hard link to (or else a copy of) `src`, atomically; nothing to do if it already is.
    A `src` that is a symbolic link gives its target's content; `dst` is always a regular file."""
    if not dst.is_symlink():  # a link (older versions left some) is replaced by the file itself
        if dst.exists() and _same_file(src, dst):
            return dst
        if dst.is_file() and dst.stat().st_size == src.stat().st_size and io_equal(src, dst):
            return dst
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.parent / f"{io.temp_prefix(dst.name)}{os.urandom(4).hex()}{dst.suffix}"
    try:
        # the link's target: os.link on Linux links a symbolic link itself (whatever follow_symlinks says)
        os.link(os.path.realpath(src), tmp)  # the input's inode and mode stay as they are (no chmod on a link)
        os.replace(tmp, dst)
        return dst
    except OSError:  # other file system, or links not allowed: copy
        if tmp.exists():
            tmp.unlink()
    with io.atomic_path(dst) as t:
        shutil.copyfile(src, t)
    return dst


def io_equal(a: Path, b: Path) -> bool:
    with open(a, "rb") as fa, open(b, "rb") as fb:
        while True:
            x, y = fa.read(1 << 20), fb.read(1 << 20)
            if x != y:
                return False
            if not x:
                return True


def bundle_frames(frames: list[Frame], out_dir: str | Path, placed: list[str] | None = None) -> list[Frame]:
    """Frames whose files live under `out_dir` (see module docstring); the input files are untouched.
    placed: given, the files bundled into `out_dir` are appended to it (POSIX paths relative to `out_dir`),
    not those that already are the input files (`out_dir` holding the capture): the record
    `remove_unbundled` takes on the next run."""
    out_dir = Path(out_dir)
    new = [dataclasses.replace(f) for f in frames]
    for attr, sub in KINDS.items():
        srcs = [getattr(f, attr) for f in frames]
        present = [Path(p) for p in srcs if p is not None]
        if not present:
            continue
        missing = [p for p in present if not p.is_file()]
        if missing:
            raise InputError("file listed in the dataset does not exist", missing[0])
        # names from where the files are, not from links' targets (targets may be anywhere, even apart)
        common = Path(os.path.commonpath([str(unfollowed(p).parent) for p in present]))
        dest_root = out_dir / sub
        for f, src in zip(new, srcs):
            if src is None:
                continue
            src = Path(src)
            rel = unfollowed(src).relative_to(common).as_posix()
            dst = confined(dest_root, rel, src, "bundled file")
            if placed is not None and unfollowed(dst) != unfollowed(src):
                placed.append(f"{sub}/{rel}")
            if not dst.is_symlink() and _same_file(src, dst):
                setattr(f, attr, dst)
                continue
            setattr(f, attr, place_file(src, dst))
    return new


def remove_unbundled(out_dir: str | Path, earlier, placed, inputs=()) -> list[Path]:
    """Remove the files an earlier `bundle_frames` placed into `out_dir` (`earlier`, its `placed` record)
    that this one did not (`placed`): the views of a capture that are gone (a rebuild with fewer views left
    their photos in the twin). Only a recorded file inside `out_dir`'s bundle folders (`KINDS`), never
    through a link, never one of `inputs` (this run's input files); empty sub-folders they leave go too.
    Returns what went."""
    out_dir = Path(out_dir)
    keep = set(placed)
    skip = {unfollowed(p) for p in inputs}
    removed: list[Path] = []
    for rel in earlier:
        if not isinstance(rel, str) or rel in keep or rel.split("/", 1)[0] not in KINDS.values():
            continue
        if posixpath.normpath(rel) != rel:   # "images/../frame.json" passed the folder test above, and
            continue                         # "images/./0.png" is not "images/0.png" this run placed: never ours
        try:
            p = confined(out_dir, rel)
        except InputError:   # a record is read from the folder: a path leading out of it is not ours
            continue
        if unfollowed(p) in skip or not (p.is_symlink() or p.is_file()):
            continue
        p.unlink()
        removed.append(p)
        top = out_dir / rel.split("/", 1)[0]
        d = p.parent
        while d != top and d.is_relative_to(top):
            try:
                d.rmdir()   # only when empty
            except OSError:
                break
            d = d.parent
    if removed:
        log.info("removed %d file(s) of views no longer in the capture from %s (e.g. %s)", len(removed), out_dir,
                 removed[0].relative_to(out_dir))
    return removed
