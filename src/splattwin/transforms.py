"""Rotations, quaternions and rigid transforms: the one place that knows quaternion orders.

Built on `scipy.spatial.transform.Rotation` (vectorised over any leading batch shape); nothing here is
hand-written rotation algebra beyond 4x4 bookkeeping.

Conventions (docs/CONTRACTS.md):
* In memory quaternions are **wxyz** (scalar first: MuJoCo, gsplat/3DGS, viser, mink) and are named
  `quat_wxyz`. The **xyzw** order (scipy, ROS, glTF, MoveIt scene files) appears only at a file or
  library boundary, through `quat_xyzw_from_wxyz` / `quat_wxyz_from_xyzw`.
* `T_a_b` [..., 4, 4] maps points in frame b to frame a (metres); `R_a_b` [..., 3, 3] its rotation.
* Quaternions returned here are unit length with w >= 0 (one of the two equivalent signs, chosen so
  that results are reproducible), except where a function says otherwise (`canonical=False`).
* Zero-length input quaternions (e.g. a degenerate splat in a PLY) are read as the identity rotation.
* The torch (differentiable) quaternion -> matrix used by the rasterizers and densification is
  `splattwin.splat.reference.quat_to_rotmat`; the numba kernels keep their own inlined copy.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["quat_xyzw_from_wxyz", "quat_wxyz_from_xyzw", "quat_wxyz_from_matrix", "matrix_from_quat_wxyz",
           "quat_mul_wxyz", "quat_wxyz_z_to", "mujoco_quat_wxyz_from_matrix", "pose_from_pos_quat_wxyz", "pos_quat_wxyz_from_pose", "make_pose",
           "invert_pose", "rot_z", "yaw_of", "pose_xyz_yaw", "pose_from_file_value"]


def quat_xyzw_from_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    """[..., 4] wxyz -> [..., 4] xyzw (same rotation, for scipy / ROS / glTF)."""
    q = np.asarray(quat_wxyz, dtype=float)
    return np.concatenate([q[..., 1:4], q[..., :1]], axis=-1)


def quat_wxyz_from_xyzw(quat_xyzw: np.ndarray) -> np.ndarray:
    """[..., 4] xyzw -> [..., 4] wxyz."""
    q = np.asarray(quat_xyzw, dtype=float)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def _rotations(R: np.ndarray):
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must be [..., 3, 3], got {R.shape}")
    return Rotation.from_matrix(R.reshape(-1, 3, 3)), R.shape[:-2]


def quat_wxyz_from_matrix(R: np.ndarray, canonical: bool = True) -> np.ndarray:
    """Rotation matrices [..., 3, 3] -> unit quaternions [..., 4] wxyz.

    canonical=True: the sign with w >= 0. canonical=False: scipy's own choice (Shepperd's method: the
    component computed from the largest of trace and diagonal is positive), which the embedded-scene
    generator and the twin's splat files were first written with; kept there so their bytes do not
    change (either sign is the same rotation)."""
    rot, batch = _rotations(R)
    if not len(rot):
        return np.zeros((*batch, 4))
    q = quat_wxyz_from_xyzw(rot.as_quat(canonical=canonical))
    return q.reshape(*batch, 4)


def mujoco_quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> [4] wxyz quaternion by MuJoCo's own `mju_mat2Quat`, for quaternions written into
    MuJoCo models (MJCF bodies). Same rotation as `quat_wxyz_from_matrix`, but the sign and the last bit
    can differ, and MuJoCo's contact dynamics amplify a 1-ulp change of an object's pose into millimetres
    over a pick-and-place rollout: with MuJoCo's conversion the models and rollouts stay bit-identical
    to those MuJoCo makes from the matrix (and to earlier splattwin versions)."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).reshape(9))
    return q


def _scipy_rotations_wxyz(quat_wxyz: np.ndarray):
    """(scipy Rotation of the flattened [M, 4] wxyz quaternions, batch shape); zero-length rows -> identity."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(quat_wxyz, dtype=float)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must be [..., 4], got {q.shape}")
    batch = q.shape[:-1]
    flat = q.reshape(-1, 4)
    if not len(flat):
        return None, batch
    zero = ~np.any(flat != 0.0, axis=1)
    if zero.any():
        flat = flat.copy()
        flat[zero] = (1.0, 0.0, 0.0, 0.0)
    return Rotation.from_quat(quat_xyzw_from_wxyz(flat)), batch


def matrix_from_quat_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    """Quaternions [..., 4] wxyz (normalised here) -> rotation matrices [..., 3, 3]."""
    rot, batch = _scipy_rotations_wxyz(quat_wxyz)
    if rot is None:
        return np.zeros((*batch, 3, 3))
    return rot.as_matrix().reshape(*batch, 3, 3)


def quat_mul_wxyz(a_wxyz: np.ndarray, b_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product a * b (apply b, then a) of wxyz quaternions, broadcast over [..., 4] -> [..., 4].

    Both are normalised first (a zero quaternion is the identity, as everywhere here); the result is unit
    length and keeps the product's sign (not made canonical), so a * q and a * (-q) stay opposite like the
    inputs. Written out rather than through scipy's Rotation: the playback moves every object's Gaussians
    with it each frame, and the Rotation round trip cost ~12 ms per 9k Gaussians."""
    a, b = np.broadcast_arrays(_unit_wxyz(a_wxyz), _unit_wxyz(b_wxyz))
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _unit_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    """[..., 4] wxyz quaternions normalised; zero rows -> the identity (1, 0, 0, 0)."""
    q = np.asarray(quat_wxyz, dtype=float)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must be [..., 4], got {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))


def quat_wxyz_z_to(directions: np.ndarray) -> np.ndarray:
    """[..., 3] directions (normalised here) -> [..., 4] wxyz quaternions of the shortest rotation taking
    +z onto them (-z: half a turn about x)."""
    from scipy.spatial.transform import Rotation

    n = np.asarray(directions, dtype=float)
    batch = n.shape[:-1]
    n = n.reshape(-1, 3) / np.linalg.norm(n.reshape(-1, 3), axis=1, keepdims=True)
    axis = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)   # z x n
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, n[:, 2])
    unit = np.where(s[:, None] > 0, axis / np.where(s > 0, s, 1.0)[:, None], [[1.0, 0.0, 0.0]])
    if not len(n):
        return np.zeros((*batch, 4))
    q = Rotation.from_rotvec(unit * angle[:, None]).as_quat(canonical=True)
    return quat_wxyz_from_xyzw(q).reshape(*batch, 4)


def make_pose(R: np.ndarray | None = None, p: np.ndarray | None = None) -> np.ndarray:
    """T [..., 4, 4] from a rotation [..., 3, 3] (identity if None) and a translation [..., 3] (0 if None)."""
    batch = np.broadcast_shapes(np.shape(R)[:-2] if R is not None else (), np.shape(p)[:-1] if p is not None else ())
    T = np.zeros((*batch, 4, 4))
    T[..., :3, :3] = np.eye(3) if R is None else R
    if p is not None:
        T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def pose_from_pos_quat_wxyz(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """Position [..., 3] (m) and quaternion [..., 4] wxyz -> T [..., 4, 4] (e.g. a MuJoCo free joint's qpos)."""
    return make_pose(matrix_from_quat_wxyz(quat_wxyz), np.asarray(pos, dtype=float))


def pos_quat_wxyz_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T [..., 4, 4] -> (position [..., 3] m, quaternion [..., 4] wxyz)."""
    T = np.asarray(T, dtype=float)
    return T[..., :3, 3].copy(), quat_wxyz_from_matrix(T[..., :3, :3])


def invert_pose(T_a_b: np.ndarray) -> np.ndarray:
    """T_b_a from T_a_b [..., 4, 4] (rigid: R^T, -R^T p)."""
    T = np.asarray(T_a_b, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def pose_from_file_value(value, what: str, where=None, rigid: bool = False) -> np.ndarray:
    """T [4, 4] float64 from a value read from a file: a 4x4 (or 3x4, completed with 0 0 0 1) nested list
    of finite numbers. rigid=True also requires an orthonormal, right-handed rotation (to 1e-4) and the
    last row 0 0 0 1. Anything else: InputError("<what>: <problem>", where)."""
    from splattwin.errors import InputError

    try:
        M = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: not a numeric matrix ({e})", where) from None
    if M.shape == (3, 4):
        M = np.vstack([M, [0, 0, 0, 1.0]])
    if M.shape != (4, 4):
        raise InputError(f"{what}: expected a 4x4 matrix, got shape {M.shape}", where)
    if not np.all(np.isfinite(M)):
        raise InputError(f"{what}: matrix is not finite", where)
    R = M[:3, :3]
    if rigid and (not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0
                  or not np.allclose(M[3], [0, 0, 0, 1])):
        raise InputError(f"{what}: not a rigid transform (rotation part must be orthonormal, last row 0 0 0 1)", where)
    return M


def rot_z(yaw: float) -> np.ndarray:
    """[3, 3] rotation by `yaw` rad about +z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_of(R: np.ndarray) -> float:
    """rad: heading of a rotation's x axis in the xy plane (atan2 of R[1,0], R[0,0]); R [3,3] or T [4,4]."""
    R = np.asarray(R, dtype=float)
    return math.atan2(float(R[1, 0]), float(R[0, 0]))


def pose_xyz_yaw(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """T [4, 4] translated to (x, y, z) m and rotated by `yaw` rad about +z."""
    return make_pose(rot_z(yaw), np.array([x, y, z], dtype=float))
