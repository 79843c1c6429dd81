from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from splattwin.robot.ik import ArmIK
from splattwin.robot.world import BasePose


def _rot(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    # TCP z down, closing axis rotated by yaw
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([1.0, -1.0, -1.0])


@pytest.mark.parametrize("xyz,yaw", [((0.1, 0.1, 0.1), 0.3), ((-0.1, -0.25, 0.05), -1.2), ((0.2, 0.2, 0.3), 2.0)])
def test_ik_reaches_pose(panda, xyz, yaw):
    base = BasePose()
    ik = ArmIK(panda, base.matrix())
    T = np.eye(4)
    T[:3, :3] = _rot(yaw)
    T[:3, 3] = xyz
    q = ik.solve(T, panda.home)
    assert q is not None
    # independent forward kinematics: the full Panda model placed at the base pose
    spec = panda.spec(visual=False)
    spec.body(panda.root_body).pos = [base.x, base.y, base.z]
    m = spec.compile()
    d = mujoco.MjData(m)
    d.qpos[[m.joint(n).qposadr[0] for n in panda.arm_joints]] = q
    mujoco.mj_kinematics(m, d)
    sid = m.site(panda.tcp_site).id
    assert np.linalg.norm(d.site_xpos[sid] - T[:3, 3]) < 1e-3                       # 1 mm
    R = d.site_xmat[sid].reshape(3, 3)
    angle = math.acos(np.clip((np.trace(R.T @ T[:3, :3]) - 1) / 2, -1, 1))
    assert angle < math.radians(1.0)                                                # 1 degree
    lo, hi = m.jnt_range[[m.joint(n).id for n in panda.arm_joints]].T
    assert np.all(q >= lo) and np.all(q <= hi)


def test_ik_out_of_reach_returns_none(panda):
    ik = ArmIK(panda, BasePose().matrix())
    T = np.eye(4)
    T[:3, :3] = _rot(0.0)
    T[:3, 3] = [0.8, 0.0, 0.1]          # 1.3 m from the base: beyond the Panda's 0.855 m reach
    assert ik.solve(T, panda.home) is None
