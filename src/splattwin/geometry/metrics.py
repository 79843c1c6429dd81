"""Geometric fidelity against ground truth (paper Table 5): Chamfer distance, precision, recall, F1.

Distances are nearest-neighbour distances (scipy cKDTree) between the reconstructed points and points
sampled evenly on the ground-truth mesh. Chamfer = mean of the two directed mean distances (m).
Precision = fraction of reconstructed points within `threshold` of the GT; recall = fraction of GT
samples within `threshold` of the reconstruction; F1 their harmonic mean.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import trimesh


@dataclass
class Fidelity:
    """Geometric fidelity of reconstructed points against ground truth (`fidelity`, `mesh_fidelity`).

    chamfer: mean of the two mean nearest-neighbour distances (m); precision / recall: share of reconstructed /
    ground-truth points within the threshold of the other set; f1: their harmonic mean; n_points: number of
    reconstructed points."""

    chamfer: float
    precision: float
    recall: float
    f1: float
    n_points: int

    def to_dict(self) -> dict:
        return asdict(self)


def sample_surface(mesh: trimesh.Trimesh, spacing: float = 0.002, max_points: int = 200000, seed: int = 0,
                   drop_supported: float | None = None) -> np.ndarray:
    """Points [M,3] evenly on the mesh surface, about one per spacing^2 of area.

    drop_supported: if given (a table height z), drop samples on downward faces lying on that plane
    (within 2 mm): the part of an object pressed on the table that no camera can ever see.
    """
    n = int(np.clip(mesh.area / spacing**2, 100, max_points))
    pts, fid = trimesh.sample.sample_surface(mesh, n, seed=seed)
    if drop_supported is not None:
        nz = mesh.face_normals[fid][:, 2]
        hidden = (nz < -0.9) & (np.abs(pts[:, 2] - drop_supported) < 0.002)
        pts = pts[~hidden]
    return np.asarray(pts)


def fidelity(points: np.ndarray, gt_points: np.ndarray, threshold: float = 0.005) -> Fidelity:
    """Metrics of reconstructed points [N,3] vs ground-truth samples [M,3] (same frame, m)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return Fidelity(chamfer=float("inf"), precision=0.0, recall=0.0, f1=0.0, n_points=0)
    d_pg, _ = cKDTree(gt_points).query(points, workers=-1)
    d_gp, _ = cKDTree(points).query(gt_points, workers=-1)
    p = float(np.mean(d_pg < threshold))
    r = float(np.mean(d_gp < threshold))
    f1 = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return Fidelity(chamfer=float(0.5 * (d_pg.mean() + d_gp.mean())), precision=p, recall=r, f1=f1,
                    n_points=int(len(points)))


def mesh_fidelity(mesh: trimesh.Trimesh, gt_mesh: trimesh.Trimesh, threshold: float = 0.005, spacing: float = 0.002,
                  seed: int = 0) -> Fidelity:
    """Fidelity of a reconstructed mesh against a GT mesh (same frame, m), both sampled evenly at
    `spacing` over their whole surface (what `splattwin demo` reports in geometry_metrics.json)."""
    return fidelity(sample_surface(mesh, spacing, seed=seed), sample_surface(gt_mesh, spacing, seed=seed), threshold)
