"""One writer per output folder: a lock kept inside the folder (`OUT/.splattwin/lock`).

Two `splattwin build`s (or a build and a `plan`, `export`, `report`, ...) writing into one folder would
interleave their files and leave whichever finished last, with exit 0 for both. Every command that
writes into a folder holds its lock: the second one exits 2 at once, naming the holder's PID.

Mechanism: an exclusive `flock` on the lock file (advisory, POSIX). The kernel releases it when the
holder exits in any way, `kill -9` included, so a lock left by a killed run is never in force: the next
run takes it over (it says so, naming the dead PID recorded in the file) and then removes the killed
run's temporary files (`splattwin.io.clean_temp`). The file itself is never deleted (deleting it would
let two processes lock two different files); it records `{pid, host, command, started}` of the holder.

Re-entrant within a process: `build` holds the lock and calls stage functions that may take it again.

A forked child (a process pool's worker) closes its copies of the lock descriptors at once: the flock
belongs to the open file, shared with the child, so a worker outliving a killed parent would otherwise
keep the folder locked and the killed run could never resume. (Closing, not unlocking: an unlock from
the child would release the parent's lock too.)

Taking the lock also checks the folder for symbolic links that lead out of it (a received twin folder
whose `splat/` is a link to elsewhere would make every write there land outside `--out`): such a link
is an InputError naming it, before anything is written. The lock file itself is written before that check,
so it is never opened through a link (`O_NOFOLLOW`), nor its folder `.splattwin/` followed out of the folder.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import fcntl
import json
import logging
import os
import socket
import sys
import threading
from pathlib import Path
from typing import Iterator

from splattwin.errors import InputError

log = logging.getLogger(__name__)

STATE_DIR = ".splattwin"
LOCK_NAME = "lock"

_held: dict[str, list] = {}   # resolved folder -> [fd, depth]
_guard = threading.Lock()


def _forget_in_child() -> None:
    """After fork, in the child: drop the inherited lock descriptors (see the module docstring)."""
    global _guard
    _guard = threading.Lock()   # a lock another thread of the parent held at fork time would never be released
    for fd, _depth in _held.values():
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


os.register_at_fork(after_in_child=_forget_in_child)


def lock_path(folder: str | Path) -> Path:
    return Path(folder) / STATE_DIR / LOCK_NAME


def _read_holder(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        raw = os.read(fd, 4096)
        info = json.loads(raw.decode("utf-8")) if raw.strip() else {}
        return info if isinstance(info, dict) else {}
    except (OSError, ValueError):
        return {}


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except (OSError, ValueError, TypeError, OverflowError) as e:
        return isinstance(e, PermissionError)
    return True


def prepare_output_dir(folder: str | Path, what: str = "output folder") -> Path:
    """Create `folder` (and parents) or InputError if it exists as something other than a folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{what} exists and is not a folder", folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{what} cannot be created: a parent is a file", folder) from None
    except OSError as e:
        raise InputError(f"{what} cannot be created ({e.strerror or e})", folder) from None
    return folder


def acquire(folder: str | Path, command: str | None = None) -> None:
    """Take the folder's lock (create the folder if needed). InputError if another process holds it."""
    folder = prepare_output_dir(folder)
    key = str(folder.resolve())
    with _guard:
        if key in _held:
            _held[key][1] += 1
            return
        state = folder / STATE_DIR
        if state.is_symlink():   # a received folder's .splattwin/ linked elsewhere: the lock would be written there
            from splattwin.paths import confined

            confined(folder, STATE_DIR, state, "lock folder")
        state.mkdir(exist_ok=True)
        path = state / LOCK_NAME
        try:
            # O_NOFOLLOW: the lock is truncated and written before check_links looks at the folder, so a received
            # folder's .splattwin/lock linked to a file elsewhere had that file emptied
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise InputError("the lock file is a symbolic link; splattwin writes its lock there and never "
                                 "through a link: remove it", path) from None
            raise InputError(f"cannot create the lock file ({e.strerror or e})", path) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read_holder(fd)
            os.close(fd)
            if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise InputError(f"cannot lock the output folder ({e.strerror or e})", path) from None
            who = f"PID {holder.get('pid', '?')}"
            if holder.get("pid") and not _pid_alive(holder["pid"]):
                who += " (exited; a process it started still holds the lock)"
            if holder.get("host") and holder.get("host") != socket.gethostname():
                who += f" on {holder['host']}"
            since = f", running {holder['command']!r} since {holder.get('started', '?')}" if holder.get("command") else ""
            raise InputError(f"another splattwin process ({who}{since}) is writing to this folder; wait for it to "
                             f"finish or stop it (its lock: {path})", folder) from None
        prev = _read_holder(fd)
        if prev.get("pid") and prev.get("pid") != os.getpid():
            state_txt = "no longer running" if not _pid_alive(prev["pid"]) else "its lock was released"
            log.warning("taking over the lock of %s left by PID %s (%s; killed run?)", folder, prev["pid"], state_txt)
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "command": command or " ".join([Path(sys.argv[0]).name] + sys.argv[1:])[:500],
                "started": _dt.datetime.now().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode("utf-8"), 0)
        _held[key] = [fd, 1]
    from splattwin.io import clean_temp

    try:
        check_links(folder)
    except InputError:
        release(folder)
        raise
    clean_temp(folder)


def check_links(folder: str | Path) -> None:
    """InputError for the first symbolic link under `folder` that resolves outside it."""
    root = Path(folder).resolve()
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            if p.is_symlink() and not p.resolve().is_relative_to(root):
                raise InputError(f"the output folder holds a symbolic link to {os.readlink(p)!r}, outside it; "
                                 f"splattwin never writes outside the output folder: remove the link", p)


def release(folder: str | Path) -> None:
    key = str(Path(folder).resolve())
    with _guard:
        entry = _held.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] > 0:
            return
        fd = entry[0]
        del _held[key]
        try:
            os.ftruncate(fd, 0)  # a clean exit leaves no holder behind
        except OSError:
            pass
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def holds(folder: str | Path) -> bool:
    """True if this process holds the folder's lock."""
    return str(Path(folder).resolve()) in _held


@contextlib.contextmanager
def output_lock(folder: str | Path, command: str | None = None) -> Iterator[Path]:
    """`with output_lock(out):` hold the lock of `out` for the block (see module docstring).

    A command that fails (bad input, Ctrl-C) before writing anything into a folder it created leaves no
    folder behind: only its lock was there, and an empty `OUT/.splattwin/lock` would look like a run."""
    created = not Path(folder).exists()
    acquire(folder, command)
    done = False
    try:
        yield Path(folder)
        done = True
    finally:
        if created and not done:
            _remove_if_untouched(Path(folder))   # still locked: nobody else can be writing there
        release(folder)


def _remove_if_untouched(folder: Path) -> None:
    """Remove `folder` if it holds nothing but our state folder with its lock file."""
    state = folder / STATE_DIR
    try:
        if [p.name for p in folder.iterdir()] != [STATE_DIR] or [p.name for p in state.iterdir()] != [LOCK_NAME]:
            return
        (state / LOCK_NAME).unlink()
        state.rmdir()
        folder.rmdir()
    except OSError:   # something appeared meanwhile, or no permission: leave it
        pass
