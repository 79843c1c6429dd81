from __future__ import annotations

import pytest

from splattwin.errors import InputError
from splattwin.lock import LOCK_NAME, STATE_DIR, holds, output_lock


def test_a_failed_command_leaves_no_folder_it_created_and_wrote_nothing_to(tmp_path):
    out = tmp_path / "new" / "out"
    with pytest.raises(InputError):
        with output_lock(out):
            assert (out / STATE_DIR / LOCK_NAME).is_file() and holds(out)
            raise InputError("bad input", tmp_path / "capture")
    assert not out.exists() and not holds(out)
    with pytest.raises(KeyboardInterrupt):   # Ctrl-C before anything was written: same
        with output_lock(out):
            raise KeyboardInterrupt
    assert not out.exists()


def test_a_folder_that_existed_or_got_outputs_stays(tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(InputError):
        with output_lock(existing):
            raise InputError("bad input", tmp_path)
    assert existing.is_dir()
    out = tmp_path / "out"
    with pytest.raises(InputError):
        with output_lock(out):
            (out / "transforms.json").write_text("{}")
            raise InputError("bad input", tmp_path)
    assert (out / "transforms.json").is_file() and (out / STATE_DIR / LOCK_NAME).is_file()
    ok = tmp_path / "ok"
    with output_lock(ok):
        pass
    assert (ok / STATE_DIR / LOCK_NAME).is_file()   # a successful run keeps its (released) lock file


_KILLED_PLAN = """
import os, sys, time
from pathlib import Path
from splattwin.executor import Job, LocalExecutor
from splattwin.lock import output_lock

def work(pid_file):
    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(60)

out, pid_file = sys.argv[1], sys.argv[2]
with output_lock(out):
    ex = LocalExecutor(workers=1)
    h = ex.submit(Job(key="k", fn=work, args=(pid_file,)))
    while not Path(pid_file).is_file():
        time.sleep(0.05)
    print("ready", flush=True)
    time.sleep(60)
"""


def test_a_killed_run_s_pool_workers_neither_keep_its_lock_nor_outlive_it(tmp_path):
    """`kill -9` of `plan` while its trial workers run: the workers (forked, sharing the lock's open file)
    must not keep the folder locked, so the killed run resumes at once, and they exit with their parent."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from splattwin.lock import acquire, release

    out, pid_file = tmp_path / "twin", tmp_path / "worker.pid"
    (tmp_path / "plan.py").write_text(_KILLED_PLAN)
    proc = subprocess.Popen([sys.executable, str(tmp_path / "plan.py"), str(out), str(pid_file)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        worker = int(pid_file.read_text())
        with pytest.raises(InputError, match="another splattwin process"):
            acquire(out)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        acquire(out)        # the worker still runs (its sleep), but holds no lock
        release(out)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            pytest.fail("the pool worker outlived its killed parent")
    finally:
        proc.kill()


@pytest.mark.parametrize("link", ["lock", "folder"])
def test_a_lock_linked_out_of_the_folder_writes_nothing_there(tmp_path, link):
    """found by fuzzing a received twin: OUT/.splattwin/lock a symbolic link to a file elsewhere was opened,
    truncated and written (the holder's PID) before the folder's links were checked, so `splattwin report TWIN`
    emptied that file (then refused the link, exit 2). Likewise a .splattwin/ linked to a folder elsewhere got
    the lock. Now neither is followed: an InputError naming the link, the file elsewhere untouched."""
    import os

    out, elsewhere = tmp_path / "received", tmp_path / "elsewhere"
    (out / STATE_DIR).mkdir(parents=True)
    elsewhere.mkdir()
    victim = elsewhere / "notes.txt"
    victim.write_text("precious\n")
    if link == "lock":
        os.symlink(victim, out / STATE_DIR / LOCK_NAME)
    else:
        (out / STATE_DIR).rmdir()
        os.symlink(elsewhere, out / STATE_DIR)
    with pytest.raises(InputError) as e:
        with output_lock(out):
            pass
    assert e.value.path == out / STATE_DIR / (LOCK_NAME if link == "lock" else "")
    assert victim.read_text() == "precious\n" and sorted(p.name for p in elsewhere.iterdir()) == ["notes.txt"]
