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
    out = " ".join(capsys.readouterr().out.split())
    assert e.value.code == 0 and "--trials" in out and "per-axis standard deviation" in out and "--sigma-yaw" in out


@pytest.mark.slow
def test_plan_writes_trajectories_and_results(gt_twin_default: Path, tmp_path: Path):
    """`splattwin plan TWIN` writes results, trajectories, the rollout and the viewer's playback track into
    TWIN/robot, so `splattwin view TWIN` then shows the robot."""
    import shutil

    from splattwin.robot.rollout import Rollout
    from splattwin.playback.view_model import load_robot_track

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_default, twin)
    out = twin / "robot"
    assert main(["plan", str(twin), "--no-render"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["nominal"]["success"] and res["nominal"]["collisions"] == 0
    assert [s["success"] for s in res["nominal"]["steps"]] == [True, True, True]
    assert res["options"]["render"] is False and res["options"]["trials"] == 0   # what made these results
    from splattwin.robot.outputs import results_twin

    assert results_twin(res, twin) is None              # made on this twin, as it is (its digest recorded)
    tj = Trajectory.load_json(out / "trajectory.json")
    tc = Trajectory.load_csv(out / "trajectory.csv")
    ty = Trajectory.load_ros2_yaml(out / "trajectory.ros2.yaml")
    ty = Trajectory.load_ros2_yaml(out / "trajectory.goal.ros2.yaml", gripper_path=out / "gripper.ros2.yaml")
    # the real Panda's joint names by default (franka_ros, panda_moveit_config); the simulation's are mapped
    assert tj.joint_names == [f"panda_joint{i}" for i in range(1, 8)] == tc.joint_names == ty.joint_names
    assert tj.meta["joint_map"] == {f"panda_joint{i}": f"joint{i}" for i in range(1, 8)}
    assert tj.meta["base_pose"]["translation"] == [-0.5, 0.0, 0.0] and tj.meta["base_frame"] == "panda_link0"
    assert len(tj.gripper) == 7 and [g.command for g in ty.gripper] == [g.command for g in tj.gripper]
    assert (out / "base_transform.yaml").is_file() and (out / "moveit" / "collision_objects.yaml").is_file()
    for t in (tc, ty):
        np.testing.assert_allclose(t.q, tj.q, atol=1e-6)
        np.testing.assert_allclose(t.t, tj.t, atol=1e-6)
    assert tj.duration > 5.0 and np.all(np.diff(tj.t) > 0)
    assert (out / "segments" / "step1_transit.json").is_file()
    assert res["notes"] == ["rendering disabled (--no-render)"]
    ro = Rollout.load(out / "rollout.npz")
    assert ro.steps() == [1, 2, 3] and ro.t[-1] == pytest.approx(res["nominal"]["sim_time"])
    assert ro.joint_names == list(tj.meta["joint_map"].values())
    assert tj.duration == pytest.approx(ro.t[-1])          # the exported timeline is the executed one
    # the servos' tracking error is reported; with the velocity feed-forward it is millimetres at the TCP
    assert res["tracking"]["tcp_max_m"] < 0.01 and res["tracking"]["joint_max_rad"] < 0.01
    track = load_robot_track(twin)
    assert track is not None and len(track) > 100 and set(track.object_poses) == set(ro.object_poses)
    assert track.times[0] >= ro.t[0] and track.times[-1] == pytest.approx(ro.t[-1])


def test_plan_missing_object_is_input_error(gt_twin_small: Path, tmp_path: Path, capsys):
    task = tmp_path / "t.yaml"
    task.write_text("- pick: purple_unicorn\n- place_on: blue_box\n")
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(tmp_path / "o"), "--no-render"]) == 2
    err = capsys.readouterr().err
    assert "purple_unicorn" in err and str(task) in err
    assert not (tmp_path / "o" / "results.json").exists()     # refused before planning anything


def test_plan_unreachable_goal_is_input_error_before_planning(gt_twin_small: Path, tmp_path: Path, capsys):
    task = tmp_path / "far.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.28, 0.0, 0.0], size: 0.1}\n")
    rc = main(["plan", str(gt_twin_small), "--task", str(task), "--base-pose=-0.5,0,-0.3,0",
               "--out", str(tmp_path / "o"), "--no-render"])
    err = capsys.readouterr().err
    assert rc == 2 and "step 1: goal region" in err and "no IK solution" in err and str(task) in err
    assert not (tmp_path / "o" / "results.json").exists()


def test_plan_bad_options(gt_twin_small: Path, tmp_path: Path):
    assert main(["plan", str(gt_twin_small), "--base-pose", "1,2", "--out", str(tmp_path)]) == 2
    assert main(["plan", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2


def test_plan_custom_joint_names_with_a_named_base_frame(gt_twin_small: Path, tmp_path: Path):
    """--joint-names as a list + --base-frame: the base frame is named in base_transform.yaml, the base-frame
    MoveIt scene, the trajectories' meta and results.json; a malformed frame id is refused before planning."""
    import yaml

    task = tmp_path / "one.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05, 0.0], size: 0.1}\n")
    names = ",".join(f"arm_j{i}" for i in range(1, 8))
    out = tmp_path / "o"
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render",
                 "--joint-names", names, "--base-frame", "cell1/arm_base"]) == 0
    tf = yaml.safe_load((out / "base_transform.yaml").read_text())
    assert tf["header"]["frame_id"] == "twin" and tf["child_frame_id"] == "cell1/arm_base"
    assert "--child-frame-id cell1/arm_base" in (out / "base_transform.yaml").read_text()
    msgs = yaml.safe_load((out / "moveit" / "collision_objects.yaml").read_text())
    assert msgs and {m["header"]["frame_id"] for m in msgs} == {"cell1/arm_base"}
    tj = Trajectory.load_json(out / "trajectory.json")
    assert tj.joint_names == names.split(",") and tj.meta["base_frame"] == "cell1/arm_base"
    res = json.loads((out / "results.json").read_text())
    assert res["base_frame"] == "cell1/arm_base" and res["options"]["base_frame"] == "cell1/arm_base"
    for bad in ("/cell1/arm_base", "arm base"):
        assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(tmp_path / "o2"), "--no-render",
                     "--joint-names", names, "--base-frame", bad]) == 2
    assert not (tmp_path / "o2").exists()


def _renamed_panda(tmp_path: Path) -> Path:
    """The Menagerie Panda MJCF with every body, joint, site, tendon and actuator renamed (prefix 'arm_'),
    meshes referenced from the original folder: a user arm that only works through the robot options."""
    import re

    from splattwin.robot.assets import panda_model_path

    src = panda_model_path()
    xml = src.read_text()
    xml = re.sub(r'(<(?:body|joint|site|general|position|fixed)\b[^>]*?\bname=")([^"]+)"', r'\1arm_\2"', xml)
    xml = re.sub(r'\b(joint|joint1|joint2|tendon)="([^"]+)"', r'\1="arm_\2"', xml)
    xml = xml.replace('meshdir="assets"', f'meshdir="{src.parent / "assets"}"')
    assert 'name="tcp"' not in xml and 'name="arm_tcp"' in xml and 'name="hand"' not in xml
    out = tmp_path / "my_arm.xml"
    out.write_text(xml)
    return out


@pytest.mark.slow
def test_user_robot_mjcf_runs_a_pick_and_place(gt_twin_default: Path, tmp_path: Path):
    """A user-supplied arm MJCF (the Panda with renamed bodies/joints/site, TCP site 'arm_tcp') on another
    base pose runs one pick-and-place step through the CLI: grasped, placed, no collisions."""
    arm = _renamed_panda(tmp_path)
    task = tmp_path / "one_step.yaml"
    task.write_text("- pick: blue_box\n- place_on: cardboard_box\n")
    out = tmp_path / "robot"
    rc = main(["plan", str(gt_twin_default), "--task", str(task), "--robot-mjcf", str(arm), "--tcp-site", "arm_tcp",
               "--base-pose=-0.55,0.02,0,0.05", "--out", str(out), "--no-render"])
    res = json.loads((out / "results.json").read_text())
    step = res["nominal"]["steps"][0]
    assert rc == 0, step["failure"]
    assert step["success"] and step["grasped"] and step["placed"] and res["nominal"]["collisions"] == 0
    assert res["robot_mjcf"] == str(arm) and res["base_pose"]["x"] == -0.55
    tj = Trajectory.load_json(out / "trajectory.json")
    assert tj.joint_names == [f"arm_joint{i}" for i in range(1, 8)]
    from splattwin.robot.rollout import Rollout

    ro = Rollout.load(out / "rollout.npz")           # recorded with the user's joint names
    assert ro.joint_names == tj.joint_names and (out / "playback.npz").is_file()
    # a wrong TCP site name is bad input
    assert main(["plan", str(gt_twin_default), "--task", str(task), "--robot-mjcf", str(arm),
                 "--out", str(tmp_path / "o2"), "--no-render"]) == 2


def test_plan_keeps_only_this_runs_outputs(gt_twin_small: Path, tmp_path: Path, capsys):
    """A run replaces the earlier run's outputs: none of its per-step files, frames or extra trials stay
    beside the new ones; files of other names, and what a link points to, are left alone; a bad task
    leaves the earlier outputs as they were."""
    from splattwin.robot.options import RobotOptions
    from splattwin.robot.stage import RobotInputs, run

    out = tmp_path / "o"
    stale = [out / "segments" / "step2_transit.json", out / "segments" / "step1_approach_retry1.json",
             out / "frames" / "frame_005_step3_grasp.png", out / "frames" / "overview.png",
             out / "trials" / "4.json", out / "trials" / "4.rollout.npz",
             out / "trials" / "1.rollout.npz",        # trial 1 re-runs without recording: not its rollout
             out / "trials" / "1.json"]               # (another key: re-run)
    kept = [out / "segments" / "notes.txt", out / "trials" / "README.md", out / "keep" / "step5_lift.json",
            out / "keep" / "frame_001_start.png"]
    for p in stale + kept:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("{}")
    link = out / "segments" / "step7_lift.json"
    link.symlink_to(out / "keep" / "step5_lift.json")
    (out / "frames" / "sub").symlink_to(out / "keep", target_is_directory=True)
    task = tmp_path / "one.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05, 0.0], size: 0.1}\n")
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render",
                 "--trials", "1"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert len(res["nominal"]["steps"]) == 1 and res["trials"]["trials"] == 1
    assert [p for p in stale if p.exists()] == [out / "trials" / "1.json"]
    assert json.loads((out / "trials" / "1.json").read_text())["seed"] == 1      # rewritten by this run
    assert all(p.is_file() for p in kept) and not link.is_symlink() and (out / "frames" / "sub").is_symlink()
    segs = sorted(p.name for p in (out / "segments").iterdir())
    assert segs and all(n.startswith("step1_") for n in segs if n != "notes.txt")
    # a task refused before planning leaves the finished run's outputs as they were
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    bad = tmp_path / "bad.yaml"
    bad.write_text("- pick: purple_unicorn\n- place_on: blue_box\n")
    assert main(["plan", str(gt_twin_small), "--task", str(bad), "--out", str(out), "--no-render"]) == 2
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # the pipeline records the error instead: its results.json stands alone
    r = run(RobotInputs(gt_twin_small, out), RobotOptions(task=str(bad), render=False), progress=False,
            record_errors=True)
    assert r.error and "purple_unicorn" in json.loads(r.results.read_text())["error"]
    assert not list((out / "segments").glob("step*")) and not list((out / "trials").glob("*.json"))
    assert not (out / "trajectory.json").exists() and not (out / "rollout.npz").exists()
    capsys.readouterr()


def test_plan_count_options_are_bounded(gt_twin_small: Path, tmp_path: Path, capsys):
    """--trials 10**12 grew memory without bound: counts beyond the documented limits are bad input."""
    from splattwin.cluster.options import SweepOptions
    from splattwin.errors import InputError
    from splattwin.executor import MAX_RETRIES, MAX_WORKERS
    from splattwin.robot.options import MAX_TRIALS, RobotOptions

    out = tmp_path / "o"
    for flag, n in (("--trials", 10 ** 12), ("--trials", MAX_TRIALS + 1), ("--cluster.workers", MAX_WORKERS + 1),
                    ("--cluster.max-retries", MAX_RETRIES + 1)):
        assert main(["plan", str(gt_twin_small), flag, str(n), "--out", str(out), "--no-render"]) == 2
        assert f"{flag.removeprefix('--cluster.')}" in capsys.readouterr().err
    assert not out.exists()
    RobotOptions(trials=MAX_TRIALS).validate()
    with pytest.raises(InputError, match="--trials"):
        SweepOptions(trials=MAX_TRIALS + 1).validate()


def test_plan_planner_typo_is_refused_before_the_previous_run_is_removed(gt_twin_small: Path, tmp_path: Path,
                                                                        capsys):
    """`--planner RRTconnect` (a typo) removed the previous run's files, then stopped with an internal error
    (ValueError from the planner, exit 1): the planner is now one of the option's choices, refused at once."""
    out = tmp_path / "robot"
    out.mkdir()
    (out / "results.json").write_text("{}")   # the previous run's
    with pytest.raises(SystemExit) as e:
        main(["plan", str(gt_twin_small), "--planner", "RRTconnect", "--out", str(out), "--no-render"])
    assert e.value.code == 2
    assert "invalid choice: 'RRTconnect'" in capsys.readouterr().err
    assert (out / "results.json").read_text() == "{}"


def test_plan_trials_on_an_unreachable_cluster_are_refused_before_the_run(gt_twin_small: Path, tmp_path: Path,
                                                                         capsys):
    """--trials on a Ray address nobody answers at: refused before the nominal run. Before, the nominal run
    removed the previous run's files and the trials' executor failed only after it."""
    import socket

    out = tmp_path / "robot"
    out.mkdir()
    (out / "results.json").write_text("{}")   # the previous run's
    with socket.socket() as s:   # a port nobody listens on, held bound (refusing) so that nobody takes it meanwhile
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        assert main(["plan", str(gt_twin_small), "--trials", "2", "--cluster.ray-address", f"127.0.0.1:{port}",
                     "--out", str(out), "--no-render"]) == 2
    assert f"no Ray cluster answers at '127.0.0.1:{port}'" in capsys.readouterr().err
    assert (out / "results.json").read_text() == "{}"


@pytest.mark.slow
def test_plan_failing_after_the_grasp_writes_nothing_for_the_real_arm(gt_twin_small: Path, tmp_path: Path,
                                                                      monkeypatch, capsys):
    """A successful run writes the real-arm files (timeline, gripper goals, program) and records the
    simulation's deviations from Menagerie; a run failing after the grasp (the hand closed on the object in
    the air) removes them and writes none: its attempted segments stay, results.json and the output say why."""
    from splattwin.robot.outputs import REAL_ROBOT_FILES

    out = tmp_path / "o"
    task = tmp_path / "one.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05, 0.0], size: 0.1}\n")
    args = ["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render"]
    assert main(args) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["real_robot"]["written"] and all((out / n).is_file() for n in REAL_ROBOT_FILES)
    assert res["robot"]["simulation_deviations"]["gripper_servo"]["model_stiffness_N_per_m"] == 100.0
    assert list((out / "program").glob("*_gripper_grasp.goal.ros2.yaml"))
    capsys.readouterr()
    monkeypatch.setattr("splattwin.robot.judge.judge_grasp", lambda *a, **k: False)
    assert main(args) == 1
    res = json.loads((out / "results.json").read_text())
    assert not res["nominal"]["success"] and not res["real_robot"]["written"]
    assert "not lifted" in res["real_robot"]["reason"] and res["real_robot"]["reason"] in res["notes"][0]
    assert not any((out / n).exists() for n in REAL_ROBOT_FILES) and not list((out / "program").iterdir())
    assert (out / "segments" / "step1_close.json").is_file() and (out / "segments" / "step1_lift.json").is_file()
    assert "no trajectory for the real arm" in " ".join(capsys.readouterr().out.split())


@pytest.mark.slow
def test_plan_fr3_outside_the_fr3_limits_exits_2(gt_twin_small: Path, tmp_path: Path, monkeypatch, capsys):
    """With --joint-names fr3 the exported trajectory is checked against the FR3's limits: outside them
    (here joint 1 held to +-0.1 mrad) the plan runs, results.json records which joint left them when, no
    real-robot file is written and `plan` exits 2 saying so, once."""
    from splattwin.robot import export
    from splattwin.robot.outputs import REAL_ROBOT_FILES

    tight = dict(export.FR3_LIMITS, q_min=(-1e-4,) + export.FR3_LIMITS["q_min"][1:],
                 q_max=(1e-4,) + export.FR3_LIMITS["q_max"][1:])
    monkeypatch.setitem(export.NAMED_LIMITS, "fr3", tight)
    out = tmp_path / "o"
    task = tmp_path / "one.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05, 0.0], size: 0.1}\n")
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render",
                 "--joint-names", "fr3"]) == 2
    cap = capsys.readouterr()
    err, said = " ".join(cap.err.split()), " ".join((cap.out + cap.err).split())
    # the refusal is on stderr, its reason said once (the summary), not three times
    assert "no files for the real arm" in err and said.count("fr3_joint1 at t = 0.010 s") == 1
    res = json.loads((out / "results.json").read_text())
    assert res["nominal"]["success"] and not res["real_robot"]["written"]
    assert res["real_robot"]["limit_violations"][0].startswith("fr3_joint1 at t = ")
    assert not any((out / n).exists() for n in REAL_ROBOT_FILES)
    assert json.loads((out / "segments" / "step1_transit.json").read_text())["joint_names"][0] == "fr3_joint1"


def _floating_twin(gt_twin: Path, dest: Path, lift: float = 0.05) -> Path:
    """A copy of a ground-truth twin whose cardboard box hovers `lift` m above the table (as a twin whose
    mesh ends above its support: physics drops it when the simulation starts)."""
    import shutil

    shutil.copytree(gt_twin, dest)
    doc = json.loads((dest / "twin.json").read_text())
    box = next(o for o in doc["objects"] if o["name"] == "cardboard_box")
    box["T_world_obj"][2][3] += lift
    (dest / "twin.json").write_text(json.dumps(doc))
    return dest


def test_settle_check_measures_what_physics_moves_before_the_robot_acts(gt_twin_small: Path, tmp_path: Path):
    """The start check steps physics with the arm held and restores the state: nothing moves on the
    ground-truth twin; a box 5 cm up falls 5 cm and is named."""
    from splattwin.robot.execute import unsettled
    from splattwin.robot.world import build_world

    w = build_world(gt_twin_small, visual=False)
    q0, t0 = w.qpos(), w.time
    s = w.settle_check()
    assert s["moved"] == [] and unsettled(s) is None
    assert max(v["moved_m"] for v in s["objects"].values()) < 1e-3
    assert (w.qpos() == q0).all() and w.time == t0
    w = build_world(_floating_twin(gt_twin_small, tmp_path / "float"), visual=False)
    s = w.settle_check()
    assert s["moved"] == ["cardboard_box"] and s["objects"]["cardboard_box"]["dz_m"] == pytest.approx(-0.05, abs=0.005)
    assert "cardboard_box moved 5.0 cm (fell)" in unsettled(s)
    # audit 8c L2: a twin posed by the robot may owe it to its poses or hand-eye calibration; say so, briefly
    assert s["frame_source"] != "robot" and "hand-eye" not in unsettled(s)
    for source in ("robot", "sfm+robot"):
        msg = unsettled({**s, "frame_source": source})
        assert "floating or sunken" in msg and "robot poses or hand-eye calibration" in msg


@pytest.mark.slow
def test_plan_on_a_floating_object_writes_nothing_for_the_real_arm(gt_twin_small: Path, tmp_path: Path, capsys):
    """A twin object that physics moves before the robot acts (5 cm above the table: it falls) makes the run
    no validation of the twin, even when the task succeeds on the lowered scene: results.json says which
    object moved how far, no real-arm file is written, the summary says so once and `plan` exits 2."""
    from splattwin.robot.outputs import REAL_ROBOT_FILES

    twin = _floating_twin(gt_twin_small, tmp_path / "float")
    out = tmp_path / "o"
    task = tmp_path / "one.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05, 0.0], size: 0.1}\n")
    assert main(["plan", str(twin), "--task", str(task), "--out", str(out), "--no-render"]) == 2
    cap = capsys.readouterr()
    said = " ".join((cap.out + cap.err).split())
    res = json.loads((out / "results.json").read_text())
    assert res["nominal"]["success"] and not res["validated"] and not res["real_robot"]["written"]
    assert res["settle"]["moved"] == ["cardboard_box"]
    assert res["real_robot"]["not_at_rest"]["cardboard_box"]["moved_m"] == pytest.approx(0.05, abs=0.005)
    assert "cardboard_box moved 5.0 cm" in res["real_robot"]["reason"]
    assert not any((out / n).exists() for n in REAL_ROBOT_FILES)
    assert "NOT a validation of the twin" in said and said.count("cardboard_box moved 5.0 cm") == 1


@pytest.mark.slow
def test_plan_refreshes_the_twins_report(gt_twin_small: Path, tmp_path: Path, capsys):
    """audit 7B D13: after `plan` the report still showed the build's robot run (a FAILURE of the default
    task) until `splattwin report` was run by hand. A twin with a report gets it re-written by plan."""
    import shutil

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    assert main(["report", str(twin), "--no-video"]) == 0
    page = twin / "report" / "index.html"
    assert "no robot task run" in page.read_text()
    task = tmp_path / "one_step.yaml"
    task.write_text("- pick: yellow_cube\n- place_on: blue_box\n")
    capsys.readouterr()
    assert main(["plan", str(twin), "--task", str(task), "--no-render"]) == 0
    assert f"report: {page} (refreshed" in " ".join(capsys.readouterr().out.split())
    html = page.read_text()
    assert "no robot task run" not in html and "overall: SUCCESS" in html and "one_step.yaml" in html
    # --no-report leaves it as it is (the default task's three steps are not in it)
    before = page.read_bytes()
    assert main(["plan", str(twin), "--no-render", "--no-report"]) == 0
    assert page.read_bytes() == before


@pytest.mark.slow
def test_plan_records_its_seconds_for_the_reports_timings(gt_twin_small: Path, tmp_path: Path):
    """After `plan` refreshed the report, its timings table still gave the robot row the build's robot
    stage seconds (pipeline.json) beside the plan's results. The plan's seconds and memory are now recorded
    in pipeline.json's robot record, and the table shows them; the other stages keep the build's figures."""
    import re
    import shutil

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    build = {"poses": {"key": "k1", "outputs": {}, "seconds": 12.5, "peak_rss_gib": 1.25},
             "twin": {"key": "k2", "outputs": {}, "seconds": 4.0, "peak_rss_gib": 2.0},
             "robot": {"key": "k3", "outputs": {}, "seconds": 777.0, "peak_rss_gib": 3.5}}
    (twin / "pipeline.json").write_text(json.dumps(build))
    assert main(["report", str(twin), "--no-video"]) == 0

    def rows() -> dict:
        html = (twin / "report" / "index.html").read_text()
        return {m[0]: (m[1], m[2]) for m in
                re.findall(r"<tr><td>(poses|robot)</td><td>([^<]*)</td><td>([^<]*)</td>", html)}

    assert rows() == {"poses": ("12.5", "1.25"), "robot": ("777", "3.5")}
    task = tmp_path / "one_step.yaml"
    task.write_text("- pick: yellow_cube\n- place_on: blue_box\n")
    assert main(["plan", str(twin), "--task", str(task), "--no-render"]) == 0
    state = json.loads((twin / "pipeline.json").read_text())
    plan = state["robot"]["plan"]
    assert 0 < plan["seconds"] < 777 and plan["peak_rss_gib"] > 0
    assert state["poses"] == build["poses"] and state["robot"]["seconds"] == 777.0   # the build's, kept
    got = rows()
    assert got["poses"] == ("12.5", "1.25")
    assert got["robot"] == (f"{plan['seconds']:.4g}", f"{plan['peak_rss_gib']:.4g}")
    html = (twin / "report" / "index.html").read_text()
    assert "robot stage took 777.0 s" in html
    # recorded with --no-report too: a later `splattwin report` shows the newest plan's seconds
    assert main(["plan", str(twin), "--task", str(task), "--no-render", "--no-report"]) == 0
    again = json.loads((twin / "pipeline.json").read_text())["robot"]["plan"]
    assert again["finished"] > plan["finished"]
    assert main(["report", str(twin), "--no-video"]) == 0
    assert rows()["robot"][0] == f"{again['seconds']:.4g}"


@pytest.mark.slow
def test_a_failed_run_records_the_tasks_steps_and_the_report_names_those_not_attempted(gt_twin_small: Path,
                                                                                      tmp_path: Path, monkeypatch):
    """The executor stops at the first failed step, and results.json held only the steps that ran: the
    report could not say which of the task's steps were never attempted. `nominal.task_steps` lists them
    all now (here step 1's transit is blocked: steps 2-3 of the default task were not attempted)."""
    import shutil

    from splattwin.report.build import build_report
    from splattwin.robot.planning import PlanningError
    from splattwin.robot.task import load_task
    from splattwin.twin.manifest import Manifest

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)

    def blocked(self, q_start, q_goal, label):
        raise PlanningError("injected: blocked")

    monkeypatch.setattr("splattwin.robot.motion.MotionPlanner.free_path", blocked)
    assert main(["plan", str(twin), "--no-render", "--no-report"]) == 1
    nom = json.loads((twin / "robot" / "results.json").read_text())["nominal"]
    task = load_task(None, Manifest.load(twin))
    assert [s["index"] for s in nom["steps"]] == [1] and not nom["steps"][0]["success"]
    assert [{k: v for k, v in t.items() if k != "region"} for t in nom["task_steps"]] == [
        {"index": k, "pick": s.pick, "goal": s.goal_name, "place": "on" if s.place_on else "in"}
        for k, s in enumerate(task.steps, start=1)]
    assert nom["task_steps"][2]["region"] == {"center": [round(float(v), 6) for v in task.steps[2].place_in.center],
                                              "size": [0.24, 0.24]}
    assert len(nom["task_steps"]) == 3
    import html as htmllib

    page = htmllib.unescape(build_report(twin).read_text())
    robot = page.split("Robot task in physics")[1].split("</section>")[0]
    later = ", ".join(f"{t['pick']} {t['place']} {t['goal']}" for t in nom["task_steps"][1:])
    assert f"the run stopped at the failed step 1 of 3: steps 2-3 ({later}) were not attempted." in robot
    assert robot.count("not attempted</td>") == 2     # their rows in the step table


def test_results_record_the_task_by_content_and_the_criteria(gt_twin_small: Path, tmp_path: Path):
    """results.json named the task file only (a relative path, whatever it holds after an edit) and not the
    thresholds the steps were judged by: now the file's sha256, each region's numbers and the criteria."""
    import hashlib

    task = tmp_path / "mine.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05], size: 0.1}\n")
    out = tmp_path / "o"
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render", "--no-report"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["task_sha256"] == hashlib.sha256(task.read_bytes()).hexdigest()
    assert res["nominal"]["task_steps"] == [{"index": 1, "pick": "yellow_cube", "goal": "region", "place": "in",
                                             "region": {"center": [0.1, -0.05, 0.0], "size": [0.1, 0.1]}}]
    c = res["criteria"]
    assert (c["lift_fraction"], c["lift_m"], c["rest_speed_m_s"], c["tilt_max_deg"], c["height_tol_m"],
            c["settle_s"]) == (0.6, 0.1, 0.01, 10.0, 0.015, 0.6)
    assert "bounding-box footprint inside the region" in c["definition"]
    # the task edited and run again: the record follows the file
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.05, -0.1], size: 0.12}\n")
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render", "--no-report"]) == 0
    res2 = json.loads((out / "results.json").read_text())
    assert res2["task_sha256"] == hashlib.sha256(task.read_bytes()).hexdigest() != res["task_sha256"]
    assert res2["nominal"]["task_steps"][0]["region"] == {"center": [0.05, -0.1, 0.0], "size": [0.12, 0.12]}


def test_plan_says_why_it_exits_1_after_a_successful_nominal_run(gt_twin_small: Path, tmp_path: Path, monkeypatch,
                                                                   capsys):
    """The nominal run succeeded ('overall: success', real-arm files written) but a trial failed: exit 1, and
    now stderr says that this is why and the summary lists the failed trial."""
    from types import SimpleNamespace

    import splattwin.robot.stage as stage

    trials = {"trials": 2, "successes": 1, "ci95": [0.1, 0.9], "sigma": 0.005, "sigma_yaw": 0.05, "collisions": 0,
              "results": [{"success": True, "seed": 1, "steps": []},
                          {"success": False, "seed": 2, "steps": [
                              {"index": 1, "pick": "yellow_cube", "success": False,
                               "failure": "'yellow_cube' not lifted with the gripper"}]}]}
    run = SimpleNamespace(steps=[], success=True, sim_time=1.0, wall_s=1.0, settle=None)
    res = stage.RobotResult(results=tmp_path / "results.json", success=True, details={
        "run": run, "trials": trials, "paths": {"results": tmp_path / "results.json"}, "real_robot": {"written": True}})
    monkeypatch.setattr(stage, "run", lambda *a, **k: res)
    assert main(["plan", str(gt_twin_small), "--out", str(tmp_path / "o"), "--no-render", "--no-report"]) == 1
    out = capsys.readouterr()
    assert "trial 2 (seed 2, trials/2.json) failed at step 1 (yellow_cube): 'yellow_cube' not lifted" in out.out
    assert "exit 1: 1 of 2 perturbed trials failed" in out.err


def test_a_place_blocked_by_a_neighbour_names_it(gt_twin_small: Path, tmp_path: Path):
    """The blue box into a region that reaches over the hammer: the plan failed with rejection counts only
    ('descent collision': 95, ...); now the step's failure names the object crowding the goal."""
    task = tmp_path / "t.yaml"
    task.write_text("- pick: blue_box\n- place_in: {center: [0.0, 0.3], size: 0.12}\n")
    out = tmp_path / "o"
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render", "--no-report"]) == 1
    step = json.loads((out / "results.json").read_text())["nominal"]["steps"][0]
    assert "descent collision" in step["failure"]
    assert "the goal is crowded: 'toy_hammer' 0.3 cm from its centre ('blue_box' reaches 5.0 cm" in step["failure"]


def test_results_name_the_task_file_absolutely(gt_twin_small: Path, tmp_path: Path, monkeypatch):
    """`plan --task tasks/mine.yaml` recorded "tasks/mine.yaml", relative to wherever plan ran."""
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "mine.yaml").write_text("- pick: yellow_cube\n"
                                                  "- place_in: {center: [0.1, -0.05], size: 0.1}\n")
    monkeypatch.chdir(tmp_path)
    assert main(["plan", str(gt_twin_small), "--task", "tasks/mine.yaml", "--out", str(tmp_path / "o"), "--no-render",
                 "--no-report"]) == 0
    res = json.loads((tmp_path / "o" / "results.json").read_text())
    assert res["task"] == str((tmp_path / "tasks" / "mine.yaml").resolve())


def test_an_object_without_any_grasp_says_what_to_check(gt_twin_small: Path, tmp_path: Path, monkeypatch):
    """Before: "no antipodal grasp fits the gripper on 'yellow_cube'" and nothing more (seen on a 300-iteration
    twin of the small scene); now its size, the opening, the fingertip clearance and what to check."""
    monkeypatch.setattr("splattwin.robot.selection.GraspSelector.ranked", lambda self, obj, belief: [])
    task = tmp_path / "t.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05], size: 0.1}\n")
    out = tmp_path / "o"
    assert main(["plan", str(gt_twin_small), "--task", str(task), "--out", str(out), "--no-render", "--no-report"]) == 1
    failure = json.loads((out / "results.json").read_text())["nominal"]["steps"][0]["failure"]
    assert failure.startswith("no antipodal grasp fits the gripper on 'yellow_cube': its collision mesh (2.5 x 2.5 x "
                              "2.5 cm) offers no pair of opposite faces closer than the gripper's 8.0 cm opening")
    assert "check its mesh in the report" in failure


def test_planning_says_too_wide_in_the_words_of_validation(gt_twin_small: Path, tmp_path: Path, monkeypatch):
    """Where planning finds no grasp on an object wider than the gripper (validation skipped here) it said "no
    antipodal grasp fits the gripper ... (22.0 x 22.0 x 2.5 cm)": now what validation says of it."""
    from tests.robot.test_task import _widened

    twin = _widened(gt_twin_small, tmp_path, "yellow_cube", 0.22 / 0.025)
    monkeypatch.setattr("splattwin.robot.task.validate_task", lambda *a, **k: None)
    monkeypatch.setattr("splattwin.robot.selection.GraspSelector.ranked", lambda self, obj, belief: [])
    task = tmp_path / "t.yaml"
    task.write_text("- pick: yellow_cube\n- place_in: {center: [0.1, -0.05], size: 0.3}\n")
    out = tmp_path / "o"
    # not 1: the widened cube overlaps its neighbours and moves as the twin settles (no files for a real arm)
    assert main(["plan", str(twin), "--task", str(task), "--out", str(out), "--no-render", "--no-report"]) != 0
    failure = json.loads((out / "results.json").read_text())["nominal"]["steps"][0]["failure"]
    assert failure == ("object 'yellow_cube' is too wide for the gripper: its narrowest width is 22.0 cm (the "
                       "gripper opens 8.0 cm)")
