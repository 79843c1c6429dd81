"""Atomic file writes: every artifact is written to a temporary file beside its target, flushed to disk
(fsync) and renamed.

A killed run therefore never leaves a half-written artifact under its final name; readers see the old
file or the new one, also after a power cut. Temporary files are named `.<name>.tmp<PID>-<random><ext>`
(`temp_dir` folders alike), so the next run into the same folder can find and remove those of a killed
run (`clean_temp`, called under the output-folder lock).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

log = logging.getLogger(__name__)

# .<target name>.tmp<pid>-<8 random chars from mkstemp/mkdtemp><suffix>
_TEMP_RE = re.compile(r"^\..+\.tmp(?P<pid>\d+)-[a-z0-9_]{8}")


def temp_prefix(name: str) -> str:
    """The prefix of this process's temporary files for target `name` (mkstemp's `prefix`): a killed run's
    are recognised by it and removed by the next run (`clean_temp`)."""
    return f".{name}.tmp{os.getpid()}-"


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def _artifact_mode() -> int:
    """0666 minus the umask: the permissions of an ordinary new file."""
    return 0o666 & ~_umask()


def fsync_path(path: str | Path) -> None:
    """Flush a file's data (or a folder's entries) to disk; file systems that cannot do it are skipped."""
    try:
        fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if Path(path).is_dir() else 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success it is renamed onto `path`.

    `suffix` defaults to the target's suffix so libraries that pick a format by extension still work.
    On an exception the temporary file is removed and the target is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes 0600 files; artifacts get the usual permissions (0666 minus the umask).
        os.chmod(tmp_path, _artifact_mode())
        fsync_path(tmp_path)  # data on disk before the rename makes it visible
        os.replace(tmp_path, path)
        fsync_path(path.parent)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def temp_dir(parent: str | Path, name: str) -> Path:
    """A new empty folder `.<name>.tmp<PID>-XXXXXXXX` in `parent` with ordinary permissions (0777 minus
    the umask, not mkdtemp's 0700), to be filled and renamed into place."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(name), dir=parent))
    os.chmod(tmp, 0o777 & ~_umask())
    return tmp


def clean_temp(folder: str | Path) -> list[Path]:
    """Remove the temporary files and folders of killed runs under `folder` (any not made by this
    process). Call it only while holding the folder's lock (`splattwin.lock`), when no other splattwin
    process writes there. Returns what was removed."""
    folder = Path(folder)
    removed: list[Path] = []
    me = os.getpid()
    if not folder.is_dir():
        return removed
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in list(dirnames) + filenames:
            m = _TEMP_RE.match(name)
            if m is None or int(m.group("pid")) == me:
                continue
            p = Path(dirpath) / name
            try:
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                    dirnames.remove(name)
                else:
                    p.unlink()
                removed.append(p)
            except OSError as e:
                log.warning("could not remove temporary %s of an earlier run: %s", p, e)
    if removed:
        log.info("removed %d temporary file(s) left by a killed run in %s", len(removed), folder)
    return removed


def remove_stale(folder: str | Path, keep: set[str], suffix: str | None = None, dirs: bool = False) -> list[Path]:
    """Remove from `folder` the entries an earlier run wrote for things that are gone (an object no longer
    in the twin): files ending in `suffix` (or, with dirs=True, sub-folders) whose name is not in `keep`.
    Never follows a link (a link is removed itself); leaves every other entry alone. Returns what went."""
    folder = Path(folder)
    removed: list[Path] = []
    if folder.is_symlink() or not folder.is_dir():
        return removed
    with os.scandir(folder) as it:
        entries = list(it)
    for e in entries:
        if e.name in keep or _TEMP_RE.match(e.name):
            continue
        p = folder / e.name
        if dirs and e.is_dir(follow_symlinks=False):
            shutil.rmtree(p)
        elif not dirs and suffix is not None and e.name.endswith(suffix) and (e.is_symlink() or e.is_file()):
            p.unlink()
        else:
            continue
        removed.append(p)
    if removed:
        log.info("removed %s of an earlier run (no longer in the twin)", ", ".join(str(r) for r in removed))
    return removed


def remove_files(folder: str | Path, names, empty_folder: bool = False) -> list[Path]:
    """Remove the files `names` (plain names, no folders) from `folder`, where an earlier run wrote them.
    Never follows a link (a link named so is removed itself, a linked `folder` is left alone); a folder
    of that name is left alone. empty_folder: also remove `folder` itself when it is then empty.
    Returns what went."""
    folder = Path(folder)
    removed: list[Path] = []
    if folder.is_symlink() or not folder.is_dir():
        return removed
    for name in names:
        if not name or "/" in name or name in (".", ".."):
            raise ValueError(f"not a plain file name: {name!r}")
        p = folder / name
        if p.is_symlink() or p.is_file():
            p.unlink()
            removed.append(p)
    if empty_folder:
        try:
            folder.rmdir()              # only when empty
        except OSError:
            pass
    if removed:
        log.info("removed %s of an earlier run", ", ".join(str(r) for r in removed))
    return removed


def write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | Path, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, indent: int = 2, strict: bool = True) -> Path:
    """Write `obj` as JSON, atomically. strict (the default) writes standard JSON: NaN and infinities
    become null (Python's default writes the bare tokens NaN/Infinity, which JSON.parse, jq, the viewer's
    browser and most other readers reject); readers here take null as "not measured"."""
    if strict:
        obj = finite_or_none(obj)
    text = json.dumps(obj, indent=indent, sort_keys=False, default=_json_default, allow_nan=not strict)
    return write_text(path, text + "\n")


def finite_or_none(obj: Any) -> Any:
    """`obj` with every non-finite float (NaN, +-inf; numpy scalars and arrays included) replaced by None."""
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    return obj


def write_npy(path: str | Path, array: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)
    return Path(path)


def write_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return Path(path)


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write uint8/uint16 HxW or HxWxC as PNG/JPEG (format from the suffix), atomically."""
    from PIL import Image

    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format=_pil_format(path))
    return path


def _pil_format(path: Path) -> str:
    ext = path.suffix.lower()
    return {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(ext, "PNG")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json(path: str | Path, missing: str = "file not found", max_bytes: int | None = None) -> Any:
    """Parse a JSON file; InputError naming the file when it is missing, larger than `max_bytes` (default:
    `splattwin.limits.MAX_JSON_BYTES`; records use MAX_RECORD_BYTES), too deeply nested or not valid JSON."""
    from splattwin.limits import read_json as _read

    return _read(path, missing, max_bytes)


def read_record(path: str | Path) -> Any:
    """A stage's JSON record read within `splattwin.limits.MAX_RECORD_BYTES`, or None when it is missing,
    unreadable, over that limit or not valid JSON: for readers that go on without it (the report, the build's
    headline, stale checks) of a twin that may be someone else's."""
    from splattwin import limits
    from splattwin.errors import InputError

    try:
        return read_json(path, max_bytes=limits.MAX_RECORD_BYTES)
    except InputError:
        return None
