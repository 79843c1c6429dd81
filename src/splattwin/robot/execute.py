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
* free motions (transit, transfer) keep OBJECT_CLEARANCE (15 mm, ~3 sigma at 5 mm per axis) from the
  twin's objects, the short Cartesian segments near the target the planning margin (5 mm);
* the place pose is computed for the object where it sits in the hand after the grasp: `in_hand="sensed"`
  (default) reads it from the simulation, standing in for an in-hand estimate on the real cell (a wrist
  camera); `in_hand="planned"` assumes it sits as planned on the perceived pose (no in-hand sensing);
* fallbacks: a grasp whose transit finds no path (or no verified timing) gives way to the next ranked
  grasp, a place pose whose transfer finds no path to the grasp's next place pose, before the step fails.

Grasp heights follow the support surface under the object (table or the object below it, from the
belief), not the object mesh's bottom: reconstructed objects sink a few mm into the table, and the
fingertips (which reach 8.9 mm beyond the Panda's TCP, measured from the model) must keep the planning
margin above the surface in the closed pose.

Execution drives the arm's position servos (actuators 1-7) along time-parameterised trajectories with
gravity/Coriolis compensation added as applied joint forces (as the Franka controller does), and
monitors every contact. Per-step success as in the paper: the right object grasped and lifted; placed
inside the goal region and at rest after settling; no contact of the robot with anything but the target
and no contact of the carried object with anything during transfer.
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from splattwin.robot import grasp as grasp_mod
from splattwin.robot.ik import ArmIK
from splattwin.robot.task import Region, Step, Task
from splattwin.robot.trajectory import Trajectory
from splattwin.robot.world import World, hand_points_tcp, qpos_from_pose

log = logging.getLogger(__name__)

PREGRASP = 0.08          # m back along the approach before grasping
LIFT = 0.10              # m straight up after closing
PLACE_CLEARANCE = 0.004  # m released above the support
SPEED = 0.5              # fraction of the joint velocity/acceleration limits for free motions
SLOW = 0.15              # ... for Cartesian approach/descent
CLOSE_TIME = 0.6         # s for the gripper to close and the grasp to settle
OPEN_TIME = 0.4
SETTLE_TIME = 0.6        # s after the retreat before judging the placement
TILT_MAX = math.radians(10)
TOUCH_DEPTH = 0.001      # m: fingers may touch the target on the approach, not penetrate it deeper than this
FLOOR_TOLERANCE = 0.0015  # m: fingertips above the support by the planning margin plus this (IK, sampling)
GUARD_HOLD = 0.15        # s the arm holds still after a guarded approach stopped
LANDING_COS = math.cos(math.radians(45))  # hand-target contact normal this close to the approach axis = landing
MAX_TOUCHES = 2          # touch-based corrections of the believed object pose per step
OBJECT_CLEARANCE = 0.015  # m kept from the twin's objects on free motions: ~3x the per-axis pose error


@dataclass
class StepResult:
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
    grasp: dict = field(default_factory=dict)
    failure: str | None = None
    final_xyz: list = field(default_factory=list)


@dataclass
class RunResult:
    success: bool
    steps: list[StepResult]
    collisions: int
    plan_ms: list[float]
    sim_time: float
    wall_s: float
    trajectories: list[tuple[str, Trajectory]] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        return {"success": self.success, "collisions": self.collisions, "plan_ms": self.plan_ms,
                "sim_time": self.sim_time, "wall_s": self.wall_s, "steps": [asdict(s) for s in self.steps],
                "trajectories": [name for name, _ in self.trajectories]}


IN_HAND = ("sensed", "planned")  # where the transfer assumes the held object sits (module docstring)


class StepFailed(Exception):
    pass


# -- time parameterisation -------------------------------------------------------------------------

def time_path(path: np.ndarray, vel: np.ndarray, acc: np.ndarray, joint_names: list[str], dt: float = 0.01,
              checker=None) -> Trajectory:
    """Joint path [M,n] -> Trajectory within vel/acc limits (TOPP-RA via planning's timing module); with a
    checker, the sampled trajectory (spline corners included) is re-checked for collisions."""
    try:
        from splattwin.robot.timing import time_parameterize
    except ImportError:  # the timing module is written in parallel; keep a simple fallback meanwhile
        time_parameterize = None
    path = np.asarray(path, float)
    if time_parameterize is not None:
        return time_parameterize(path, vel, acc, dt=dt, checker=checker, joint_names=list(joint_names))
    seg = np.diff(path, axis=0)
    # per segment: trapezoid-free conservative timing (rest to rest), bounded by vel and acc
    durs = [max(float(np.max(np.abs(s) / vel)) * 1.5, float(np.max(np.sqrt(6 * np.abs(s) / acc)))) for s in seg]
    t_knots = np.concatenate([[0.0], np.cumsum(durs)])
    t = np.arange(0.0, t_knots[-1] + dt, dt)
    t[-1] = min(t[-1], t_knots[-1]) if len(t) > 1 else t[-1]
    k = np.clip(np.searchsorted(t_knots, t, side="right") - 1, 0, len(seg) - 1)
    s = np.clip((t - t_knots[k]) / np.maximum(np.asarray(durs)[k], 1e-9), 0, 1)
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5   # quintic: zero velocity/acceleration at each knot
    q = path[k] + seg[k] * s[:, None]
    t = np.maximum.accumulate(t + np.arange(len(t)) * 1e-12)
    qd = np.gradient(q, t, axis=0)
    return Trajectory(t, q, qd, np.gradient(qd, t, axis=0), list(joint_names))


def _truncate(tr: Trajectory, t_stop: float) -> Trajectory:
    """The executed part of a trajectory stopped at t_stop (s from its start); ends at rest."""
    t_stop = float(np.clip(t_stop, 0.0, tr.duration))
    keep = tr.t - tr.t[0] < t_stop - 1e-9
    keep[0] = True
    # end exactly at the commanded configuration of the stop (what the servos held)
    t = np.append(tr.t[keep], tr.t[0] + t_stop) if t_stop > 1e-9 else tr.t[keep]
    q = np.vstack([tr.q[keep], tr.sample(tr.t[0] + t_stop)]) if t_stop > 1e-9 else tr.q[keep]
    qd = np.vstack([tr.qd[keep], np.zeros(tr.dof)]) if t_stop > 1e-9 else np.zeros_like(tr.qd[keep])
    qdd = np.vstack([tr.qdd[keep], np.zeros(tr.dof)]) if t_stop > 1e-9 else np.zeros_like(tr.qdd[keep])
    return Trajectory(t, q, qd, qdd, list(tr.joint_names))


def _chain(*its):
    for it in its:
        yield from it


# -- the executor ----------------------------------------------------------------------------------

class Executor:
    """Runs a task on a World. `belief`: T_world_obj per object used for planning (default: the twin's)."""

    def __init__(self, world: World, belief: dict[str, np.ndarray] | None = None, seed: int = 0,
                 planner: str = "RRTConnect", plan_time: float = 1.0, margin: float = 0.005,
                 frame_cb: Callable[[str, World], None] | None = None, object_clearance: float = OBJECT_CLEARANCE,
                 in_hand: str = "sensed"):
        from splattwin.robot.planning import CollisionChecker

        if in_hand not in IN_HAND:
            raise ValueError(f"in_hand must be one of {IN_HAND}, got {in_hand!r}")
        self.in_hand = in_hand

        self.w = world
        self.m, self.d = world.model, world.data
        self.robot = world.robot
        self.belief = {o: (np.asarray(belief[o]) if belief and o in belief else world.manifest.object(o).pose)
                       for o in world.objects}
        self.seed, self.planner, self.plan_time = seed, planner, plan_time
        self.object_clearance = float(object_clearance)
        self.ik = ArmIK(self.robot, world.base.matrix())
        self.checker = CollisionChecker(self.m, self.d, world.arm_qpos_adr, margin=margin,
                                        tcp_site=self.robot.tcp_site)
        self.frame_cb = frame_cb
        self.plan_ms: list[float] = []
        self.trajs: list[tuple[str, Trajectory]] = []
        self._grasp_cache: dict[tuple[str, float], list[grasp_mod.Grasp]] = {}
        # how far the opened fingers reach beyond the TCP along the approach (m): grasp heights keep the
        # fingertips the planning margin above the support surface
        self.tip_depth = float(hand_points_tcp(world)[:, 2].max(initial=grasp_mod.TIP_DEPTH))
        self.is_robot = np.zeros(self.m.nbody, bool)
        self.is_robot[list(world.robot_bodies)] = True
        self.hand_bodies = list(self.robot.hand_bodies)
        self.grip_dofs = [int(self.m.joint(n).qposadr[0]) for n in self.robot.gripper_joints]
        self.arm_dofs = world.arm_dof_adr
        self.q = world.arm_q()
        self.sim_t0 = float(self.d.time)

    # ---- planning world state ----------------------------------------------------------------------
    def _plan_state(self, gripper_half: float) -> None:
        """Freeze belief poses, current arm and the given finger opening (m) into the checker (detached)."""
        import mujoco

        d = mujoco.MjData(self.m)
        d.qpos[:] = self.d.qpos
        for o, T in self.belief.items():
            a = self.w.obj_qpos_adr[o]
            d.qpos[a:a + 7] = qpos_from_pose(T)
        d.qpos[self.w.arm_qpos_adr] = self.q
        for a in self.grip_dofs:
            d.qpos[a] = gripper_half
        self.checker.detach()
        self.checker.set_world_state(d)

    @contextmanager
    def _allowing(self, obj: str, others: list[str], penetration: float | None = None):
        """Contacts of `obj` with `others` are not collisions inside the block (up to `penetration`)."""
        pairs = [(obj, b) for b in others]
        for a, b in pairs:
            self.checker.allow(a, b, penetration=penetration)
        try:
            yield
        finally:
            for a, b in pairs:
                self.checker.disallow(a, b)

    def _cartesian(self, q0: np.ndarray, T0: np.ndarray, T1: np.ndarray, n: int = 6) -> np.ndarray | None:
        """Joint path [n+1,7] following the straight TCP segment T0 -> T1 (same orientation)."""
        path = [q0]
        q = q0
        for s in np.linspace(0, 1, n + 1)[1:]:
            T = T1.copy()
            T[:3, 3] = (1 - s) * T0[:3, 3] + s * T1[:3, 3]
            q = self.ik.solve(T, q, q_posture=q)
            if q is None or np.max(np.abs(q - path[-1])) > 0.5:
                return None
            path.append(q)
        return np.array(path)

    def _first_pair(self, path: np.ndarray, step: float = 0.002) -> tuple[str, str] | None:
        """The first colliding geom pair along a joint path (for messages), or None."""
        for a, b in zip(path[:-1], path[1:]):
            k = max(1, int(math.ceil(float(np.max(np.abs(b - a))) / step)))
            for j in range(k + 1):
                pair = self.checker.first_collision(a + (j / k) * (b - a))
                if pair is not None:
                    return pair
        return self.checker.first_collision(path[0])

    def _plan(self, q_goal: np.ndarray, label: str) -> np.ndarray:
        from splattwin.robot.planning import plan_path

        from splattwin.robot.planning import PlanningError

        t0 = time.perf_counter()
        seed = self.seed + len(self.plan_ms)
        held = self.checker.attached_body
        # free motions keep object_clearance from the twin's objects (their poses carry the reconstruction
        # error); if that leaves no path (objects close together), the plain margin still holds
        self.checker.set_clearance({o: self.object_clearance for o in self.w.objects if o != held})
        try:
            path = plan_path(self.checker, self.q, q_goal, time_limit=self.plan_time, planner=self.planner, seed=seed)
        except PlanningError as e:
            log.debug("%s: no path with %.0f mm object clearance (%s); planning with the margin", label,
                      self.object_clearance * 1e3, e)
            self.checker.set_clearance({})
            path = plan_path(self.checker, self.q, q_goal, time_limit=self.plan_time, planner=self.planner, seed=seed)
        finally:
            self.checker.set_clearance({})
            self.plan_ms.append((time.perf_counter() - t0) * 1e3)
        return path

    def _grasps(self, obj: str) -> list[grasp_mod.Grasp]:
        """Candidates on the object's collision mesh, for the support surface it rests on (belief)."""
        import trimesh

        T_obj = self.belief[obj]
        floor_obj = round(self._support_height(obj) - float(T_obj[2, 3]), 4)   # object frame (upright)
        key = (obj, floor_obj)
        if key not in self._grasp_cache:
            entry = self.w.manifest.object(obj)
            mesh = trimesh.load(self.w.twin_dir / entry.collision_mesh, force="mesh")
            self._grasp_cache[key] = grasp_mod.synthesize(
                mesh.vertices, mesh.faces, max_width=self.robot.max_opening, floor=floor_obj,
                tip_depth=self.tip_depth, floor_clearance=self.checker.margin + FLOOR_TOLERANCE)
        return self._grasp_cache[key]

    def _support_height(self, obj: str) -> float:
        """World z (m) of the surface under `obj` in the belief: the table top, or the top of another
        object whose footprint holds obj's centre and whose top is below obj's centre. Reconstructed
        objects can sink a few mm into their support; the grasp must clear the surface, not the mesh."""
        T = self.belief[obj]
        z = float(self.w.manifest.background.table_height)
        for o, T_o in self.belief.items():
            if o == obj:
                continue
            ext = np.asarray(self.w.manifest.object(o).bbox_extent, float)
            p = np.linalg.inv(T_o) @ np.append(T[:3, 3], 1.0)
            top = float((T_o[:3, 3] + T_o[:3, 2] * ext[2] / 2)[2])
            if abs(p[0]) <= ext[0] / 2 and abs(p[1]) <= ext[1] / 2 and top < T[2, 3]:
                z = max(z, top)
        return z

    def _support_of(self, obj: str) -> list[str]:
        """Bodies the object rests on / touches now (for allowed contacts when it leaves them)."""
        names = {"world"}
        b = self.w.obj_body[obj]
        for k in range(self.d.ncon):
            g1, g2 = self.d.contact.geom[k]
            b1, b2 = int(self.m.geom_bodyid[g1]), int(self.m.geom_bodyid[g2])
            if b in (b1, b2):
                other = b2 if b1 == b else b1
                if not self.is_robot[other]:
                    names.add(self.w.body_name(other))
        return sorted(names)

    def _place_targets(self, step: Step, obj: str) -> list[np.ndarray]:
        """Candidate T_world_obj at the goal (upright, yaw variants), best first."""
        T_now = self.belief[obj]
        ext = np.asarray(self.w.manifest.object(obj).bbox_extent, float)
        yaw_now = math.atan2(T_now[1, 0], T_now[0, 0])
        if step.place_on is not None:
            T_sup = self.belief[step.place_on]
            sup_ext = np.asarray(self.w.manifest.object(step.place_on).bbox_extent, float)
            xyz = T_sup[:3, 3] + T_sup[:3, 2] * sup_ext[2] / 2
            z = xyz[2] + ext[2] / 2 + PLACE_CLEARANCE
            yaw_sup = math.atan2(T_sup[1, 0], T_sup[0, 0])
            yaws = [yaw_sup + k * math.pi / 2 for k in range(4)]
        else:
            reg = step.place_in
            xyz = reg.center.copy()
            z = self.w.manifest.background.table_height + ext[2] / 2 + PLACE_CLEARANCE
            yaws = [k * math.pi / 4 for k in range(8)]
            # keep only yaws whose footprint fits inside the region
            fits = []
            for y in yaws:
                c, s = abs(math.cos(y)), abs(math.sin(y))
                fx, fy = c * ext[0] + s * ext[1], s * ext[0] + c * ext[1]
                if fx <= reg.size[0] - 0.02 and fy <= reg.size[1] - 0.02:
                    fits.append(y)
            yaws = fits or yaws
        wrap = lambda a: (a + math.pi) % (2 * math.pi) - math.pi  # noqa: E731
        yaws.sort(key=lambda y: abs(wrap(y - yaw_now)))
        out = []
        for y in yaws:
            T = np.eye(4)
            c, s = math.cos(y), math.sin(y)
            T[:2, :2] = [[c, -s], [s, c]]
            T[:3, 3] = [xyz[0], xyz[1], z]
            out.append(T)
        return out

    # ---- step planning -------------------------------------------------------------------------------
    def plan_step(self, step: Step, res: StepResult) -> dict:
        """The best-ranked grasp + place pose with IK solutions and collision-free straight segments."""
        plan = next(self.step_candidates(step, res), None)
        if plan is None:
            raise StepFailed(self._no_candidate_message(step, res))
        return plan

    def _no_candidate_message(self, step: Step, res: StepResult) -> str:
        why = res.grasp.get("rejections", {})
        return (f"none of {res.grasp.get('tried', 0)} grasp candidates on {step.pick!r} has a reachable, "
                f"collision-free approach, lift and place (rejections: {why})")

    def step_candidates(self, step: Step, res: StepResult):
        """Yield feasible plans, best-ranked grasp first: dict with the grasp, q_pre, approach and lift
        paths [K,n], the first feasible place option (`place`) and an iterator over the grasp's further
        place options (`more_places`, computed lazily). Rejection counts go to res.grasp["rejections"]."""
        obj = step.pick
        T_obj = self.belief[obj]
        T_base = self.w.base.matrix()
        cands = grasp_mod.rank_grasps(self._grasps(obj), T_obj, T_base)
        why: dict[str, int] = {}
        res.grasp = {"candidates": len(cands), "tried": 0, "rejections": why}
        if not cands:
            raise StepFailed(f"no antipodal grasp fits the gripper on {obj!r}")
        support = self._support_of(obj)
        half_open = self.robot.max_opening / 2

        def reject(reason: str) -> None:
            why[reason] = why.get(reason, 0) + 1

        for g in cands[:16]:
            res.grasp["tried"] += 1
            T_grasp = T_obj @ g.T_obj_tcp
            T_pre = T_grasp.copy()
            T_pre[:3, 3] -= T_grasp[:3, 2] * PREGRASP
            q_pre = self.ik.solve(T_pre, self.q, q_posture=self.robot.home)
            if q_pre is None:
                reject("pregrasp IK")
                continue
            approach = self._cartesian(q_pre, T_pre, T_grasp)
            if approach is None:
                reject("approach IK")
                continue
            q_grasp = approach[-1]
            self._plan_state(half_open)
            # the open fingers straddle the target: they may touch it, not land on it or push into it
            with self._allowing(obj, self.hand_bodies, penetration=TOUCH_DEPTH):
                ok = self.checker.is_valid(q_pre) and self.checker.path_is_valid(approach, 0.002)
                if not ok and log.isEnabledFor(logging.DEBUG):  # name the pair while the exceptions still apply
                    log.debug("approach collision %s", self._first_pair(approach))
            if not ok:
                reject("approach collision")
                continue
            T_lift = T_grasp.copy()
            T_lift[:3, 3] += [0, 0, LIFT]
            lift = self._cartesian(q_grasp, T_grasp, T_lift)
            if lift is None:
                reject("lift IK")
                continue
            T_tcp_obj = np.linalg.inv(g.T_obj_tcp)
            self._plan_state(g.width / 2)
            self.checker.attach(obj, T_tcp_obj)
            with self._allowing(obj, support):
                ok = self.checker.path_is_valid(lift[1:], 0.002) if len(lift) > 2 else True
            self.checker.detach()
            if not ok:
                reject("lift collision")
                continue
            places = self._place_options(step, obj, g, lift[-1], reject)
            first = next(places, None)
            if first is None:
                continue
            res.grasp.update({"kind": g.kind, "width": g.width, "score": g.score})
            yield {"grasp": g, "q_pre": q_pre, "T_pre": T_pre, "T_grasp": T_grasp, "approach": approach,
                   "lift": lift, "T_tcp_obj": T_tcp_obj, "support": support, "place": first,
                   "more_places": places}

    def _place_options(self, step: Step, obj: str, g: grasp_mod.Grasp, q_lift: np.ndarray, reject,
                       T_obj_tcp: np.ndarray | None = None):
        """Yield place options for grasp g, best first: dict(T_place_obj, q_pp, descent, retreat).
        T_obj_tcp: the object held at this pose in the hand (default: the grasp's planned one)."""
        T_obj_tcp = g.T_obj_tcp if T_obj_tcp is None else T_obj_tcp
        T_tcp_obj = np.linalg.inv(T_obj_tcp)
        goal_support = [step.place_on] if step.place_on else ["world"]
        for T_place_obj in self._place_targets(step, obj):
            # the checker is shared with other planning between resumptions: set the carrying state anew
            self._plan_state(g.width / 2)
            self.checker.attach(obj, T_tcp_obj)
            try:
                T_place = T_place_obj @ T_obj_tcp
                T_pp = T_place.copy()
                T_pp[:3, 3] += [0, 0, LIFT]
                q_pp = self.ik.solve(T_pp, q_lift, q_posture=self.robot.home)
                if q_pp is None or not self.checker.is_valid(q_pp):
                    reject("pre-place IK/collision")
                    continue
                descent = self._cartesian(q_pp, T_pp, T_place)
                if descent is None:
                    reject("descent IK")
                    continue
                with self._allowing(obj, goal_support):
                    ok = self.checker.path_is_valid(descent[:-1], 0.002)
                if not ok:
                    reject("descent collision")
                    continue
                T_ret = T_place.copy()
                T_ret[:3, 3] -= T_place[:3, 2] * PREGRASP
                retreat = self._cartesian(descent[-1], T_place, T_ret)
                if retreat is None:
                    reject("retreat IK")
                    continue
                self.checker.detach()
                if not self._retreat_clear(obj, T_place_obj, retreat):
                    reject("retreat collision")
                    continue
            finally:
                self.checker.detach()
            yield {"T_place_obj": T_place_obj, "q_pp": q_pp, "descent": descent, "retreat": retreat}

    def _retreat_clear(self, obj: str, T_place_obj: np.ndarray, retreat: np.ndarray) -> bool:
        """The opened hand backs off the released object (at its place pose) without landing on it or
        touching anything else within the margin."""
        saved = self.belief[obj]
        self.belief[obj] = T_place_obj
        try:
            self._plan_state(self.robot.max_opening / 2)
        finally:
            self.belief[obj] = saved
        with self._allowing(obj, self.hand_bodies, penetration=TOUCH_DEPTH):
            ok = self.checker.path_is_valid(retreat, 0.002)
            if not ok and log.isEnabledFor(logging.DEBUG):
                log.debug("retreat collision %s", self._first_pair(retreat))
        return ok

    # ---- physics -------------------------------------------------------------------------------------
    def _track(self, traj: Trajectory | None, grip: float, duration: float | None, monitor: dict,
               guard: Callable[[], bool] | None = None) -> float | None:
        """Drive the servos along traj (or hold) with gripper ctrl `grip`; record contacts in monitor.

        guard: checked every few physics steps during the motion; when it fires the arm stops where it is
        commanded at that moment (held for GUARD_HOLD s) and the time into traj (s) is returned, else None.
        """
        import mujoco

        m, d = self.m, self.d
        dt = m.opt.timestep
        T = traj.duration if traj is not None else 0.0
        total = T + (duration or 0.0)
        n = int(math.ceil(total / dt))
        q_hold = traj.q[-1] if traj is not None else self.q
        d.ctrl[self.w.grip_act] = grip
        geom_body = m.geom_bodyid
        # servo targets for every physics step at once (linear interpolation of the 100 Hz samples)
        ts = np.arange(n) * dt
        Q = traj.sample(np.minimum(ts, T)) if traj is not None else np.broadcast_to(q_hold, (n, len(q_hold)))
        i = 0
        stopped: float | None = None
        while i < n:
            d.ctrl[self.w.arm_act] = Q[i]
            d.qfrc_applied[:] = 0.0
            d.qfrc_applied[self.arm_dofs] = d.qfrc_bias[self.arm_dofs]
            mujoco.mj_step(m, d)
            if i % 2 == 0 and d.ncon:
                self._scan(geom_body[d.contact.geom[: d.ncon]], d.contact.dist[: d.ncon], monitor)
            if guard is not None and stopped is None and i % 4 == 0 and ts[i] < T and guard():
                # a guarded move: stop and hold the commanded configuration of this instant
                stopped = float(ts[i])
                q_hold = Q[i].copy()
                n = i + 1 + int(math.ceil(GUARD_HOLD / dt))
                Q = np.broadcast_to(q_hold, (n, len(q_hold)))
            i += 1
        self.q = np.array(q_hold, dtype=float)
        return stopped

    def _landing_side(self, obj: str) -> float | None:
        """+1 / -1: the side (along the TCP y = closing axis) of a hand contact that pushes on the target
        along the approach direction — a finger landing on top of it instead of straddling it; None if
        there is none. (A Franka senses this as an external force along the approach axis; its torque
        about the TCP x axis gives the side.) Contacts with a normal across the approach (a finger
        grazing the target's side) do not count."""
        d, m = self.d, self.m
        nc = d.ncon
        if not nc:
            return None
        target = self.w.obj_body[obj]
        T = self.w.tcp_pose()
        geoms = d.contact.geom[:nc]
        b1, b2 = m.geom_bodyid[geoms[:, 0]], m.geom_bodyid[geoms[:, 1]]
        hand = self.is_robot
        sel = (((b1 == target) & hand[b2]) | ((b2 == target) & hand[b1])) & (d.contact.dist[:nc] < 0)
        if not sel.any():
            return None
        normals = d.contact.frame[:nc, :3][sel]
        along = np.abs(normals @ T[:3, 2]) > LANDING_COS
        if not along.any():
            return None
        side = (d.contact.pos[:nc][sel][along] - T[:3, 3]) @ T[:3, 1]
        return float(np.sign(side.mean())) or 1.0

    def _scan(self, bodies: np.ndarray, dist: np.ndarray, mon: dict) -> None:
        touching = dist < 0.0
        b = bodies[touching]
        if not len(b):
            mon["active"] = set()
            return
        rob = self.is_robot[b]
        active = set()
        target = mon["target"]
        for (b1, b2), (r1, r2) in zip(b.tolist(), rob.tolist()):
            if r1 and r2:
                continue
            if r1 or r2:
                other = b2 if r1 else b1
                if other == target:
                    continue
                active.add(("robot", min(b1, b2), max(b1, b2)))
            elif mon.get("carrying") and target in (b1, b2):
                other = b2 if b1 == target else b1
                if other in mon.get("allowed_obj", ()):
                    continue
                active.add(("object", min(b1, b2), max(b1, b2)))
        for key in active - mon["active"]:
            mon["events"].append(key)
        mon["active"] = active

    def _traj(self, path: np.ndarray, speed: float, label: str, checked: bool = False) -> Trajectory:
        tr = time_path(path, self.robot.vel_limits * speed, self.robot.acc_limits * speed, self.robot.arm_joints,
                       checker=self.checker if checked else None)
        self.trajs.append((label, tr))
        return tr

    def _hold(self, label: str, duration: float) -> None:
        """Record a stand-still (gripper action) in the exported trajectory."""
        self.trajs.append((label, Trajectory.hold(self.q, duration, joint_names=self.robot.arm_joints)))

    def _snap(self, label: str) -> None:
        if self.frame_cb is not None:
            self.frame_cb(label, self.w)

    # ---- one step -------------------------------------------------------------------------------------
    def _reach(self, step: Step, res: StepResult, k: int, mon: dict, tag: str = "") -> dict:
        """Plan and execute the transit to the pre-grasp of the best candidate whose transit plans; a
        candidate whose transit finds no path (or no verified timing) falls back to the next one."""
        from splattwin.robot.planning import PlanningError

        failures = []
        for plan in self.step_candidates(step, res):
            self._plan_state(self.robot.max_opening / 2)
            try:
                transit = self._plan(plan["q_pre"], f"step{k}_transit{tag}")
                tr = time_path(transit, self.robot.vel_limits * SPEED, self.robot.acc_limits * SPEED,
                               self.robot.arm_joints, checker=self.checker)
            except (PlanningError, RuntimeError) as e:
                failures.append(str(e))
                res.grasp.setdefault("fallbacks", []).append(f"transit: {e}"[:300])
                continue
            self.trajs.append((f"step{k}_transit{tag}", tr))
            self._track(tr, self.robot.gripper_open, 0.1, mon)
            return plan
        if failures:
            raise StepFailed(f"no transit to any of {len(failures)} feasible grasps on {step.pick!r}: "
                             f"{failures[0]}")
        raise StepFailed(self._no_candidate_message(step, res))

    def _approach(self, step: Step, res: StepResult, k: int, mon: dict) -> dict:
        """Reach and descend onto a grasp with a guarded approach. When a finger lands on the target (the
        object is further off its believed pose than the gripper's clearance along the closing axis),
        stop, back off to the pre-grasp, shift the believed object pose towards that finger by the
        clearance plus half a finger pad and re-plan: a touch-based correction, at most MAX_TOUCHES times."""
        obj = step.pick
        touches = 0
        T_twin = self.belief[obj].copy()
        while True:
            tag = f"_retry{touches}" if touches else ""
            plan = self._reach(step, res, k, mon, tag)
            tr = self._traj(plan["approach"], SLOW, f"step{k}_approach{tag}")
            landed: list[float] = []

            def guard() -> bool:
                side = self._landing_side(obj)
                if side is not None:
                    landed.append(side)
                return side is not None

            stopped = self._track(tr, self.robot.gripper_open, 0.1, mon, guard=guard)
            if stopped is None:
                res.grasp["touch_corrections"] = touches
                res.grasp["belief_correction_m"] = (self.belief[obj][:3, 3] - T_twin[:3, 3]).round(5).tolist()
                return plan
            side = landed[0]
            touches += 1
            self.trajs[-1] = (f"step{k}_approach{tag}_stopped", _truncate(tr, stopped))
            self._hold(f"step{k}_touch{touches}", GUARD_HOLD)
            if touches > MAX_TOUCHES:
                raise StepFailed(f"a finger landed on {obj!r} on the approach {touches} times "
                                 f"(the object is far from its twin pose)")
            # back off along the approach axis to the pre-grasp (the reverse of the approach so far)
            back = self._cartesian(self.q, self.ik.fk(self.q), plan["T_pre"])
            if back is None:
                raise StepFailed(f"no way back from a finger landing on {obj!r}")
            self._track(self._traj(back, SLOW, f"step{k}_backoff{touches}"), self.robot.gripper_open, 0.1, mon)
            g = plan["grasp"]
            shift = (self.robot.max_opening - g.width) / 2 + grasp_mod.PAD_HALF
            T = self.belief[obj].copy()
            T[:3, 3] += side * shift * plan["T_grasp"][:3, 1]
            log.info("finger landed on %s: belief shifted %.1f mm along the closing axis", obj, side * shift * 1e3)
            self.belief[obj] = T

    def run_step(self, k: int, step: Step) -> StepResult:
        from splattwin.robot.planning import PlanningError

        obj = step.pick
        res = StepResult(index=k, pick=obj, goal=step.goal_name)
        n_plan = len(self.plan_ms)
        mon = {"target": self.w.obj_body[obj], "active": set(), "events": [], "carrying": False}
        open_c, closed_c = self.robot.gripper_open, self.robot.gripper_closed
        try:
            plan = self._approach(step, res, k, mon)
            g = plan["grasp"]
            z0 = self.w.object_pose(obj)[2, 3]
            self._hold(f"step{k}_close", CLOSE_TIME)
            self._track(None, closed_c, CLOSE_TIME, mon)
            self._snap(f"step{k}_grasp")
            mon["carrying"] = True
            mon["allowed_obj"] = {self.w.model.body(s).id for s in plan["support"]}
            self._track(self._traj(plan["lift"], SLOW, f"step{k}_lift"), closed_c, 0.2, mon)
            res.lifted_m = float(self.w.object_pose(obj)[2, 3] - z0)
            res.grasped = bool(res.lifted_m > 0.6 * LIFT and self._held(obj))
            if not res.grasped:
                raise StepFailed(f"{obj!r} not lifted with the gripper (rose {res.lifted_m * 100:.1f} cm)")
            # transfer: plan with the object attached where it sits in the hand now (sensed, or as planned:
            # the jaws centre it along the closing axis); a place pose whose transfer finds no path falls
            # back to the grasp's next place option
            if self.in_hand == "sensed":
                T_tcp_obj = np.linalg.inv(self.w.tcp_pose()) @ self.w.object_pose(obj)
            else:
                T_tcp_obj = np.linalg.inv(g.T_obj_tcp)
            self.belief[obj] = self.ik.fk(self.q) @ T_tcp_obj
            # place poses for the object where it was sensed in the hand (it may have settled off the
            # planned grasp), then the planned ones (all there is without in-hand sensing)
            held = (self._place_options(step, obj, g, self.q, lambda reason: None, T_obj_tcp=np.linalg.inv(T_tcp_obj))
                    if self.in_hand == "sensed" else iter(()))
            place, transfer_traj, failures = None, None, []
            for option in _chain(held, [plan["place"]], plan["more_places"]):
                self._plan_state(g.width / 2)
                self.checker.attach(obj, T_tcp_obj)
                try:
                    transfer = self._plan(option["q_pp"], f"step{k}_transfer")
                    transfer_traj = self._traj(transfer, SPEED, f"step{k}_transfer", checked=True)
                    place = option
                    break
                except (PlanningError, RuntimeError) as e:
                    failures.append(str(e))
                    res.grasp.setdefault("fallbacks", []).append(f"transfer: {e}"[:300])
                finally:
                    self.checker.detach()
            if place is None:
                raise StepFailed(f"no transfer path to any of {len(failures)} place poses for {obj!r}: "
                                 f"{failures[0] if failures else 'none feasible'}")
            self._track(transfer_traj, closed_c, 0.1, mon)
            goal_body = self.w.model.body(step.place_on).id if step.place_on else 0
            mon["allowed_obj"] = {goal_body, 0}
            self._track(self._traj(place["descent"], SLOW, f"step{k}_descent"), closed_c, 0.1, mon)
            mon["carrying"] = False
            self._hold(f"step{k}_open", OPEN_TIME)
            self._track(None, open_c, OPEN_TIME, mon)
            self._snap(f"step{k}_release")
            self._track(self._traj(place["retreat"], SLOW, f"step{k}_retreat"), open_c, SETTLE_TIME, mon)
            self.belief[obj] = place["T_place_obj"]
            self._judge_place(step, obj, res)
        except StepFailed as e:
            res.failure = str(e)
        except PlanningError as e:  # report, do not crash the trial
            res.failure = f"planning: {e}"
        res.plan_ms = self.plan_ms[n_plan:]
        events = mon["events"]
        res.robot_collisions = sum(1 for e in events if e[0] == "robot")
        res.object_collisions = sum(1 for e in events if e[0] == "object")
        res.collision_pairs = sorted({f"{e[0]}: {self.w.body_name(e[1])} - {self.w.body_name(e[2])}" for e in events})
        res.final_xyz = self.w.object_pose(obj)[:3, 3].round(4).tolist()
        res.success = bool(res.failure is None and res.grasped and res.placed and res.at_rest
                           and res.robot_collisions == 0 and res.object_collisions == 0)
        if res.failure is None and not res.success:
            res.failure = ("collision: " + "; ".join(res.collision_pairs)) if res.collision_pairs else \
                "not placed inside the goal region at rest"
        return res

    def _held(self, obj: str) -> bool:
        """Both fingers touch the object."""
        b = self.w.obj_body[obj]
        fingers = {self.m.body(n).id for n in self.robot.hand_bodies if n != self.m.body(self.m.site_bodyid[self.w.tcp_site]).name}
        touched = set()
        for k in range(self.d.ncon):
            g1, g2 = self.d.contact.geom[k]
            b1, b2 = int(self.m.geom_bodyid[g1]), int(self.m.geom_bodyid[g2])
            if b in (b1, b2):
                touched.add(b2 if b1 == b else b1)
        return len(fingers & touched) >= min(2, len(fingers))

    def _judge_place(self, step: Step, obj: str, res: StepResult) -> None:
        T = self.w.object_pose(obj)
        dof = int(self.m.jnt_dofadr[self.m.joint(f"{obj}/free").id])
        speed = float(np.linalg.norm(self.d.qvel[dof:dof + 3]))
        tilt = math.acos(float(np.clip(T[2, 2], -1, 1)))
        ext = np.asarray(self.w.manifest.object(obj).bbox_extent, float)
        res.at_rest = bool(speed < 0.01 and tilt < TILT_MAX)
        if step.place_on is not None:
            Ts = self.w.object_pose(step.place_on)
            sup_ext = np.asarray(self.w.manifest.object(step.place_on).bbox_extent, float)
            p = np.linalg.inv(Ts) @ np.append(T[:3, 3], 1.0)
            inside = abs(p[0]) <= sup_ext[0] / 2 and abs(p[1]) <= sup_ext[1] / 2
            on_top = abs(p[2] - (sup_ext[2] / 2 + ext[2] / 2)) < 0.015
            res.placed = bool(inside and on_top)
        else:
            reg: Region = step.place_in
            # every bounding-box corner of the object inside the region, resting on the table
            corners = np.array([[sx * ext[0] / 2, sy * ext[1] / 2, 0, 1] for sx in (-1, 1) for sy in (-1, 1)])
            xy = (T @ corners.T).T[:, :2]
            inside = all(reg.contains_xy(c) for c in xy)
            on_table = abs(T[2, 3] - ext[2] / 2 - self.w.manifest.background.table_height) < 0.015
            res.placed = bool(inside and on_table)

    # ---- whole task -----------------------------------------------------------------------------------
    def run(self, task: Task, stop_on_failure: bool = True) -> RunResult:
        t0 = time.perf_counter()
        self._snap("start")
        steps = []
        for k, step in enumerate(task.steps, start=1):
            r = self.run_step(k, step)
            steps.append(r)
            log.info("step %d %s -> %s: %s%s", k, step.pick, step.goal_name, "ok" if r.success else "FAILED",
                     "" if r.success else f" ({r.failure})")
            if not r.success and stop_on_failure:
                break
        self._snap("end")
        ok = len(steps) == len(task.steps) and all(s.success for s in steps)
        return RunResult(success=ok, steps=steps, collisions=sum(s.robot_collisions + s.object_collisions for s in steps),
                         plan_ms=list(self.plan_ms), sim_time=float(self.d.time - self.sim_t0),
                         wall_s=time.perf_counter() - t0, trajectories=self.trajs)
