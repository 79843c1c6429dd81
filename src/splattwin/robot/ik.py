"""Inverse kinematics of the TCP site with mink (differential IK, QP solved by daqp).

Tasks: FrameTask on the TCP site (position + orientation), a light PostureTask towards a preferred
configuration (resolves the Panda's redundancy, keeps solutions near the seed) and ConfigurationLimit.
Runs on a robot-only model (no free joints) with the base at the world's base pose, so targets are given
directly in the twin/world frame: T_world_tcp [4,4], metres.
"""

from __future__ import annotations

import numpy as np

from splattwin.robot.assets import RobotModel


class ArmIK:
    """IK solver for one robot at one base pose. Not thread-safe (one configuration buffer)."""

    def __init__(self, robot: RobotModel, T_world_base: np.ndarray, posture_cost: float = 1e-2):
        import mink

        from splattwin.robot.world import JointMap
        from splattwin.transforms import quat_wxyz_from_matrix

        spec = robot.spec(visual=False)
        root = spec.body(robot.root_body)
        root.pos = np.asarray(T_world_base)[:3, 3].tolist()
        root.quat = quat_wxyz_from_matrix(np.asarray(T_world_base)[:3, :3]).tolist()
        self.model = spec.compile()
        self.robot = robot
        self.joints = JointMap.from_model(self.model, robot)
        self.cfg = mink.Configuration(self.model)
        self.frame = mink.FrameTask(robot.tcp_site, "site", position_cost=1.0, orientation_cost=1.0, lm_damping=1e-3)
        self.posture = mink.PostureTask(self.model, cost=posture_cost)
        self.limits = [mink.ConfigurationLimit(self.model, gain=0.95, min_distance_from_limits=0.01)]
        self.lower = self.model.jnt_range[[self.model.joint(n).id for n in robot.arm_joints], 0]
        self.upper = self.model.jnt_range[[self.model.joint(n).id for n in robot.arm_joints], 1]

    def _full_q(self, q_arm: np.ndarray) -> np.ndarray:
        return self.joints.full(q_arm, self.model.qpos0)

    def fk(self, q_arm: np.ndarray) -> np.ndarray:
        """T_world_tcp [4,4] at arm configuration q_arm [n] (rad)."""
        self.cfg.update(self._full_q(q_arm))
        return self.cfg.get_transform_frame_to_world(self.robot.tcp_site, "site").as_matrix()

    def solve(self, T_world_tcp: np.ndarray, q_seed: np.ndarray, q_posture: np.ndarray | None = None,
              pos_tol: float = 5e-4, rot_tol: float = np.radians(0.5), max_iters: int = 300,
              dt: float = 0.05) -> np.ndarray | None:
        """Arm joints [n] (rad) putting the TCP at T_world_tcp, or None if not reached within tolerance."""
        import mink

        self.cfg.update(self._full_q(q_seed))
        self.frame.set_target(mink.SE3.from_matrix(np.asarray(T_world_tcp, dtype=np.float64)))
        self.posture.set_target(self._full_q(q_posture if q_posture is not None else q_seed))
        tasks = [self.frame, self.posture]
        best = np.inf
        stall = 0
        for _ in range(max_iters):
            err = self.frame.compute_error(self.cfg)
            e = np.linalg.norm(err[:3]) + 0.1 * np.linalg.norm(err[3:])
            if np.linalg.norm(err[:3]) < pos_tol and np.linalg.norm(err[3:]) < rot_tol:
                q = self.joints.arm(self.cfg.q)
                if np.all(q >= self.lower - 1e-6) and np.all(q <= self.upper + 1e-6):
                    return np.clip(q, self.lower, self.upper)
                return None
            # the posture task biases the solution; once the TCP error stops shrinking it only holds the
            # TCP off target, so finish with the frame task alone
            stall = stall + 1 if e > 0.9 * best else 0
            best = min(best, e)
            if stall >= 5 and len(tasks) == 2:
                tasks = [self.frame]
            elif stall >= 30:
                return None   # a local minimum away from the target: unreachable from this seed
            vel = mink.solve_ik(self.cfg, tasks, dt, solver="daqp", damping=1e-3, limits=self.limits)
            self.cfg.integrate_inplace(vel, dt)
        return None
