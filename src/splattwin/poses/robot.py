"""Robot (eye-in-hand) camera poses: end-effector poses `T_base_ee` per image + hand-eye `T_ee_cam`.

The camera pose in the robot base frame is T_base_cam = T_base_ee @ T_ee_cam (OpenCV camera frame:
x right, y down, z forward; metres). Files are JSON or YAML:

    # robot poses: a list, or {"poses": [...], "T_ee_cam": ...(optional hand-eye inline)}
    - {image: train_000.png, T_base_ee: [[...4x4...]]}
    - {image: train_001.png, position: [x, y, z], quat_xyzw: [x, y, z, w]}   # or quat_wxyz: [w, x, y, z]

    # hand-eye: a 4x4 matrix, or {T_ee_cam: 4x4} or {position: [...], quat_xyzw | quat_wxyz: [...]}

Entries without an "image" key are matched to the dataset's frames in order (counts must agree).
The quaternion order must be explicit: a bare "quat"/"orientation" key is refused (the two conventions
are both common and silently swapping them gives plausible but wrong poses).

Units: metres, unless the file is a mapping with `units: mm` (`{units: mm, poses: [...]}`, and for a
hand-eye file `{units: mm, T_ee_cam: ...}`): many controllers (ABB, KUKA, Fanuc, UR in mm mode) export
millimetres. A fixed-base arm's flange stays within its reach of the base (a Panda: 0.855 m), so a flange
translation beyond MAX_REACH_M (3 m) is refused as a likely millimetre file (read as metres it gave a twin
1000x too large, still marked metric); a hand-eye translation beyond MAX_HAND_EYE_M (1 m) likewise.

Eye-in-hand only: the camera rides on the arm. An eye-to-hand (fixed camera) setup is not a robot-pose
capture: every image has the same camera pose T_base_cam, and a static scene seen from one place gives no
parallax; `camera_poses_in_base` refuses cameras that all sit at one place and warns when their optical
axes do not meet in front of them (an inverted hand-eye, T_cam_ee given for T_ee_cam, often does that). An
inverted hand-eye that is mostly a turn about the flange z axis keeps the axes in front: the photos' relative
rotations catch that one (`splattwin.poses.hand_eye_check`, run by `estimate_poses`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splattwin.errors import InputError
from splattwin.transforms import pose_from_file_value, pose_from_pos_quat_wxyz, quat_wxyz_from_xyzw

log = logging.getLogger(__name__)

MAX_REACH_M = 3.0      # flange distance from the base: above any fixed-base arm's reach (Panda 0.855 m, UR10 1.3 m)
MAX_HAND_EYE_M = 1.0   # camera distance from the flange: a wrist camera is centimetres away
MIN_CAMERA_SPREAD_M = 1e-3  # camera centres closer than this all together: one fixed camera, no parallax
_UNITS = {"m": 1.0, "metre": 1.0, "metres": 1.0, "meter": 1.0, "meters": 1.0,
          "mm": 1e-3, "millimetre": 1e-3, "millimetres": 1e-3, "millimeter": 1e-3, "millimeters": 1e-3}


@dataclass
class RobotPose:
    """One end-effector pose. image: image name (file name or stem) or None (matched by order)."""

    T_base_ee: np.ndarray
    image: str | None = None


def _read_structured(path: Path) -> Any:
    from splattwin.limits import load_yaml, read_json

    if not path.is_file():
        raise InputError("file does not exist", path)
    if path.suffix.lower() == ".json":
        return read_json(path)
    return load_yaml(path)  # safe loader, bounded size and aliases


def parse_transform(obj: Any, where: Path, what: str, matrix_key: str) -> np.ndarray:
    """A rigid transform [4,4] from a 4x4 (or 3x4) nested list, {matrix_key: 4x4}, or position + quaternion."""
    if isinstance(obj, dict):
        if matrix_key in obj:
            return parse_transform(obj[matrix_key], where, what, matrix_key)
        if "position" in obj or "translation" in obj:
            pos = obj.get("position", obj.get("translation"))
            if "quat_xyzw" in obj:
                q = quat_wxyz_from_xyzw(_vec(obj["quat_xyzw"], 4, where, f"{what}: quat_xyzw"))
            elif "quat_wxyz" in obj:
                q = _vec(obj["quat_wxyz"], 4, where, f"{what}: quat_wxyz")
            else:
                bad = [k for k in ("quat", "quaternion", "orientation", "rotation") if k in obj]
                raise InputError(f"{what}: give the orientation as 'quat_xyzw' or 'quat_wxyz' (explicit order)"
                                 + (f", not {bad[0]!r}" if bad else ""), where)
            n = np.linalg.norm(q)
            if not (abs(n - 1.0) < 1e-3):
                raise InputError(f"{what}: quaternion is not unit length (norm {n:.4g})", where)
            return pose_from_pos_quat_wxyz(_vec(pos, 3, where, f"{what}: position"), q / n)
        raise InputError(f"{what}: expected '{matrix_key}' (4x4) or 'position' + 'quat_xyzw'/'quat_wxyz', "
                         f"got keys {sorted(obj)}", where)
    return pose_from_file_value(obj, what, where, rigid=True)


def _vec(v: Any, n: int, where: Path, what: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64).ravel()
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: not numeric", where) from e
    if a.size != n or not np.all(np.isfinite(a)):
        raise InputError(f"{what}: expected {n} finite numbers, got {v!r}", where)
    return a


def _units(data: Any, where: Path) -> float:
    """Metres per file unit from a mapping's optional `units` key (default metres)."""
    if not isinstance(data, dict) or "units" not in data:
        return 1.0
    u = data["units"]
    if not isinstance(u, str) or u.strip().lower() not in _UNITS:
        raise InputError(f"units must be 'm' or 'mm', got {str(u)[:40]!r}", where)
    return _UNITS[u.strip().lower()]


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    if s == 1.0:
        return T
    T = T.copy()
    T[:3, 3] *= s
    return T


def _check_hand_eye(T: np.ndarray, where: Path, units_given: bool) -> np.ndarray:
    d = float(np.linalg.norm(T[:3, 3]))
    if d > MAX_HAND_EYE_M:
        hint = ("" if units_given else "; if the file is in millimetres, add 'units: mm' (as a mapping "
                "{units: mm, T_ee_cam: ...}) or divide the translation by 1000")
        raise InputError(f"hand-eye: the camera is {d:.4g} m from the flange, more than {MAX_HAND_EYE_M:g} m: "
                         f"not a wrist camera's offset (expected T_ee_cam in metres){hint}", where)
    return T


def load_robot_poses(path: str | Path) -> tuple[list[RobotPose], np.ndarray | None]:
    """Read a robot pose file. Returns (poses, T_ee_cam if given inline else None), metres."""
    path = Path(path)
    data = _read_structured(path)
    scale = _units(data, path)
    units_given = isinstance(data, dict) and "units" in data
    inline = None
    if isinstance(data, dict):
        if "T_ee_cam" in data or "hand_eye" in data:
            inline = parse_transform(data.get("T_ee_cam", data.get("hand_eye")), path, "hand-eye", "T_ee_cam")
            inline = _check_hand_eye(_scaled(inline, scale), path, units_given)
        data = data.get("poses", data.get("frames"))
    if not isinstance(data, list) or not data:
        raise InputError("expected a non-empty list of end-effector poses (or {poses: [...]})", path)
    poses = []
    for i, entry in enumerate(data):
        image = None
        if isinstance(entry, dict):
            image = entry.get("image", entry.get("file_path", entry.get("name")))
            image = None if image is None else str(image)
        T = _scaled(parse_transform(entry, path, f"pose {i}", "T_base_ee"), scale)
        poses.append(RobotPose(T_base_ee=T, image=image))
    # a fixed-base arm's flange stays within reach of its base: farther means another unit (mm)
    reach = np.array([np.linalg.norm(p.T_base_ee[:3, 3]) for p in poses])
    far = int(np.argmax(reach))
    if reach[far] > MAX_REACH_M:
        hint = ("" if units_given else "; the file is probably in millimetres: write it as "
                "{units: mm, poses: [...]} or divide the positions by 1000")
        raise InputError(f"pose {far}: the end effector is {reach[far]:.4g} m from the robot base, beyond any "
                         f"fixed-base arm's reach (refused above {MAX_REACH_M:g} m; positions must be metres)"
                         f"{hint}", path)
    named = [p.image is not None for p in poses]
    if any(named) and not all(named):
        raise InputError("either every pose names its image or none does (then they follow the image order)", path)
    return poses, inline


def load_hand_eye(path: str | Path) -> np.ndarray:
    """Read a hand-eye calibration file: T_ee_cam [4,4] (camera frame in the end-effector frame)."""
    path = Path(path)
    data = _read_structured(path)
    units_given = isinstance(data, dict) and "units" in data
    T = _scaled(parse_transform(data, path, "hand-eye", "T_ee_cam"), _units(data, path))
    return _check_hand_eye(T, path, units_given)


EYE_TO_HAND = ("robot poses are for an eye-in-hand camera (mounted on the arm: T_base_cam = T_base_ee @ "
               "T_ee_cam); for a fixed camera (eye-to-hand) see README 'Robot poses'")


def camera_poses_in_base(poses: list[RobotPose], T_ee_cam: np.ndarray) -> list[np.ndarray]:
    """T_base_cam = T_base_ee @ T_ee_cam for each pose. Returns list of [4,4].

    Cheap plausibility checks of the eye-in-hand geometry (`check_eye_in_hand`)."""
    T = [p.T_base_ee @ T_ee_cam for p in poses]
    check_eye_in_hand(T)
    return T


def check_eye_in_hand(T_base_cam: list[np.ndarray]) -> None:
    """InputError when all cameras sit at one place (a fixed camera: no parallax to build from); a warning
    when their optical axes do not meet in front of most of them (cameras looking away from a common
    scene: an inverted hand-eye, T_cam_ee given for T_ee_cam, or a mis-mounted frame)."""
    if len(T_base_cam) < 2:
        return
    C = np.array([T[:3, 3] for T in T_base_cam])
    D = np.array([T[:3, 2] for T in T_base_cam])  # optical axes (OpenCV z forward)
    spread = float(np.max(np.linalg.norm(C - C.mean(axis=0), axis=1)))
    if spread < MIN_CAMERA_SPREAD_M:
        raise InputError(f"all {len(C)} cameras are at the same place (within {spread * 1000:.2g} mm) although "
                         f"the images should come from a moving arm: {EYE_TO_HAND}")
    # least-squares point nearest to all optical axes: sum (I - d d^T) p = sum (I - d d^T) c
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(C, D):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    ev = np.linalg.eigvalsh(A)
    if ev[0] < 0.05 * len(C):  # axes (nearly) parallel: no common point, nothing to check
        return
    p = np.linalg.solve(A, b)
    ahead = np.einsum("ij,ij->i", p - C, D)
    if np.mean(ahead > 0) < 0.5:
        log.warning("the cameras' optical axes meet %.2f m behind most of them (%d of %d look away from the "
                    "point nearest to all their axes): is the hand-eye inverted (T_cam_ee given for T_ee_cam)? %s",
                    float(-np.median(ahead)), int(np.sum(ahead <= 0)), len(C), EYE_TO_HAND)


def match_to_images(poses: list[RobotPose], image_names: list[str], where: Path) -> dict[str, np.ndarray]:
    """Map each image name to its T_base_ee. Names match by file name or stem; unnamed poses go by order."""
    if poses[0].image is None:
        if len(poses) != len(image_names):
            raise InputError(f"{len(poses)} robot poses but {len(image_names)} images; name the images "
                             f"('image' key) or give one pose per image in order", where)
        return {n: p.T_base_ee for n, p in zip(image_names, poses)}
    out: dict[str, np.ndarray] = {}
    lookup = {}
    for n in image_names:
        lookup[n] = n
        lookup[Path(n).name] = n
        lookup[Path(n).stem] = n
    first: dict[str, str] = {}
    for p in poses:
        key = p.image
        n = lookup.get(key) or lookup.get(Path(key).name) or lookup.get(Path(key).stem)
        if n is None:
            raise InputError(f"robot pose for image {key!r}: no such image in the dataset", where)
        if n in out:   # the later pose silently replaced the earlier one
            raise InputError(f"two robot poses for image {n!r} (given as {first[n]!r} and {key!r}); give one pose "
                             f"per image", where)
        out[n], first[n] = p.T_base_ee, key
    return out
