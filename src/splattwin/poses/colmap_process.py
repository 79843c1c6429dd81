"""Run a pycolmap step in a child process (`splattwin.poses.colmap_worker`) and stay responsive.

Why a process: pycolmap's extraction, matching and mapping block in C++ and ignore Ctrl-C until they
return (minutes on large photos). The parent waits on the child's progress lines with a short timeout, so
KeyboardInterrupt is raised within a fraction of a second; the child is then terminated (SIGTERM, SIGKILL
after 2 s) and whatever the step had half-written is cleaned: its `*.tmp` output folder is removed and the
SQLite database's hot journal is rolled back, leaving the last committed features/matches for a resumed
run. Progress: the child's own events (mapping: one per registered image) plus a poll of the database
(extraction: images with keypoints; matching: pairs matched), shown through `StageProgress`. The child's
peak resident memory (VmHWM) is recorded per step.

The poll reads through one connection (`_DatabaseWatch`), opened before the worker starts and kept until it
has ended. It used to open and close a connection every second, and COLMAP opens the database with no busy
timeout (`Database::Open`, several times per step): an open that met the poll's connection being opened or
closed (SQLite takes exclusive locks when the first connection to a WAL database rebuilds the log's index,
and when the last one checkpoints and deletes the log) failed at once with "SQLite error: database is
locked", reported as "No registered database factory succeeded" (a known-poses triangulation's extraction
failed so in a test run; a poll run continuously from another process made 56 of 300 opens of an existing
database fail). With a connection that stays open the worker's opens are never the first or the last, and
in WAL mode a reader does not block a writer.

A worker that ends by SIGTERM or SIGINT: Slurm, Kubernetes and docker signal every process of a job, and the
worker (no handler of its own, its own session) may die before this process's Python handler has run, so
its exit status (-15) arrived first and the stop was reported as a failed step (exit 1, "internal error").
The parent therefore waits up to PARENT_SIGNAL_GRACE_S for its own signal (`_await_own_signal`): if it
comes, the step is an interruption like any other (KeyboardInterrupt: exit 143 / 130, the step cleaned up);
if not, someone signalled the worker alone, and `StoppedFromOutside` says so, naming the signal.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import queue
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from splattwin import interrupt
from splattwin.errors import StoppedFromOutside
from splattwin.poses.progress import StageProgress

log = logging.getLogger(__name__)

TERMINATE_GRACE_S = 2.0
# seconds this process waits for its own copy of the SIGTERM / SIGINT its worker died of (a job scheduler signals
# every process, in no set order; `_await_own_signal`); only a worker killed alone costs the wait
PARENT_SIGNAL_GRACE_S = 1.0
_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
# seconds between two polls of the step's database for progress (`_DatabaseWatch`), and the longest wait for
# a line of the worker between two checks for an interrupt
PROGRESS_POLL_S = 1.0
LINE_WAIT_S = 0.25


class StepError(RuntimeError):
    """A pycolmap step failed in the child (message, plus the tail of its stderr)."""

    def __init__(self, step: str, message: str, stderr_tail: str = ""):
        self.step, self.message, self.stderr_tail = step, message, stderr_tail
        super().__init__(f"{step}: {message}" + (f"\n{stderr_tail}" if stderr_tail else ""))


@dataclass
class StepStats:
    """Wall seconds, CPU seconds (user + system, all threads) and peak resident memory of one step."""

    seconds: float
    peak_rss_bytes: int
    cpu_seconds: float = 0.0


def _children_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _package_root() -> str:
    import splattwin

    return str(Path(splattwin.__file__).resolve().parents[1])


def _read_hwm(pid: int) -> int:
    """Peak resident set size (VmHWM) of a live process in bytes; 0 where /proc is unavailable."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def terminate(proc: subprocess.Popen) -> None:
    """SIGTERM (the worker has no handler: it dies at once), SIGKILL if it is still there after the grace."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(TERMINATE_GRACE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _await_own_signal(grace_s: float = PARENT_SIGNAL_GRACE_S) -> None:
    """After a worker died of SIGTERM / SIGINT: wait up to `grace_s` seconds for this process's own signal.
    Raises KeyboardInterrupt when it comes (Python's handler raises it in the sleep; `interrupt.check()` for
    one the CLI's handler recorded, e.g. while the main thread was elsewhere); returns when none came."""
    from splattwin import interrupt

    deadline = time.monotonic() + grace_s
    while True:
        interrupt.check()
        left = deadline - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(0.05, left))


def _signal_name(rc: int) -> str:
    """The signal of a negative Popen return code ("SIGTERM"; "signal 77" for one Python does not name)."""
    try:
        return signal.Signals(-rc).name
    except ValueError:
        return f"signal {-rc}"


def recover_database(db: str | Path) -> None:
    """Settle the database after a step: roll back a transaction a killed writer left open (SQLite does so
    on the first access) and fold COLMAP's write-ahead log into the file (no -wal/-shm files left)."""
    db = Path(db)
    if not db.is_file():
        return
    try:
        con = sqlite3.connect(str(db), timeout=5.0)
        try:
            con.execute("SELECT count(*) FROM sqlite_master").fetchone()
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        finally:
            con.close()
    except sqlite3.Error as e:
        log.warning("could not check the SfM database %s after an interruption: %s", db, e)


_COUNTED = ("images", "keypoints", "matches", "two_view_geometries")


class _DatabaseWatch:
    """The parent's one connection to a step's COLMAP database, open while the worker runs (see the module
    docstring): created here in WAL mode if the file is new, as COLMAP creates it, so the worker never
    opens the file first. `count(table)`: rows in a table that grows during the step, None while the
    worker has not created it yet (or the database is busy)."""

    def __init__(self, db: str | Path):
        self.con = sqlite3.connect(str(db), timeout=5.0, isolation_level=None)
        try:
            self.con.execute("PRAGMA journal_mode=WAL").fetchall()
        except BaseException:
            self.con.close()
            raise

    def count(self, table: str) -> int | None:
        if table not in _COUNTED:
            raise ValueError(f"not a counted table: {table!r}")
        try:
            # fetchall: the statement runs to its end, so no read transaction stays open between polls
            return int(self.con.execute(f"SELECT count(*) FROM {table}").fetchall()[0][0])
        except sqlite3.Error:
            return None

    def close(self) -> None:
        self.con.close()


def _close_pipes(proc: subprocess.Popen, readers: list[threading.Thread]) -> None:
    """Close the worker's stdout/stderr pipes once their reader threads have ended (each step left two open
    file objects behind: ResourceWarning "unclosed file" in every SfM run). A reader still running (a worker
    that did not end) keeps its pipe: closing it under the thread would raise there."""
    for t in readers:
        t.join(1.0)
    for t, pipe in zip(readers, (proc.stdout, proc.stderr)):
        if pipe is not None and not t.is_alive():
            pipe.close()


def db_counts(db: str | Path) -> dict[str, int]:
    """Rows in the COLMAP database tables that grow during a step ({} while the file is busy or new). Opens
    and closes a connection: not for polling while a worker opens the database (`_DatabaseWatch` is)."""
    out: dict[str, int] = {}
    try:
        con = sqlite3.connect(f"file:{Path(db).resolve()}?mode=ro", uri=True, timeout=0.2)
        try:
            for t in _COUNTED:
                out[t] = int(con.execute(f"SELECT count(*) FROM {t}").fetchone()[0])
        finally:
            con.close()
    except sqlite3.Error:
        return {}
    return out


# COLMAP's message when every way of opening the database failed; with SQLite "database is locked" behind it (COLMAP
# sets no busy timeout), a lock held for a moment by another connection: seen in 1 of ~2200 test runs after the poll
# kept one connection open (module docstring), in a known-poses triangulation's extraction
TRANSIENT_DB_ERROR = "No registered database factory succeeded"


def run_step(job: dict, job_dir: Path, progress: StageProgress, label: str, total: int = 1,
             poll_table: str | None = None, cleanup: list[Path] | None = None
             ) -> tuple[dict, StepStats]:
    """`_run_step_once`, run once more when COLMAP could not open its database (`TRANSIENT_DB_ERROR`): every step
    resumes from what its database holds, so the second run does only what the first left undone."""
    try:
        return _run_step_once(job, job_dir, progress, label, total, poll_table, cleanup)
    except StepError as e:
        if TRANSIENT_DB_ERROR not in e.message:
            raise
        log.warning("%s: COLMAP could not open its database (%s); running the step once more", job["step"],
                    e.message)
    return _run_step_once(job, job_dir, progress, label, total, poll_table, cleanup)


def _run_step_once(job: dict, job_dir: Path, progress: StageProgress, label: str, total: int = 1,
                   poll_table: str | None = None, cleanup: list[Path] | None = None
                   ) -> tuple[dict, StepStats]:
    """Run `job` (a dict with "step" and the step's arguments, see colmap_worker) in a child process.

    progress: shows `label` with done/`total`; with `poll_table` ("keypoints", "two_view_geometries", ...),
      about once a second the rows of that table of the job's database ("db") are the count, read through
      one connection open from before the child starts until it has ended (`_DatabaseWatch`); the child's
      own progress events also update it.
    cleanup: paths removed if the step is interrupted or fails (its half-written outputs).
    Returns (the child's result dict, StepStats). Raises StepError if the step fails, KeyboardInterrupt
    (after stopping the child and cleaning up) if interrupted, also when the signal reached the child first
    (`_await_own_signal`), StoppedFromOutside (cleaned up too) when someone sent the child alone SIGTERM or
    SIGINT.
    """
    job_dir.mkdir(parents=True, exist_ok=True)
    from splattwin import io

    # a temporary name of ours (removed after the step; a killed run's by the next run, `io.clean_temp`)
    fd, name = tempfile.mkstemp(prefix=io.temp_prefix(f"job_{job['step']}.json"), suffix=".json", dir=job_dir)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(job))
    job_path = Path(name)
    env = os.environ.copy()
    env["PYTHONPATH"] = _package_root() + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0, cpu0 = time.perf_counter(), _children_cpu()
    watch = None
    try:
        if poll_table is not None:
            watch = _DatabaseWatch(job["db"])   # before the child: its opens of the database are never the first
        proc = subprocess.Popen([sys.executable, "-m", "splattwin.poses.colmap_worker", str(job_path)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, env=env,
                                start_new_session=True, text=True, bufsize=1)
    except BaseException:
        if watch is not None:
            watch.close()
        job_path.unlink(missing_ok=True)
        raise
    lines: queue.Queue = queue.Queue()
    err_tail: collections.deque = collections.deque(maxlen=40)

    def _pump_out() -> None:
        for line in proc.stdout:  # type: ignore[union-attr]
            lines.put(line)
        lines.put(None)

    def _pump_err() -> None:
        for line in proc.stderr:  # type: ignore[union-attr]
            err_tail.append(line.rstrip())

    threads = [threading.Thread(target=_pump_out, daemon=True), threading.Thread(target=_pump_err, daemon=True)]
    for t in threads:
        t.start()
    result: dict | None = None
    error: str | None = None
    done, peak, last_poll = 0, 0, 0.0
    progress.update(label, 0, total)
    try:
        while True:
            # the CLI's SIGTERM handler again: `import pycolmap` here (sfm.run) installed glog's, which ended a
            # `timeout`/`docker stop` of SfM with a C stack trace; also a Ctrl-C a library swallowed
            interrupt.check()
            try:
                line = lines.get(timeout=LINE_WAIT_S)
            except queue.Empty:
                line = ""
            if line is None:
                break
            if line:
                try:
                    msg = json.loads(line)
                except json.JSONDecodeError:
                    err_tail.append(line.rstrip())
                    msg = {}
                ev = msg.get("event")
                if ev == "progress":
                    done = int(msg.get("done", done))
                    total = int(msg.get("total", total)) or total
                    progress.update(label, done, total)
                elif ev == "result":
                    result = {k: v for k, v in msg.items() if k != "event"}
                elif ev == "error":
                    error = str(msg.get("message"))
            now = time.monotonic()
            if now - last_poll >= PROGRESS_POLL_S:
                last_poll = now
                peak = max(peak, _read_hwm(proc.pid))
                if watch is not None:
                    v = watch.count(poll_table)
                    if v is not None and v != done:
                        done = v
                        progress.update(label, done, total)
            progress.tick()
        peak = max(peak, _read_hwm(proc.pid))
        rc = proc.wait()
        for t in threads:
            t.join(1.0)
        if rc < 0 and -rc in _STOP_SIGNALS:   # this process's own signal may still be on its way
            _await_own_signal()
    except BaseException:
        terminate(proc)
        if watch is not None:
            watch.close()
        _remove(cleanup)
        if "db" in job:
            recover_database(job["db"])
        raise
    finally:
        if watch is not None:
            watch.close()   # (closing twice is harmless) before `recover_database` checkpoints the log
        job_path.unlink(missing_ok=True)
        _close_pipes(proc, threads)
    if "db" in job:
        recover_database(job["db"])
    stats = StepStats(seconds=time.perf_counter() - t0, peak_rss_bytes=peak, cpu_seconds=_children_cpu() - cpu0)
    if result is None or rc != 0:
        _remove(cleanup)
        if "db" in job:
            recover_database(job["db"])
        tail = "\n".join(list(err_tail)[-15:])
        if rc < 0 and -rc in _STOP_SIGNALS:   # and this process got none within the grace: not a step failure
            raise StoppedFromOutside(
                f"the SfM worker was terminated by {_signal_name(rc)} (another process or the job scheduler) "
                f"during the {job['step']} step; nothing half-written was kept: run the same command again to "
                f"resume from the SfM work folder {job_dir}")
        if rc < 0:   # SIGKILL: most often the kernel's out-of-memory killer
            error = error or (f"the pycolmap worker was killed by {_signal_name(rc)}"
                              + (" (out of memory? the kernel's log, dmesg, says)" if -rc == signal.SIGKILL else ""))
        raise StepError(job["step"], error or f"the pycolmap worker exited with status {rc}", tail)
    progress.update(label, total if job["step"] != "map" else done, total)
    return result, stats


def _remove(paths: list[Path] | None) -> None:
    for p in paths or []:
        p = Path(p)
        for q in (p, p.with_name(p.name + ".tmp")):
            if q.is_dir():
                shutil.rmtree(q, ignore_errors=True)
            elif q.exists():
                q.unlink(missing_ok=True)
