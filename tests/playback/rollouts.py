"""Synthetic rollouts for the playback tests: the object carried along a path, the arm interpolated."""

from __future__ import annotations

import numpy as np

from splattwin.robot.rollout import Rollout

from .conftest import OBJ_CENTRE

HOME = np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])
REACH = np.array([0.3, 0.5, -0.2, -2.0, 0.1, 2.4, 0.5])


def synthetic_rollout(duration: float = 0.6, rate: float = 100.0) -> Rollout:
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    s = t / t[-1]
    q = HOME + s[:, None] * (REACH - HOME)
    width = 0.08 - 0.05 * s
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, 3] = OBJ_CENTRE + s[:, None] * np.array([-0.12, 0.1, 0.0]) + np.sin(np.pi * s)[:, None] * [0, 0, 0.05]
    yaw = 0.8 * s
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    qpos = np.concatenate([q, width[:, None] / 2, width[:, None] / 2], 1)
    step = np.where(s < 0.1, -1, 1)
    return Rollout(t=t, qpos=qpos, q_arm=q, gripper_width=width, action_q_arm=q + 0.01, action_gripper=width - 0.002,
                   object_poses={"blue_box": T}, joint_names=[f"joint{i + 1}" for i in range(7)], step_index=step)
