"""The pipeline's robot stage without a task: it runs because the twin changed, and removes robot results
of a `plan` made on an earlier twin (the report would show them, `render` play them, as this twin's)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from splattwin.pipeline.build import BuildOptions, _robot
from splattwin.pipeline.runner import Context
from splattwin.robot.outputs import twin_digest

_spec = importlib.util.spec_from_file_location("_robot_outputs_helpers",
                                               Path(__file__).parents[1] / "robot" / "test_outputs.py")
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def _planned(twin: Path) -> list[Path]:
    """robot/ as `splattwin plan` leaves it, made on the twin as it is now."""
    out = twin / "robot"
    (out / "trials").mkdir(parents=True)
    (out / "results.json").write_text(json.dumps({"nominal": {"success": True}, "twin_digest": twin_digest(twin)}))
    files = [out / "results.json", out / "rollout.npz", out / "playback.npz", out / "trials" / "1.json"]
    for f in files[1:]:
        f.write_bytes(b"x")
    return files


def _ctx(twin: Path) -> Context:
    return Context(out=twin, options={}, config=BuildOptions(), progress=False)


def test_robot_stage_without_task_removes_results_of_an_earlier_twin(tmp_path):
    twin = helpers.small_twin(tmp_path / "t")
    files = _planned(twin)
    (twin / "robot" / "notes.txt").write_text("mine")
    helpers.small_twin(twin, name="dessert")          # rebuilt with another object (masks renamed)
    assert _robot(_ctx(twin)) == {}
    assert not any(f.exists() for f in files)
    assert (twin / "robot" / "notes.txt").read_text() == "mine"     # not ours to remove


def test_robot_stage_without_task_keeps_results_of_this_twin(tmp_path):
    """A `plan` run by hand on the same, unchanged twin (e.g. rebuilt identically, other run times) stays."""
    from splattwin.twin.manifest import Manifest

    twin = helpers.small_twin(tmp_path / "t")
    files = _planned(twin)
    man = Manifest.load(twin)
    man.timings["geometry"] = 1.5
    man.save(twin)
    assert _robot(_ctx(twin)) == {}
    assert all(f.exists() for f in files)


def test_robot_stage_without_task_removes_results_it_cannot_check(tmp_path):
    twin = helpers.small_twin(tmp_path / "t")
    files = _planned(twin)
    files[0].write_text(json.dumps({"nominal": {"success": True}}))    # an earlier splattwin's: no digest
    _robot(_ctx(twin))
    assert not any(f.exists() for f in files)
