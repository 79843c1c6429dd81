"""Trajectory data object: JSON / CSV / ROS 2 YAML round trips, message fields, concatenation, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from splattwin.errors import InputError
from splattwin.robot.trajectory import Trajectory, concatenate

NAMES = [f"panda_joint{i}" for i in range(1, 8)]


def make(n: int = 25, t0: float = 0.0, q0: np.ndarray | None = None, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * 0.0137                      # not a round dt: exercises nanosec conversion
    q = (np.zeros(7) if q0 is None else q0) + np.cumsum(rng.normal(0, 0.01, (n, 7)), axis=0)
    q[0] = np.zeros(7) if q0 is None else q0
    return Trajectory(t, q, rng.normal(size=(n, 7)), rng.normal(size=(n, 7)), list(NAMES))


def assert_same(a: Trajectory, b: Trajectory, atol: float = 0.0):
    assert a.joint_names == b.joint_names
    for x, y in ((a.t, b.t), (a.q, b.q), (a.qd, b.qd), (a.qdd, b.qdd)):
        np.testing.assert_allclose(x, y, atol=atol, rtol=0)


def test_json_and_csv_round_trip(tmp_path):
    tr = make()
    assert_same(Trajectory.load_json(tr.save_json(tmp_path / "a.json")), tr)
    assert_same(Trajectory.load_csv(tr.save_csv(tmp_path / "a.csv")), tr)
    header = (tmp_path / "a.csv").read_text().splitlines()[0].split(",")
    assert header[:2] == ["t", "q_panda_joint1"] and header[-1] == "qdd_panda_joint7"
    assert not list(tmp_path.glob(".*"))                   # no temporary files left behind


def test_ros2_yaml_fields_and_round_trip(tmp_path):
    tr = make()
    path = tr.save_ros2_yaml(tmp_path / "traj.yaml", frame_id="panda_link0")
    msg = yaml.safe_load(path.read_text())
    assert msg["header"]["frame_id"] == "panda_link0"
    assert msg["joint_names"] == NAMES
    assert len(msg["points"]) == len(tr)
    p = msg["points"][7]
    assert set(p) >= {"positions", "velocities", "accelerations", "time_from_start"}
    assert len(p["positions"]) == 7 and len(p["velocities"]) == 7 and len(p["accelerations"]) == 7
    t = 7 * 0.0137
    assert p["time_from_start"] == {"sec": int(t), "nanosec": int(round((t - int(t)) * 1e9))}
    last = msg["points"][-1]["time_from_start"]
    assert last["sec"] == int(tr.t[-1]) and 0 <= last["nanosec"] < 1_000_000_000
    back = Trajectory.load_ros2_yaml(path)
    assert_same(back, tr, atol=1e-9)                       # nanosecond time resolution


def test_concatenate_and_hold():
    a = make(10)
    h = Trajectory.hold(a.q[-1], duration=0.5, dt=0.01, joint_names=NAMES)
    assert len(h) == 51 and np.all(h.qd == 0) and h.duration == pytest.approx(0.5)
    b = make(12, t0=3.0, q0=a.q[-1], seed=1)
    c = concatenate([a, h, b])
    assert len(c) == len(a) + len(h) - 1 + len(b) - 1
    assert np.all(np.diff(c.t) > 0)
    assert c.duration == pytest.approx(a.duration + h.duration + b.duration)
    np.testing.assert_array_equal(c.q[-1], b.q[-1])
    jump = make(5, q0=np.ones(7))
    with pytest.raises(ValueError, match="starts .* rad away"):
        concatenate([a, jump])


def test_sample_interpolates():
    tr = Trajectory(np.array([0.0, 1.0]), np.array([[0.0], [2.0]]), np.zeros((2, 1)), np.zeros((2, 1)))
    assert tr.sample(0.25)[0] == pytest.approx(0.5)
    assert tr.joint_names == ["joint1"]


def test_bad_input(tmp_path):
    with pytest.raises(InputError, match="not found"):
        Trajectory.load_json(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"t": [0, 1], "q": [[0]]}')
    with pytest.raises(InputError, match="bad.json"):
        Trajectory.load_json(tmp_path / "bad.json")
    (tmp_path / "bad.csv").write_text("time,x\n0,1\n")
    with pytest.raises(InputError, match="CSV header"):
        Trajectory.load_csv(tmp_path / "bad.csv")
    (tmp_path / "bad.yaml").write_text("points: [{positions: [1]}]\njoint_names: [a]\n")
    with pytest.raises(InputError, match="JointTrajectory"):
        Trajectory.load_ros2_yaml(tmp_path / "bad.yaml")
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(np.array([0.0, 0.0]), np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1)))


def test_plot_png(tmp_path):
    from PIL import Image

    tr = make()
    out = tr.save_plot(tmp_path / "traj.png", vel_limits=np.full(7, 2.0), acc_limits=np.full(7, 5.0))
    img = Image.open(out)
    assert img.format == "PNG" and img.size[0] > 500 and img.size[1] > 500
    # not blank: curves and axes drawn in more than a handful of colours
    assert len(np.unique(np.asarray(img.convert("RGB")).reshape(-1, 3), axis=0)) > 20


def with_gripper(tr: Trajectory) -> Trajectory:
    from splattwin.robot.trajectory import GripperCommand

    return Trajectory(tr.t, tr.q, tr.qd, tr.qdd, tr.joint_names,
                      [GripperCommand.open(0.0, 0.08), GripperCommand.grasp(tr.t[9], 0.0521, force=30.0)],
                      {"robot": "test arm", "base_frame": "panda_link0"})


def test_gripper_commands_and_metadata_round_trip(tmp_path):
    """Gripper commands (time, open/grasp, width, and a grasp's speed/force/epsilon) and metadata survive
    every file; the CSV carries the command in effect per sample; version-1 files (none) still load."""
    from splattwin.robot.trajectory import UNITS

    tr = with_gripper(make())
    doc = tr.to_dict()
    assert doc["units"] == UNITS and doc["units"]["q"] == "rad" and doc["robot"] == "test arm"
    back = Trajectory.load_json(tr.save_json(tmp_path / "a.json"))
    assert_same(back, tr)
    assert back.gripper == tr.gripper and back.meta == tr.meta
    g = back.gripper[1]
    assert (g.command, g.width, g.force, g.epsilon_inner, g.epsilon_outer) == ("grasp", 0.0521, 30.0, 0.01, 0.01)
    csv_back = Trajectory.load_csv(tr.save_csv(tmp_path / "a.csv"))
    assert_same(csv_back, tr)
    assert [(c.t, c.command, c.width) for c in csv_back.gripper] == [(c.t, c.command, c.width) for c in tr.gripper]
    header = (tmp_path / "a.csv").read_text().splitlines()[0].split(",")
    assert header[-2:] == ["gripper_width", "gripper_grasp"]
    rows = np.loadtxt(tmp_path / "a.csv", delimiter=",", skiprows=1)       # plain numbers: numpy reads it
    np.testing.assert_array_equal(rows[:9, -2:], [[0.08, 0.0]] * 9)
    np.testing.assert_array_equal(rows[9:, -2:], [[0.0521, 1.0]] * (len(tr) - 9))
    tr.save_ros2_yaml(tmp_path / "t.yaml")
    tr.save_ros2_gripper_yaml(tmp_path / "g.yaml")
    ros = Trajectory.load_ros2_yaml(tmp_path / "t.yaml", gripper_path=tmp_path / "g.yaml")
    assert_same(ros, tr, atol=1e-9)
    assert [(c.command, c.width, c.speed, c.force) for c in ros.gripper] == \
        [(c.command, c.width, c.speed, c.force) for c in tr.gripper]
    goals = yaml.safe_load((tmp_path / "g.yaml").read_text())["goals"]
    assert goals[1]["action"] == "franka_msgs/action/Grasp"
    assert goals[1]["goal"] == {"width": 0.0521, "epsilon": {"inner": 0.01, "outer": 0.01}, "speed": 0.05,
                                "force": 30.0}
    assert goals[0] == {"time_from_start": {"sec": 0, "nanosec": 0}, "command": "open",
                        "action": "franka_msgs/action/Move", "goal": {"width": 0.08, "speed": 0.05}}
    # version 1: no units, metadata or gripper
    v1 = {"format": "splattwin.trajectory", "version": 1, "joint_names": NAMES, "t": tr.t.tolist(),
          "q": tr.q.tolist(), "qd": tr.qd.tolist(), "qdd": tr.qdd.tolist()}
    old = Trajectory.from_dict(v1)
    assert old.gripper == [] and old.meta == {}


def test_ros2_goal_wraps_the_trajectory_and_the_frame_is_not_world(tmp_path):
    """A FollowJointTrajectory goal (`trajectory: ...`) for `ros2 action send_goal`; joint positions have
    no frame, so header.frame_id is empty unless a base frame is given."""
    tr = make()
    assert tr.to_ros2_msg()["header"]["frame_id"] == ""
    path = tr.save_ros2_goal_yaml(tmp_path / "goal.yaml", controller="fr3_arm_controller")
    text = path.read_text()
    assert "ros2 action send_goal /fr3_arm_controller/follow_joint_trajectory" in text
    goal = yaml.safe_load(text)
    assert set(goal) == {"trajectory"} and goal["trajectory"]["joint_names"] == NAMES
    assert_same(Trajectory.load_ros2_yaml(path), tr, atol=1e-9)


def test_holds_last_exactly_as_long_as_asked_and_carry_commands_through_concatenation():
    """A hold ends at exactly its duration (the servos hold a whole number of physics steps, not of the
    100 Hz samples), `held_until` appends one, and concatenation keeps gripper commands in place."""
    h = Trajectory.hold(np.zeros(7), 0.1006, dt=0.01, joint_names=NAMES)
    assert h.duration == pytest.approx(0.1006, abs=1e-12) and np.all(np.diff(h.t) > 0)
    a = make(10)
    ext = a.held_until(a.duration + 0.213)
    assert ext.duration == pytest.approx(a.duration + 0.213, abs=1e-12)
    np.testing.assert_array_equal(ext.q[len(a):], np.repeat(a.q[-1:], len(ext) - len(a), axis=0))
    assert np.all(ext.qd[len(a):] == 0)
    g = with_gripper(make(12, q0=ext.q[-1], seed=1))
    c = concatenate([ext, g])
    assert [x.t for x in c.gripper] == pytest.approx([ext.duration, ext.duration + g.t[9]])
    assert c.duration == pytest.approx(ext.duration + g.duration)


def test_accelerations_follow_the_sampled_velocities():
    """TOPP-RA's piecewise-constant accelerations sampled at a switch point disagree with the velocities
    around it; the exported ones are the velocities' central differences (within the limits)."""
    dt, acc = 0.01, 5.0
    t = np.arange(41) * dt
    t_sw = 0.2053                                             # accelerate, then brake: switch between samples
    qd = np.where(t < t_sw, acc * t, acc * t_sw - acc * (t - t_sw))[:, None]
    qdd = np.where(t < t_sw, acc, -acc)[:, None]              # as sampled from the bang-bang profile
    q = np.cumsum(qd, axis=0) * dt
    tr = Trajectory(t, q, qd, qdd, ["j"])
    fd = (qd[2:] - qd[:-2]) / (t[2:, None] - t[:-2, None])
    assert np.abs(tr.qdd[1:-1] - fd).max() > 1.0               # the sampled ones do disagree
    out = tr.with_velocity_accelerations()
    np.testing.assert_allclose(out.qdd[1:-1], fd, atol=1e-9)
    assert np.abs(out.qdd).max() <= acc + 1e-9
    np.testing.assert_array_equal(out.q, tr.q)
    np.testing.assert_array_equal(out.qd, tr.qd)


def test_save_plot_leaves_the_callers_matplotlib_backend(tmp_path):
    """save_plot called matplotlib.use("Agg"), switching a notebook's backend (its inline figures stopped
    showing); it draws on a Figure of its own now (audit 10A L11)."""
    import matplotlib
    from PIL import Image

    before = matplotlib.get_backend()
    matplotlib.use("svg")   # stands for the caller's own (a notebook's inline) backend
    try:
        tr = Trajectory(np.array([0.0, 0.5, 1.0]), np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 2)))
        out = tr.save_plot(tmp_path / "traj.png", vel_limits=[1.0, 1.0])
        assert matplotlib.get_backend() == "svg"
        assert Image.open(out).format == "PNG"
    finally:
        matplotlib.use(before)


def test_round_trips_compare_equal():
    """`Trajectory.load_json(p) == tr` raised ValueError (array fields; audit 10A L1)."""
    tr = make()
    same = Trajectory(tr.t.copy(), tr.q.copy(), tr.qd.copy(), tr.qdd.copy(), list(NAMES))
    assert tr == same and tr != make(seed=1)


def test_csv_that_is_not_text_is_bad_input(tmp_path, monkeypatch):
    """A binary or NUL-holding file raised UnicodeDecodeError / csv.Error (an internal error), and the whole
    file was read whatever its size (audit 10A L12): bounded UTF-8 text, InputError naming the file."""
    from splattwin import limits

    (tmp_path / "bin.csv").write_bytes(b"t,q_a,qd_a,qdd_a\n\x80\xff\xfe0,1,2,3\n")
    with pytest.raises(InputError, match=r"bin\.csv: .*not UTF-8"):
        Trajectory.load_csv(tmp_path / "bin.csv")
    (tmp_path / "nul.csv").write_bytes(b"t,q_a,qd_a,qdd_a\n0,\x00,2,3\n")
    with pytest.raises(InputError, match=r"nul\.csv: "):
        Trajectory.load_csv(tmp_path / "nul.csv")
    tr = make(n=200)
    p = tr.save_csv(tmp_path / "big.csv")
    monkeypatch.setattr(limits, "MAX_TEXT_BYTES", 1000)
    with pytest.raises(InputError, match=r"big\.csv"):
        Trajectory.load_csv(p)
    monkeypatch.undo()
    assert Trajectory.load_csv(p).joint_names == NAMES
