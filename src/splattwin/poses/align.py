"""Similarity transforms (Sim(3)): Umeyama alignment and applying a similarity to cameras and points.

A similarity is stored as a [4,4] matrix S = [[s R, t], [0, 1]] mapping points from a source frame to a
target frame (`S_tgt_src`). Umeyama is written here (a dozen lines of numpy) rather than taken from
`pycolmap.estimate_sim3d` because we also need the residuals and a scale-uncertainty estimate; the
tests check it against pycolmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splattwin.capture.camera import Camera


@dataclass
class Sim3Fit:
    """Umeyama fit tgt ≈ s R src + t.

    S: [4,4] similarity (tgt <- src). scale: s. residuals: [N] metres (target units), per point.
    scale_uncertainty_rel: 1-sigma relative scale uncertainty from the residual scatter.
    """

    S: np.ndarray
    scale: float
    residuals: np.ndarray
    scale_uncertainty_rel: float

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2))) if self.residuals.size else 0.0


def umeyama(src: np.ndarray, tgt: np.ndarray, with_scale: bool = True) -> Sim3Fit:
    """Least-squares similarity tgt ≈ s R src + t (Umeyama 1991).

    Args: src, tgt [N,3], N >= 3 not collinear. Returns Sim3Fit. Raises ValueError on degenerate input.
    """
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    if src.shape != tgt.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need matching [N,3] point sets with N >= 3, got {src.shape} and {tgt.shape}")
    mu_s, mu_t = src.mean(0), tgt.mean(0)
    xs, xt = src - mu_s, tgt - mu_t
    var_s = float(np.mean(np.sum(xs ** 2, axis=1)))
    if var_s < 1e-24:
        raise ValueError("source points coincide")
    cov = xt.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    if D[1] < 1e-12 * max(D[0], 1e-300):
        raise ValueError("points are collinear: rotation is undetermined")
    E = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1.0
    R = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / var_s) if with_scale else 1.0
    t = mu_t - s * R @ mu_s
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    res = np.linalg.norm(src @ (s * R).T + t - tgt, axis=1)
    # Scale is a ratio of spreads: its relative error ~ residual scatter / (target spread * sqrt(N - dof)).
    dof = max(len(src) - 7.0 / 3.0, 1.0)
    spread = np.sqrt(np.mean(np.sum(xt ** 2, axis=1)))
    unc = float(np.sqrt(np.sum(res ** 2) / dof) / (spread * np.sqrt(len(src))))
    return Sim3Fit(S=S, scale=s, residuals=res, scale_uncertainty_rel=unc)


def sim3_scale(S: np.ndarray) -> float:
    """Scale factor s of a similarity [4,4]."""
    return float(np.cbrt(np.linalg.det(S[:3, :3])))


def sim3_inverse(S: np.ndarray) -> np.ndarray:
    """Inverse similarity [4,4]."""
    s = sim3_scale(S)
    R = S[:3, :3] / s
    out = np.eye(4)
    out[:3, :3] = R.T / s
    out[:3, 3] = -(R.T @ S[:3, 3]) / s
    return out


def transform_points(S: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a similarity/rigid [4,4] to points [N,3]."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    return p @ S[:3, :3].T + S[:3, 3]


def transform_pose(S: np.ndarray, T_src_cam: np.ndarray) -> np.ndarray:
    """Camera-to-world pose [4,4] in the source frame -> the same camera in the target frame (rigid result)."""
    s = sim3_scale(S)
    T = np.eye(4)
    T[:3, :3] = (S[:3, :3] / s) @ T_src_cam[:3, :3]
    T[:3, 3] = S[:3, :3] @ T_src_cam[:3, 3] + S[:3, 3]
    return T


def transform_camera(S: np.ndarray, cam: Camera) -> Camera:
    """A Camera moved into the target frame of similarity S (intrinsics unchanged)."""
    return Camera(K=cam.K, width=cam.width, height=cam.height, T_world_cam=transform_pose(S, cam.T_world_cam),
                  dist=cam.dist, name=cam.name)
