"""The transforms module against MuJoCo's own quaternion routines and analytic cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from splattwin.transforms import (invert_pose, make_pose, matrix_from_quat_wxyz, pos_quat_wxyz_from_pose,
                                  pose_from_pos_quat_wxyz, pose_xyz_yaw, quat_mul_wxyz, quat_wxyz_from_matrix,
                                  quat_wxyz_from_xyzw, quat_wxyz_z_to, quat_xyzw_from_wxyz, rot_z, yaw_of,
                                  pose_from_file_value, mujoco_quat_wxyz_from_matrix)


def _random_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_quaternions_match_mujoco():
    import mujoco

    for q in _random_quats(50):
        R_mj = np.zeros(9)
        mujoco.mju_quat2Mat(R_mj, q)
        R = matrix_from_quat_wxyz(q)
        np.testing.assert_allclose(R, R_mj.reshape(3, 3), atol=1e-12)
        q_back = quat_wxyz_from_matrix(R)
        q_mj = np.zeros(4)
        mujoco.mju_mat2Quat(q_mj, R.ravel())
        assert q_back[0] >= 0 and abs(abs(q_back @ q_mj) - 1) < 1e-12    # same rotation, canonical sign
        assert abs(abs(q_back @ q) - 1) < 1e-12


def test_known_rotations_and_orders():
    q = np.array([math.cos(0.25), 0.0, 0.0, math.sin(0.25)])      # 0.5 rad about z, wxyz
    np.testing.assert_allclose(matrix_from_quat_wxyz(q), rot_z(0.5), atol=1e-15)
    np.testing.assert_allclose(quat_xyzw_from_wxyz(q), [0, 0, math.sin(0.25), math.cos(0.25)])
    np.testing.assert_array_equal(quat_wxyz_from_xyzw(quat_xyzw_from_wxyz(q)), q)
    np.testing.assert_allclose(quat_wxyz_from_matrix(np.eye(3)), [1, 0, 0, 0])
    # a 180 deg turn about x: w = 0
    np.testing.assert_allclose(np.abs(quat_wxyz_from_matrix(np.diag([1.0, -1.0, -1.0]))), [0, 1, 0, 0], atol=1e-15)
    assert yaw_of(rot_z(2.5)) == pytest.approx(2.5) and yaw_of(pose_xyz_yaw(1, 2, 3, -1.0)) == pytest.approx(-1.0)


def test_batched_poses_roundtrip_and_invert():
    q = _random_quats(24, seed=1).reshape(2, 3, 4, 4)
    p = np.random.default_rng(2).normal(size=(2, 3, 4, 3))
    T = pose_from_pos_quat_wxyz(p, q)
    assert T.shape == (2, 3, 4, 4, 4)
    p2, q2 = pos_quat_wxyz_from_pose(T)
    np.testing.assert_allclose(p2, p)
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, axis=-1)), 1.0, atol=1e-12)
    Ti = invert_pose(T)
    np.testing.assert_allclose(Ti @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Ti[0, 1, 2], np.linalg.inv(T[0, 1, 2]), atol=1e-12)
    assert quat_wxyz_from_matrix(np.zeros((0, 3, 3))).shape == (0, 4)
    assert matrix_from_quat_wxyz(np.zeros((0, 4))).shape == (0, 3, 3)
    np.testing.assert_array_equal(make_pose(), np.eye(4))
    with pytest.raises(ValueError):
        quat_wxyz_from_matrix(np.eye(4))


def test_quat_mul_matches_mujoco_and_keeps_sign():
    import mujoco

    a, b = _random_quats(30, seed=3), _random_quats(30, seed=4)
    ab = quat_mul_wxyz(a, 2.5 * b)                              # inputs are normalised first
    for qa, qb, q in zip(a, b, ab):
        q_mj = np.zeros(4)
        mujoco.mju_mulQuat(q_mj, qa, qb)
        np.testing.assert_allclose(q, q_mj, atol=1e-14)      # same sign as the Hamilton product
    np.testing.assert_allclose(matrix_from_quat_wxyz(ab), matrix_from_quat_wxyz(a) @ matrix_from_quat_wxyz(b), atol=1e-12)
    a0_b = quat_mul_wxyz(a[0], b)                               # one [4] broadcast over [N,4]
    assert a0_b.shape == (30, 4)
    np.testing.assert_array_equal(a0_b[3], quat_mul_wxyz(a[0], b[3]))
    np.testing.assert_allclose(quat_mul_wxyz(a[0], -b), -a0_b, atol=1e-15)   # sign follows the inputs
    assert quat_mul_wxyz(np.zeros((0, 4)), np.zeros((0, 4))).shape == (0, 4)
    z = b.copy()
    z[7] = 0.0                                                  # a zero quaternion is the identity
    np.testing.assert_allclose(quat_mul_wxyz(a[0], z)[7], a[0] / np.linalg.norm(a[0]), atol=1e-15)
    np.testing.assert_allclose(quat_mul_wxyz(z[7], a)[2], a[2] / np.linalg.norm(a[2]), atol=1e-15)
    ab_grid = quat_mul_wxyz(a[:3, None], b[None, :5])           # [3,1,4] x [1,5,4] -> [3,5,4]
    assert ab_grid.shape == (3, 5, 4)
    np.testing.assert_array_equal(ab_grid[2, 4], quat_mul_wxyz(a[2], b[4]))
    with pytest.raises(ValueError, match="4"):
        quat_mul_wxyz(np.ones(3), np.ones(4))


def test_zero_quaternion_is_identity():
    q = np.array([[0.0, 0, 0, 0], [0.0, 0, 0, 2.0]])
    R = matrix_from_quat_wxyz(q)
    np.testing.assert_array_equal(R[0], np.eye(3))
    np.testing.assert_allclose(R[1], rot_z(math.pi), atol=1e-15)


def test_canonical_flag_only_changes_the_sign():
    from scipy.spatial.transform import Rotation

    R = Rotation.random(40, random_state=5).as_matrix()
    q_c, q_s = quat_wxyz_from_matrix(R), quat_wxyz_from_matrix(R, canonical=False)
    assert np.all(q_c[:, 0] >= 0)
    np.testing.assert_array_equal(q_s, quat_wxyz_from_xyzw(Rotation.from_matrix(R).as_quat()))  # scipy's own sign
    np.testing.assert_array_equal(np.abs(q_c), np.abs(q_s))
    assert np.any(q_s[:, 0] < 0)


def test_quat_z_to_takes_z_onto_directions():
    n = np.random.default_rng(6).normal(size=(50, 3))
    n = np.concatenate([n, [[0, 0, 1.0], [0, 0, -1.0], [0, 0, -3.0], [1e-9, 0, -1.0]]])
    q = quat_wxyz_z_to(n)
    R = matrix_from_quat_wxyz(q)
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(R[..., 2], unit, atol=1e-12)            # +z lands on n
    np.testing.assert_allclose(q[-4], [1, 0, 0, 0])                    # already +z: no turn
    np.testing.assert_allclose(q[-3], [0, 1, 0, 0], atol=1e-15)        # -z: half a turn about x
    # shortest rotation: its axis is perpendicular to both z and n (no spin about n)
    axis = q[:-4, 1:]
    np.testing.assert_allclose(axis[:, 2], 0.0, atol=1e-15)
    np.testing.assert_allclose(np.einsum("ij,ij->i", axis, unit[:-4]), 0.0, atol=1e-12)


def test_pose_from_file_value_checks_what_a_file_gave():
    from splattwin.errors import InputError

    T = pose_xyz_yaw(0.1, 0.2, 0.3, 0.4)
    np.testing.assert_array_equal(pose_from_file_value(T.tolist(), "T"), T)
    np.testing.assert_array_equal(pose_from_file_value(T[:3].tolist(), "T", rigid=True), T)   # 3x4 completed
    scaled = T.copy()
    scaled[:3, :3] *= 2.0
    np.testing.assert_array_equal(pose_from_file_value(scaled.tolist(), "T"), scaled)          # not rigid: fine
    for bad, msg in [([[1, 0], [0, 1]], "expected a 4x4 matrix"), ([["a"] * 4] * 4, "not a numeric matrix"),
                     ([[float("nan")] * 4] * 4, "not finite"), (None, "expected a 4x4 matrix")]:
        with pytest.raises(InputError, match=msg) as e:
            pose_from_file_value(bad, "T_x", "f.json")
        assert "T_x" in str(e.value) and "f.json" in str(e.value)
    for bad in (scaled, np.diag([1.0, 1.0, -1.0, 1.0])):                                       # scale, mirror
        with pytest.raises(InputError, match="not a rigid transform"):
            pose_from_file_value(bad.tolist(), "T", rigid=True)


def test_mujoco_conversion_is_mujocos_and_the_same_rotation():
    import mujoco
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(20, random_state=8).as_matrix():
        q = mujoco_quat_wxyz_from_matrix(R)
        q_mj = np.zeros(4)
        mujoco.mju_mat2Quat(q_mj, R.ravel())
        np.testing.assert_array_equal(q, q_mj)
        assert abs(abs(q @ quat_wxyz_from_matrix(R)) - 1) < 1e-12
