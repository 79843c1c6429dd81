"""Confined paths: every path read from a file stays inside that file's folder.

Datasets (transforms.json `file_path`, depth and mask paths, COLMAP image names, cameras.json image
names), mask indexes and twin manifests name other files by path. Those files are often received from
someone else, so a path read from them is accepted only when it is relative and, with every `..` and
symbolic link resolved, still inside the folder it is relative to. Anything else is an InputError
naming the file that held the path (the CLI exits 2).

Names that become paths (object and view names) are checked by `splattwin.names` first; `child`
joins such a name onto a folder and checks the result the same way.

The files splattwin itself wrote into a twin, training or poses folder are read through `own_file`: never
through a symbolic link out of that folder (`LinkOutside`, an InputError naming the link). A capture folder's
links are followed (docs/CONTRACTS.md, "Symbolic links").
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from splattwin.errors import InputError, short_repr


def is_inside(path: str | Path, root: str | Path) -> bool:
    """True if `path`, resolved (symlinks and `..`), is `root` or lies under it."""
    return Path(path).resolve().is_relative_to(Path(root).resolve())


def confined(root: str | Path, rel, where: str | Path | None = None, what: str = "path",
             resolve: bool = True) -> Path:
    """`root / rel` if `rel` is a relative path that stays inside `root` once resolved.

    root: the folder the path is relative to (usually the folder of the file it was read from).
    rel: the path as read from the file (str or Path). where: the file, named in the error.
    resolve=False: the path as written only (its `..`), without touching the disk (no folder to resolve
    links in yet). Returns the joined (not resolved) path, so callers see the same paths as before.
    """
    if isinstance(rel, Path):
        text = str(rel)
    elif isinstance(rel, str):
        text = rel
    else:
        raise InputError(f"{what} must be a string, got {type(rel).__name__} {short_repr(rel, 100)}", where)
    if not text or "\x00" in text:
        raise InputError(f"{what} {short_repr(text, 100)} is empty or contains a NUL byte", where)
    p = Path(text)
    if p.is_absolute() or text.startswith("~"):
        raise InputError(f"{what} {short_repr(text, 100)} is absolute; paths in this file must be relative to its folder "
                         f"{root}", where)
    full = Path(root) / p
    if not resolve:
        import posixpath

        norm = posixpath.normpath(p.as_posix())
        inside = not (norm == ".." or norm.startswith("../"))
    else:
        try:
            inside = is_inside(full, root)
        except RuntimeError:   # Path.resolve before Python 3.13: a loop of symbolic links (was exit 1)
            raise InputError(f"{what} {short_repr(text, 100)} is a loop of symbolic links", where) from None
        _check_usable(full, text, where, what)
    if not inside:
        raise InputError(f"{what} {short_repr(text, 100)} leads outside its folder {root} (after resolving '..' and "
                         f"symbolic links); refusing to read or write there", where)
    return full


def _check_usable(full: Path, text: str, where, what: str) -> None:
    """InputError for a path the file system refuses to look up: a name longer than it allows (a 300-character
    file_path made the reader's is_file() raise OSError ENAMETOOLONG, exit 1) or a loop of symbolic links.
    A path that does not exist is fine here (its reader says so)."""
    try:
        os.stat(full)
    except OSError as e:
        if e.errno in (errno.ENAMETOOLONG, errno.ELOOP):
            raise InputError(f"{what} {short_repr(text, 100)} cannot be looked up: {os.strerror(e.errno)}",
                             where) from None


def child(root: str | Path, name: str, where: str | Path | None = None, what: str = "name") -> Path:
    """`root / name` for a name already checked by `splattwin.names`, verified to stay inside `root`
    (e.g. a folder `objects/<name>` that is a symbolic link to elsewhere is refused)."""
    return confined(root, name, where, what)


def unfollowed(path: str | Path) -> Path:
    """`path` made absolute with its folder resolved but not its last component: a symbolic link keeps
    its own name. Names and relative paths of a user's files (SfM image names, bundled file names,
    transforms.json `file_path`) come from where the user put them, never from a link's target (a
    capture folder of links to photos elsewhere is still `images/000.jpg`). Reading goes through the
    link as usual."""
    p = Path(path).absolute()
    if p.name in ("", ".", ".."):
        return p.resolve()
    return p.parent.resolve() / p.name


def relative_to(path: str | Path, root: str | Path) -> str | None:
    """`path` relative to `root` as a POSIX string when it lies inside it (resolved), else None."""
    try:
        return Path(os.path.relpath(Path(path).resolve(), Path(root).resolve())).as_posix() \
            if is_inside(path, root) else None
    except ValueError:
        return None


class LinkOutside(InputError):
    """A file splattwin wrote is a symbolic link out of its folder (`own_file`): bad input even where a bad file
    is only a warning (e.g. the geometry stage's optional cameras), as nothing may be read through it."""


def own_file(root: str | Path, path: str | Path, what: str = "file") -> Path:
    """`path`, a file splattwin wrote in the folder `root` (a twin, build, training or poses folder: its
    records, checkpoints, PLYs, npz), unchanged when it lies inside `root` once its symbolic links are
    resolved, or does not exist (its reader says so). Such folders may be received from someone else, and a
    link planted there would have the file read from anywhere (`splat/train.json -> /etc/passwd`): a link
    leading out of `root` is an InputError naming the link (exit 2). Links inside `root` are followed.

    Capture folders (a user's photos and their metadata) are the deliberate exception and are not checked:
    datasets are commonly links into a dataset store (docs/CONTRACTS.md)."""
    p = Path(path)
    if not (p.is_symlink() or p.exists()) or is_inside(p, root):
        return p
    link = p
    try:
        parts = p.relative_to(root).parts
    except ValueError:
        parts = ()
    q = Path(root)
    for part in parts:   # name the outermost link that leads out (a linked folder, else the file)
        q = q / part
        if q.is_symlink() and not is_inside(q, root):
            link = q
            break
    target = os.readlink(link) if link.is_symlink() else str(link.resolve())
    raise LinkOutside(f"{what} is a symbolic link to {target!r}, outside its folder {root}; splattwin reads the "
                     f"files it wrote only from inside their folder: replace the link by the file", link)
