"""The COLMAP steps' job files (poses.colmap_process.run_step)."""

from __future__ import annotations

import os
import sys

import pytest

from splattwin import io
from splattwin.poses import colmap_process
from splattwin.poses.progress import StageProgress


def test_a_job_file_carries_our_temporary_name(tmp_path, monkeypatch):
    """A `kill -9` during SfM left `poses/sfm/.job_extract_<pid>.json` for ever: the job file is named as
    our temporary files are, so the next run that takes the folder's lock removes it (`io.clean_temp`)."""
    seen = []

    def popen(argv, **kw):
        seen.append(argv[-1])
        raise OSError("no child in this test")

    monkeypatch.setattr(colmap_process.subprocess, "Popen", popen)
    with pytest.raises(OSError):
        colmap_process.run_step({"step": "extract"}, tmp_path, progress=None, label="extract")
    name = os.path.basename(seen[0])
    m = io._TEMP_RE.match(name)
    assert m is not None and int(m.group("pid")) == os.getpid() and name.endswith(".json")
    assert list(tmp_path.iterdir()) == []          # and a step that could not start leaves none


def test_a_worker_killed_by_sigkill_is_named_so(tmp_path, monkeypatch):
    """A worker the kernel's out-of-memory killer ends (SIGKILL) read "the pycolmap worker exited with
    status -9": the step's error names the signal and its likely cause."""
    real = colmap_process.subprocess.Popen

    def popen(argv, **kw):   # a worker that dies of SIGKILL at once
        return real([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"], **kw)

    monkeypatch.setattr(colmap_process.subprocess, "Popen", popen)
    with pytest.raises(colmap_process.StepError) as e:
        colmap_process.run_step({"step": "extract"}, tmp_path, progress=StageProgress(enabled=False),
                                 label="extract")
    assert e.value.message == "the pycolmap worker was killed by SIGKILL (out of memory? the kernel's log, dmesg, says)"


@pytest.mark.parametrize("worker", ['print(\'{"event": "result"}\')', "import sys; sys.exit(3)"])
def test_a_step_leaves_no_pipe_of_its_worker_open(tmp_path, monkeypatch, worker):
    """Each step left the worker's stdout and stderr pipes open (ResourceWarning "unclosed file" twice per SfM
    step), when it succeeded and when it failed."""
    import gc
    import warnings

    real = colmap_process.subprocess.Popen
    made = []

    def popen(argv, **kw):
        made.append(real([sys.executable, "-c", worker], **kw))
        return made[-1]

    monkeypatch.setattr(colmap_process.subprocess, "Popen", popen)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", ResourceWarning)
        try:
            colmap_process.run_step({"step": "extract"}, tmp_path, progress=StageProgress(enabled=False),
                                     label="extract")
        except colmap_process.StepError:
            pass
        gc.collect()
    assert made and made[0].stdout.closed and made[0].stderr.closed
    assert not [w for w in seen if issubclass(w.category, ResourceWarning) and "unclosed file" in str(w.message)]




# a worker that opens the step's database as COLMAP's steps do (pycolmap.Database.open; several times per step),
# many times over, and reports the opens that failed and when (CLOCK_MONOTONIC, the same in every process) it
# opened the database first and closed it last
_OPENING_WORKER = """
import json, sys, time
import pycolmap
pycolmap.logging.minloglevel = 3
failed, t0 = [], time.monotonic()
for k in range(int(sys.argv[2])):
    try:
        pycolmap.Database.open(sys.argv[1]).close()
    except RuntimeError as e:
        failed.append(str(e))
print(json.dumps({"event": "result", "failed": failed, "first": t0, "last": time.monotonic()}), flush=True)
"""


def test_the_progress_poll_never_makes_the_workers_database_open_fail(tmp_path, monkeypatch):
    """The parent's progress poll opened and closed a connection to the step's database every second, while
    COLMAP opens it (several times per step) with no busy timeout: an open that met the poll's connection
    being opened or closed failed at once with "SQLite error: database is locked", reported as "No
    registered database factory succeeded" (a known-poses triangulation's extraction failed so in a test
    run). The parent now connects once, before the worker starts, and closes after it has ended. Here the
    poll runs continuously (each worker line waited for 1 ms) while a worker opens a new database 1000
    times: no connection of the parent may open between the worker's first open and its last close (the
    old poll opened hundreds), and no open may fail (the old poll failed 0 to 73 of them, by timing)."""
    pytest.importorskip("pycolmap")
    import sqlite3
    import time

    monkeypatch.setattr(colmap_process, "PROGRESS_POLL_S", 0.0)
    monkeypatch.setattr(colmap_process, "LINE_WAIT_S", 0.001)
    real_popen, real_connect = colmap_process.subprocess.Popen, sqlite3.connect
    db = tmp_path / "database.db"
    connects, polls = [], []

    def popen(argv, **kw):
        return real_popen([sys.executable, "-c", _OPENING_WORKER, str(db), "1000"], **kw)

    def connect(target, *a, **kw):
        if str(db) in str(target):
            connects.append(time.monotonic())
        return real_connect(target, *a, **kw)

    monkeypatch.setattr(colmap_process.subprocess, "Popen", popen)
    monkeypatch.setattr(sqlite3, "connect", connect)
    count = colmap_process._DatabaseWatch.count
    monkeypatch.setattr(colmap_process._DatabaseWatch, "count",
                        lambda self, table: polls.append(table) or count(self, table))
    res, _ = colmap_process.run_step({"step": "extract", "db": str(db)}, tmp_path, StageProgress(enabled=False),
                                     "extract", poll_table="keypoints")
    during = [t for t in connects if res["first"] <= t <= res["last"]]
    assert during == [], f"the parent connected {len(during)} times while the worker opened the database"
    assert res["failed"] == [], f"{len(res['failed'])} of 1000 opens failed: {res['failed'][0]}"
    assert len(polls) > 100   # the poll did run alongside the opens


def test_a_step_whose_database_could_not_be_opened_runs_once_more(tmp_path, monkeypatch, caplog):
    """COLMAP opens its database with no busy timeout, and a lock held for a moment elsewhere failed the whole run
    ('extract: RuntimeError: No registered database factory succeeded.', once in a full test run); the step now
    runs once more (it resumes from its database). Any other failure, or the same one twice, is the error."""
    import logging

    real = colmap_process.subprocess.Popen
    runs = tmp_path / "runs"
    runs.mkdir()

    def worker(fail_times: int, message: str) -> str:
        return (f"import json, pathlib, sys\n"
                f"runs = pathlib.Path({str(runs)!r})\n"
                f"n = len(list(runs.iterdir())); (runs / str(n)).touch()\n"
                f"if n < {fail_times}:\n"
                f"    print(json.dumps({{'event': 'error', 'message': {message!r}}})); sys.exit(1)\n"
                f"print(json.dumps({{'event': 'result', 'keypoints': 7}}))\n")

    def run(fail_times: int, message: str):
        for f in runs.iterdir():
            f.unlink()
        monkeypatch.setattr(colmap_process.subprocess, "Popen",
                            lambda argv, **kw: real([sys.executable, "-c", worker(fail_times, message)], **kw))
        return colmap_process.run_step({"step": "extract"}, tmp_path, progress=StageProgress(enabled=False),
                                       label="extract")

    locked = "RuntimeError: No registered database factory succeeded."
    with caplog.at_level(logging.WARNING, logger="splattwin.poses.colmap_process"):
        res, _ = run(1, locked)
    assert res == {"keypoints": 7} and len(list(runs.iterdir())) == 2
    assert "running the step once more" in caplog.text
    with pytest.raises(colmap_process.StepError, match="No registered database factory"):
        run(2, locked)
    assert len(list(runs.iterdir())) == 2
    with pytest.raises(colmap_process.StepError, match="out of disk"):
        run(1, "RuntimeError: out of disk")
    assert len(list(runs.iterdir())) == 1
