"""The real-arm program (robot/program.json, program/): arm phases between blocking gripper actions that,
laid end to end with each gripper phase as the simulated hold, give the executed timeline; the real-robot
files only for a successful run within the named robot's limits; the grasp width where the fingers stopped."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.robot.trajectory import GripperCommand, Trajectory

SIM = [f"joint{i}" for i in range(1, 8)]


def _motion(q0, dq, n=31, grip=None) -> Trajectory:
    """A rest-to-rest motion q0 -> q0 + dq over n samples at 100 Hz (smooth: zero velocity at both ends),
    then a 0.1 s settle hold."""
    s = np.linspace(0.0, 1.0, n)
    blend = 3 * s ** 2 - 2 * s ** 3
    t = np.arange(n) * 0.01
    dur = t[-1]
    q = q0 + blend[:, None] * dq
    qd = ((6 * s - 6 * s ** 2) / dur)[:, None] * dq
    tr = Trajectory(t, q, qd, np.zeros_like(q), SIM, [grip] if grip else [])
    return tr.held_until(dur + 0.1)


def _hold(q, dur, grip) -> Trajectory:
    h = Trajectory.hold(q, dur, joint_names=SIM)
    h.gripper = [grip]
    return h


def _pick_place_segments(q6: float = 1.57, d6: float = 0.05) -> list[tuple[str, Trajectory]]:
    """transit (open at its start) + approach, close hold (grasp), lift + transfer, open hold, retreat: what
    the executor records for one step. Joint 6 starts at q6 and the transit moves it by d6."""
    q0 = np.array([0.0, 0.0, 0.0, -1.57, 0.0, q6, -0.78])
    d = np.array([0.1, 0.05, -0.02, 0.1, 0.0, d6, 0.1])
    transit = _motion(q0, d, grip=GripperCommand.open(0.0, 0.08))
    approach = _motion(transit.q[-1], 0.2 * d)
    close = _hold(approach.q[-1], 0.6, GripperCommand.grasp(0.0, 0.027, planned_width=0.0198))
    lift = _motion(close.q[-1], -0.2 * d)
    transfer = _motion(lift.q[-1], np.roll(d, 1), n=41)
    opened = _hold(transfer.q[-1], 0.402, GripperCommand.open(0.0, 0.08))
    retreat = _motion(opened.q[-1], -0.1 * d)
    return [("step1_transit", transit), ("step1_approach", approach), ("step1_close", close),
            ("step1_lift", lift), ("step1_transfer", transfer), ("step1_open", opened),
            ("step1_retreat", retreat)]


def _names():
    from splattwin.robot.export import export_names

    return export_names(None, SIM, "link0", default_model=True)


def _program_timeline(out: Path, dt: float = 0.01) -> tuple[Trajectory, dict]:
    """The program as written (program.json and its goal files only) played as the validation ran it."""
    from splattwin.robot.trajectory import concatenate

    doc = json.loads((out / "program.json").read_text())
    parts, end = [], None
    for p in doc["phases"]:
        assert (out / p["file"]).is_file()
        if p["kind"] == "arm":
            tr = Trajectory.load_ros2_yaml(out / p["file"])
            np.testing.assert_allclose(tr.q[0], p["start_q"]) and np.testing.assert_allclose(tr.q[-1], p["end_q"])
            assert tr.t[0] == 0.0 and tr.duration == pytest.approx(p["duration_s"], abs=1e-6)
            assert np.abs(tr.qd[0]).max() == 0.0 and np.abs(tr.qd[-1]).max() < 1e-6   # rest to rest
            if end is not None:   # starts where the phase before ended
                np.testing.assert_allclose(tr.q[0], end, atol=1e-9)
            end = tr.q[-1]
        else:
            assert p["blocking"] is True
            q = np.asarray(p["q"])
            if end is not None:
                np.testing.assert_allclose(q, end, atol=1e-9)
            end = q
            d = p["simulated_duration_s"]
            tr = (Trajectory.hold(q, d, dt, doc["joint_names"]) if d > 0 else
                  Trajectory(np.zeros(1), q[None], np.zeros((1, 7)), np.zeros((1, 7)), doc["joint_names"]))
            goal = p["goal"]
            tr.gripper = [GripperCommand(0.0, p["command"], goal["width"], goal.get("speed"), goal.get("force"),
                                         (goal.get("epsilon") or {}).get("inner"),
                                         (goal.get("epsilon") or {}).get("outer"))]
        parts.append(tr)
    return concatenate(parts), doc


def _assert_program_is_the_timeline(out: Path) -> dict:
    """The arm phases with the gripper phases (as stand-stills of their simulated duration) equal the
    executed timeline (trajectory.json) in positions, and each gripper phase sits exactly at a gripper
    command change of the timeline, with that command's goal."""
    full = Trajectory.load_json(out / "trajectory.json")
    prog, doc = _program_timeline(out)
    assert prog.duration == pytest.approx(full.duration, abs=1e-9)
    assert doc["validated_duration_s"] == pytest.approx(full.duration, abs=1e-6)
    ts = np.union1d(full.t, prog.t)
    np.testing.assert_allclose(prog.sample(ts), full.sample(ts), atol=1e-9)
    grip = [p for p in doc["phases"] if p["kind"] == "gripper"]
    assert [(p["timeline_start_s"], p["command"]) for p in grip] == \
        [(pytest.approx(g.t, abs=1e-6), g.command) for g in full.gripper]
    assert [(g.t, g.command, g.width) for g in prog.gripper] == \
        [(pytest.approx(g.t, abs=1e-6), g.command, g.width) for g in full.gripper]
    for p, g in zip(grip, full.gripper):
        assert p["goal"] == g.ros2_goal()["goal"]
        assert p["file"].endswith("_gripper_grasp.goal.ros2.yaml" if g.command == "grasp"
                                  else "_gripper_move.goal.ros2.yaml")
    kinds = [p["kind"] for p in doc["phases"]]
    assert all(a != b for a, b in zip(kinds, kinds[1:]))      # arm and gripper phases alternate
    return doc


def test_program_phases_laid_end_to_end_are_the_executed_timeline(tmp_path):
    from splattwin.robot.outputs import write_trajectories

    paths, notes, real = write_trajectories(tmp_path, _pick_place_segments(), {"robot": "panda"}, _names())
    assert real["written"] and notes == [] and "program.json" in real["files"]
    doc = _assert_program_is_the_timeline(tmp_path)
    assert [(p["kind"], p.get("command"), p.get("segments")) for p in doc["phases"]] == [
        ("gripper", "open", None), ("arm", None, ["step1_transit", "step1_approach"]),
        ("gripper", "grasp", None), ("arm", None, ["step1_lift", "step1_transfer"]),
        ("gripper", "open", None), ("arm", None, ["step1_retreat"])]
    assert [p["simulated_duration_s"] for p in doc["phases"] if p["kind"] == "gripper"] == [0.0, 0.6, 0.402]
    # how long the real hand moves its fingers at the exported speed (not the simulated hold)
    assert doc["phases"][2]["real_finger_motion_s"] == pytest.approx((0.08 - 0.027) / 0.05, abs=1e-3)
    assert doc["phases"][2]["planned_width"] == 0.0198 and doc["start"]["gripper"] == "open"
    from splattwin.robot.program import build_phases, timeline
    from splattwin.robot.trajectory import concatenate

    segs = _pick_place_segments()
    played, full = timeline(build_phases(segs)), concatenate([tr for _, tr in segs])
    np.testing.assert_allclose(played.sample(full.t), full.q, atol=1e-12)
    assert [(g.t, g.command) for g in played.gripper] == [(pytest.approx(g.t), g.command) for g in full.gripper]
    text = (tmp_path / "program" / "02_gripper_grasp.goal.ros2.yaml").read_text()
    assert "franka_msgs/action/Grasp" in text and "wait for its result" in text
    import yaml

    assert yaml.safe_load(text) == doc["phases"][2]["goal"]


@pytest.mark.slow
def test_program_of_the_executed_default_task(default_run, tmp_path):
    """The paper's three steps as executed: the program cuts the timeline at every gripper command and its
    phases reproduce it; every arm phase starts and ends at rest."""
    from splattwin.robot.outputs import write_trajectories

    _, r = default_run
    paths, notes, real = write_trajectories(tmp_path, r.trajectories, {}, _names())
    assert real["written"], real
    doc = _assert_program_is_the_timeline(tmp_path)
    assert sum(p["kind"] == "gripper" for p in doc["phases"]) == 7      # open, then grasp + open per step


def test_arm_phase_that_does_not_end_at_rest_is_refused():
    """A gripper action cannot start while the arm still moves: such a cut is an error, not a program."""
    from splattwin.robot.program import build_phases

    segs = _pick_place_segments()
    label, approach = segs[1]
    qd = approach.qd.copy()
    qd[-1, 0] = 0.05          # still moving when the grasp starts
    segs[1] = (label, Trajectory(approach.t, approach.q, qd, approach.qdd, SIM))
    with pytest.raises(ValueError, match="does not end at rest"):
        build_phases(segs)


def test_failed_run_writes_no_files_for_the_real_arm(tmp_path):
    """A failed run (here: after the grasp, the hand closed on an object in the air) keeps the attempted
    segments for inspection but writes no trajectory, gripper goals or program."""
    from splattwin.robot.outputs import REAL_ROBOT_FILES, write_trajectories

    segs = _pick_place_segments()[:4]       # ends with the lift after the grasp
    paths, notes, real = write_trajectories(tmp_path, segs, {}, _names(),
                                            failed="the task failed at step 1 (hammer): not lifted")
    assert real == {"written": False, "reason": "the task failed at step 1 (hammer): not lifted", "files": []}
    assert notes == ["no trajectory for the real arm: the task failed at step 1 (hammer): not lifted"]
    assert not any((tmp_path / n).exists() for n in REAL_ROBOT_FILES) and not (tmp_path / "program").exists()
    assert sorted(p.name for p in (tmp_path / "segments").iterdir()) == sorted(f"{n}.json" for n, _ in segs)


def test_fr3_limits_checked_on_the_exported_trajectory(tmp_path):
    """--joint-names fr3 checks the trajectory against the FR3's limits (not the Panda's it was planned
    with): a q6 below the FR3's 0.5445 rad (fine on a Panda) writes no real-robot files and says which
    joint and when; the same trajectory with Panda names is written."""
    from splattwin.robot.export import FR3_LIMITS, export_names, limit_violations
    from splattwin.robot.outputs import write_trajectories

    segs = _pick_place_segments(q6=0.56, d6=-0.05)   # the transit takes joint 6 from 0.56 to 0.51 rad
    fr3 = export_names("fr3", SIM, "link0", default_model=True)
    bad = limit_violations(segs[0][1].renamed(fr3.joint_names), FR3_LIMITS)
    assert bad == ["fr3_joint6 at t = 0.120 s: position 0.5424 below the FR3's 0.5445 rad "
                   "(29 samples, worst 0.5100 at t = 0.300 s)"]
    out = tmp_path / "fr3"
    paths, notes, real = write_trajectories(out, segs, {}, fr3)
    assert not real["written"] and "fr3_joint6 at t = " in real["reason"] and real["limit_violations"]
    assert not (out / "trajectory.json").exists() and not (out / "program.json").exists()
    assert (out / "segments" / "step1_transit.json").is_file()
    paths, notes, real = write_trajectories(tmp_path / "panda", segs, {}, _names())
    assert real["written"] and (tmp_path / "panda" / "program.json").is_file()
    # velocities too: 2.62 rad/s is the FR3's joint-1 limit
    fast = Trajectory(np.array([0.0, 0.01]), np.zeros((2, 7)) + [0, 0, 0, -1.5, 0, 1.5, 0],
                      np.array([[0.0] * 7, [2.7, 0, 0, 0, 0, 0, 0]]), np.zeros((2, 7)), fr3.joint_names)
    assert [b.split(":")[0] for b in limit_violations(fast, FR3_LIMITS)] == ["fr3_joint1 at t = 0.010 s"]


def test_grasp_tolerances_cover_the_planned_and_the_stopped_width():
    """The grasp is exported at the width the fingers stopped at; epsilon keeps both it and the planned width
    inside with at least 5 mm to spare (and never below 1 cm); the planned width is recorded."""
    from splattwin.robot.trajectory import GRASP_EPSILON, GRASP_MARGIN, grasp_epsilons

    for measured, planned in ((0.0272, 0.0198), (0.0516, 0.0525), (0.03, 0.05), (0.04, None)):
        inner, outer = grasp_epsilons(measured, planned)
        p = measured if planned is None else planned
        for w in (measured, p):
            assert measured - inner + GRASP_MARGIN - 1e-12 <= w <= measured + outer - GRASP_MARGIN + 1e-12
        assert min(inner, outer) >= GRASP_EPSILON
    assert grasp_epsilons(0.0272, 0.0198)[0] == pytest.approx(0.0124)
    g = GripperCommand.grasp(1.0, 0.0272, epsilon=0.0124, epsilon_outer=0.01, planned_width=0.0198)
    assert GripperCommand.from_dict(g.to_dict()) == g and g.ros2_goal()["goal"]["epsilon"] == {"inner": 0.0124,
                                                                                              "outer": 0.01}


@pytest.mark.slow
def test_grasp_is_exported_at_the_width_the_fingers_stopped(default_run):
    """Each grasp command's width is the finger opening at the end of its close hold in the run."""
    _, r = default_run
    t, grasps = 0.0, []
    for label, tr in r.trajectories:
        if label.endswith("_close"):
            grasps.append((t + tr.duration, tr.gripper[0]))
        t += tr.duration
    ro = r.rollout
    assert len(grasps) == 3
    for t_end, g in grasps:
        assert g.command == "grasp" and g.planned_width is not None
        assert g.width == pytest.approx(ro.gripper_width[ro.at(t_end + 1e-6)], abs=1e-9)
        assert g.width - g.epsilon_inner <= min(g.width, g.planned_width) - 0.005 + 1e-12
        assert g.width + g.epsilon_outer >= max(g.width, g.planned_width) + 0.005 - 1e-12


def test_simulation_deviations_record_the_stiffened_gripper(panda):
    from splattwin.robot.world import GRIP_STIFFNESS, simulation_deviations

    d = simulation_deviations(panda)
    s = d["gripper_servo"]
    assert s["stiffness_N_per_m"] == GRIP_STIFFNESS and s["model_stiffness_N_per_m"] == 100.0
    assert "gravity_compensation" in d and "servo_feed_forward" in d
