from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from splattwin.robot.trials import (TrialSpec, YAW_LEVER, default_sigma_yaw, load_finished, perturb_poses, rollout_path,
                                    run_trials, trial_key, wilson_interval)


def test_wilson_interval_reference_values():
    # reference values of the Wilson score interval (z = 1.96)
    lo, hi = wilson_interval(20, 20)
    assert lo == pytest.approx(0.8389, abs=1e-3) and hi == 1.0
    lo, hi = wilson_interval(9, 10)
    assert lo == pytest.approx(0.5958, abs=1e-3) and hi == pytest.approx(0.9821, abs=1e-3)
    lo, hi = wilson_interval(0, 5)
    assert lo == 0.0 and hi == pytest.approx(0.4345, abs=1e-3)


def test_perturbation_statistics():
    """sigma is the per-axis standard deviation of x and y; yaw has sigma_yaw (default sigma / YAW_LEVER)."""
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.025]
    rng = np.random.default_rng(0)
    sigma = 0.005
    samples = [perturb_poses({"o": T}, sigma, rng)["o"] for _ in range(4000)]
    dxy = np.array([s[:2, 3] - T[:2, 3] for s in samples])
    yaw = np.array([math.atan2(s[1, 0], s[0, 0]) for s in samples])
    np.testing.assert_allclose(dxy.std(axis=0), [sigma, sigma], rtol=0.05)                     # per axis
    assert abs(np.corrcoef(dxy.T)[0, 1]) < 0.05 and np.all(np.abs(dxy.mean(axis=0)) < 3 * sigma / 60)
    assert np.std(yaw) == pytest.approx(default_sigma_yaw(sigma), rel=0.05)
    assert default_sigma_yaw(sigma) == pytest.approx(sigma / YAW_LEVER)
    assert all(s[2, 3] == T[2, 3] and abs(s[2, 2] - 1) < 1e-12 for s in samples)               # still on the table
    yaw2 = [math.atan2(s[1, 0], s[0, 0]) for s in (perturb_poses({"o": T}, sigma, rng, sigma_yaw=0.2)["o"]
                                                   for _ in range(2000))]
    assert np.std(yaw2) == pytest.approx(0.2, rel=0.06)


@pytest.mark.slow
def test_trials_in_process_pool_resume_after_kill(gt_twin_default: Path, tmp_path: Path):
    """Each finished trial is written atomically to trials/<i>.json; a re-run with the same seed, sigma
    and N reuses them and runs only the missing ones (as after a killed run)."""
    spec = TrialSpec(str(gt_twin_default), None)
    summary = run_trials(spec, n=2, sigma=0.005, workers=2, progress=False, out_dir=tmp_path)
    assert summary["trials"] == 2 and summary["workers"] == 2 and summary["resumed"] == 0
    assert summary["successes"] == 2, [r.get("error") or [s["failure"] for s in r["steps"]] for r in summary["results"]]
    assert summary["collisions"] == 0
    assert summary["ci95"][0] == pytest.approx(wilson_interval(2, 2)[0])
    assert {r["seed"] for r in summary["results"]} == {1, 2}
    assert summary["sigma"] == 0.005 and "per-axis" in summary["sigma_definition"]
    files = [tmp_path / "trials" / f"{i}.json" for i in (1, 2)]
    assert all(f.is_file() for f in files)
    stored = json.loads(files[0].read_text())
    assert stored["key"]["seed"] == 1 and stored["key"]["sigma"] == 0.005
    mtime = files[0].stat().st_mtime_ns
    mtimes = [f.stat().st_mtime_ns for f in files]
    again = run_trials(spec, n=2, sigma=0.005, workers=2, progress=False, out_dir=tmp_path)
    assert again["resumed"] == 2 and [f.stat().st_mtime_ns for f in files] == mtimes   # nothing re-run
    assert [r["success"] for r in again["results"]] == [r["success"] for r in summary["results"]]
    files[1].unlink()                          # trial 2 "killed" before it finished
    third = run_trials(spec, n=2, sigma=0.005, workers=2, progress=False, out_dir=tmp_path)
    assert third["resumed"] == 1 and third["successes"] == 2 and files[1].is_file()
    assert files[0].stat().st_mtime_ns == mtime
    # another sigma, seed or twin is another trial: a stored result is not reused for it
    assert load_finished(files[0], replace(spec, sigma=0.005, seed=1)) is not None
    assert load_finished(files[0], replace(spec, sigma=0.004, seed=1)) is None
    assert load_finished(files[0], replace(spec, sigma=0.005, seed=2)) is None
    assert load_finished(files[0], replace(spec, sigma=0.005, seed=1, sigma_yaw=0.1)) is None
    # a rebuilt twin (same folder, other twin.json) invalidates the stored trials
    other = tmp_path / "other_twin"
    other.mkdir()
    (other / "twin.json").write_text((gt_twin_default / "twin.json").read_text() + " ")
    moved = {**stored, "key": {**stored["key"], "twin": str(other.resolve())}}
    (tmp_path / "moved.json").write_text(json.dumps(moved))
    assert load_finished(tmp_path / "moved.json", replace(spec, twin_dir=str(other), sigma=0.005, seed=1)) is None


def test_resume_with_rollouts_needs_the_results_own_rollout(gt_twin_small: Path, tmp_path: Path):
    """A rollout file beside a result that does not name it is another run's: not a finished recorded trial."""
    spec = TrialSpec(str(gt_twin_small), None, sigma=0.005, seed=1)
    p = tmp_path / "1.json"
    d = {"success": True, "collisions": 0, "steps": [], "key": trial_key(spec)}
    p.write_text(json.dumps(d))
    rollout_path(p).write_bytes(b"an earlier run's rollout")
    assert load_finished(p, spec) is not None
    assert load_finished(p, spec, rollouts=True) is None
    p.write_text(json.dumps({**d, "rollout": rollout_path(p).name}))
    assert load_finished(p, spec, rollouts=True) is not None


def test_a_stored_trial_is_not_reused_after_its_meshes_or_the_code_change(gt_twin_small: Path, tmp_path: Path,
                                                                           monkeypatch):
    """The key covered twin.json only: a twin whose collision meshes were rebuilt with the same twin.json,
    or an upgraded splattwin, reused the old outcomes (`build` re-ran the robot stage, the trials did not)."""
    import shutil

    from splattwin import hashing
    from splattwin.twin.manifest import Manifest

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    spec = TrialSpec(str(twin), None, sigma=0.005, seed=1)
    p = tmp_path / "1.json"
    p.write_text(json.dumps({"success": True, "collisions": 0, "steps": [], "key": trial_key(spec)}))
    assert load_finished(p, spec) is not None
    monkeypatch.setattr(hashing, "code_digest", lambda *a, **k: "another version")
    assert load_finished(p, spec) is None
    monkeypatch.undo()
    assert load_finished(p, spec) is not None
    m = Manifest.load(twin)
    mesh = twin / next(o.collision_mesh for o in m.objects if o.collision_mesh)
    mesh.write_bytes(mesh.read_bytes() + b"\n")
    assert load_finished(p, spec) is None


@pytest.mark.parametrize("field,value", [("success", "no"), ("collisions", "x"), ("plan_ms", ["a", "b"]),
                                         ("plan_ms", [float("nan")]), ("trial_wall_s", "slow"), ("collisions", True)])
def test_resume_ignores_a_wrongly_typed_stored_result_with_a_warning(tmp_path: Path, capsys, caplog, field, value):
    """A stored result with the right key but wrong types is re-run (with a warning naming it), not summed
    ("success": "no" counted as a success; "collisions": "x" crashed the summary). The warning goes through
    the package's logger, not printed to stderr (audit 10A L6)."""
    import logging

    (tmp_path / "twin").mkdir()
    (tmp_path / "twin" / "twin.json").write_text("{}")
    spec = TrialSpec(str(tmp_path / "twin"), None, sigma=0.005, seed=1)
    good = {"success": False, "collisions": 0, "plan_ms": [12.5], "steps": [], "trial_wall_s": 1.0,
            "key": trial_key(spec)}
    p = tmp_path / "1.json"
    p.write_text(json.dumps(good))
    assert load_finished(p, spec) is not None and capsys.readouterr().err == ""
    p.write_text(json.dumps({**good, field: value}))
    with caplog.at_level(logging.WARNING, logger="splattwin.robot.trials"):
        assert load_finished(p, spec) is None
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("1.json" in m and field in m for m in warned), warned
    assert capsys.readouterr().err == ""


def test_a_twin_posed_by_the_robot_puts_the_arm_at_its_base(gt_twin_small: Path, tmp_path: Path):
    """--robot-poses twins are in the robot base frame: the arm stands at its origin, not 0.5 m behind the table
    centre, where the default put it (0.5 m from the real base: plans for the wrong robot, or reach errors)."""
    import shutil

    from splattwin.robot.options import RobotOptions
    from splattwin.robot.world import BasePose
    from splattwin.poses.twin_frame import TwinFrame

    assert TrialSpec.from_options(gt_twin_small, RobotOptions()).base == BasePose()      # a table frame: beside it
    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    d = json.loads((twin / "twin.json").read_text())
    d["frame"].update(source="robot", scaled=True, T_twin_input=np.eye(4).tolist())
    (twin / "twin.json").write_text(json.dumps(d))
    assert TrialSpec.from_options(twin, RobotOptions()).base == BasePose(0.0, 0.0, 0.0, 0.0)
    assert TrialSpec.from_options(twin, RobotOptions(base_pose="0.1,0,0,0")).base == BasePose(0.1, 0.0, 0.0, 0.0)
    # in Python as with `splattwin plan`: TrialSpec(twin, task) and build_world(twin) put the arm there too (they
    # put it beside the table, 0.5 m from where plan put it, api13 E1); an explicit base is kept
    from splattwin.robot.world import build_world

    assert TrialSpec(str(twin), None).base == BasePose(0.0, 0.0, 0.0, 0.0)
    assert TrialSpec(str(gt_twin_small), None).base == BasePose()
    assert TrialSpec(str(twin), None, base=BasePose(0.1)).base == BasePose(0.1)
    assert build_world(twin, visual=False).base == BasePose(0.0, 0.0, 0.0, 0.0)
    # the frame's own move of the robot frame (a yaw and a shift) carries the base with it; sfm+robot: origin
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [0.2, -0.1, 0.0]
    b, _ = BasePose.default_for(TwinFrame(source="robot", scaled=True, T_twin_input=T.tolist()))
    assert (b.x, b.y, b.z) == pytest.approx((0.2, -0.1, 0.0)) and b.yaw == pytest.approx(math.pi / 2)
    S = 3.0 * np.eye(4)
    S[3, 3] = 1.0
    S[:3, 3] = [5, 5, 5]
    assert BasePose.default_for(TwinFrame(source="sfm+robot", scaled=True, T_twin_input=S.tolist()))[0] == \
        BasePose(0.0, 0.0, 0.0, 0.0)
    tilted = np.eye(4)
    tilted[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    b, why = BasePose.default_for(TwinFrame(source="robot", scaled=True, T_twin_input=tilted.tolist()))
    assert b == BasePose() and "--base-pose" in why


def test_run_once_refuses_a_twin_path_for_its_spec(tmp_path: Path):
    """run_once("TWIN") failed with "'str' object has no attribute 'twin_dir'" (audit 10A L19)."""
    from splattwin.robot.trials import run_once

    with pytest.raises(TypeError, match=r"^spec must be a TrialSpec .*TrialSpec\(twin_dir.*, got str$"):
        run_once(str(tmp_path))


def test_a_task_warning_is_said_by_the_nominal_run_not_by_every_trial(gt_twin_small: Path, tmp_path: Path, caplog):
    """A goal that may be crowded was warned about once per run: `plan --trials 3` printed it 4 times."""
    import logging

    from splattwin.robot.trials import run_once, run_trial_job

    task = tmp_path / "t.yaml"
    task.write_text("- pick: blue_box\n- place_in: {center: [0.0, 0.3], size: 0.12}\n")   # reaches over the hammer
    spec = TrialSpec(str(gt_twin_small), str(task), sigma=0.005, seed=1)
    with caplog.at_level(logging.WARNING, logger="splattwin.robot.task"):
        run_trial_job(spec, None)
        assert not [r for r in caplog.records if "may collide" in r.getMessage()]
        run_once(TrialSpec(str(gt_twin_small), str(task)))
    said = [r.getMessage() for r in caplog.records if "may collide" in r.getMessage()]
    assert len(said) == 1 and "'toy_hammer'" in said[0]


def test_run_once_takes_a_task_as_plain_data(gt_twin_small: Path):
    """A notebook's goal needed a task YAML written to a file: run_once read spec.task_path only, and parse_task
    wanted a path to name in errors (api13 E2). run_once(spec, task=[...]) takes the steps as data (or a Task),
    checked as a file's are, the errors naming the step."""
    from splattwin.errors import InputError
    from splattwin.robot.task import parse_task
    from splattwin.robot.trials import run_once

    spec = TrialSpec(str(gt_twin_small), None)
    with pytest.raises(InputError, match=r"step 1: goal region centre \[3.0, 3.0, 0.0\] is off the table"):
        run_once(spec, task=[{"pick": "blue_box", "place_in": {"center": [3.0, 3.0], "size": 0.1}}])
    goal = [{"pick": "blue_box", "place_in": {"center": [0.15, -0.05], "size": 0.15}}]
    for task in (goal, parse_task(goal)):
        result, _, _ = run_once(spec, task=task)
        assert result.success, result.steps
        assert result.task_steps == [{"index": 1, "pick": "blue_box", "goal": "region", "place": "in",
                                      "region": {"center": [0.15, -0.05, 0.0], "size": [0.15, 0.15]}}]
