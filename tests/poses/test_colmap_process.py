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
