"""Collision checker and OMPL planning on the Menagerie Panda in a small world (table, thin wall, objects).

Reference for "collision-free": an independent dense sweep with plain MuJoCo on the *unmodified* model
(zero margin), counting any penetrating contact between a robot body and the world.
"""

from __future__ import annotations

import statistics
import time

import mujoco
import numpy as np
import pytest

from splattwin.robot.assets import panda_model_path
from splattwin.robot.planning import CollisionChecker, PlanningError, interpolate_path, plan_path

HOME = np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])
# either side of the wall (TCP at x 0.36, y ±0.25, z 0.2): the straight joint-space line crosses it
Q_LEFT = np.array([0.6, 0.3, 0.0, -2.0, 0.0, 1.57079, -0.7853])
Q_RIGHT = np.array([-0.6, 0.3, 0.0, -2.0, 0.0, 1.57079, -0.7853])
WALL_HALF = (0.25, 0.004, 0.2)     # 8 mm thick, 40 cm tall, centred at x 0.5 on the table


def build_world(wall: bool = True) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(panda_model_path()))
    for k in list(spec.keys):
        spec.delete(k)
    wb = spec.worldbody
    wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.6, 0.6, 0.02], pos=[0.5, 0, -0.02])
    if wall:
        wb.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(WALL_HALF), pos=[0.5, 0, 0.2])
    b = wb.add_body(name="box", pos=[0.4, 0.4, 0.03])      # resting on the table: world-world contact
    b.add_freejoint()
    b.add_geom(name="box_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.03, 0.03])
    w = wb.add_body(name="wide", pos=[-0.5, 0.6, 0.03])     # parked far away; held in the attach test
    w.add_freejoint()
    w.add_geom(name="wide_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.06, 0.06, 0.03])
    p = wb.add_body(name="probe", pos=[0.0, -0.6, 0.5])     # parked far away; tests move it
    p.add_freejoint()
    p.add_geom(name="probe_geom", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02])
    return spec.compile()


@pytest.fixture(scope="module")
def world():
    m = build_world()
    d = mujoco.MjData(m)
    d.qpos[:7] = HOME
    d.qpos[7:9] = 0.04                  # fingers open
    mujoco.mj_kinematics(m, d)
    return m, d


@pytest.fixture()
def checker(world):
    m, d = world
    return CollisionChecker(m, d, list(range(7)), margin=0.005)


def robot_world_penetration(m: mujoco.MjModel, d0: mujoco.MjData, path: np.ndarray, step: float = 0.00025):
    """Reference sweep: deepest penetration (m, <= 0 means none) between arm bodies and world geoms."""
    d = mujoco.MjData(m)
    d.qpos[:] = d0.qpos
    arm_bodies = set(range(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "link1"), m.nbody)) - {
        mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("box", "wide", "probe")}
    worst = 0.0
    for q in interpolate_path(path, step):
        d.qpos[:7] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        for k in range(d.ncon):
            b1, b2 = (int(m.geom_bodyid[g]) for g in d.contact.geom[k])
            if (b1 in arm_bodies) != (b2 in arm_bodies):
                worst = max(worst, -float(d.contact.dist[k]))
    return worst


def test_world_contacts_ignored_and_home_valid(checker):
    # the box rests on the table (a world-world contact) and must not make anything invalid
    assert checker.is_valid(HOME)
    assert checker.is_valid(Q_LEFT) and checker.is_valid(Q_RIGHT)
    assert checker.first_collision(HOME) is None


def test_straight_line_shortcut_returns_two_points(checker):
    q_goal = HOME + np.array([0.3, -0.2, 0.1, 0.2, 0.0, -0.1, 0.4])
    path = plan_path(checker, HOME, q_goal, seed=0)
    assert path.shape == (2, 7)
    np.testing.assert_array_equal(path[0], HOME)
    np.testing.assert_array_equal(path[1], q_goal)


def test_wall_path_found_dense_and_reproducible(world, checker):
    m, d = world
    assert not checker.path_is_valid(np.stack([Q_LEFT, Q_RIGHT]))   # the wall blocks the straight line
    half = CollisionChecker(m, d, list(range(7)), margin=0.0025)
    times, paths = [], []
    # a wall-clock limit far above the ~0.1-1.1 s a query takes on a loaded machine: RRTConnect stops at its
    # first path, so the limit changes no result, only whether a slow machine fails the test
    for seed in range(10):
        t0 = time.perf_counter()
        path = plan_path(checker, Q_LEFT, Q_RIGHT, seed=seed, time_limit=10.0)
        times.append(time.perf_counter() - t0)
        paths.append(path)
        assert path.shape[1] == 7 and len(path) >= 3
        np.testing.assert_array_equal(path[0], Q_LEFT)                # endpoints exact
        np.testing.assert_array_equal(path[-1], Q_RIGHT)
        assert checker.path_is_valid(path, resolution=None, max_sweep=0.0025)
        # the sweep-certified guarantee: clear by margin - max_sweep = 2.5 mm along the continuous motion
        assert half.path_is_valid(path, resolution=0.00025)
        assert np.all(path >= checker.lower) and np.all(path <= checker.upper)
    # independent reference on the unmodified model: no penetration anywhere along the first paths
    for path in paths[:3]:
        assert robot_world_penetration(m, d, path) <= 0.0
    again = plan_path(checker, Q_LEFT, Q_RIGHT, seed=3, time_limit=10.0)
    np.testing.assert_array_equal(again, paths[3])                    # seeded: same path
    print(f"\nmedian planning time over the wall, 10 seeded queries: {statistics.median(times) * 1e3:.1f} ms")


def test_start_and_goal_in_collision_name_the_geoms(checker):
    q_table = Q_LEFT.copy()
    q_table[1] = 1.2                     # shoulder forward: the hand goes into the table
    assert not checker.is_valid(q_table)
    with pytest.raises(PlanningError, match=r"start configuration in collision.*table"):
        plan_path(checker, q_table, HOME)
    pair = checker.first_collision(q_table)
    assert pair is not None and any("table" in p for p in pair)
    with pytest.raises(PlanningError, match=r"goal configuration in collision.*table"):
        plan_path(checker, HOME, q_table)
    q_lim = HOME.copy()
    q_lim[3] = 0.5                       # joint4 upper limit is -0.0698
    with pytest.raises(PlanningError, match=r"goal configuration violates a joint limit: joint joint4"):
        plan_path(checker, HOME, q_lim)


def _place_probe_at_distance(world, target: float) -> np.ndarray:
    """World qpos with the probe sphere `target` m from the nearest robot collision geom at HOME."""
    m, d0 = world
    d = mujoco.MjData(m)
    d.qpos[:] = d0.qpos
    adr = int(m.jnt_qposadr[m.body("probe").jntadr[0]])
    tcp = m.site("tcp").id
    mujoco.mj_kinematics(m, d)
    d.qpos[adr:adr + 3] = d.site_xpos[tcp] + np.array([0.0, 0.0, -0.08])   # below the fingertips
    probe_geom = m.geom("probe_geom").id
    robot_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] >= m.body("link1").id
                   and m.geom_bodyid[g] < m.body("box").id and m.geom_contype[g]]
    for _ in range(4):                  # move along the closest-point direction to the target gap
        mujoco.mj_kinematics(m, d)
        best, best_ft = np.inf, None
        for g in robot_geoms:
            ft = np.zeros(6)
            dist = mujoco.mj_geomDistance(m, d, probe_geom, g, 0.5, ft)
            if dist < best:
                best, best_ft = dist, ft
        direction = best_ft[:3] - best_ft[3:]      # from robot surface towards the probe
        direction /= np.linalg.norm(direction)
        d.qpos[adr:adr + 3] += direction * (target - best)
    return d.qpos.copy(), best


def _probe_state(world, distance: float, tol: float):
    """(model, data, arm q) with the probe `distance` m from the robot (checked to `tol`)."""
    m, _ = world
    qpos, dist = _place_probe_at_distance(world, distance)
    assert abs(dist - distance) < tol
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    return m, d, qpos[:7]


def test_margin_counts_near_contacts(world):
    m, d, q = _probe_state(world, 0.003, 2e-4)
    tight = CollisionChecker(m, d, list(range(7)), margin=0.005)
    loose = CollisionChecker(m, d, list(range(7)), margin=0.001)
    assert not tight.is_valid(q)        # 3 mm < 5 mm margin
    assert loose.is_valid(q)            # 3 mm > 1 mm margin
    assert any("probe" in p for p in tight.first_collision(q))
    # allow(): contacts between the fingers/hand and the probe stop counting
    bodies = {m.body(int(m.geom_bodyid[g])).name for g in range(m.ngeom) if m.geom_contype[g]
              and m.geom_bodyid[g] >= m.body("hand").id and m.geom_bodyid[g] < m.body("box").id}
    for b in bodies:
        tight.allow(b, "probe")
    assert tight.is_valid(q)
    for b in bodies:
        tight.disallow(b, "probe")
    assert not tight.is_valid(q)
    # allow(..., penetration=p): the pair may touch (3 mm < margin is fine) but not penetrate deeper than p
    for b in bodies:
        tight.allow(b, "probe", penetration=0.001)
    assert tight.is_valid(q)
    qpos_in, dist_in = _place_probe_at_distance(world, -0.003)
    assert abs(dist_in + 0.003) < 5e-4
    d.qpos[:] = qpos_in
    tight.set_world_state(d)
    assert not tight.is_valid(q)        # 3 mm deep > 1 mm allowed
    assert any("probe" in p for p in tight.first_collision(q))
    for b in bodies:
        tight.allow(b, "probe")         # ignored entirely: even the penetration does not count
    assert tight.is_valid(q)
    for b in bodies:
        tight.disallow(b, "probe")
        tight.allow(b, "probe", penetration=0.005)
    assert tight.is_valid(q)            # 3 mm deep < 5 mm allowed
    with pytest.raises(ValueError):
        tight.allow("hand", "probe", penetration=-0.001)


def test_object_clearance_widens_the_margin_for_named_bodies(world):
    """set_clearance: the probe 10 mm from the hand is clear with the 5 mm margin, not with a 15 mm
    clearance around the probe; other bodies keep the margin; allow() still wins; {} restores."""
    m, d, q = _probe_state(world, 0.010, 3e-4)
    c = CollisionChecker(m, d, list(range(7)), margin=0.005)
    assert c.is_valid(q)
    c.set_clearance({"probe": 0.015})
    assert not c.is_valid(q) and any("probe" in p for p in c.first_collision(q))
    c.set_clearance({"probe": 0.008})
    assert c.is_valid(q)                 # 10 mm > 8 mm
    c.set_clearance({"box": 0.015})      # another body: the probe keeps the plain margin
    assert c.is_valid(q)
    c.set_clearance({"probe": 0.015})
    bodies = {m.body(int(m.geom_bodyid[g])).name for g in range(m.ngeom) if m.geom_contype[g]
              and m.geom_bodyid[g] >= m.body("hand").id and m.geom_bodyid[g] < m.body("box").id}
    for b in bodies:
        c.allow(b, "probe", penetration=0.001)
    assert c.is_valid(q)
    for b in bodies:
        c.disallow(b, "probe")
    assert not c.is_valid(q)
    c.set_clearance({})
    assert c.is_valid(q)
    with pytest.raises(ValueError):
        c.set_clearance({"probe": -0.01})


def test_attach_held_box(world):
    m, d = world
    checker = CollisionChecker(m, d, list(range(7)), margin=0.005)
    # fingertips ~11 cm above the table beside the wall, pointing down
    q = np.array([-0.6, 0.3, 0.0, -2.3, 0.0, 2.6, 0.185])
    dd = mujoco.MjData(m)
    dd.qpos[:] = d.qpos
    dd.qpos[:7] = q
    mujoco.mj_kinematics(m, dd)
    tcp = m.site("tcp").id
    z_tcp = dd.site_xpos[tcp][2]
    assert 0.04 < z_tcp < 0.2 and dd.site_xmat[tcp][8] < -0.95
    assert checker.is_valid(q)
    # a 12 cm wide box held at the TCP overlaps the open fingers: those contacts exist but are ignored
    checker.attach("wide", np.eye(4))
    assert checker.is_valid(q)
    # reference: the unmodified model in the same state really has the box penetrating the fingers
    ref = mujoco.MjData(m)
    ref.qpos[:] = checker.data.qpos
    mujoco.mj_kinematics(m, ref)
    mujoco.mj_collision(m, ref)
    wide_geom = m.geom("wide_geom").id
    fingers = {m.body("left_finger").id, m.body("right_finger").id}
    touching = [k for k in range(ref.ncon) if wide_geom in ref.contact.geom[k]
                and {int(m.geom_bodyid[g]) for g in ref.contact.geom[k]} & fingers]
    assert touching and min(ref.contact.dist[k] for k in touching) < 0
    assert checker.data.ncon == 0       # the checker's broad phase skips those pairs altogether
    # held with its centre 1 cm above the table (TCP frame z = approach, pointing down): into the table
    T_low = np.eye(4)
    T_low[2, 3] = z_tcp - 0.01
    checker.attach("box", T_low)
    assert checker.attached_body == "box"
    assert not checker.is_valid(q)
    pair = checker.first_collision(q)
    assert pair is not None and {"table", "box_geom"} <= {p.split(" ")[0] for p in pair}
    checker.detach()
    assert checker.is_valid(q) and checker.attached_body is None
    with pytest.raises(ValueError, match="no free joint"):
        checker.attach("hand", np.eye(4))


def test_plan_with_attached_box_avoids_wall(world):
    m, d = world
    checker = CollisionChecker(m, d, list(range(7)), margin=0.005)
    T = np.eye(4)
    T[2, 3] = 0.05                      # box held 5 cm beyond the TCP
    checker.attach("box", T)
    path = plan_path(checker, Q_LEFT, Q_RIGHT, seed=1, time_limit=10.0)
    assert checker.path_is_valid(path, resolution=None, max_sweep=0.0025)
    half = CollisionChecker(m, d, list(range(7)), margin=0.0025)
    half.attach("box", T)
    assert half.path_is_valid(path, resolution=0.00025)
    checker.detach()


def test_sweep_radii_bound_real_displacements(world, checker):
    """Σ r_i |Δq_i| bounds how far any collidable robot geom moves (reference: MuJoCo forward kinematics)."""
    m, _ = world
    d = mujoco.MjData(m)
    moving = [g for g in range(m.ngeom)
              if m.geom_contype[g] and m.body("link1").id <= m.geom_bodyid[g] < m.body("box").id]
    rng = np.random.default_rng(0)
    ratios = []
    for _ in range(100):
        q = rng.uniform(checker.lower, checker.upper)
        dq = rng.normal(0.0, 0.02, 7)
        d.qpos[:7] = q
        mujoco.mj_kinematics(m, d)
        x0 = d.geom_xpos[moving].copy()
        d.qpos[:7] = q + dq
        mujoco.mj_kinematics(m, d)
        ratios.append(np.max(np.linalg.norm(d.geom_xpos[moving] - x0, axis=1)) / (checker.sweep_radii @ np.abs(dq)))
    assert max(ratios) <= 1.0
    assert max(ratios) > 0.2            # and not uselessly loose
    # holding an object further out increases the radii of every joint
    T = np.eye(4)
    T[2, 3] = 0.1
    r0 = checker.sweep_radii.copy()
    checker.attach("box", T)
    assert np.all(checker.sweep_radii > r0)
    checker.detach()
    np.testing.assert_allclose(checker.sweep_radii, r0)
    # the step count follows the bound: 5 mm sweep over a 0.1 rad joint-1 move of ~1.1 m radius
    assert checker.segment_steps(HOME, HOME + np.array([0.1, 0, 0, 0, 0, 0, 0]), None, 0.005) == \
        int(np.ceil(0.1 * checker.sweep_radii[0] / 0.005))


def test_planner_choice_timeout_and_bad_names(checker):
    # BITstar refines until the limit; its first path took ~0.15 s with the machine loaded (0.3 s was too close)
    path = plan_path(checker, Q_LEFT, Q_RIGHT, planner="BITstar", seed=0, time_limit=1.5)
    assert checker.path_is_valid(path, resolution=None, max_sweep=0.0025)
    np.testing.assert_array_equal(path[[0, -1]], np.stack([Q_LEFT, Q_RIGHT]))
    with pytest.raises(PlanningError, match=r"found no collision-free path in 0\.00 s.*blocked by wall"):
        plan_path(checker, Q_LEFT, Q_RIGHT, time_limit=0.001, seed=0)
    with pytest.raises(ValueError, match="unknown planner"):
        plan_path(checker, Q_LEFT, Q_RIGHT, planner="AStar")
    with pytest.raises(ValueError, match="7 values"):
        plan_path(checker, Q_LEFT[:6], Q_RIGHT)


def test_self_collision_counted_adjacent_links_not(world, checker):
    m, _ = world
    folded = np.array([0.0, 0.0, 0.0, -3.0, 0.0, 0.2, 0.0])     # hand folded back onto the shoulder
    pair = checker.first_collision(folded)
    assert pair is not None and {"link1", "hand"} <= {p.split("[")[0] for p in pair}
    # link0-link1 are 1 mm apart by design (MuJoCo does not filter them: link0 is welded to the world);
    # as adjacent links they never count, even with a large self margin
    loose = CollisionChecker(m, world[1], list(range(7)), margin=0.005, self_margin=0.005)
    assert loose.is_valid(HOME)


SMALL_ARM = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="base" pos="0 0 0.1">
      <geom type="cylinder" size="0.05 0.05"/>
      <body name="l1" pos="0 0 0.1">
        <joint name="j1" type="hinge" axis="0 0 1" pos="0.03 0 0" range="-3 3"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
        <body name="l2" pos="0.3 0 0">
          <joint name="j2" type="slide" axis="1 0 0" range="0 0.2"/>
          <geom type="box" size="0.1 0.02 0.02" pos="0.1 0 0"/>
          <body name="l3" pos="0.2 0 0">
            <joint name="j3" type="hinge" axis="0 1 0" range="-2 2"/>
            <geom type="capsule" fromto="0 0 0 0 0 -0.25" size="0.02"/>
            <site name="tcp" pos="0 0 -0.27"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_sweep_bound_generic_arm_with_offset_hinge_and_slide():
    m = mujoco.MjModel.from_xml_string(SMALL_ARM)
    d = mujoco.MjData(m)
    checker = CollisionChecker(m, None, [0, 1, 2], margin=0.005)
    assert checker.joint_names == ["j1", "j2", "j3"]
    assert checker.sweep_radii[1] == 1.0          # slide joint: metres per metre
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = rng.uniform(checker.lower, checker.upper)
        dq = rng.normal(0.0, 0.02, 3)
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        x0 = d.geom_xpos[1:].copy()
        d.qpos[:] = q + dq
        mujoco.mj_kinematics(m, d)
        moved = np.max(np.linalg.norm(d.geom_xpos[1:] - x0, axis=1))
        assert moved <= checker.sweep_radii @ np.abs(dq) + 1e-12
    # pointing straight down, the last link reaches into the floor
    down_q = np.array([0.0, 0.2, 0.0])
    assert not checker.is_valid(down_q)
    assert checker.first_collision(down_q)[0].startswith("floor")


def test_sampling_helpers():
    from splattwin.robot.planning import _coarse_to_fine

    for n in (1, 2, 3, 7, 64, 65, 1000):
        order = _coarse_to_fine(n)
        assert sorted(order.tolist()) == list(range(n))       # every sample exactly once
        assert order[0] == 0
    assert _coarse_to_fine(9)[:3].tolist() == [0, 8, 4]         # endpoints, then the middle
    path = np.array([[0.0, 0.0], [1.0, 0.5], [1.0, 0.5 + 1e-3]])
    dense = interpolate_path(path, 0.1)
    assert np.max(np.abs(np.diff(dense, axis=0))) <= 0.1 + 1e-12
    for w in path:                                              # waypoints kept
        assert np.min(np.max(np.abs(dense - w), axis=1)) == 0.0


def test_a_check_budget_plans_the_same_on_a_slow_machine(checker):
    """With max_checks a seeded query spends a budget of validity checks, not of wall time: on a machine ten
    times slower (each check delayed) it returns the very same path, where a wall-clock limit that the fast
    machine met ends without one; a budget too small names the checks spent."""
    from splattwin.robot.planning import PLAN_CHECKS

    fast = plan_path(checker, Q_LEFT, Q_RIGHT, seed=4, time_limit=60.0, max_checks=PLAN_CHECKS)
    t0 = time.perf_counter()
    plan_path(checker, Q_LEFT, Q_RIGHT, seed=4, time_limit=60.0)
    wall = time.perf_counter() - t0
    check = checker.collision_free

    def slow(q):
        time.sleep(2e-3)     # ~50x a check's own time
        return check(q)

    checker.collision_free = slow
    try:
        again = plan_path(checker, Q_LEFT, Q_RIGHT, seed=4, time_limit=60.0, max_checks=PLAN_CHECKS)
        np.testing.assert_array_equal(again, fast)
        with pytest.raises(PlanningError, match=r"no collision-free path in [0-9.]+ s"):
            plan_path(checker, Q_LEFT, Q_RIGHT, seed=4, time_limit=max(wall, 0.05), retries=0)
        with pytest.raises(PlanningError, match=r"no collision-free path in 40 collision checks \([0-9.]+ s\)"):
            plan_path(checker, Q_LEFT, Q_RIGHT, seed=4, time_limit=60.0, max_checks=40)
    finally:
        del checker.collision_free


def test_motion_planner_plans_with_the_check_budget(monkeypatch):
    """MotionPlanner's queries (both the one with object clearance and its fallback) pass PLAN_CHECKS and a
    wall-clock cap far above the ~1 s the budget takes, so the budget decides."""
    from splattwin.robot import motion
    from splattwin.robot.planning import PLAN_CHECKS

    seen = []

    def fake(checker, q_start, q_goal, **kw):
        seen.append(kw)
        raise PlanningError("injected")

    class Checker:
        attached_body = None

        def set_clearance(self, c):
            pass

    mp = motion.MotionPlanner.__new__(motion.MotionPlanner)
    mp.checker, mp.seed, mp.plan_ms, mp.planner, mp.object_clearance = Checker(), 0, [], "RRTConnect", 0.01
    mp.world = type("W", (), {"objects": ["a"]})()
    mp.plan_time, mp.plan_checks = 60.0, PLAN_CHECKS
    monkeypatch.setattr(motion, "plan_path", fake)
    with pytest.raises(PlanningError):
        mp.free_path(HOME, HOME, "test")
    assert len(seen) == 2 and all(kw["max_checks"] == PLAN_CHECKS and kw["time_limit"] >= 30 for kw in seen)
    import inspect

    defaults = inspect.signature(motion.MotionPlanner.__init__).parameters
    assert defaults["plan_checks"].default == PLAN_CHECKS and defaults["plan_time"].default >= 30
