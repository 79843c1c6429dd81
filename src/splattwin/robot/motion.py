"""Motion planning against the robot's belief: the planning scene, Cartesian segments, free-space paths
and their time parameterisation.

The planning scene is a `CollisionChecker` (planning.py) frozen at the belief: objects at their believed
poses, the arm where the servos hold it, the fingers at a given opening (`freeze`). Free motions keep
`object_clearance` (15 mm, ~3 sigma at 5 mm per axis) from the twin's objects; when that leaves no path
(objects close together) the plain planning margin still holds. Cartesian segments (approach, lift,
descent, retreat) follow a straight TCP line by IK (mink) and are checked by the caller with the
exceptions their contact allows (`allowing`). Joint paths become trajectories by TOPP-RA (timing.py).
Units: rad, m, s; T_world_tcp [4,4].
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import contextmanager

import numpy as np

from splattwin.robot.ik import ArmIK
from splattwin.robot.planning import PLAN_CHECKS, CollisionChecker, PlanningError, plan_path
from splattwin.robot.selection import Belief
from splattwin.robot.timing import time_parameterize
from splattwin.robot.trajectory import Trajectory
from splattwin.robot.world import World

log = logging.getLogger(__name__)

SPEED = 0.5               # fraction of the joint velocity/acceleration limits for free motions
SLOW = 0.15               # ... for Cartesian approach/descent
OBJECT_CLEARANCE = 0.015  # m kept from the twin's objects on free motions: ~3x the per-axis pose error
CARTESIAN_STEPS = 6       # IK waypoints along a straight TCP segment
MAX_JOINT_JUMP = 0.5      # rad between Cartesian waypoints: more means the IK switched branches
DENSE_CHECK = 0.002       # rad: resolution of the dense checks of Cartesian segments


def time_path(path: np.ndarray, vel: np.ndarray, acc: np.ndarray, joint_names: list[str], dt: float = 0.01,
              checker: CollisionChecker | None = None) -> Trajectory:
    """Joint path [M,n] -> Trajectory within vel/acc limits (TOPP-RA); with a checker, the sampled
    trajectory (spline corners included) is re-checked for collisions."""
    return time_parameterize(np.asarray(path, float), vel, acc, dt=dt, checker=checker, joint_names=list(joint_names))


def truncate(tr: Trajectory, t_stop: float) -> Trajectory:
    """The executed part of a trajectory stopped at t_stop (s from its start); ends at rest."""
    t_stop = float(np.clip(t_stop, 0.0, tr.duration))
    keep = tr.t - tr.t[0] < t_stop - 1e-9
    keep[0] = True
    if t_stop <= 1e-9:
        return Trajectory(tr.t[keep], tr.q[keep], np.zeros_like(tr.qd[keep]), np.zeros_like(tr.qdd[keep]),
                          list(tr.joint_names))
    # end exactly at the commanded configuration of the stop (what the servos held)
    return Trajectory(np.append(tr.t[keep], tr.t[0] + t_stop), np.vstack([tr.q[keep], tr.sample(tr.t[0] + t_stop)]),
                      np.vstack([tr.qd[keep], np.zeros(tr.dof)]), np.vstack([tr.qdd[keep], np.zeros(tr.dof)]),
                      list(tr.joint_names))


class MotionPlanner:
    """Plans arm motions on a World against a belief (object name -> T_world_obj, shared with the caller).

    plan_ms: wall time (ms) of every free-space planning query, in order.
    plan_checks: state validity checks each OMPL attempt may spend (`planning.PLAN_CHECKS`, ~1 s on 2 cores):
    a seeded run plans the same motions on a loaded machine; plan_time (s) caps an attempt's wall time only
    against a stuck query.
    """

    def __init__(self, world: World, belief: Belief, seed: int = 0, planner: str = "RRTConnect",
                 plan_time: float = 60.0, margin: float = 0.005, object_clearance: float = OBJECT_CLEARANCE,
                 plan_checks: int = PLAN_CHECKS):
        self.world, self.belief = world, belief
        self.robot = world.robot
        self.seed, self.planner, self.plan_time, self.plan_checks = seed, planner, plan_time, plan_checks
        self.object_clearance = float(object_clearance)
        self.ik = ArmIK(self.robot, world.base.matrix())
        self.checker = CollisionChecker(world.model, world.data, world.joints.arm_qpos, margin=margin,
                                        tcp_site=self.robot.tcp_site)
        self.plan_ms: list[float] = []

    @property
    def margin(self) -> float:
        return self.checker.margin

    # ---- planning scene ------------------------------------------------------------------------------
    def freeze(self, q_arm: np.ndarray, gripper_width: float, belief: Belief | None = None) -> None:
        """Freeze the belief poses (or `belief`), the arm at q_arm and the fingers `gripper_width` m apart
        into the checker, nothing attached."""
        d = self.world.planning_state(self.belief if belief is None else belief, q_arm, gripper_width)
        self.checker.detach()
        self.checker.set_world_state(d)

    @contextmanager
    def allowing(self, obj: str, others: list[str], penetration: float | None = None):
        """Contacts of `obj` with `others` are not collisions inside the block (up to `penetration` m)."""
        pairs = [(obj, b) for b in others]
        for a, b in pairs:
            self.checker.allow(a, b, penetration=penetration)
        try:
            yield
        finally:
            for a, b in pairs:
                self.checker.disallow(a, b)

    @contextmanager
    def carrying(self, obj: str, T_tcp_obj: np.ndarray):
        """`obj` moves with the TCP at T_tcp_obj [4,4] inside the block."""
        self.checker.attach(obj, T_tcp_obj)
        try:
            yield
        finally:
            self.checker.detach()

    # ---- paths --------------------------------------------------------------------------------------
    def cartesian(self, q0: np.ndarray, T0: np.ndarray, T1: np.ndarray, n: int = CARTESIAN_STEPS) -> np.ndarray | None:
        """Joint path [n+1,7] following the straight TCP segment T0 -> T1 (T1's orientation), or None
        when IK fails or jumps branches."""
        path = [q0]
        q = q0
        for s in np.linspace(0, 1, n + 1)[1:]:
            T = T1.copy()
            T[:3, 3] = (1 - s) * T0[:3, 3] + s * T1[:3, 3]
            q = self.ik.solve(T, q, q_posture=q)
            if q is None or np.max(np.abs(q - path[-1])) > MAX_JOINT_JUMP:
                return None
            path.append(q)
        return np.array(path)

    def path_clear(self, path: np.ndarray) -> bool:
        """Dense check of a Cartesian joint path in the current planning scene."""
        return self.checker.path_is_valid(path, DENSE_CHECK)

    def first_pair(self, path: np.ndarray, step: float = DENSE_CHECK) -> tuple[str, str] | None:
        """The first colliding geom pair along a joint path (for messages), or None."""
        for a, b in zip(path[:-1], path[1:]):
            k = max(1, int(math.ceil(float(np.max(np.abs(b - a))) / step)))
            for j in range(k + 1):
                pair = self.checker.first_collision(a + (j / k) * (b - a))
                if pair is not None:
                    return pair
        return self.checker.first_collision(path[0])

    def free_path(self, q_start: np.ndarray, q_goal: np.ndarray, label: str) -> np.ndarray:
        """Collision-free joint path [M,n] (OMPL) in the frozen scene, keeping object_clearance from every
        object but the held one where possible. Raises PlanningError."""
        t0 = time.perf_counter()
        seed = self.seed + len(self.plan_ms)
        held = self.checker.attached_body
        self.checker.set_clearance({o: self.object_clearance for o in self.world.objects if o != held})
        try:
            path = plan_path(self.checker, q_start, q_goal, time_limit=self.plan_time, planner=self.planner, seed=seed,
                             max_checks=self.plan_checks)
        except PlanningError as e:
            log.debug("%s: no path with %.0f mm object clearance (%s); planning with the margin", label,
                      self.object_clearance * 1e3, e)
            self.checker.set_clearance({})
            path = plan_path(self.checker, q_start, q_goal, time_limit=self.plan_time, planner=self.planner, seed=seed,
                             max_checks=self.plan_checks)
        finally:
            self.checker.set_clearance({})
            self.plan_ms.append((time.perf_counter() - t0) * 1e3)
        return path

    def trajectory(self, path: np.ndarray, speed: float, checked: bool = False) -> Trajectory:
        """Time-parameterised path at `speed` x the robot's limits; `checked`: re-check the sampled
        trajectory against the current planning scene."""
        return time_path(path, self.robot.vel_limits * speed, self.robot.acc_limits * speed, self.robot.arm_joints,
                         checker=self.checker if checked else None)

    def hold(self, q: np.ndarray, duration: float) -> Trajectory:
        """A stand-still at q [n] for `duration` s (while the gripper acts)."""
        return Trajectory.hold(q, duration, joint_names=self.robot.arm_joints)
