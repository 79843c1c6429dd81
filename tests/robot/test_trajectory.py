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
