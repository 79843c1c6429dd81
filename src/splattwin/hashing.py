"""Content digests for stage keys: of input files and folders (cached by size and mtime), and of code.

`DigestCache.digest(path)` is the SHA-256 of a file's bytes, or of a folder's sorted (relative path,
file digest) list (symbolic links are hashed as their target text, never followed), or "missing". A
file is re-read only when its size, mtime, ctime or inode changed since it was last hashed: the cache
(a JSON file, e.g. TWIN/.splattwin/digests.json) makes a re-run over gigabytes of photos cost a stat()
per file. A cache entry whose size and times still match is trusted; a rewrite that keeps the same size
within the file system's timestamp granularity (and keeps the inode) is the one change it can miss.

`code_digest(modules, functions)` hashes the source files of the named modules/packages (every file of
a package folder: .py plus package data such as task YAML, not caches) and the source text of the given
functions, so a stage's key changes whenever the code it runs changes.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import inspect
import json
import logging
import os
import stat
from collections.abc import Callable, Iterable
from pathlib import Path

from splattwin.errors import InputError

log = logging.getLogger(__name__)

DIGEST_CACHE = ".splattwin/digests.json"   # a twin's digest cache (relative to the twin folder)
MAX_TREE_FILES = 200_000
_SKIP_DIRS = {"__pycache__", ".git", ".splattwin"}
_SKIP_SUFFIXES = (".pyc", ".pyo", ".nbi", ".nbc")
_CHUNK = 1 << 20


def sha256_file(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class DigestCache:
    """SHA-256 digests of files and folders with a size+mtime prefilter (see module docstring)."""

    def __init__(self, cache_path: str | Path | None = None):
        self.cache_path = Path(cache_path) if cache_path is not None else None
        self._entries: dict[str, list] = {}
        self._dirty = False
        if self.cache_path is not None and self.cache_path.is_file():
            from splattwin import limits

            try:   # bounded: a received twin's cache is someone else's file (~200 bytes an entry)
                data = limits.read_json(self.cache_path, max_bytes=limits.MAX_RECORD_BYTES)
                if isinstance(data, dict) and isinstance(data.get("files"), dict):
                    self._entries = {k: v for k, v in data["files"].items()
                                     if isinstance(k, str) and isinstance(v, list) and len(v) == 2}
            except (OSError, InputError) as e:
                log.warning("%s is unreadable (%s); hashing inputs afresh", self.cache_path, e)

    def file(self, path: str | Path) -> str:
        path = Path(path)
        st = path.stat()
        key = str(path.resolve())
        stamp = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
        hit = self._entries.get(key)
        if hit is not None and hit[0] == stamp and isinstance(hit[1], str):
            return hit[1]
        digest = sha256_file(path)
        self._entries[key] = [stamp, digest]
        self._dirty = True
        return digest

    def tree(self, folder: str | Path) -> str:
        folder = Path(folder)
        h = hashlib.sha256()
        n = 0
        for dirpath, dirnames, filenames in os.walk(folder):
            dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS)
            for name in sorted(filenames):
                if name.endswith(_SKIP_SUFFIXES) or name.startswith(".") and ".tmp" in name:
                    continue
                p = Path(dirpath) / name
                n += 1
                if n > MAX_TREE_FILES:
                    raise InputError(f"more than {MAX_TREE_FILES} files under this folder; point at the dataset "
                                     f"itself", folder)
                rel = p.relative_to(folder).as_posix()
                st = p.lstat()
                if stat.S_ISLNK(st.st_mode):
                    d = "link:" + os.readlink(p)
                elif stat.S_ISREG(st.st_mode):
                    d = self.file(p)
                else:
                    continue
                h.update(f"{rel}\0{d}\n".encode("utf-8", "surrogateescape"))
        return h.hexdigest()

    def digest(self, path: str | Path | None) -> str:
        """Digest of a file or folder; "missing" if it does not exist, "none" for None."""
        if path is None:
            return "none"
        path = Path(path)
        if path.is_dir():
            return "tree:" + self.tree(path)
        if path.is_file():
            return "file:" + self.file(path)
        return "missing"

    def files(self, paths: Iterable[str | Path | None]) -> str:
        """One digest over several files, e.g. a dataset's images: their order, file names and contents
        (not their folders, so the same capture at another place has the same digest)."""
        h = hashlib.sha256()
        for p in paths:
            name = "" if p is None else Path(p).name
            h.update(f"{name}\0{self.digest(p)}\n".encode("utf-8", "surrogateescape"))
        return h.hexdigest()

    def save(self) -> None:
        if self.cache_path is None or not self._dirty:
            return
        from splattwin import io

        live = {k: v for k, v in self._entries.items() if Path(k).exists()}
        io.write_json(self.cache_path, {"files": live}, indent=None)
        self._dirty = False


# JSON outputs that also record the run that wrote them: the entries a command run by hand rewrites on an
# unchanged result. twin.json: `splattwin export` re-times the exports and lists those it adds (`exports`,
# `export_files`); `versions` are the run's packages. They are not the twin: a stage's output identity
# (`output_digest`) and the robot's twin digest (`splattwin.robot.outputs.twin_digest`) leave them out.
TWIN_RUN_RECORD = ("timings", "versions", "exports", "export_files")
_RUN_RECORDS = {"twin.json": TWIN_RUN_RECORD}


def output_digest(folder: str | Path, rel: str, cache: DigestCache) -> str:
    """The identity of a stage's output file `rel` (relative to `folder`, the twin): its contents' digest
    (`DigestCache.digest`), or for a JSON file that records its run (`_RUN_RECORDS`: twin.json) the digest
    of the JSON less those entries ("json:..."; a file that does not parse as an object: its bytes')."""
    from splattwin import io

    p = Path(folder) / rel
    skip = _RUN_RECORDS.get(Path(rel).as_posix())
    if skip and p.is_file():
        doc = io.read_record(p)
        if isinstance(doc, dict):
            doc = {k: v for k, v in doc.items() if k not in skip}
            return "json:" + hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()
    return cache.digest(p)


def output_digests(folder: str | Path, outputs: dict, cache: DigestCache) -> dict[str, str]:
    """{"@rel/path": `output_digest`} of the files a stage record promises (its "@rel/path" outputs)."""
    return {v: output_digest(folder, v[1:], cache) for v in outputs.values() if isinstance(v, str) and v.startswith("@")}


def changed_outputs(folder: str | Path, rec: dict, cache: DigestCache) -> list[str]:
    """The files a stage record (TWIN/pipeline.json: {"outputs", "digests"}) promises whose identity
    differs from the recorded one: rewritten since the stage wrote them (a command run by hand). Empty for
    a record without digests. A digest recorded whole (before a file's run record was left out) still
    matches the unchanged file."""
    want = rec.get("digests")
    if not isinstance(want, dict):
        return []
    outputs = rec.get("outputs")
    now = output_digests(folder, outputs if isinstance(outputs, dict) else {}, cache)
    return [k[1:] for k, d in now.items()
            if want.get(k) != d and not (d.startswith("json:") and want.get(k) == cache.digest(Path(folder) / k[1:]))]


@functools.lru_cache(maxsize=None)
def module_digest(name: str) -> str:
    """SHA-256 over the source files of module or package `name` as it would be imported now."""
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None and not spec.submodule_search_locations:
        raise ValueError(f"no module named {name!r}")
    h = hashlib.sha256()
    if spec.submodule_search_locations:
        for root in spec.submodule_search_locations:
            root = Path(root)
            for dirpath, dirnames, filenames in os.walk(root):
                dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS)
                for fname in sorted(filenames):
                    if fname.endswith(_SKIP_SUFFIXES):
                        continue
                    p = Path(dirpath) / fname
                    h.update(p.relative_to(root).as_posix().encode() + b"\0")
                    h.update(p.read_bytes())
    else:
        h.update(Path(spec.origin).read_bytes())
    return h.hexdigest()


def code_digest(modules: Iterable[str] = (), functions: Iterable[Callable] = ()) -> str:
    """Digest of the named modules' source and the given functions' source text (see module doc)."""
    h = hashlib.sha256()
    for m in sorted(set(modules)):
        h.update(f"{m}\0{module_digest(m)}\n".encode())
    for fn in functions:
        try:
            src = inspect.getsource(fn)
        except (OSError, TypeError):
            src = getattr(fn, "__qualname__", repr(fn))
        h.update(src.encode("utf-8"))
    return h.hexdigest()
