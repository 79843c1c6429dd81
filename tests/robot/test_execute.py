from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.robot.execute import Executor
from splattwin.robot.monitor import ContactKind, MonitorState
from splattwin.robot.trajectory import concatenate
from splattwin.robot.task import load_task
from splattwin.robot.world import build_world


@pytest.mark.slow
def test_default_task_succeeds_on_gt_twin(default_run):
    """The paper's three steps on the ground-truth twin: all succeed, zero collisions, physics only."""
    w, r = default_run
    assert w.model.nq == 9 + 7 * len(w.objects)
    assert [s.success for s in r.steps] == [True, True, True], [s.failure for s in r.steps]
    assert r.success and r.collisions == 0
    for s in r.steps:
        assert s.grasped and s.lifted_m > 0.06 and s.placed and s.at_rest
        assert len(s.plan_ms) == 2 and all(p > 0 for p in s.plan_ms)
    # final arrangement: yellow cube on the blue box on the cardboard box, hammer in the target frame
    T_card, T_blue, T_cube = (w.object_pose(n) for n in ("cardboard_box", "blue_box", "yellow_cube"))
    assert np.linalg.norm(T_blue[:2, 3] - T_card[:2, 3]) < 0.05 and T_blue[2, 3] > T_card[2, 3] + 0.07
    assert np.linalg.norm(T_cube[:2, 3] - T_blue[:2, 3]) < 0.03 and T_cube[2, 3] > T_blue[2, 3] + 0.03
    tf = w.manifest.config["target_frame"]
    assert np.all(np.abs(w.object_pose("toy_hammer")[:2, 3] - tf["center"][:2]) < tf["size"] / 2)
    # trajectories are continuous and executed in physics (no teleporting objects)
    assert r.sim_time > 5.0
    names = [n for n, _ in r.trajectories]
    assert "step1_transfer" in names and "step3_retreat" in names


def test_collision_monitor_counts_robot_hitting_the_table(gt_twin_small: Path):
    w = build_world(gt_twin_small, visual=False)
    ex = Executor(w)
    T = ex.motion.ik.fk(w.robot.home)
    T[:3, 3] = [-0.05, 0.35, -0.01]          # 1 cm into the table, away from every object
    q = ex.motion.ik.solve(T, w.robot.home)
    assert q is not None
    path = np.stack([w.robot.home, q])
    mon = MonitorState(target=w.object_body("blue_box"))
    ex.servo.track(ex.motion.trajectory(path, 0.3), w.robot.gripper_open, 0.2, mon)
    hits = [e for e in mon.events if e.kind is ContactKind.ROBOT]
    assert hits and any("world" in (w.body_name(e.body_a), w.body_name(e.body_b)) for e in hits)
    assert mon.count(ContactKind.ROBOT) == len(hits) and mon.count(ContactKind.OBJECT) == 0
    # the same motion to 5 cm above the table touches nothing
    w2 = build_world(gt_twin_small, visual=False)
    ex2 = Executor(w2)
    T[:3, 3] = [-0.05, 0.35, 0.05]
    q2 = ex2.motion.ik.solve(T, w2.robot.home)
    mon2 = MonitorState(target=w2.object_body("blue_box"))
    ex2.servo.track(ex2.motion.trajectory(np.stack([w2.robot.home, q2]), 0.3), w2.robot.gripper_open, 0.2, mon2)
    assert mon2.events == []


def test_hammer_sunk_into_the_table_is_still_graspable(gt_twin_default: Path):
    """A reconstructed object sits a few mm into the table (bottom below the table top): the grasp height
    follows the support surface, so the fingertips keep the planning margin above the table in the closed
    pose and the approach is collision-free (the finger-table contact was the reconstructed twin's step-3
    failure). Planning only, on the belief poses."""
    from splattwin.robot.world import hand_points_tcp

    w = build_world(gt_twin_default, visual=False)
    T = w.manifest.object("toy_hammer").pose.copy()
    T[2, 3] -= 0.003                                    # 3 mm into the table
    ex = Executor(w, belief={"toy_hammer": T})
    assert 0.0085 < ex.tip_depth < 0.0095               # Menagerie Panda fingertips beyond the TCP
    task = load_task(None, w.manifest)
    step = task.steps[2]
    assert step.pick == "toy_hammer"
    plan = ex.plan_step(step)
    q = plan.approach[-1]
    # independent check on the world model: the lowest finger point at the grasp is above the table
    # by the planning margin
    qpos = w.joints.full(q, w.qpos())
    T_tcp = w.tcp_poses(qpos[None])[0]
    lowest = float(((T_tcp[:3, :3] @ hand_points_tcp(w).T).T + T_tcp[:3, 3])[:, 2].min())
    assert lowest >= w.manifest.background.table_height + ex.motion.margin
    # the pads still hold the handle: the TCP is below the hammer's top
    ext = w.manifest.object("toy_hammer").bbox_extent
    assert T_tcp[2, 3] < T[2, 3] + ext[2] / 2 - 0.004


def _shifted(T: np.ndarray, d_obj: np.ndarray) -> np.ndarray:
    T = np.array(T, float)
    T[:3, 3] += T[:3, :3] @ np.asarray(d_obj, float)
    return T


@pytest.mark.slow
def test_finger_landing_on_the_box_is_corrected_by_touch(gt_twin_default: Path):
    """The blue box (6 cm across the grasp, 8 cm gripper: 1 cm clearance per side) lies 15 mm off its
    twin pose along the closing axis: the first approach lands a finger on its top. The guarded approach
    stops, backs off, shifts the believed pose towards that finger and grasps it; no collisions."""
    w0 = build_world(gt_twin_default, visual=False)
    nominal = {o: w0.manifest.object(o).pose for o in w0.objects}
    task = load_task(None, w0.manifest)
    for sign in (1, -1):
        poses = dict(nominal)
        poses["blue_box"] = _shifted(nominal["blue_box"], [0.0, sign * 0.015, 0.0])   # box y: its 6 cm side
        w = build_world(gt_twin_default, poses=poses, visual=False)
        ex = Executor(w, belief=nominal, seed=0)
        r = ex.run_step(1, task.steps[0])
        assert r.success and r.robot_collisions == 0 and r.object_collisions == 0, r.failure
        assert r.grasp.touch_corrections == 1
        # the corrected belief is closer to the true pose than the twin's
        true_offset = poses["blue_box"][:3, 3] - nominal["blue_box"][:3, 3]
        assert np.linalg.norm(np.array(r.grasp.belief_correction_m) - true_offset) < 0.008
        names = [n for n, _ in ex.trajs]
        assert names[:6] == ["step1_transit", "step1_approach_stopped", "step1_touch1", "step1_backoff1",
                             "step1_transit_retry1", "step1_approach_retry1"], names
        full = concatenate([t for _, t in ex.trajs])            # one continuous exported trajectory
        assert full.duration > 5.0


@pytest.mark.slow
def test_blocked_best_grasp_falls_back_to_the_next_ranked(gt_twin_default: Path):
    """An obstacle (the yellow cube, 8 mm beside the blue box's long face, off-centre) blocks the best
    (central) grasp's finger: the step uses a lower-ranked grasp and still succeeds without collisions."""
    w0 = build_world(gt_twin_default, visual=False)
    poses = {o: w0.manifest.object(o).pose for o in w0.objects}
    cube = _shifted(poses["blue_box"], [0.015, 0.03 + 0.008 + 0.0125, 0.0])
    cube[2, 3] = poses["yellow_cube"][2, 3]
    poses["yellow_cube"] = cube
    w = build_world(gt_twin_default, poses=poses, visual=False)
    ex = Executor(w, belief=poses, seed=0)
    step = load_task(None, w.manifest).steps[0]
    best = ex.selector.ranked("blue_box", ex.belief)[0]
    r = ex.run_step(1, step)
    assert r.success and r.robot_collisions == 0 and r.object_collisions == 0, r.failure
    assert r.grasp.tried > 1 and r.grasp.rejections.get("approach collision", 0) >= 1
    assert r.grasp.score < best.score
    # the cube was not pushed
    assert np.linalg.norm(w.object_pose("yellow_cube")[:2, 3] - cube[:2, 3]) < 0.002


@pytest.mark.slow
def test_failed_motion_plans_fall_back_to_next_grasp_and_place(gt_twin_default: Path, monkeypatch):
    """No transit path to the best grasp and no transfer path to the first place pose (the planner is
    made to fail once each): the step falls back to the next grasp and the next place pose."""
    from splattwin.robot.planning import PlanningError
    from splattwin.robot.selection import place_targets

    w = build_world(gt_twin_default, visual=False)
    ex = Executor(w, seed=0)
    step = load_task(None, w.manifest).steps[0]
    real_plan = ex.motion.free_path
    failed = []

    def flaky(q_start, q_goal, label):
        kind = label.split("_")[-1]
        if kind not in failed:
            failed.append(kind)
            raise PlanningError(f"injected: no {kind} path")
        return real_plan(q_start, q_goal, label)

    monkeypatch.setattr(ex.motion, "free_path", flaky)
    first_place = place_targets(step, "blue_box", ex.belief, w.manifest, ex.selector.shapes)[0]
    r = ex.run_step(1, step)
    assert failed == ["transit", "transfer"]
    assert r.success and r.robot_collisions == 0 and r.object_collisions == 0, r.failure
    assert r.grasp.tried >= 2
    assert [f.split(":")[0] for f in r.grasp.fallbacks] == ["transit", "transfer"]
    # placed with another yaw than the first place option (the options differ in yaw)
    T = w.object_pose("blue_box")
    dyaw = np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(first_place[1, 0], first_place[0, 0])
    assert np.cos(dyaw) < np.cos(np.radians(45))


@pytest.mark.slow
def test_all_motion_plans_failing_fails_the_step_with_reasons(gt_twin_default: Path, monkeypatch):
    from splattwin.robot.planning import PlanningError

    w = build_world(gt_twin_default, visual=False)
    ex = Executor(w, seed=0)
    step = load_task(None, w.manifest).steps[0]

    def never(q_start, q_goal, label):
        raise PlanningError("injected: blocked")

    monkeypatch.setattr(ex.motion, "free_path", never)
    r = ex.run_step(1, step)
    assert not r.success and "no transit to any of" in r.failure and "blocked" in r.failure
    assert len(r.grasp.fallbacks) == r.grasp.tried - sum(r.grasp.rejections.values()) > 1


@pytest.mark.slow
def test_transfer_without_in_hand_sensing(gt_twin_default: Path):
    """in_hand="planned": the transfer assumes the object sits in the hand as grasped on the perceived
    pose (no in-hand estimate). With the box 4 mm off its twin pose the step still places it."""
    w0 = build_world(gt_twin_default, visual=False)
    nominal = {o: w0.manifest.object(o).pose for o in w0.objects}
    task = load_task(None, w0.manifest)
    with pytest.raises(ValueError, match="in_hand"):
        Executor(w0, in_hand="oracle")
    poses = dict(nominal)
    poses["blue_box"] = _shifted(nominal["blue_box"], [0.004, 0.0, 0.0])
    w = build_world(gt_twin_default, poses=poses, visual=False)
    ex = Executor(w, belief=nominal, seed=0, in_hand="planned")
    r = ex.run_step(1, task.steps[0])
    assert r.success and r.robot_collisions == 0 and r.object_collisions == 0, r.failure


@pytest.mark.slow
def test_a_failed_placement_reports_its_cause(gt_twin_default: Path, monkeypatch):
    """The step's failure is the judge's words for what went wrong, not a generic "not placed": here the
    judge is made to see the placed object tipped over; the step records the object's final tilt too."""
    from splattwin.robot import judge

    w = build_world(gt_twin_default, visual=False)
    ex = Executor(w, seed=0)
    step = load_task(None, w.manifest).steps[0]
    real = judge.judge_place

    def tipped(world, step_, obj, shapes=None):
        v = real(world, step_, obj, shapes)
        return judge.Placement(placed=False, at_rest=False, speed=v.speed, tilt=1.2,
                               why=judge.place_failure(obj, step_, False, False, v.speed, 1.2, "not on 'x'"))

    monkeypatch.setattr(judge, "judge_place", tipped)
    r = ex.run_step(1, step)
    assert not r.success and r.grasped
    assert r.failure.startswith(f"{step.pick!r} tipped over: it ended tilted 69 deg"), r.failure
    assert f"uneven top of {step.place_on!r}" in r.failure
    assert 0.0 <= r.final_tilt_deg < 10.0   # in physics it did land upright


def test_a_goal_a_later_step_disturbs_fails_its_step(gt_twin_small: Path):
    """Each step was judged only when it ended: a later step that pushes an earlier-placed object out of its
    goal (object-object contact after a release is no collision) left the task a success. Now the end of
    the task re-judges every placed object no later step picks; here the cube is moved off its region
    (standing in for a push) when step 2 releases the hammer."""
    from splattwin.robot.task import parse_task

    w = build_world(gt_twin_small, visual=False)
    task = parse_task([{"pick": "yellow_cube", "place_in": {"center": [0.0, -0.1], "size": 0.1}},
                       {"pick": "toy_hammer", "place_in": {"center": [0.05, 0.15], "size": 0.24}}], gt_twin_small)

    def push(label: str, world) -> None:
        if label == "step2_release":
            T = world.object_pose("yellow_cube").copy()
            T[0, 3] += 0.15
            world.set_object_pose("yellow_cube", T)

    res = Executor(w, frame_cb=push).run(task)
    assert not res.success and len(res.steps) == 2 and res.steps[1].success
    s1 = res.steps[0]
    assert not s1.success and s1.grasped and s1.placed   # placed when its own step ended
    assert s1.failure.startswith("at the end of the task (step 2), a later step had disturbed it: 'yellow_cube' "
                                 "not inside the region 'region'")
    # undisturbed, the same task succeeds
    assert Executor(build_world(gt_twin_small, visual=False)).run(task).success


def test_step_and_run_results_document_every_field():
    """help(StepResult) showed only the dataclass signature: what grasped, placed, at_rest mean and the units of
    lifted_m, final_xyz, final_tilt_deg were nowhere in Python (api13 E3)."""
    import dataclasses
    import re

    from splattwin.robot.execute import RunResult, StepResult

    for cls in (StepResult, RunResult):
        doc = cls.__doc__ or ""
        assert not doc.startswith(cls.__name__ + "("), f"{cls.__name__} has only the generated docstring"
        missing = [f.name for f in dataclasses.fields(cls) if not re.search(rf"\b{f.name}\b", doc)]
        assert not missing, (cls.__name__, missing)
