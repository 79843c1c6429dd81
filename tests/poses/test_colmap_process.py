"""The COLMAP steps' job files (poses.colmap_process.run_step)."""

from __future__ import annotations

import os

import pytest

from splattwin import io
from splattwin.poses import colmap_process


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
