"""Joint trajectories: a plain data object that saves/loads itself (JSON, CSV, ROS 2 YAML).

`Trajectory` holds a time-sampled joint trajectory: t [T] s (from 0, increasing), q [T,n] rad,
qd [T,n] rad/s, qdd [T,n] rad/s², joint_names [n]. The ROS 2 export is a `trajectory_msgs/JointTrajectory`
message as YAML (header.frame_id, joint_names, points[].positions/velocities/accelerations/
time_from_start {sec, nanosec}), the form `ros2 topic pub` and MoveIt tooling read.
All writes are atomic (splattwin.io).
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from splattwin.errors import InputError
from splattwin.io import read_json, write_json, write_text

__all__ = ["Trajectory", "concatenate"]


@dataclass
class Trajectory:
    """Time-sampled joint trajectory. Shapes: t [T], q/qd/qdd [T, n]; units s, rad, rad/s, rad/s²."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    joint_names: list[str] = field(default_factory=list)

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
        """Stand still at q ([n] rad) for `duration` s, sampled every `dt` s (e.g. while the gripper closes)."""
        q = np.asarray(q, dtype=float).reshape(-1)
        k = max(1, int(math.ceil(duration / dt - 1e-9)))
        t = np.linspace(0.0, k * dt, k + 1)
        z = np.zeros((k + 1, len(q)))
        return cls(t, np.repeat(q[None], k + 1, axis=0), z, z.copy(), list(joint_names or []))

    def shifted(self, dt: float) -> "Trajectory":
        return Trajectory(self.t + dt, self.q.copy(), self.qd.copy(), self.qdd.copy(), list(self.joint_names))

    # ---- JSON ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": "splattwin.trajectory", "version": 1, "joint_names": self.joint_names,
                "t": self.t.tolist(), "q": self.q.tolist(), "qd": self.qd.tolist(), "qdd": self.qdd.tolist()}

    @classmethod
    def from_dict(cls, d: dict, path: str | Path | None = None) -> "Trajectory":
        try:
            return cls(np.asarray(d["t"]), np.asarray(d["q"]), np.asarray(d["qd"]), np.asarray(d["qdd"]),
                       list(d.get("joint_names", [])))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not a valid trajectory: {e}", path) from e

    def save_json(self, path: str | Path) -> Path:
        return write_json(path, self.to_dict())

    @classmethod
    def load_json(cls, path: str | Path) -> "Trajectory":
        return cls.from_dict(read_json(path, missing="trajectory file not found"), Path(path))

    # ---- CSV ----------------------------------------------------------------------------------------
    def save_csv(self, path: str | Path) -> Path:
        """Columns: t, then q_<joint>..., qd_<joint>..., qdd_<joint>... (full float precision)."""
        buf = _io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["t"] + [f"{p}_{n}" for p in ("q", "qd", "qdd") for n in self.joint_names])
        data = np.concatenate([self.t[:, None], self.q, self.qd, self.qdd], axis=1)
        for row in data:
            w.writerow([repr(float(v)) for v in row])
        return write_text(path, buf.getvalue())

    @classmethod
    def load_csv(cls, path: str | Path) -> "Trajectory":
        path = Path(path)
        if not path.is_file():
            raise InputError("trajectory file not found", path)
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        if not rows or rows[0][:1] != ["t"] or (len(rows[0]) - 1) % 3:
            raise InputError("CSV header must be t, q_<joint>..., qd_<joint>..., qdd_<joint>...", path)
        n = (len(rows[0]) - 1) // 3
        names = [c[2:] for c in rows[0][1:1 + n]]
        try:
            data = np.array([[float(v) for v in r] for r in rows[1:]], dtype=float).reshape(-1, 1 + 3 * n)
        except ValueError as e:
            raise InputError(f"bad number in trajectory CSV: {e}", path) from e
        return cls(data[:, 0], data[:, 1:1 + n], data[:, 1 + n:1 + 2 * n], data[:, 1 + 2 * n:], names)

    # ---- picture ------------------------------------------------------------------------------------
    def save_plot(self, path: str | Path, vel_limits: Sequence[float] | None = None,
                  acc_limits: Sequence[float] | None = None, title: str | None = None) -> Path:
        """PNG: positions, velocities and accelerations over time, per joint, limits dashed (matplotlib)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from splattwin.io import atomic_path

        fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
        colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
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
        plt.close(fig)
        return path

    # ---- ROS 2 --------------------------------------------------------------------------------------
    def to_ros2_msg(self, frame_id: str = "world") -> dict:
        """trajectory_msgs/JointTrajectory as a plain dict (header, joint_names, points)."""
        points = []
        for k in range(len(self.t)):
            t_rel = float(self.t[k] - self.t[0])
            sec = int(math.floor(t_rel))
            nanosec = int(round((t_rel - sec) * 1e9))
            if nanosec >= 1_000_000_000:
                sec, nanosec = sec + 1, nanosec - 1_000_000_000
            points.append({"positions": self.q[k].tolist(), "velocities": self.qd[k].tolist(),
                           "accelerations": self.qdd[k].tolist(), "effort": [],
                           "time_from_start": {"sec": sec, "nanosec": nanosec}})
        return {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id},
                "joint_names": list(self.joint_names), "points": points}

    def save_ros2_yaml(self, path: str | Path, frame_id: str = "world") -> Path:
        import yaml

        return write_text(path, yaml.safe_dump(self.to_ros2_msg(frame_id), sort_keys=False,
                                               default_flow_style=None, width=1 << 16))

    @classmethod
    def load_ros2_yaml(cls, path: str | Path) -> "Trajectory":
        from splattwin.limits import load_yaml

        path = Path(path)
        if not path.is_file():
            raise InputError("trajectory file not found", path)
        msg = load_yaml(path)  # bounded size and aliases: a trajectory may come from someone else
        try:
            pts = msg["points"]
            t = np.array([p["time_from_start"]["sec"] + p["time_from_start"]["nanosec"] * 1e-9 for p in pts])
            q = np.array([p["positions"] for p in pts], dtype=float)
            n = q.shape[1]
            qd = np.array([p.get("velocities") or [0.0] * n for p in pts], dtype=float)
            qdd = np.array([p.get("accelerations") or [0.0] * n for p in pts], dtype=float)
            return cls(t, q, qd, qdd, list(msg["joint_names"]))
        except (KeyError, TypeError, IndexError, ValueError) as e:
            raise InputError(f"not a trajectory_msgs/JointTrajectory YAML: {e}", path) from e


def concatenate(trajs: Sequence[Trajectory], tol: float = 1e-6) -> Trajectory:
    """Join trajectories end to start in time; the first sample of each later one is dropped when it
    repeats the previous end. Raises ValueError when the joints differ or the positions jump (> tol rad)."""
    trajs = [tr for tr in trajs if len(tr)]
    if not trajs:
        raise ValueError("nothing to concatenate")
    names = trajs[0].joint_names
    ts, qs, qds, qdds = [trajs[0].t - trajs[0].t[0]], [trajs[0].q], [trajs[0].qd], [trajs[0].qdd]
    t_end = float(ts[0][-1])
    for k, tr in enumerate(trajs[1:], start=1):
        if tr.joint_names != names:
            raise ValueError(f"trajectory {k} has joints {tr.joint_names}, expected {names}")
        jump = float(np.max(np.abs(tr.q[0] - qs[-1][-1])))
        if jump > tol:
            raise ValueError(f"trajectory {k} starts {jump:.3g} rad away from where trajectory {k - 1} ends")
        t = tr.t - tr.t[0] + t_end
        ts.append(t[1:])
        qs.append(tr.q[1:])
        qds.append(tr.qd[1:])
        qdds.append(tr.qdd[1:])
        if len(t) > 1:
            t_end = float(t[-1])
    return Trajectory(np.concatenate(ts), np.concatenate(qs), np.concatenate(qds), np.concatenate(qdds),
                      list(names))
