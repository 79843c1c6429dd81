"""Time parameterisation of joint paths within velocity and acceleration limits (TOPP-RA via `toppra`).

`time_parameterize(path, vel_limits, acc_limits, dt)` turns a piecewise-linear joint path [M, n] (rad), e.g.
from `plan_path`, into a `Trajectory` sampled every `dt` s that starts and ends at rest:

1. A cubic spline through the waypoints, parametrised by chord length, with extra knots `corner` rad
   before and after every interior waypoint (and along long segments) so it passes through every waypoint
   and stays within a few mrad of the straight segments instead of swinging wide at corners.
2. TOPP-RA (`toppra.algorithm.TOPPRA`, `ParametrizeConstAccel`) finds the time-optimal speed along the
   spline under joint velocity and acceleration limits; limits are applied with a small safety factor.
3. Verification of the sampled result: velocities/accelerations (analytic and finite differences) within
   the limits, every sample within `path_tol` rad of the geometric path, and, when a `CollisionChecker` is
   given, the sampled trajectory densely re-checked. If anything fails, the fallback is exact: straight
   segments, each with a time-optimal trapezoidal profile that stops at every waypoint (written here because
   it is a closed form a few lines long; toppra would only reproduce it numerically).

Units: rad, s, rad/s, rad/s². The sampling grid is exactly `dt`: the time-optimal duration is stretched up
to the next multiple of dt, which only lowers speeds and accelerations.
"""

from __future__ import annotations

import logging
import math
from typing import Sequence

import numpy as np

from splattwin.robot.trajectory import Trajectory

__all__ = ["PANDA_VEL_LIMITS", "PANDA_ACC_LIMITS", "time_parameterize", "trapezoid_segments",
           "path_deviation", "check_limits"]

#: rad/s, Franka Emika Panda datasheet joint velocity limits.
PANDA_VEL_LIMITS = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
#: rad/s², conservative Panda joint acceleration limits (a quarter of the datasheet's 15, 7.5, 10, 12.5,
#: 15, 20, 20): smooth motions for the position servos; scale with `acc_scale`.
PANDA_ACC_LIMITS = np.array([3.75, 1.875, 2.5, 3.125, 3.75, 5.0, 5.0])

log = logging.getLogger(__name__)


def _dedupe(path: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    keep = [0] + [k for k in range(1, len(path)) if np.max(np.abs(path[k] - path[k - 1])) > tol]
    return path[keep]


def path_deviation(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Euclidean joint-space distance (rad) of each point [K,n] to the polyline `path` [M,n]. Returns [K]."""
    points = np.atleast_2d(points)
    path = np.atleast_2d(path)
    if len(path) == 1:
        return np.linalg.norm(points - path[0], axis=1)
    a, b = path[:-1], path[1:]                                    # [S,n]
    ab = b - a
    denom = np.maximum(np.einsum("sn,sn->s", ab, ab), 1e-18)
    ap = points[:, None, :] - a[None]                             # [K,S,n]
    u = np.clip(np.einsum("ksn,sn->ks", ap, ab) / denom, 0.0, 1.0)
    closest = a[None] + u[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None, :] - closest, axis=-1), axis=1)


def check_limits(traj: Trajectory, vel_limits: np.ndarray, acc_limits: np.ndarray, rtol: float = 1e-6) -> str | None:
    """Describe the first velocity/acceleration limit violation (sampled values and finite differences)."""
    v = np.asarray(vel_limits) * (1 + rtol) + 1e-9
    a = np.asarray(acc_limits) * (1 + rtol) + 1e-9
    if np.any(np.abs(traj.qd) > v):
        return f"velocity {np.max(np.abs(traj.qd) / v):.3f}x the limit"
    if np.any(np.abs(traj.qdd) > a):
        return f"acceleration {np.max(np.abs(traj.qdd) / a):.3f}x the limit"
    if len(traj.t) > 2:
        h = np.diff(traj.t)[:, None]
        vel_fd = np.diff(traj.q, axis=0) / h
        if np.any(np.abs(vel_fd) > v):
            return f"finite-difference velocity {np.max(np.abs(vel_fd) / v):.3f}x the limit"
        acc_fd = np.diff(vel_fd, axis=0) / (0.5 * (h[1:] + h[:-1]))
        if np.any(np.abs(acc_fd) > a):
            return f"finite-difference acceleration {np.max(np.abs(acc_fd) / a):.3f}x the limit"
    return None


def _spline_knots(path: np.ndarray, corner: float, max_step: float) -> np.ndarray:
    """Waypoints plus knots `corner` rad either side of each interior waypoint and every <= max_step rad."""
    out = [path[0]]
    n_seg = len(path) - 1
    for k in range(n_seg):
        a, b = path[k], path[k + 1]
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        e = min(corner, 0.3 * length)
        lo = e if k > 0 else 0.0
        hi = length - e if k < n_seg - 1 else length
        stops = [lo] if lo > 0 else []
        inner = hi - lo
        m = max(1, int(math.ceil(inner / max_step)))
        stops += [lo + inner * i / m for i in range(1, m)]
        if hi < length:
            stops.append(hi)
        out.extend(a + s * u for s in stops)
        out.append(b)
    return np.asarray(out)


def _sample_uniform(duration: float, dt: float, evaluate) -> Trajectory:
    """Sample q(t), qd, qdd for t in [0, duration] on a grid of exactly dt, stretching time to N*dt."""
    n = max(1, int(math.ceil(duration / dt - 1e-9)))
    k = duration / (n * dt)                       # <= 1: time stretch factor
    t = np.arange(n + 1) * dt
    q, qd, qdd = evaluate(np.minimum(t * k, duration))
    return Trajectory(t, q, qd * k, qdd * k * k)


def _toppra(path: np.ndarray, vel: np.ndarray, acc: np.ndarray, dt: float, corner: float) -> Trajectory:
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    knots = _spline_knots(path, corner, max_step=0.25)
    ss = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
    geom = ta.SplineInterpolator(ss, knots)
    pc_vel = constraint.JointVelocityConstraint(np.stack([-vel, vel], axis=1))
    pc_acc = constraint.JointAccelerationConstraint(
        np.stack([-acc, acc], axis=1), discretization_scheme=constraint.DiscretizationType.Interpolation)
    # gridpoints: dense near corners, where curvature limits speed
    grid = np.unique(np.concatenate([np.linspace(0, ss[-1], max(50, int(ss[-1] / 0.01))), ss]))
    inst = algo.TOPPRA([pc_vel, pc_acc], geom, gridpoints=grid, parametrizer="ParametrizeConstAccel")
    jt = inst.compute_trajectory(0.0, 0.0)
    if jt is None:
        raise RuntimeError("TOPP-RA found no feasible parameterisation")

    def evaluate(t: np.ndarray):
        return jt(t), jt(t, 1), jt(t, 2)

    traj = _sample_uniform(float(jt.duration), dt, evaluate)
    traj.q[0], traj.q[-1] = path[0], path[-1]    # spline endpoints are the waypoints up to round-off
    traj.qd[0] = traj.qd[-1] = 0.0
    return traj


def trapezoid_segments(path: np.ndarray, vel: np.ndarray, acc: np.ndarray, dt: float) -> Trajectory:
    """Exact fallback: straight segments, each a time-optimal trapezoidal (or triangular) profile, rest to rest.

    For segment Δ the path coordinate s in [0,1] obeys |ṡ| <= min_i v_i/|Δ_i|, |s̈| <= min_i a_i/|Δ_i|.
    """
    path = np.atleast_2d(path)
    segs = []
    for a, b in zip(path[:-1], path[1:]):
        d = b - a
        ad = np.abs(d)
        nz = ad > 1e-12
        vs = float(np.min(vel[nz] / ad[nz]))
        as_ = float(np.min(acc[nz] / ad[nz]))
        if vs * vs / as_ >= 1.0:                  # triangular: never reaches vs
            vs = math.sqrt(as_)
            t_acc, t_flat = vs / as_, 0.0
        else:
            t_acc, t_flat = vs / as_, 1.0 / vs - vs / as_
        segs.append((a, d, vs, as_, t_acc, t_flat, 2 * t_acc + t_flat))
    total = sum(s[-1] for s in segs)
    starts = np.concatenate([[0.0], np.cumsum([s[-1] for s in segs])])

    def evaluate(t: np.ndarray):
        n = path.shape[1]
        q, qd, qdd = np.empty((len(t), n)), np.empty((len(t), n)), np.empty((len(t), n))
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(segs) - 1)
        for j, (a, d, vs, as_, ta_, tf, T) in enumerate(segs):
            m = idx == j
            tau = np.clip(t[m] - starts[j], 0.0, T)
            s = np.where(tau < ta_, 0.5 * as_ * tau ** 2,
                         np.where(tau < ta_ + tf, 0.5 * as_ * ta_ ** 2 + vs * (tau - ta_),
                                  1.0 - 0.5 * as_ * (T - tau) ** 2))
            sd = np.where(tau < ta_, as_ * tau, np.where(tau < ta_ + tf, vs, as_ * (T - tau)))
            sdd = np.where(tau < ta_, as_, np.where(tau < ta_ + tf, 0.0, -as_))
            q[m] = a + s[:, None] * d
            qd[m] = sd[:, None] * d
            qdd[m] = sdd[:, None] * d
        return q, qd, qdd

    traj = _sample_uniform(total, dt, evaluate)
    traj.q[-1] = path[-1]
    traj.qd[-1] = 0.0
    return traj


def time_parameterize(path: np.ndarray, vel_limits: Sequence[float] | np.ndarray = PANDA_VEL_LIMITS,
                      acc_limits: Sequence[float] | np.ndarray = PANDA_ACC_LIMITS, dt: float = 0.01, *,
                      vel_scale: float = 1.0, acc_scale: float = 1.0, checker=None,
                      joint_names: Sequence[str] | None = None, path_tol: float = 0.01,
                      corner: float = 0.05, check_resolution: float | None = None,
                      max_sweep: float | None = None, method: str = "toppra") -> Trajectory:
    """Time-parameterise a joint path [M, n] (rad) into a rest-to-rest `Trajectory` sampled every dt s.

    Args:
        vel_limits, acc_limits: [n] rad/s, rad/s² (defaults: the Panda's).
        vel_scale, acc_scale: factors in (0, 1] applied to the limits (slower, gentler motions).
        checker: optional `CollisionChecker`; the sampled spline trajectory must pass its dense re-check
            (`check_resolution` / `max_sweep` as in `plan_path`; default max_sweep = margin / 2). The
            straight-segment fallback lies exactly on the (already checked) path and needs no re-check.
        path_tol: rad, largest allowed distance of any sample from the waypoints' polyline.
        corner: rad, distance of the extra spline knots either side of each interior waypoint.
        method: "toppra" (spline + TOPP-RA, falling back to "trapezoid" when verification fails) or
            "trapezoid" (straight segments, stop at each waypoint).
    """
    path = np.atleast_2d(np.asarray(path, dtype=float))
    if path.ndim != 2 or len(path) == 0:
        raise ValueError(f"path must be [M, n], got {path.shape}")
    n = path.shape[1]
    vel = np.asarray(vel_limits, dtype=float).reshape(-1) * vel_scale
    acc = np.asarray(acc_limits, dtype=float).reshape(-1) * acc_scale
    if vel.shape != (n,) or acc.shape != (n,):
        raise ValueError(f"limits must have {n} values, got {vel.shape}, {acc.shape}")
    if np.any(vel <= 0) or np.any(acc <= 0) or dt <= 0:
        raise ValueError("limits, scales and dt must be positive")
    if method not in ("toppra", "trapezoid"):
        raise ValueError(f"unknown method {method!r} (toppra | trapezoid)")
    names = list(joint_names) if joint_names is not None else (
        list(checker.joint_names) if checker is not None and getattr(checker, "dof", None) == n else [])
    path = _dedupe(path)
    if len(path) == 1:
        z = np.zeros((1, n))
        return Trajectory(np.zeros(1), path.copy(), z, z.copy(), names)

    def verified(traj: Trajectory) -> str | None:
        problem = check_limits(traj, vel, acc)
        if problem is None:
            dev = float(np.max(path_deviation(traj.q, path)))
            if dev > path_tol:
                problem = f"deviates {dev:.4f} rad from the path (tolerance {path_tol})"
        if problem is None and checker is not None and check_collisions:
            sweep = max_sweep if (max_sweep is not None or check_resolution is not None) else \
                max(0.5 * checker.margin, 0.001)
            if not checker.path_is_valid(traj.q, check_resolution, sweep):
                problem = "the sampled trajectory collides"
        return problem

    check_collisions = True

    if method == "toppra":
        safety = 0.97
        for attempt in range(3):
            try:
                traj = _toppra(path, vel * safety, acc * safety, dt, corner)
            except Exception as e:  # toppra raises plain exceptions on infeasible/degenerate input
                log.info("TOPP-RA failed (%s); falling back to trapezoidal segments", e)
                break
            traj.joint_names = names or traj.joint_names
            problem = verified(traj)
            if problem is None:
                return traj
            log.info("TOPP-RA result rejected (%s), attempt %d", problem, attempt + 1)
            if "limit" in problem:
                safety *= 0.9       # between TOPP-RA grid points the limits can be exceeded slightly
            else:
                corner *= 0.3       # tighter corners: closer to the polyline
    traj = trapezoid_segments(path, vel, acc, dt)
    traj.joint_names = names or traj.joint_names
    check_collisions = False     # exactly on the given path
    problem = verified(traj)
    if problem is not None:      # closed form within the limits by construction: a bug if this fires
        raise RuntimeError(f"time parameterisation failed its own verification: {problem}")
    return traj
