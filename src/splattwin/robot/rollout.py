"""The recorded rollout: the single record of what happened in physics during a task's execution.

`Rollout` holds the executed motion at the control rate (one sample per physics step, when the servo
targets are set) in the twin (world) frame: metres, radians, seconds. It is what the viewer's playback
track and a photoreal (dynamic splat) playback are made from: `qpos` replays the simulation exactly
(forward kinematics of every body), the other arrays are the same state by name.

`RolloutRecorder` collects it during execution (`execute.Executor` owns one); `Rollout.save` writes
robot/rollout.npz atomically and `Rollout.load` reads it back without unpickling, with every size
bounded before anything is allocated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.equality import dataclass_eq
from splattwin.errors import InputError
from splattwin.limits import load_npz

FORMAT = "splattwin.rollout"
VERSION = 1
MAX_SAMPLES = 5_000_000        # a day of simulated time at 500 Hz is far beyond any task
MAX_NQ = 10_000
MAX_OBJECTS = 1_000
MAX_NAME = 256                 # characters of a joint or object name
MAX_BYTES = 4 << 30            # uncompressed bytes of all arrays together


def _rows(a, T: int) -> np.ndarray:
    """`a` as float64 [T, k]; with T = 0 (a run whose first step failed before any motion) k is taken from
    a's own last axis, which reshape(0, -1) cannot infer."""
    a = np.asarray(a, dtype=np.float64)
    return a.reshape(T, -1) if T else a.reshape(0, a.shape[-1] if a.ndim == 2 else 0)


@dataclass
class Rollout:
    """Executed motion at the control rate; twin (world) frame, metres, radians, seconds."""

    t: np.ndarray                          # [T] s from the start of the run
    qpos: np.ndarray                       # [T, nq] full MuJoCo qpos (exact replay / forward kinematics)
    q_arm: np.ndarray                      # [T, 7] rad, measured arm joints
    gripper_width: np.ndarray              # [T] m, measured distance between the fingers
    action_q_arm: np.ndarray               # [T, 7] rad, commanded arm joint targets
    action_gripper: np.ndarray             # [T] m, commanded finger distance
    object_poses: dict[str, np.ndarray]    # object name -> [T, 4, 4] T_world_obj
    joint_names: list[str]                 # the 7 arm joint names
    step_index: np.ndarray                 # [T] int, task step each sample belongs to (-1 between steps)

    __eq__ = dataclass_eq   # array-aware: `Rollout.load(p) == r` (splattwin.equality)

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        T = len(self.t)
        self.qpos = _rows(self.qpos, T)
        self.q_arm = _rows(self.q_arm, T)
        self.action_q_arm = _rows(self.action_q_arm, T)
        self.gripper_width = np.asarray(self.gripper_width, dtype=np.float64).reshape(T)
        self.action_gripper = np.asarray(self.action_gripper, dtype=np.float64).reshape(T)
        self.step_index = np.asarray(self.step_index, dtype=np.int64).reshape(T)
        self.object_poses = {str(k): np.asarray(v, dtype=np.float64).reshape(T, 4, 4)
                             for k, v in self.object_poses.items()}
        self.joint_names = [str(n) for n in self.joint_names]
        n = self.q_arm.shape[1]
        if self.action_q_arm.shape[1] != n or len(self.joint_names) != n:
            raise ValueError(f"{n} measured arm joints, {self.action_q_arm.shape[1]} commanded, "
                             f"{len(self.joint_names)} joint names")
        if T > 1 and np.any(np.diff(self.t) <= 0):
            raise ValueError("rollout times must be strictly increasing")

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration(self) -> float:
        """s from the first to the last sample."""
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    def steps(self) -> list[int]:
        """The task steps (1-based) that have samples, in order."""
        return [int(k) for k in np.unique(self.step_index) if k >= 0]

    def at(self, t: float) -> int:
        """Index of the last sample at or before time t (s), clamped to the rollout."""
        return int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, max(len(self.t) - 1, 0)))

    # ---- file -------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write an .npz (compressed, atomic; only plain arrays, loadable with allow_pickle=False)."""
        from splattwin import io

        names = list(self.object_poses)
        poses = (np.stack([self.object_poses[n] for n in names]) if names
                 else np.zeros((0, len(self.t), 4, 4)))
        return io.write_npz(path, format=np.array(FORMAT), version=np.array(VERSION), t=self.t, qpos=self.qpos,
                            q_arm=self.q_arm, gripper_width=self.gripper_width, action_q_arm=self.action_q_arm,
                            action_gripper=self.action_gripper, object_names=np.array(names, dtype=str),
                            object_poses=poses, joint_names=np.array(self.joint_names, dtype=str),
                            step_index=self.step_index)

    @classmethod
    def load(cls, path: str | Path) -> "Rollout":
        """Read a rollout .npz; InputError naming the file when it is missing, malformed or too large."""
        path = Path(path)
        if not path.is_file():
            raise InputError("rollout file not found", path)
        arrays = load_npz(path, "robot record", max_bytes=MAX_BYTES, check=_check_rollout_headers)
        need = ("format", "version", "t", "qpos", "q_arm", "gripper_width", "action_q_arm", "action_gripper",
                "object_names", "object_poses", "joint_names", "step_index")
        missing = [k for k in need if k not in arrays]
        if missing:
            raise InputError(f"not a rollout file: missing {', '.join(missing)}", path)
        version = arrays["version"]
        # int() of a complex, text or many-element array raises TypeError/ValueError, not a mismatch
        if (str(arrays["format"]) != FORMAT or version.dtype.kind not in "iu" or version.size != 1
                or int(version.reshape(-1)[0]) != VERSION):
            raise InputError(f"not a {FORMAT} v{VERSION} file (format {arrays['format']!s}, "
                             f"version {arrays['version']!s})", path)
        t, qpos = arrays["t"], arrays["qpos"]
        T = len(t)
        if t.ndim != 1 or T > MAX_SAMPLES or qpos.ndim != 2 or qpos.shape[0] != T or qpos.shape[1] > MAX_NQ:
            raise InputError(f"rollout sizes out of range: t {t.shape}, qpos {qpos.shape}", path)
        names = [str(n) for n in arrays["object_names"].reshape(-1)]
        joint_names = [str(n) for n in arrays["joint_names"].reshape(-1)]
        poses = arrays["object_poses"]
        if (len(names) > MAX_OBJECTS or poses.shape != (len(names), T, 4, 4)
                or any(len(n) > MAX_NAME for n in names + joint_names) or len(set(names)) != len(names)):
            raise InputError(f"rollout objects malformed: {len(names)} names, poses {poses.shape}", path)
        for k in ("t", "qpos", "q_arm", "gripper_width", "action_q_arm", "action_gripper", "object_poses"):
            if arrays[k].dtype.kind not in "fi" or not np.all(np.isfinite(arrays[k])):
                raise InputError(f"rollout array {k!r} is not finite numbers", path)
        if arrays["step_index"].dtype.kind != "i":
            raise InputError("rollout array 'step_index' is not integers", path)
        try:
            return cls(t=t, qpos=qpos, q_arm=arrays["q_arm"], gripper_width=arrays["gripper_width"],
                       action_q_arm=arrays["action_q_arm"], action_gripper=arrays["action_gripper"],
                       object_poses=dict(zip(names, poses)), joint_names=joint_names,
                       step_index=arrays["step_index"])
        except ValueError as e:
            raise InputError(f"rollout arrays inconsistent: {e}", path) from e


_PER_SAMPLE = ("t", "qpos", "q_arm", "gripper_width", "action_q_arm", "action_gripper", "step_index")


def _check_rollout_headers(h: dict) -> str | None:
    """The rollout's shapes from the headers alone: T samples (<= MAX_SAMPLES) in every per-sample array,
    at most MAX_NQ columns, MAX_OBJECTS object poses, so a bomb of valid-looking zeros is refused unread."""
    if "t" not in h or len(h["t"][0]) != 1:
        return "missing or malformed 't' (sample times)"
    T = h["t"][0][0]
    if T > MAX_SAMPLES:
        return f"{T} samples, more than {MAX_SAMPLES}"
    for k in _PER_SAMPLE:
        if k in h:
            shape = h[k][0]
            if not 1 <= len(shape) <= 2 or shape[0] != T or (len(shape) == 2 and shape[1] > MAX_NQ):
                return f"array {k!r} has shape {shape}, expected [{T}] or [{T}, <= {MAX_NQ}]"
    if "object_poses" in h:
        shape = h["object_poses"][0]
        if len(shape) != 4 or shape[0] > MAX_OBJECTS or shape[1:] != (T, 4, 4):
            return f"rollout objects malformed: 'object_poses' has shape {shape}, expected [<= {MAX_OBJECTS}, {T}, 4, 4]"
    for k, n in (("object_names", MAX_OBJECTS), ("joint_names", MAX_NQ)):
        if k in h:
            shape, dtype = h[k]
            if int(np.prod(shape, dtype=object)) > n or dtype.itemsize > 4 * MAX_NAME:
                return f"array {k!r} has shape {shape} of {dtype}, more than {n} names of {MAX_NAME} characters"
    return None


class RolloutRecorder:
    """Collects one sample per control step during execution; `rollout(world)` assembles the `Rollout`.

    Samples are appended to preallocated blocks (a physics step costs far more than a copy). `step` is
    the task step the next samples belong to (-1 between steps)."""

    BLOCK = 4096

    def __init__(self, nq: int, n_arm: int):
        self.nq, self.n_arm = nq, n_arm
        self.step = -1
        self._n = 0
        self._blocks: list[dict[str, np.ndarray]] = []

    def __len__(self) -> int:
        return self._n

    def record(self, t: float, qpos: np.ndarray, action_q_arm: np.ndarray, action_gripper: float) -> None:
        """One sample: time (s), qpos [nq] after the step, commanded arm targets [n_arm] rad, commanded
        finger distance (m)."""
        k = self._n % self.BLOCK
        if k == 0:
            self._blocks.append({"t": np.empty(self.BLOCK), "qpos": np.empty((self.BLOCK, self.nq)),
                                 "act": np.empty((self.BLOCK, self.n_arm)), "grip": np.empty(self.BLOCK),
                                 "step": np.empty(self.BLOCK, np.int64)})
        b = self._blocks[-1]
        b["t"][k] = t
        b["qpos"][k] = qpos
        b["act"][k] = action_q_arm
        b["grip"][k] = action_gripper
        b["step"][k] = self.step
        self._n += 1

    def _cat(self, key: str) -> np.ndarray:
        if not self._blocks:
            shape = {"qpos": (0, self.nq), "act": (0, self.n_arm)}.get(key, (0,))
            return np.zeros(shape, np.int64 if key == "step" else float)
        parts = [b[key] for b in self._blocks]
        return np.concatenate(parts)[: self._n]

    def rollout(self, world) -> Rollout:
        """The recorded samples as a `Rollout`, measured values read through the world's joint map."""
        qpos = self._cat("qpos")
        j = world.joints
        return Rollout(t=self._cat("t"), qpos=qpos, q_arm=j.arm(qpos), gripper_width=j.gripper_width(qpos),
                       action_q_arm=self._cat("act"), action_gripper=self._cat("grip"),
                       object_poses={o: j.object_pose(qpos, o) for o in world.objects},
                       joint_names=list(world.robot.arm_joints), step_index=self._cat("step"))
