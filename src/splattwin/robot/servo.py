"""Execution in physics: drive the arm's position servos along a trajectory, monitor contacts, record.

`Servo.track` runs one motion (or a hold) through `World.step` at the physics rate: the servo targets
are the trajectory's 100 Hz samples interpolated linearly at every physics step (the control step), with
its velocities fed forward (without, the Menagerie servos lag by kd/kp = 0.1 s: up to 74 mm at the TCP),
gravity/Coriolis compensation is applied by the world, every other step's contacts go to the monitor,
and every step is appended to the rollout recorder. A guard (e.g. a finger landing on the target)
can stop a motion: the arm then holds the commanded configuration of that instant.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from splattwin.robot.monitor import MonitorState, scan
from splattwin.robot.rollout import RolloutRecorder
from splattwin.robot.trajectory import Trajectory
from splattwin.robot.world import World

GUARD_HOLD = 0.15        # s the arm holds still after a guarded motion stopped
SCAN_EVERY = 2           # physics steps between contact scans
GUARD_EVERY = 4          # physics steps between guard checks


class Servo:
    """Executes motions on a World. `q` is the commanded arm configuration the servos hold now [n] rad;
    `elapsed` the simulated time (s) the last `track` ran: a whole number of physics steps, so the exported
    timeline (motion + hold) is built from it, not from the requested durations."""

    def __init__(self, world: World, recorder: RolloutRecorder | None = None):
        self.world = world
        self.recorder = recorder
        self.q = world.arm_q()
        self.t0 = world.time
        self.elapsed = 0.0

    def track(self, traj: Trajectory | None, grip: float, duration: float | None, monitor: MonitorState,
              guard: Callable[[], bool] | None = None, feed_forward: bool = True) -> float | None:
        """Drive the servos along traj (None: hold `q`) with gripper command `grip`, then hold the end
        for `duration` s; contacts go to `monitor`.

        feed_forward: command the reference velocity too (`World.step`), so the arm follows traj
        without the position servos' lag. guard: checked every few physics steps during the motion; when it fires the arm stops where it is
        commanded at that moment (held for GUARD_HOLD s) and the time into traj (s) is returned, else None.
        """
        w = self.world
        dt = float(w.model.opt.timestep)
        T = traj.duration if traj is not None else 0.0
        n = int(math.ceil((T + (duration or 0.0)) / dt))
        q_hold = traj.q[-1] if traj is not None else self.q
        w.command_gripper(grip)
        grip_width = float(w.gripper_width_of_ctrl(grip))
        # servo targets for every physics step at once (linear interpolation of the 100 Hz samples)
        ts = np.arange(n) * dt
        Q = traj.sample(np.minimum(ts, T)) if traj is not None else np.broadcast_to(q_hold, (n, len(q_hold)))
        # reference velocities, fed forward (World.step); zero once the motion has ended
        Qd = (np.stack([np.interp(ts, traj.t - traj.t[0], traj.qd[:, j], right=0.0) for j in range(traj.dof)], axis=-1)
              if traj is not None and feed_forward else None)
        rec, is_robot, data = self.recorder, w.is_robot, w.data
        i = 0
        stopped: float | None = None
        while i < n:
            w.step(Q[i], None if Qd is None else Qd[i])
            if rec is not None:
                rec.record(w.time - self.t0, data.qpos, Q[i], grip_width)
            if i % SCAN_EVERY == 0 and data.ncon:
                pairs, dist = w.contact_bodies()
                scan(monitor, pairs, dist, is_robot, t=w.time - self.t0)
            if guard is not None and stopped is None and i % GUARD_EVERY == 0 and ts[i] < T and guard():
                # a guarded move: stop and hold the commanded configuration of this instant
                stopped = float(ts[i])
                q_hold = Q[i].copy()
                n = i + 1 + int(math.ceil(GUARD_HOLD / dt))
                Q = np.broadcast_to(q_hold, (n, len(q_hold)))
                Qd = None
            i += 1
        self.q = np.array(q_hold, dtype=float)
        self.elapsed = n * dt
        return stopped
