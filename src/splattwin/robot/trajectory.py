"""Joint trajectories: a plain data object that saves/loads itself (JSON, CSV, ROS 2 YAML).

`Trajectory` holds a time-sampled joint trajectory: t [T] s (from 0, increasing), q [T,n] rad,
qd [T,n] rad/s, qdd [T,n] rad/s², joint_names [n], the gripper commands issued along it (`GripperCommand`:
time s, "open" | "grasp", target width m, speed m/s, and for a grasp force N and epsilon m, the arguments
of a Franka Hand `grasp()` / `move()`) and free `meta` data (robot, base pose, start configuration, ...).

Files:
* JSON: format/version, `units`, meta, joint_names, t, q, qd, qdd, `gripper` (list of commands).
* CSV: t, q_<joint>..., qd_<joint>..., qdd_<joint>..., then, when the trajectory has gripper commands,
  gripper_width (m) and gripper_grasp (1: grasp, 0: open): the command in effect at each sample (speed,
  force and epsilon are in the JSON and the gripper YAML only).
* ROS 2: a `trajectory_msgs/JointTrajectory` message as YAML (header.frame_id, joint_names,
  points[].positions/velocities/accelerations/time_from_start {sec, nanosec}), the form `ros2 topic pub`
  and MoveIt tooling read; `save_ros2_goal_yaml` wraps it as a `control_msgs/action/FollowJointTrajectory`
  goal (`trajectory: ...`) for `ros2 action send_goal`; `save_ros2_gripper_yaml` writes the gripper
  commands as `franka_msgs/action/Grasp` / `Move` goals with their times.
Files written before gripper commands and metadata existed load as trajectories without them.
All writes are atomic (splattwin.io).
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from splattwin.equality import dataclass_eq
from splattwin.errors import InputError
from splattwin.io import read_json, write_json, write_text

__all__ = ["Trajectory", "GripperCommand", "concatenate", "UNITS", "GRASP_FORCE", "GRIPPER_SPEED",
           "GRASP_EPSILON", "GRASP_MARGIN", "grasp_epsilons"]

FORMAT = "splattwin.trajectory"
VERSION = 2              # 2: units, meta, gripper commands (version 1 files load as before)
UNITS = {"t": "s", "q": "rad", "qd": "rad/s", "qdd": "rad/s^2", "gripper.width": "m", "gripper.speed": "m/s",
         "gripper.force": "N", "gripper.epsilon": "m", "gripper.planned_width": "m"}
# Franka Hand grasp defaults: 20 N holds the light objects of a tabletop task (the hand takes up to 70 N
# continuous) without crushing a cardboard box; 0.05 m/s is the hand's top finger speed; the object's real
# size is off the twin's by millimetres, so the grasp counts as successful within at least 1 cm either way
# (libfranka fails a grasp whose final width is outside width -inner / +outer)
GRASP_FORCE = 20.0       # N
GRIPPER_SPEED = 0.05     # m/s
GRASP_EPSILON = 0.01     # m, inner and outer: the least tolerance either side
# The exported grasp width is where the simulated fingers stopped on the object at the end of the close hold
# (the physics collides with the convex parts, not the mesh the grasp was planned on: 27.2 mm measured vs
# 19.8 mm planned on a thin hammer handle). epsilon reaches GRASP_MARGIN beyond both the measured and the
# planned width, and never less than GRASP_EPSILON (`grasp_epsilons`)
GRASP_MARGIN = 0.005     # m
COMMANDS = ("open", "grasp")
# GripperCommand's fields beside t, command and width
_OPTIONAL = ("speed", "force", "epsilon_inner", "epsilon_outer", "planned_width")
_CORE_KEYS = {"format", "version", "units", "joint_names", "t", "q", "qd", "qdd", "gripper"}


@dataclass
class GripperCommand:
    """One gripper command: issued `t` s from the trajectory's start; "open": move the fingers to `width`
    (m, finger distance) at `speed` (m/s); "grasp": close on an object `width` m wide with `force` N,
    successful when the final width is within [width - epsilon_inner, width + epsilon_outer] (m).
    planned_width (grasp): the width the grasp was planned at on the twin's mesh, recorded beside the
    exported `width` (where the simulated fingers stopped on the object; `grasp_epsilons`).
    Loaded from a CSV, only t, command and width are known (the rest None)."""

    t: float
    command: str
    width: float
    speed: float | None = None
    force: float | None = None
    epsilon_inner: float | None = None
    epsilon_outer: float | None = None
    planned_width: float | None = None

    def __post_init__(self) -> None:
        if self.command not in COMMANDS:
            raise ValueError(f"gripper command must be one of {COMMANDS}, got {self.command!r}")
        self.t, self.width = float(self.t), float(self.width)
        for k in _OPTIONAL:
            v = getattr(self, k)
            setattr(self, k, None if v is None else float(v))
        vals = [self.t, self.width] + [v for v in (getattr(self, k) for k in _OPTIONAL) if v is not None]
        if not all(math.isfinite(v) and v >= 0 for v in vals):
            raise ValueError(f"gripper command values must be finite and >= 0: {self}")

    @classmethod
    def open(cls, t: float, width: float, speed: float = GRIPPER_SPEED) -> "GripperCommand":
        """Open to `width` m (Franka Hand `move(width, speed)`)."""
        return cls(t, "open", width, speed)

    @classmethod
    def grasp(cls, t: float, width: float, force: float = GRASP_FORCE, speed: float = GRIPPER_SPEED,
              epsilon: float = GRASP_EPSILON, planned_width: float | None = None,
              epsilon_outer: float | None = None) -> "GripperCommand":
        """Grasp an object `width` m wide (Franka Hand `grasp(width, speed, force, epsilon)`); epsilon is
        the inner tolerance, and the outer one too unless `epsilon_outer` is given."""
        return cls(t, "grasp", width, speed, force, epsilon, epsilon if epsilon_outer is None else epsilon_outer,
                   planned_width)

    def shifted(self, dt: float) -> "GripperCommand":
        return replace(self, t=self.t + dt)

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict) -> "GripperCommand":
        return cls(**{k: d.get(k) for k in ("t", "command", "width", *_OPTIONAL)})

    def ros2_goal(self) -> dict:
        """{action, goal}: a franka_msgs/action/Grasp or Move goal (franka_ros2 / franka_ros field names)."""
        if self.command == "grasp":
            return {"action": "franka_msgs/action/Grasp",
                    "goal": {"width": self.width, "epsilon": {"inner": self.epsilon_inner, "outer": self.epsilon_outer},
                             "speed": self.speed, "force": self.force}}
        return {"action": "franka_msgs/action/Move", "goal": {"width": self.width, "speed": self.speed}}


def grasp_epsilons(width: float, planned_width: float | None) -> tuple[float, float]:
    """(epsilon_inner, epsilon_outer) m of a grasp exported at `width` (where the simulated fingers stopped)
    that was planned at `planned_width`: both widths lie inside [width - inner, width + outer] with at least
    GRASP_MARGIN to spare, and neither tolerance is below GRASP_EPSILON."""
    p = width if planned_width is None else float(planned_width)
    inner = max(GRASP_EPSILON, width - min(width, p) + GRASP_MARGIN)
    outer = max(GRASP_EPSILON, max(width, p) - width + GRASP_MARGIN)
    return float(inner), float(outer)


def _duration_msg(t: float) -> dict:
    """builtin_interfaces/Duration of t s (>= 0)."""
    sec = int(math.floor(t))
    nanosec = int(round((t - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return {"sec": sec, "nanosec": nanosec}


def _duration_s(d: dict) -> float:
    return d["sec"] + d["nanosec"] * 1e-9


@dataclass
class Trajectory:
    """Time-sampled joint trajectory. Shapes: t [T], q/qd/qdd [T, n]; units s, rad, rad/s, rad/s².
    gripper: commands issued along it, times in the trajectory's own clock (t). meta: JSON-able data
    written with it (robot, base pose, start configuration, joint map, ...)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    joint_names: list[str] = field(default_factory=list)
    gripper: list[GripperCommand] = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    __eq__ = dataclass_eq   # array-aware: `Trajectory.load_csv(p) == tr` (splattwin.equality)

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float).reshape(-1)
        self.q = np.atleast_2d(np.asarray(self.q, dtype=float))
        self.qd = np.atleast_2d(np.asarray(self.qd, dtype=float))
        self.qdd = np.atleast_2d(np.asarray(self.qdd, dtype=float))
        T, n = self.q.shape
        if len(self.t) != T or self.qd.shape != (T, n) or self.qdd.shape != (T, n):
            raise ValueError(f"inconsistent shapes: t {self.t.shape}, q {self.q.shape}, qd {self.qd.shape}, "
                             f"qdd {self.qdd.shape}")
        if T > 1 and np.any(np.diff(self.t) <= 0):
            raise ValueError("trajectory times must be strictly increasing")
        if not self.joint_names:
            self.joint_names = [f"joint{i + 1}" for i in range(n)]
        self.joint_names = [str(s) for s in self.joint_names]
        if len(self.joint_names) != n:
            raise ValueError(f"{len(self.joint_names)} joint names for {n} joints")
        self.gripper = sorted((g if isinstance(g, GripperCommand) else GripperCommand.from_dict(g)
                               for g in self.gripper), key=lambda g: g.t)

    # ---- properties ---------------------------------------------------------------------------------
    @property
    def duration(self) -> float:
        """s"""
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    @property
    def dof(self) -> int:
        return self.q.shape[1]

    def __len__(self) -> int:
        return len(self.t)

    def sample(self, t: float | np.ndarray) -> np.ndarray:
        """Joint positions at time(s) t (linear interpolation between samples, clamped). [n] or [K,n]."""
        ts = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.stack([np.interp(ts, self.t, self.q[:, j]) for j in range(self.dof)], axis=-1)
        return out[0] if np.ndim(t) == 0 else out

    @classmethod
    def hold(cls, q: np.ndarray, duration: float, dt: float = 0.01,
             joint_names: Sequence[str] | None = None) -> "Trajectory":
        """Stand still at q ([n] rad) for `duration` s, sampled every `dt` s from 0; the last sample is at
        exactly `duration` (so a hold matches the time the servos held, which is not always a multiple
        of dt)."""
        q = np.asarray(q, dtype=float).reshape(-1)
        k = max(1, int(math.ceil(duration / dt - 1e-9)))
        t = np.arange(k + 1) * dt
        t[-1] = max(float(duration), t[-2] + 1e-6)    # a 0 s hold still has two distinct samples
        z = np.zeros((k + 1, len(q)))
        return cls(t, np.repeat(q[None], k + 1, axis=0), z, z.copy(), list(joint_names or []))

    def shifted(self, dt: float) -> "Trajectory":
        return Trajectory(self.t + dt, self.q.copy(), self.qd.copy(), self.qdd.copy(), list(self.joint_names),
                          [g.shifted(dt) for g in self.gripper], dict(self.meta))

    def held_until(self, duration: float, dt: float = 0.01) -> "Trajectory":
        """This trajectory followed by a stand-still at its last configuration until `duration` s after
        its start (the servo's settle hold after a motion); unchanged when it already lasts that long."""
        extra = float(duration) - self.duration
        if extra <= 1e-9:
            return self
        h = Trajectory.hold(self.q[-1], extra, dt, self.joint_names)
        return concatenate([self, h]).shifted(float(self.t[0]))

    def renamed(self, joint_names: Sequence[str]) -> "Trajectory":
        """The same trajectory with other joint names (same order), e.g. the real robot's."""
        return Trajectory(self.t, self.q, self.qd, self.qdd, list(joint_names), list(self.gripper), dict(self.meta))

    def with_velocity_accelerations(self) -> "Trajectory":
        """The same trajectory with qdd the time derivative of the sampled qd (central differences,
        one-sided at the ends): TOPP-RA's accelerations are piecewise constant, so sampled at a switch
        point they disagree with the velocities around it, which a quintic-spline controller would
        follow. Central differences average the two sides, so they stay within the limits."""
        if len(self.t) < 2:
            return self
        qdd = np.gradient(self.qd, self.t, axis=0, edge_order=1)
        return Trajectory(self.t, self.q, self.qd, qdd, list(self.joint_names), list(self.gripper), dict(self.meta))

    def gripper_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(width m, grasp 1/0) of the gripper command in effect at each time t (NaN before the first)."""
        t = np.asarray(t, dtype=float)
        width, grasp = np.full(t.shape, np.nan), np.full(t.shape, np.nan)
        for g in self.gripper:  # sorted by time: a later command overrides from its time on
            on = t >= g.t - 1e-9
            width[on], grasp[on] = g.width, float(g.command == "grasp")
        return width, grasp

    # ---- JSON ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Metadata first (it is what a reader looks at), then the samples and the gripper commands."""
        meta = {k: v for k, v in self.meta.items() if k not in _CORE_KEYS}
        return {"format": FORMAT, "version": VERSION, "units": dict(UNITS), **meta,
                "joint_names": self.joint_names, "t": self.t.tolist(), "q": self.q.tolist(),
                "qd": self.qd.tolist(), "qdd": self.qdd.tolist(), "gripper": [g.to_dict() for g in self.gripper]}

    @classmethod
    def from_dict(cls, d: dict, path: str | Path | None = None) -> "Trajectory":
        """A trajectory from `to_dict`'s form; version 1 (no gripper, units or meta) too."""
        try:
            gripper = [GripperCommand.from_dict(g) for g in d.get("gripper") or []]
            meta = {k: v for k, v in d.items() if k not in _CORE_KEYS}
            return cls(np.asarray(d["t"]), np.asarray(d["q"]), np.asarray(d["qd"]), np.asarray(d["qdd"]),
                       list(d.get("joint_names", [])), gripper, meta)
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise InputError(f"not a valid trajectory: {e}", path) from e

    def save_json(self, path: str | Path) -> Path:
        return write_json(path, self.to_dict())

    @classmethod
    def load_json(cls, path: str | Path) -> "Trajectory":
        return cls.from_dict(read_json(path, missing="trajectory file not found"), Path(path))

    # ---- CSV ----------------------------------------------------------------------------------------
    def save_csv(self, path: str | Path) -> Path:
        """Columns: t, then q_<joint>..., qd_<joint>..., qdd_<joint>... (full float precision); with gripper
        commands also gripper_width (m) and gripper_grasp (1 grasp, 0 open; empty before the first)."""
        buf = _io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        cols = [self.t[:, None], self.q, self.qd, self.qdd]
        header = ["t"] + [f"{p}_{n}" for p in ("q", "qd", "qdd") for n in self.joint_names]
        if self.gripper:
            width, grasp = self.gripper_at(self.t)
            cols += [width[:, None], grasp[:, None]]
            header += list(_GRIPPER_COLUMNS)
        w.writerow(header)
        for row in np.concatenate(cols, axis=1):
            w.writerow(["" if math.isnan(v) else repr(float(v)) for v in row])
        return write_text(path, buf.getvalue())

    @classmethod
    def load_csv(cls, path: str | Path) -> "Trajectory":
        from splattwin.limits import read_text

        path = Path(path)
        if not path.is_file():
            raise InputError("trajectory file not found", path)
        # bounded and decoded up front: a binary file raised UnicodeDecodeError, a NUL byte csv.Error
        text = read_text(path, "trajectory CSV")
        try:
            rows = list(csv.reader(_io.StringIO(text, newline="")))
        except csv.Error as e:
            raise InputError(f"not a trajectory CSV: {e}", path) from None
        header = rows[0] if rows else []
        grip = tuple(header[-2:]) == _GRIPPER_COLUMNS
        ncol = len(header) - (2 if grip else 0)
        if header[:1] != ["t"] or (ncol - 1) % 3:
            raise InputError("CSV header must be t, q_<joint>..., qd_<joint>..., qdd_<joint>... "
                             "[, gripper_width, gripper_grasp]", path)
        n = (ncol - 1) // 3
        names = [c[2:] for c in header[1:1 + n]]
        try:
            data = np.array([[float(v) if v != "" else math.nan for v in r] for r in rows[1:]],
                            dtype=float).reshape(-1, len(header))
            commands = _commands_from_columns(data[:, 0], data[:, ncol], data[:, ncol + 1]) if grip else []
            return cls(data[:, 0], data[:, 1:1 + n], data[:, 1 + n:1 + 2 * n], data[:, 1 + 2 * n:ncol], names,
                       commands)
        except ValueError as e:
            raise InputError(f"bad number in trajectory CSV: {e}", path) from e

    # ---- picture ------------------------------------------------------------------------------------
    def save_plot(self, path: str | Path, vel_limits: Sequence[float] | None = None,
                  acc_limits: Sequence[float] | None = None, title: str | None = None) -> Path:
        """PNG: positions, velocities and accelerations over time, per joint, limits dashed (matplotlib)."""
        import matplotlib
        from matplotlib.figure import Figure

        from splattwin.io import atomic_path

        # a Figure of its own, not pyplot: the caller's backend and open figures stay as they are (a notebook's)
        fig = Figure(figsize=(9, 8))
        axes = fig.subplots(3, 1, sharex=True)
        colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
        for ax, data, label, lim in ((axes[0], self.q, "q [rad]", None), (axes[1], self.qd, "qd [rad/s]", vel_limits),
                                     (axes[2], self.qdd, "qdd [rad/s²]", acc_limits)):
            for j in range(self.dof):
                c = colors[j % len(colors)]
                ax.plot(self.t, data[:, j], color=c, lw=1.2, label=self.joint_names[j])
                if lim is not None:
                    ax.axhline(lim[j], color=c, ls="--", lw=0.6)
                    ax.axhline(-lim[j], color=c, ls="--", lw=0.6)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7, ncol=min(self.dof, 7), loc="upper center", bbox_to_anchor=(0.5, 1.25))
        axes[-1].set_xlabel("t [s]")
        fig.suptitle(title or f"joint trajectory, {self.duration:.2f} s, {len(self)} samples", y=0.995)
        fig.tight_layout()
        path = Path(path)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        return path

    # ---- ROS 2 --------------------------------------------------------------------------------------
    def to_ros2_msg(self, frame_id: str = "") -> dict:
        """trajectory_msgs/JointTrajectory as a plain dict (header, joint_names, points). Joint positions
        have no frame: frame_id "" (default) or the robot's base frame; stamp 0 means "start now"."""
        points = [{"positions": self.q[k].tolist(), "velocities": self.qd[k].tolist(),
                   "accelerations": self.qdd[k].tolist(), "effort": [],
                   "time_from_start": _duration_msg(float(self.t[k] - self.t[0]))} for k in range(len(self.t))]
        return {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id},
                "joint_names": list(self.joint_names), "points": points}

    def save_ros2_yaml(self, path: str | Path, frame_id: str = "") -> Path:
        """The JointTrajectory message as YAML (`ros2 topic pub`, MoveIt tooling)."""
        return write_text(path, _yaml_dump(self.to_ros2_msg(frame_id)))

    def save_ros2_goal_yaml(self, path: str | Path, frame_id: str = "", controller: str = "CONTROLLER",
                            note: str | None = None) -> Path:
        """A control_msgs/action/FollowJointTrajectory goal (`trajectory: <JointTrajectory>`), for
        `ros2 action send_goal /<controller>/follow_joint_trajectory control_msgs/action/FollowJointTrajectory
        "$(cat FILE)"` (the command is written as a comment at the top, after `note` if given)."""
        head = ((f"# {note}\n" if note else "")
                + "# control_msgs/action/FollowJointTrajectory goal; the arm must be at the first point first\n"
                f"# ros2 action send_goal /{controller}/follow_joint_trajectory "
                f"control_msgs/action/FollowJointTrajectory \"$(cat {Path(path).name})\"\n")
        return write_text(path, head + _yaml_dump({"trajectory": self.to_ros2_msg(frame_id)}))

    def save_ros2_gripper_yaml(self, path: str | Path) -> Path:
        """The gripper commands as franka_msgs/action/Grasp and Move goals, each with its time from the
        start of the arm trajectory (send each goal when the arm trajectory reaches that time)."""
        goals = [{"time_from_start": _duration_msg(g.t - float(self.t[0])), "command": g.command, **g.ros2_goal()}
                 for g in self.gripper]
        head = ("# gripper goals along the arm trajectory (franka_msgs actions; width m, speed m/s, force N);\n"
                "# send each when the arm trajectory reaches its time_from_start, e.g.\n"
                "# ros2 action send_goal /franka_gripper/grasp franka_msgs/action/Grasp \"{goal}\"\n")
        return write_text(path, head + _yaml_dump({"goals": goals}))

    @classmethod
    def load_ros2_yaml(cls, path: str | Path, gripper_path: str | Path | None = None) -> "Trajectory":
        """A JointTrajectory message YAML, or a FollowJointTrajectory goal (`trajectory: ...`); with
        `gripper_path`, the gripper goals `save_ros2_gripper_yaml` wrote (times from the first point)."""
        from splattwin.limits import load_yaml

        path = Path(path)
        if not path.is_file():
            raise InputError("trajectory file not found", path)
        msg = load_yaml(path)  # bounded size and aliases: a trajectory may come from someone else
        try:
            if isinstance(msg, dict) and "trajectory" in msg and "points" not in msg:
                msg = msg["trajectory"]
            pts = msg["points"]
            t = np.array([_duration_s(p["time_from_start"]) for p in pts])
            q = np.array([p["positions"] for p in pts], dtype=float)
            n = q.shape[1]
            qd = np.array([p.get("velocities") or [0.0] * n for p in pts], dtype=float)
            qdd = np.array([p.get("accelerations") or [0.0] * n for p in pts], dtype=float)
            names = list(msg["joint_names"])
        except (KeyError, TypeError, IndexError, ValueError) as e:
            raise InputError(f"not a trajectory_msgs/JointTrajectory YAML: {e}", path) from e
        gripper = [] if gripper_path is None else _load_gripper_goals(Path(gripper_path))
        try:
            return cls(t, q, qd, qdd, names, gripper)
        except ValueError as e:
            raise InputError(f"not a trajectory_msgs/JointTrajectory YAML: {e}", path) from e


_GRIPPER_COLUMNS = ("gripper_width", "gripper_grasp")


def _yaml_dump(doc: dict) -> str:
    import yaml

    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=1 << 16)


def _commands_from_columns(t: np.ndarray, width: np.ndarray, grasp: np.ndarray) -> list[GripperCommand]:
    """Gripper commands (t, command, width) where the CSV's gripper columns change."""
    out: list[GripperCommand] = []
    prev = (math.nan, math.nan)
    for tk, w, g in zip(t, width, grasp):
        if math.isnan(w) or math.isnan(g) or (w, g) == prev:
            continue
        out.append(GripperCommand(float(tk), "grasp" if g > 0.5 else "open", float(w)))
        prev = (w, g)
    return out


def _load_gripper_goals(path: Path) -> list[GripperCommand]:
    """The gripper commands of a `save_ros2_gripper_yaml` file (read with bounded size)."""
    from splattwin.limits import load_yaml

    if not path.is_file():
        raise InputError("gripper goals file not found", path)
    doc = load_yaml(path)
    try:
        out = []
        for g in doc["goals"]:
            goal = g["goal"]
            eps = goal.get("epsilon") or {}
            out.append(GripperCommand(_duration_s(g["time_from_start"]), g["command"], goal["width"],
                                      goal.get("speed"), goal.get("force"), eps.get("inner"), eps.get("outer")))
        return out
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"not a gripper goals YAML: {e}", path) from e


def concatenate(trajs: Sequence[Trajectory], tol: float = 1e-6) -> Trajectory:
    """Join trajectories end to start in time (from 0; gripper commands keep their place in each); the
    first sample of each later one is dropped when it repeats the previous end. Raises ValueError when the joints differ or the positions jump (> tol rad)."""
    trajs = [tr for tr in trajs if len(tr)]
    if not trajs:
        raise ValueError("nothing to concatenate")
    names = trajs[0].joint_names
    ts, qs, qds, qdds = [trajs[0].t - trajs[0].t[0]], [trajs[0].q], [trajs[0].qd], [trajs[0].qdd]
    gripper = [g.shifted(-float(trajs[0].t[0])) for g in trajs[0].gripper]
    t_end = float(ts[0][-1])
    for k, tr in enumerate(trajs[1:], start=1):
        if tr.joint_names != names:
            raise ValueError(f"trajectory {k} has joints {tr.joint_names}, expected {names}")
        jump = float(np.max(np.abs(tr.q[0] - qs[-1][-1])))
        if jump > tol:
            raise ValueError(f"trajectory {k} starts {jump:.3g} rad away from where trajectory {k - 1} ends")
        t = tr.t - tr.t[0] + t_end
        gripper += [g.shifted(t_end - float(tr.t[0])) for g in tr.gripper]
        ts.append(t[1:])
        qs.append(tr.q[1:])
        qds.append(tr.qd[1:])
        qdds.append(tr.qdd[1:])
        if len(t) > 1:
            t_end = float(t[-1])
    return Trajectory(np.concatenate(ts), np.concatenate(qs), np.concatenate(qds), np.concatenate(qdds),
                      list(names), gripper, dict(trajs[0].meta))
