"""Plan a pick-and-place task against the twin and execute it in MuJoCo physics.

Planning uses the robot's *belief* of the object poses (the twin's poses, then the commanded place poses);
the simulated world may differ (perturbed trials model reconstruction error). Per step:

  transit (OMPL, gripper open) -> approach (Cartesian; the fingers may touch the target but not penetrate
  it, everything else keeps the margin) -> close the real gripper (actuator 8, friction only, no weld) ->
  lift (Cartesian) -> transfer (OMPL, object attached to the hand in the collision checker) -> descent
  (Cartesian) -> open -> retreat (Cartesian, checked like the approach against the released object).

Robustness to the twin's pose error (the world may differ from the belief):
* guarded approach: when a finger lands on the target instead of straddling it (the object lies further
  off its twin pose along the closing axis than the gripper's clearance), the arm stops, backs off to the
  pre-grasp, shifts its belief of the object towards that finger by the clearance plus half a finger pad
  and re-plans (at most MAX_TOUCHES times per step);
* free motions (transit, transfer) keep OBJECT_CLEARANCE from the twin's objects (motion.py);
* the place pose is computed for the object where it sits in the hand after the grasp: `in_hand="sensed"`
  (default) reads it from the simulation, standing in for an in-hand estimate on the real cell (a wrist
  camera); `in_hand="planned"` assumes it sits as planned on the perceived pose (no in-hand sensing);
* fallbacks: a grasp whose transit finds no path (or no verified timing) gives way to the next ranked
  grasp, a place pose whose transfer finds no path to the grasp's next place pose, before the step fails.

The units: grasp and place selection (selection.py), feasible plans (candidates.py), motion planning
(motion.py), execution in physics (servo.py) with contact monitoring (monitor.py), judging (judge.py) and
the recorded rollout (rollout.py). This module sequences them; per-step success as in the paper: the right
object grasped and lifted; placed inside the goal region and at rest after settling; no contact of the
robot with anything but the target and no contact of the carried object with anything during transfer.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from splattwin.robot import judge
from splattwin.robot.candidates import LIFT, StepFailed, StepPlanner
from splattwin.robot.grasp import PAD_HALF, TIP_DEPTH
from splattwin.robot.monitor import MonitorState, landing_side
from splattwin.robot.motion import OBJECT_CLEARANCE, SLOW, SPEED, MotionPlanner, truncate
from splattwin.robot.planning import PlanningError
from splattwin.robot.plans import GraspPlan, GraspReport, PlacePlan
from splattwin.robot.rollout import Rollout, RolloutRecorder
from splattwin.robot.selection import GraspSelector
from splattwin.robot.servo import Servo
from splattwin.robot.task import Step, Task
from splattwin.robot.trajectory import GripperCommand, Trajectory, grasp_epsilons
from splattwin.robot.world import World, hand_points_tcp
from splattwin.transforms import invert_pose

log = logging.getLogger(__name__)

# s the simulated gripper is given to close (and the grasp to settle) / to open while the arm holds still.
# The simulated finger servo closes within ~0.1 s, far faster than a real Franka Hand at GRIPPER_SPEED (80 -> 27
# mm: ~1.1 s): the whole-timeline files keep these holds, the real arm runs robot/program.json, whose gripper
# actions block (program.py)
CLOSE_TIME = 0.6
OPEN_TIME = 0.4
SETTLE_TIME = 0.6        # s after the retreat before judging the placement
FLOOR_TOLERANCE = 0.0015  # m: fingertips above the support by the planning margin plus this (IK, sampling)
MAX_TOUCHES = 2          # touch-based corrections of the believed object pose per step
IN_HAND = ("sensed", "planned")  # where the transfer assumes the held object sits (module docstring)

__all__ = ["Executor", "StepResult", "RunResult", "StepFailed", "IN_HAND", "unsettled", "task_step_list"]


@dataclass
class StepResult:
    """One step's outcome in physics, judged as the paper does (`judge.criteria`: the thresholds and their
    definition, also results.json `criteria`). index: the step (1-based); pick / goal: object and goal names.
    success: grasped and placed and at_rest and no collision. grasped: the object rose at least
    `judge.LIFT_FRACTION` of the commanded lift with both fingers on it; lifted_m: how far it rose (m). placed:
    on its support's top (place_on) or with its footprint inside the region on the table (place_in), bottom
    within `judge.HEIGHT_TOL` m; at_rest: slower than `judge.REST_SPEED` m/s and tilted less than
    `judge.TILT_MAX` after the settle time. robot_collisions / object_collisions: contacts of the robot with
    anything but the object / of the carried object with anything but the hand, during the step;
    collision_pairs: their body names. plan_ms: motion-planning time per planned motion (ms). grasp: the grasp
    chosen and why (`GraspReport`). failure: why the step failed (None on success). final_xyz: the object's
    centre at the end (m, twin frame); final_tilt_deg: its tilt from upright then (deg)."""

    index: int
    pick: str
    goal: str
    success: bool = False
    grasped: bool = False
    lifted_m: float = 0.0
    placed: bool = False
    at_rest: bool = False
    robot_collisions: int = 0
    object_collisions: int = 0
    collision_pairs: list = field(default_factory=list)
    plan_ms: list = field(default_factory=list)
    grasp: GraspReport = field(default_factory=GraspReport)
    failure: str | None = None
    final_xyz: list = field(default_factory=list)
    final_tilt_deg: float = 0.0   # the picked object's tilt from upright at the end of the step


@dataclass
class RunResult:
    """One execution of a task in MuJoCo physics (`Executor.run`; `trials.run_once` returns it first).

    success: every step of the task ran and succeeded; steps: per-step outcome (`StepResult`);
    collisions: the steps' robot and object collisions together (`judge.collisions`); plan_ms: planning
    time per step (ms); sim_time: simulated seconds; wall_s: wall-clock seconds; trajectories: (name,
    `Trajectory`) of the executed segments and rollout: the recorded `Rollout` (twin frame, m, rad, s),
    both kept only with `keep_trajectories`; settle: the start check (see below); task_steps: every step
    of the task (`task_step_list`), those after a failed one too. `to_dict()`: the JSON record (results.json)."""

    success: bool
    steps: list[StepResult]
    collisions: int
    plan_ms: list[float]
    sim_time: float
    wall_s: float
    trajectories: list[tuple[str, Trajectory]] = field(default_factory=list, repr=False)
    rollout: Rollout | None = field(default=None, repr=False)
    # the start check (`World.settle_check`): how far physics moved each object from its twin pose before
    # the robot acted; objects in `settle["moved"]` mean the run does not validate the twin (`unsettled`)
    settle: dict | None = None
    # every step of the task, attempted or not (`task_step_list`): `steps` ends at the first failed one, so
    # without this list a failed run's record could not say which steps it never attempted
    task_steps: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"success": self.success, "collisions": self.collisions, "plan_ms": self.plan_ms,
                "sim_time": self.sim_time, "wall_s": self.wall_s, "steps": [asdict(s) for s in self.steps],
                "task_steps": self.task_steps,
                "trajectories": [name for name, _ in self.trajectories], "settle": self.settle}


def task_step_list(task: Task) -> list[dict]:
    """The task's steps as results.json `nominal.task_steps` records them: [{index (1-based), pick, goal,
    place: "on" (an object) or "in" (a region), and for a region its `region` {center [x, y, z], size
    [sx, sy]} (m, twin frame): what the step was judged against, also when the task file changes}]."""
    out = []
    for k, s in enumerate(task.steps, start=1):
        d = {"index": k, "pick": s.pick, "goal": s.goal_name, "place": "on" if s.place_on else "in"}
        if s.place_in is not None:
            d["region"] = {"center": [round(float(v), 6) for v in s.place_in.center],
                           "size": [round(float(v), 6) for v in s.place_in.size]}
        out.append(d)
    return out


def unsettled(settle: dict | None) -> str | None:
    """Why a run does not validate the twin, from its start check (`RunResult.settle`): the objects that
    physics moved from their twin poses before the robot acted (floating, sunk in, tipping), else None."""
    if not settle or not settle.get("moved"):
        return None
    robot_posed = settle.get("frame_source") in ("robot", "sfm+robot")
    parts = []
    for o in settle["moved"]:
        v = settle["objects"][o]
        fell = " (fell)" if v.get("dz_m", 0.0) < -settle["threshold_m"] else ""
        parts.append(f"{o} moved {v['moved_m'] * 100:.1f} cm{fell} and turned {v['turned_deg']:.1f} deg")
    return (f"the twin is not at rest in physics: before the robot acted, {'; '.join(parts)} from the twin pose "
            f"in {settle['time_s']:g} s (limits {settle['threshold_m'] * 100:g} cm, {settle['threshold_deg']:g} deg), "
            f"so the run was made on another scene than the twin's and does not validate it (check the object's "
            f"geometry and pose: a floating or sunken object{ROBOT_POSES_HINT if robot_posed else ''})")


# the start check's message for a twin posed by the robot (`--robot-poses`: frame source robot / sfm+robot)
ROBOT_POSES_HINT = ("; the views were posed by the robot: inconsistent robot poses or hand-eye calibration "
                    "misplace an object's splats this way too (see poses/poses_report.json hand_eye_check; "
                    "--poses.method sfm with the robot files re-estimates them)")


class Executor:
    """Runs a task on a World. `belief`: T_world_obj per object used for planning (default: the twin's).

    trajectories: (label, Trajectory) of every servo command in order: each motion with the settle hold
    the servos ran after it, and each gripper hold, lasting exactly as long as it ran in physics, so
    their concatenation is the executed timeline; a segment where the gripper command changes carries
    it (`Trajectory.gripper`, at its start: open to the full opening, or grasp at the planned width). The
    rollout (`RunResult.rollout`) records what physics did with them.
    """

    def __init__(self, world: World, belief: dict[str, np.ndarray] | None = None, seed: int = 0,
                 planner: str = "RRTConnect", plan_time: float = 60.0, margin: float = 0.005,
                 frame_cb: Callable[[str, World], None] | None = None, object_clearance: float = OBJECT_CLEARANCE,
                 in_hand: str = "sensed"):
        if in_hand not in IN_HAND:
            raise ValueError(f"in_hand must be one of {IN_HAND}, got {in_hand!r}")
        self.in_hand = in_hand
        self.world = world
        self.robot = world.robot
        self.belief = {o: (np.asarray(belief[o]) if belief and o in belief else world.manifest.object(o).pose)
                       for o in world.objects}
        self.frame_cb = frame_cb
        self.trajs: list[tuple[str, Trajectory]] = []
        self._grip_ctrl: float | None = None   # the gripper ctrl last commanded (exported when it changes)
        self.recorder = RolloutRecorder(world.model.nq, len(self.robot.arm_joints))
        self.servo = Servo(world, self.recorder)
        self.motion = MotionPlanner(world, self.belief, seed=seed, planner=planner, plan_time=plan_time,
                                    margin=margin, object_clearance=object_clearance)
        # how far the opened fingers reach beyond the TCP along the approach (m): grasp heights keep the
        # fingertips the planning margin above the support surface
        self.tip_depth = float(hand_points_tcp(world)[:, 2].max(initial=TIP_DEPTH))
        self.selector = GraspSelector(world.manifest, world.twin_dir, world.base.matrix(), self.robot.max_opening,
                                      self.tip_depth, margin + FLOOR_TOLERANCE)
        self.planner = StepPlanner(self.motion, self.selector, lambda: self.servo.q)

    @property
    def q(self) -> np.ndarray:
        """The commanded arm configuration held now [n] rad."""
        return self.servo.q

    @property
    def plan_ms(self) -> list[float]:
        return self.motion.plan_ms

    # ---- execution helpers -----------------------------------------------------------------------------
    def _track(self, label: str, tr: Trajectory | None, grip: float, settle: float, mon: MonitorState,
               guard: Callable[[], bool] | None = None, width: float | None = None) -> float | None:
        """Execute tr (None: a hold at the current q) with gripper ctrl `grip`, then hold `settle` s, and
        record it as `label` lasting exactly as long as the servos ran (motion + hold). width: the grasp
        width (m) when `grip` closes on an object. A guarded motion that stopped is recorded up to the
        stop as `<label>_stopped` (the caller records the hold there). Returns the stop time or None."""
        q0 = self.q
        stopped = self.servo.track(tr, grip, settle, mon, guard=guard)
        if tr is None:
            tr = self.motion.hold(q0, self.servo.elapsed)
        elif stopped is None:
            tr = tr.held_until(self.servo.elapsed)
        else:
            tr = truncate(tr, stopped)
            label = f"{label}_stopped"
        cmd = self._gripper_command(grip, width)
        if cmd is not None:
            tr = Trajectory(tr.t, tr.q, tr.qd, tr.qdd, tr.joint_names, [cmd])
        self.trajs.append((label, tr))
        return stopped

    def _gripper_command(self, grip: float, width: float | None) -> GripperCommand | None:
        """The command to export when the gripper ctrl changes (at the start of that segment), else None;
        called when the segment has run. The simulation closes the fingers fully (a position target) and
        the object stops them; the real hand must be told to grasp at the object's width with a force (a
        move to 0 m on an object fails). The width exported is where the fingers stopped (measured now,
        at the end of the close hold), the planned `width` is recorded beside it, and the tolerances
        cover both (`grasp_epsilons`): a real grasp fails when its final width is outside them."""
        if self._grip_ctrl == grip:
            return None
        self._grip_ctrl = grip
        if grip == self.robot.gripper_closed:
            measured = self.world.gripper_width()
            inner, outer = grasp_epsilons(measured, width)
            return GripperCommand.grasp(0.0, measured, epsilon=inner, epsilon_outer=outer, planned_width=width)
        return GripperCommand.open(0.0, self.robot.max_opening)

    def _move(self, path: np.ndarray, speed: float, label: str, grip: float, settle: float, mon: MonitorState,
              checked: bool = False) -> None:
        """Time-parameterise a joint path, execute it (then hold `settle` s) and record both as `label`."""
        self._track(label, self.motion.trajectory(path, speed, checked=checked), grip, settle, mon)

    def _gripper(self, label: str, grip: float, duration: float, mon: MonitorState,
                 width: float | None = None) -> None:
        """Open/close the gripper while the arm holds still (recorded as a stand-still); width: the grasp
        width (m) when closing on an object."""
        self._track(label, None, grip, duration, mon, width=width)

    def _snap(self, label: str) -> None:
        if self.frame_cb is not None:
            self.frame_cb(label, self.world)

    # ---- one step -------------------------------------------------------------------------------------
    def plan_step(self, step: Step, report: GraspReport | None = None) -> GraspPlan:
        """The best-ranked feasible grasp plan for a step (planning only, nothing executed)."""
        report = report if report is not None else GraspReport()
        plan = next(self.planner.candidates(step, report), None)
        if plan is None:
            raise StepFailed(self.planner.no_candidate_message(step, report))
        return plan

    def _track_first(self, options, goal: Callable, label: str, kind: str, res: StepResult, width: float,
                     gripper: float, mon: MonitorState, carrying: tuple | None = None):
        """Plan a checked free-space path from the current joints to `goal(option)` for each option in
        turn (the fingers frozen at `width`, carrying `(obj, T_tcp_obj)` if given) and execute the first
        that plans. Returns (that option or None, the failure messages of those before it)."""
        failures = []
        for option in options:
            self.motion.freeze(self.q, width)
            try:
                with self.motion.carrying(*carrying) if carrying else contextlib.nullcontext():
                    path = self.motion.free_path(self.q, goal(option), label)
                    tr = self.motion.trajectory(path, SPEED, checked=True)
            except (PlanningError, RuntimeError) as e:
                failures.append(str(e))
                res.grasp.fallbacks.append(f"{kind}: {e}"[:300])
                continue
            self._track(label, tr, gripper, 0.1, mon)
            return option, failures
        return None, failures

    def _reach(self, step: Step, res: StepResult, k: int, mon: MonitorState, tag: str = "") -> GraspPlan:
        """Plan and execute the transit to the pre-grasp of the best candidate whose transit plans; a
        candidate whose transit finds no path (or no verified timing) falls back to the next one."""
        plan, failures = self._track_first(
            self.planner.candidates(step, res.grasp), lambda p: p.q_pregrasp, f"step{k}_transit{tag}",
            "transit", res, self.robot.max_opening, self.robot.gripper_open, mon)
        if plan is not None:
            return plan
        if failures:
            raise StepFailed(f"no transit to any of {len(failures)} feasible grasps on {step.pick!r}: "
                             f"{failures[0]}")
        raise StepFailed(self.planner.no_candidate_message(step, res.grasp))

    def _approach(self, step: Step, res: StepResult, k: int, mon: MonitorState) -> GraspPlan:
        """Reach and descend onto a grasp with a guarded approach. When a finger lands on the target (the
        object is further off its believed pose than the gripper's clearance along the closing axis),
        stop, back off to the pre-grasp, shift the believed object pose towards that finger by the
        clearance plus half a finger pad and re-plan: a touch-based correction, at most MAX_TOUCHES times."""
        obj = step.pick
        w = self.world
        target = w.object_body(obj)
        touches = 0
        T_twin = self.belief[obj].copy()
        while True:
            tag = f"_retry{touches}" if touches else ""
            plan = self._reach(step, res, k, mon, tag)
            tr = self.motion.trajectory(plan.approach, SLOW)
            landed: list[float] = []

            def guard() -> bool:
                side = landing_side(w.contacts(), target, w.is_robot, w.tcp_pose()) if w.data.ncon else None
                if side is not None:
                    landed.append(side)
                return side is not None

            stopped = self._track(f"step{k}_approach{tag}", tr, self.robot.gripper_open, 0.1, mon, guard=guard)
            if stopped is None:
                res.grasp.touch_corrections = touches
                res.grasp.belief_correction_m = (self.belief[obj][:3, 3] - T_twin[:3, 3]).round(5).tolist()
                return plan
            side = landed[0]
            touches += 1
            # the servos held the stop for the rest of that track call (GUARD_HOLD and the step it fired in)
            self.trajs.append((f"step{k}_touch{touches}", self.motion.hold(self.q, self.servo.elapsed - stopped)))
            if touches > MAX_TOUCHES:
                raise StepFailed(f"a finger landed on {obj!r} on the approach {touches} times "
                                 f"(the object is far from its twin pose)")
            # back off along the approach axis to the pre-grasp (the reverse of the approach so far)
            back = self.motion.cartesian(self.q, self.motion.ik.fk(self.q), plan.T_world_pregrasp)
            if back is None:
                raise StepFailed(f"no way back from a finger landing on {obj!r}")
            self._move(back, SLOW, f"step{k}_backoff{touches}", self.robot.gripper_open, 0.1, mon)
            shift = (self.robot.max_opening - plan.grasp.width) / 2 + PAD_HALF
            T = self.belief[obj].copy()
            T[:3, 3] += side * shift * plan.T_world_grasp[:3, 1]
            log.info("finger landed on %s: belief shifted %.1f mm along the closing axis", obj, side * shift * 1e3)
            self.belief[obj] = T

    def _transfer(self, step: Step, res: StepResult, k: int, plan: GraspPlan, mon: MonitorState) -> PlacePlan:
        """Plan and execute the transfer to a place option with the object where it sits in the hand now
        (sensed, or as planned: the jaws centre it along the closing axis). Place poses for the sensed
        in-hand pose come first (it may have settled off the planned grasp), then the planned ones; a
        place pose whose transfer finds no path falls back to the next."""
        obj, g = step.pick, plan.grasp
        if self.in_hand == "sensed":
            T_tcp_obj = invert_pose(self.world.tcp_pose()) @ self.world.object_pose(obj)
        else:
            T_tcp_obj = invert_pose(g.T_obj_tcp)
        self.belief[obj] = self.motion.ik.fk(self.q) @ T_tcp_obj
        sensed = (self.planner.place_options(step, g, self.q, None, T_obj_tcp=invert_pose(T_tcp_obj))
                  if self.in_hand == "sensed" else iter(()))
        option, failures = self._track_first(
            itertools.chain(sensed, [plan.place], plan.places), lambda o: o.q_preplace, f"step{k}_transfer",
            "transfer", res, g.width, self.robot.gripper_closed, mon, carrying=(obj, T_tcp_obj))
        if option is not None:
            return option
        raise StepFailed(f"no transfer path to any of {len(failures)} place poses for {obj!r}: "
                         f"{failures[0] if failures else 'none feasible'}")

    def run_step(self, k: int, step: Step) -> StepResult:
        """Plan and execute step k (1-based) and judge it; failures are reported, never raised."""
        w = self.world
        obj = step.pick
        res = StepResult(index=k, pick=obj, goal=step.goal_name)
        n_plan = len(self.plan_ms)
        verdict = None
        mon = MonitorState(target=w.object_body(obj))
        open_c, closed_c = self.robot.gripper_open, self.robot.gripper_closed
        self.recorder.step = k
        try:
            plan = self._approach(step, res, k, mon)
            z0 = w.object_pose(obj)[2, 3]
            self._gripper(f"step{k}_close", closed_c, CLOSE_TIME, mon, width=plan.grasp.width)
            self._snap(f"step{k}_grasp")
            mon.carrying = True
            mon.allowed = frozenset(w.body_id(s) for s in plan.support)
            self._move(plan.lift, SLOW, f"step{k}_lift", closed_c, 0.2, mon)
            res.lifted_m = float(w.object_pose(obj)[2, 3] - z0)
            res.grasped = judge.judge_grasp(res.lifted_m, LIFT, judge.is_held(w, obj))
            if not res.grasped:
                raise StepFailed(f"{obj!r} not lifted with the gripper (rose {res.lifted_m * 100:.1f} cm)")
            place = self._transfer(step, res, k, plan, mon)
            mon.allowed = frozenset({w.body_id(step.place_on) if step.place_on else 0, 0})
            self._move(place.descent, SLOW, f"step{k}_descent", closed_c, 0.1, mon)
            mon.carrying = False
            self._gripper(f"step{k}_open", open_c, OPEN_TIME, mon)
            self._snap(f"step{k}_release")
            self._move(place.retreat, SLOW, f"step{k}_retreat", open_c, SETTLE_TIME, mon)
            self.belief[obj] = place.T_world_obj
            verdict = judge.judge_place(w, step, obj, self.selector.shapes)
            res.placed, res.at_rest = verdict.placed, verdict.at_rest
        except StepFailed as e:
            res.failure = str(e)
        except PlanningError as e:  # report, do not crash the trial
            res.failure = f"planning: {e}"
        finally:
            self.recorder.step = -1
        res.plan_ms = self.plan_ms[n_plan:]
        c = judge.collisions(mon, w.body_name)
        res.robot_collisions, res.object_collisions, res.collision_pairs = c.robot, c.object, c.pairs
        res.final_xyz = w.object_pose(obj)[:3, 3].round(4).tolist()
        res.final_tilt_deg = round(math.degrees(judge.tilt_of(w.object_pose(obj))), 2)
        res.success = bool(res.failure is None and res.grasped and res.placed and res.at_rest
                           and res.robot_collisions == 0 and res.object_collisions == 0)
        if res.failure is None and not res.success:
            res.failure = ("collision: " + "; ".join(res.collision_pairs)) if res.collision_pairs else \
                (verdict.why if verdict is not None and verdict.why else "not placed inside the goal region at rest")
        return res

    # ---- whole task -----------------------------------------------------------------------------------
    def recheck(self, task: Task, steps: list[StepResult]) -> None:
        """At the end of the task, each step's object that no later step picks must still be in its goal and
        at rest (`judge.judge_place`): a later place may push or tip it, and contacts between objects after
        a release are no collision of the robot or of the carried object, so the step alone would not see
        it. A step whose goal no longer holds is failed, in place, saying so."""
        w = self.world
        n = len(task.steps)
        for k, (step, res) in enumerate(zip(task.steps, steps), start=1):
            if k == n or any(later.pick == step.pick for later in task.steps[k:]):
                continue   # judged just now, or moved on purpose later
            v = judge.judge_place(w, step, step.pick, self.selector.shapes)
            if v.placed and v.at_rest:
                continue
            res.success = False
            res.failure = (f"at the end of the task (step {n}), a later step had disturbed it: {v.why} "
                           f"(now at {np.round(w.object_pose(step.pick)[:3, 3], 4).tolist()} m)")
            log.info("step %d: %s", k, res.failure)

    def run(self, task: Task, stop_on_failure: bool = True) -> RunResult:
        t0 = time.perf_counter()
        # before the robot acts: does physics leave every object where the twin puts it? (state restored)
        settle = self.world.settle_check()
        if settle["moved"]:
            log.info("%s", unsettled(settle))
        self._snap("start")
        steps = []
        for k, step in enumerate(task.steps, start=1):
            r = self.run_step(k, step)
            steps.append(r)
            log.info("step %d %s -> %s: %s%s", k, step.pick, step.goal_name, "ok" if r.success else "FAILED",
                     "" if r.success else f" ({r.failure})")
            if not r.success and stop_on_failure:
                break
        if len(steps) == len(task.steps) and all(s.success for s in steps):
            self.recheck(task, steps)
        self._snap("end")
        ok = len(steps) == len(task.steps) and all(s.success for s in steps)
        return RunResult(success=ok, steps=steps, collisions=sum(s.robot_collisions + s.object_collisions for s in steps),
                         plan_ms=list(self.plan_ms), sim_time=self.world.time - self.servo.t0,
                         wall_s=time.perf_counter() - t0, trajectories=self.trajs,
                         rollout=self.recorder.rollout(self.world), settle=settle, task_steps=task_step_list(task))
