"""`Rollout`: the executed motion of a task at the control rate, as a plain data object that saves itself.

Stand-in copy of the interface being written on the `robot` branch (that branch's version is kept at the
merge); the playback stage codes against it. Frames: twin (world) frame; units metres, radians, seconds.
Saved as one .npz (no pickles): arrays under their field names, object poses under
`object_poses/<name>`, joint names as a unicode array.
"""

from __future__ import annotations

import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.errors import InputError

MAX_SAMPLES = 2_000_000      # bound on T read from a file (100 Hz: 5.5 hours)
MAX_OBJECTS = 256
MAX_NQ = 1024
_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")


@dataclass
class Rollout:
    """Executed motion at the control rate; twin (world) frame, metres, radians, seconds.

    t [T] s; qpos [T,nq] full MuJoCo qpos (exact replay / forward kinematics); q_arm [T,7] rad measured
    arm joints; gripper_width [T] m measured distance between the fingers; action_q_arm [T,7] rad
    commanded arm joint targets; action_gripper [T] m commanded finger distance; object_poses
    {name: [T,4,4] T_world_obj}; joint_names the 7 arm joint names; step_index [T] int task step of each
    sample (-1 between steps).
    """

    t: np.ndarray
    qpos: np.ndarray
    q_arm: np.ndarray
    gripper_width: np.ndarray
    action_q_arm: np.ndarray
    action_gripper: np.ndarray
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)
    joint_names: list[str] = field(default_factory=list)
    step_index: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        T = len(self.t)
        self.qpos = np.asarray(self.qpos, dtype=np.float64).reshape(T, -1)
        self.q_arm = np.asarray(self.q_arm, dtype=np.float64).reshape(T, -1)
        self.gripper_width = np.asarray(self.gripper_width, dtype=np.float64).reshape(T)
        self.action_q_arm = np.asarray(self.action_q_arm, dtype=np.float64).reshape(T, self.q_arm.shape[1])
        self.action_gripper = np.asarray(self.action_gripper, dtype=np.float64).reshape(T)
        self.object_poses = {str(k): np.asarray(v, dtype=np.float64).reshape(T, 4, 4)
                             for k, v in self.object_poses.items()}
        self.step_index = (np.full(T, -1, np.int64) if self.step_index is None
                           else np.asarray(self.step_index, dtype=np.int64).reshape(T))
        self.joint_names = [str(n) for n in self.joint_names]
        if self.joint_names and len(self.joint_names) != self.q_arm.shape[1]:
            raise ValueError(f"{len(self.joint_names)} joint names for {self.q_arm.shape[1]} arm joints")
        if T > 1 and np.any(np.diff(self.t) <= 0):
            raise ValueError("rollout times must be strictly increasing")

    def __len__(self) -> int:
        return int(len(self.t))

    def save(self, path: str | Path) -> Path:
        """Write an .npz atomically; `load` reads it back."""
        from splattwin import io

        arrays = {"t": self.t, "qpos": self.qpos, "q_arm": self.q_arm, "gripper_width": self.gripper_width,
                  "action_q_arm": self.action_q_arm, "action_gripper": self.action_gripper,
                  "step_index": self.step_index, "joint_names": np.array(self.joint_names, dtype="U64"),
                  "object_names": np.array(list(self.object_poses), dtype="U128")}
        for name, T in self.object_poses.items():
            if not _NAME.match(name):
                raise ValueError(f"object name {name!r} is not a plain name")
            arrays[f"object_poses/{name}"] = T
        return io.write_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "Rollout":
        """Read a rollout .npz (no pickles; sizes bounded before anything large is read)."""
        path = Path(path)
        if not path.is_file():
            raise InputError("rollout file not found", path)
        try:
            with zipfile.ZipFile(path) as z:   # bound the sizes from the headers before loading
                for info in z.infolist():
                    if info.file_size > 8 * MAX_SAMPLES * max(MAX_NQ, 16) + 4096:
                        raise InputError(f"rollout member {info.filename!r} is too large", path)
            with np.load(path, allow_pickle=False) as f:
                need = ("t", "qpos", "q_arm", "gripper_width", "action_q_arm", "action_gripper", "step_index",
                        "joint_names", "object_names")
                missing = [k for k in need if k not in f.files]
                if missing:
                    raise InputError(f"not a rollout file: missing {', '.join(missing)}", path)
                t = f["t"]
                if t.ndim != 1 or len(t) > MAX_SAMPLES:
                    raise InputError(f"rollout has {t.shape} samples (at most {MAX_SAMPLES})", path)
                names = [str(n) for n in f["object_names"]]
                if len(names) > MAX_OBJECTS or not all(_NAME.match(n) for n in names):
                    raise InputError("rollout object names are malformed or too many", path)
                if f["qpos"].ndim != 2 or f["qpos"].shape[1] > MAX_NQ:
                    raise InputError(f"rollout qpos has shape {f['qpos'].shape}", path)
                poses = {}
                for n in names:
                    key = f"object_poses/{n}"
                    if key not in f.files:
                        raise InputError(f"rollout lacks the poses of object {n!r}", path)
                    poses[n] = f[key]
                return cls(t=t, qpos=f["qpos"], q_arm=f["q_arm"], gripper_width=f["gripper_width"],
                           action_q_arm=f["action_q_arm"], action_gripper=f["action_gripper"],
                           object_poses=poses, joint_names=[str(n) for n in f["joint_names"]],
                           step_index=f["step_index"])
        except (ValueError, OSError, zipfile.BadZipFile, KeyError) as e:
            raise InputError(f"cannot read rollout: {e}", path) from e
