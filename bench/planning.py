"""Benchmark: joint-space planning time per pick-and-place motion on the Menagerie Panda (OMPL + MuJoCo).

World (twin frame, table top z = 0): table, robot base at x = -0.50 facing +x, the paper's objects as
boxes (cardboard box, blue box, yellow cube, hammer as a bar), a 32 cm bottle in the way, a target
region. Motions per step of the paper's three-step task: home → pre-grasp (10 cm above the object,
top-down), lift (object attached) → pre-place (above its goal), pre-place → home. Goals come from the robot stage's mink IK.

Rows, side by side on the same motions and seeds:
  ours        plan_path: straight line first, OMPL RRTConnect at 0.002, simplify, dense re-check with a
              2.5 mm swept-displacement bound (certifies >= 2.5 mm clearance along the motion)
  ompl-fine   RRTConnect always, resolution 0.0005, simplify (stack-notes baseline), no re-check
  ompl-coarse RRTConnect always, resolution 0.002, simplify, no re-check (fast but clips thin geometry)
For every path: re-check at 0.0005 rad with a 2.5 mm margin → "clipped" counts paths that come closer
than 2.5 mm to something between the planner's checks.
Last line: JSON with plan_ms_median (ours), plan_ms_p90, clipped, the peers' medians and clips.

Usage: python bench/planning.py [--repeats 5]
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import statistics
import time

import mujoco
import numpy as np

from splattwin.robot.assets import RobotModel
from splattwin.robot.ik import ArmIK
from splattwin.robot.planning import CollisionChecker, _ompl_solve, _seed_ompl, plan_path

OBJECTS = {  # name: (centre x, y, half extents)
    "cardboard_box": (0.15, 0.25, (0.15, 0.12, 0.06)),
    "blue_box": (0.0, -0.2, (0.03, 0.03, 0.05)),
    "yellow_cube": (0.22, -0.02, (0.025, 0.025, 0.025)),
    "hammer": (-0.12, 0.12, (0.15, 0.015, 0.015)),
    "bottle": (0.05, 0.0, (0.03, 0.03, 0.16)),       # tall obstacle between the objects: forces detours
}
TASK = [("blue_box", "cardboard_box"), ("yellow_cube", "blue_box@goal"), ("hammer", "target")]
TARGET = (0.10, -0.30)


def build():
    robot = RobotModel.panda()
    spec = robot.spec()
    root = spec.body(robot.root_body)
    root.pos = [-0.5, 0.0, 0.0]
    wb = spec.worldbody
    wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.45, 0.6, 0.02], pos=[0.0, 0.0, -0.02])
    for name, (x, y, h) in OBJECTS.items():
        b = wb.add_body(name=name, pos=[x, y, h[2]])
        b.add_freejoint()
        b.add_geom(name=f"{name}_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(h))
    m = spec.compile()
    d = mujoco.MjData(m)
    adr = [int(m.joint(n).qposadr[0]) for n in robot.arm_joints]
    d.qpos[adr] = robot.home
    for n in robot.gripper_joints:
        d.qpos[m.joint(n).qposadr[0]] = 0.04
    mujoco.mj_kinematics(m, d)
    T_base = np.eye(4)
    T_base[:3, 3] = [-0.5, 0.0, 0.0]
    return robot, m, d, adr, ArmIK(robot, T_base)


def build_wall():
    """Panda at the origin, table, and an 8 mm wall between two arm configurations (as in the tests)."""
    robot = RobotModel.panda()
    spec = robot.spec()
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.6, 0.6, 0.02],
                            pos=[0.5, 0, -0.02])
    spec.worldbody.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.25, 0.004, 0.2],
                            pos=[0.5, 0, 0.2])
    m = spec.compile()
    d = mujoco.MjData(m)
    d.qpos[7:9] = 0.04
    adr = [int(m.joint(n).qposadr[0]) for n in robot.arm_joints]
    qa = np.array([0.6, 0.3, 0.0, -2.0, 0.0, 1.57079, -0.7853])
    qb = qa * np.array([-1, 1, 1, 1, 1, 1, 1])
    return (CollisionChecker(m, d, adr, margin=0.005, tcp_site=robot.tcp_site),
            CollisionChecker(m, d, adr, margin=0.0025, tcp_site=robot.tcp_site), qa, qb)


def down(x, y, z, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [x, y, z]
    return T


def motions(robot, ik):
    """[(label, q_start, q_goal, attached, T_tcp_obj)] for the three-step task."""
    out = []
    home = robot.home.copy()
    tops = {n: 2 * h[2] for n, (_, _, h) in OBJECTS.items()}
    goals = {"cardboard_box": (OBJECTS["cardboard_box"][0], OBJECTS["cardboard_box"][1], tops["cardboard_box"]),
             "target": (TARGET[0], TARGET[1], 0.0)}
    goals["blue_box@goal"] = (goals["cardboard_box"][0], goals["cardboard_box"][1],
                              tops["cardboard_box"] + tops["blue_box"])
    def solve(T, seed):
        for s in (seed, home):
            q = ik.solve(T, s, q_posture=home)
            if q is not None:
                return q
        return None

    q = home
    for obj, where in TASK:
        x, y, h = OBJECTS[obj]
        yaw = np.pi / 2 if obj == "hammer" else 0.0
        T_pre = down(x, y, tops[obj] + 0.10, yaw)
        q_pre = solve(T_pre, q)
        T_grasp = down(x, y, tops[obj] - min(0.02, h[2]), yaw)
        T_lift = down(x, y, tops[obj] + 0.15, yaw)
        q_lift = solve(T_lift, q_pre)
        gx, gy, gz = goals[where]
        T_place = down(gx, gy, gz + tops[obj] + 0.08, yaw)
        q_place = solve(T_place, q_lift)
        if q_pre is None or q_lift is None or q_place is None:
            raise RuntimeError(f"IK failed for {obj}: {[x is None for x in (q_pre, q_lift, q_place)]}")
        T_obj = np.eye(4)
        T_obj[:3, 3] = [x, y, h[2]]
        T_tcp_obj = np.linalg.inv(T_grasp) @ T_obj
        out.append((f"{obj}: home->pregrasp", q, q_pre, None, None))
        out.append((f"{obj}: lift->preplace", q_lift, q_place, obj, T_tcp_obj))
        out.append((f"{obj}: preplace->home", q_place, home, None, None))
        q = home
    return out


def run_peer(kind, checker, qa, qb, seed):
    t0 = time.perf_counter()
    if kind == "ours":
        path = plan_path(checker, qa, qb, seed=seed)
    else:
        _seed_ompl(seed)
        res = 0.0005 if kind == "ompl-fine" else 0.002
        path = _ompl_solve(checker, qa, qb, 1.0, "RRTConnect", res, True)
    return (time.perf_counter() - t0) * 1e3, path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    robot, m, d, adr, ik = build()
    checker = CollisionChecker(m, d, adr, margin=0.005, tcp_site=robot.tcp_site)
    ref = CollisionChecker(m, d, adr, margin=0.0025, tcp_site=robot.tcp_site)   # margin - max_sweep
    mots = motions(robot, ik)
    peers = ["ours", "ompl-fine", "ompl-coarse"]
    ms = {p: [] for p in peers}
    clipped = {p: 0 for p in peers}
    straight = 0
    per_motion = {}
    for rep in range(args.repeats):
        for k, (label, qa, qb, obj, T) in enumerate(mots):
            if obj is not None:
                checker.attach(obj, T)
                ref.attach(obj, T)
            for p in peers:
                t, path = run_peer(p, checker, qa, qb, seed=1 + rep * 100 + k)
                ms[p].append(t)
                if p == "ours":
                    per_motion.setdefault(label, []).append(t)
                    straight += len(path) == 2
                if path is None or not ref.path_is_valid(path, resolution=0.0005):
                    clipped[p] += 1
            checker.detach()
            ref.detach()
    # over a thin wall: every query needs the planner
    wchecker, wref, wa, wb = build_wall()
    wall_ms = {p: [] for p in peers}
    wall_clipped = {p: 0 for p in peers}
    for seed in range(10):
        for p in peers:
            t, path = run_peer(p, wchecker, wa, wb, seed=seed)
            wall_ms[p].append(t)
            if path is None or not wref.path_is_valid(path, resolution=0.0005):
                wall_clipped[p] += 1
    n = len(ms["ours"])
    print(f"{'motion':34s} {'ours median ms':>15s}")
    for label, ts in per_motion.items():
        print(f"{label:34s} {statistics.median(ts):15.1f}")
    print()
    print(f"{'planner':12s} {'median ms':>10s} {'p90 ms':>8s} {'clipped':>8s}   ({n} motions each)")
    for p in peers:
        print(f"{p:12s} {statistics.median(ms[p]):10.1f} {np.percentile(ms[p], 90):8.1f} {clipped[p]:8d}")
    print()
    print(f"{'over wall':12s} {'median ms':>10s} {'p90 ms':>8s} {'clipped':>8s}   (10 seeded queries each)")
    for p in peers:
        print(f"{p:12s} {statistics.median(wall_ms[p]):10.1f} {np.percentile(wall_ms[p], 90):8.1f} "
              f"{wall_clipped[p]:8d}")
    print(json.dumps({
        "plan_ms_median": round(statistics.median(ms["ours"]), 2),
        "plan_ms_p90": round(float(np.percentile(ms["ours"], 90)), 2),
        "motions": n, "straight_line": straight, "clipped": clipped["ours"],
        "ompl_fine_ms_median": round(statistics.median(ms["ompl-fine"]), 2), "ompl_fine_clipped": clipped["ompl-fine"],
        "ompl_coarse_ms_median": round(statistics.median(ms["ompl-coarse"]), 2),
        "ompl_coarse_clipped": clipped["ompl-coarse"],
        "wall_plan_ms_median": round(statistics.median(wall_ms["ours"]), 2), "wall_clipped": wall_clipped["ours"],
        "wall_ompl_fine_ms_median": round(statistics.median(wall_ms["ompl-fine"]), 2),
        "wall_ompl_fine_clipped": wall_clipped["ompl-fine"],
        "wall_ompl_coarse_ms_median": round(statistics.median(wall_ms["ompl-coarse"]), 2),
        "wall_ompl_coarse_clipped": wall_clipped["ompl-coarse"],
    }))


if __name__ == "__main__":
    main()
