from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.cli import main
from splattwin.robot.trajectory import Trajectory


def test_plan_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["plan", "--help"])
    assert e.value.code == 0 and "--trials" in capsys.readouterr().out


def test_plan_writes_trajectories_and_results(gt_twin_default: Path, tmp_path: Path):
    out = tmp_path / "robot"
    assert main(["plan", str(gt_twin_default), "--out", str(out), "--no-render"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["nominal"]["success"] and res["nominal"]["collisions"] == 0
    assert [s["success"] for s in res["nominal"]["steps"]] == [True, True, True]
    tj = Trajectory.load_json(out / "trajectory.json")
    tc = Trajectory.load_csv(out / "trajectory.csv")
    ty = Trajectory.load_ros2_yaml(out / "trajectory.ros2.yaml")
    assert tj.joint_names == [f"joint{i}" for i in range(1, 8)]
    for t in (tc, ty):
        np.testing.assert_allclose(t.q, tj.q, atol=1e-6)
        np.testing.assert_allclose(t.t, tj.t, atol=1e-6)
    assert tj.duration > 5.0 and np.all(np.diff(tj.t) > 0)
    assert (out / "segments" / "step1_transit.json").is_file()
    assert res["notes"] == ["rendering disabled (--no-render)"]


def test_plan_missing_object_is_input_error(gt_twin_small: Path, tmp_path: Path, capsys):
    task = tmp_path / "t.yaml"
    task.write_text("- pick: purple_unicorn\n- place_on: blue_box\n")
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(tmp_path / "o"), "--no-render"]) == 2
    err = capsys.readouterr().err
    assert "purple_unicorn" in err and str(task) in err
    assert not (tmp_path / "o" / "results.json").exists()     # refused before planning anything


def test_plan_bad_options(gt_twin_small: Path, tmp_path: Path):
    assert main(["plan", str(gt_twin_small), "--base-pose", "1,2", "--out", str(tmp_path)]) == 2
    assert main(["plan", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
