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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from splattwin.errors import InputError
from splattwin.transforms import pose_from_file_value, pose_from_pos_quat_wxyz, quat_wxyz_from_xyzw


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


def load_robot_poses(path: str | Path) -> tuple[list[RobotPose], np.ndarray | None]:
    """Read a robot pose file. Returns (poses, T_ee_cam if given inline else None)."""
    path = Path(path)
    data = _read_structured(path)
    inline = None
    if isinstance(data, dict):
        if "T_ee_cam" in data or "hand_eye" in data:
            inline = parse_transform(data.get("T_ee_cam", data.get("hand_eye")), path, "hand-eye", "T_ee_cam")
        data = data.get("poses", data.get("frames"))
    if not isinstance(data, list) or not data:
        raise InputError("expected a non-empty list of end-effector poses (or {poses: [...]})", path)
    poses = []
    for i, entry in enumerate(data):
        image = None
        if isinstance(entry, dict):
            image = entry.get("image", entry.get("file_path", entry.get("name")))
            image = None if image is None else str(image)
        poses.append(RobotPose(T_base_ee=parse_transform(entry, path, f"pose {i}", "T_base_ee"), image=image))
    named = [p.image is not None for p in poses]
    if any(named) and not all(named):
        raise InputError("either every pose names its image or none does (then they follow the image order)", path)
    return poses, inline


def load_hand_eye(path: str | Path) -> np.ndarray:
    """Read a hand-eye calibration file: T_ee_cam [4,4] (camera frame in the end-effector frame)."""
    path = Path(path)
    return parse_transform(_read_structured(path), path, "hand-eye", "T_ee_cam")


def camera_poses_in_base(poses: list[RobotPose], T_ee_cam: np.ndarray) -> list[np.ndarray]:
    """T_base_cam = T_base_ee @ T_ee_cam for each pose. Returns list of [4,4]."""
    return [p.T_base_ee @ T_ee_cam for p in poses]


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
    for p in poses:
        key = p.image
        n = lookup.get(key) or lookup.get(Path(key).name) or lookup.get(Path(key).stem)
        if n is None:
            raise InputError(f"robot pose for image {key!r}: no such image in the dataset", where)
        out[n] = p.T_base_ee
    return out
