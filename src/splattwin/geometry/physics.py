"""Stage 4: physics geometry — gravity-aligned box proxy, convex decomposition (CoACD), mass.

The object frame is the centre of the yaw-only oriented bounding box (z up, x along the longer side of
the minimum-area footprint rectangle), so objects resting on the table keep an upright frame.
MuJoCo and most engines collide a mesh as its convex hull: non-convex objects (mesh / hull volume below
`convex_ratio`) are decomposed with CoACD into convex parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from splattwin.transforms import rot_z, yaw_of


@dataclass
class YawBox:
    """Gravity-aligned oriented box. T_world_box [4,4] (rotation about z only), extent [3] side lengths (m)."""

    T_world_box: np.ndarray
    extent: np.ndarray

    @property
    def yaw(self) -> float:
        return yaw_of(self.T_world_box)


def yaw_obb(points: np.ndarray) -> YawBox:
    """Minimum-area footprint rectangle (rotating calipers over the 2D hull) extruded over the z range.

    points [N,3] world frame (m). x axis = longer footprint side; yaw in (-pi/2, pi/2].
    """
    from scipy.spatial import ConvexHull, QhullError

    xy = points[:, :2]
    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        hull = xy
    best = None
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2)) if len(hull) > 1 else np.zeros(1)
    for a in angles:
        R = rot_z(-a)[:2, :2]
        p = hull @ R.T
        lo, hi = p.min(axis=0), p.max(axis=0)
        area = np.prod(hi - lo)
        if best is None or area < best[0] - 1e-15:
            best = (area, a, lo, hi)
    _, a, lo, hi = best
    ext = hi - lo
    if ext[1] > ext[0]:  # x along the longer side
        a += np.pi / 2
        ext = ext[::-1]
        R = rot_z(-a)[:2, :2]
        p = hull @ R.T
        lo, hi = p.min(axis=0), p.max(axis=0)
    a = float(np.mod(a + np.pi / 2, np.pi) - np.pi / 2)  # (-pi/2, pi/2]
    if a <= -np.pi / 2 + 1e-12:
        a += np.pi
    R3 = rot_z(a)
    p = hull @ R3[:2, :2]  # box-frame footprint (R^T applied to row vectors)
    lo, hi = p.min(axis=0), p.max(axis=0)
    centre_box = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2])
    z0, z1 = points[:, 2].min(), points[:, 2].max()
    T = np.eye(4)
    T[:3, :3] = R3
    T[:2, 3] = R3[:2, :2] @ centre_box
    T[2, 3] = (z0 + z1) / 2
    return YawBox(T_world_box=T, extent=np.array([hi[0] - lo[0], hi[1] - lo[1], z1 - z0]))


def convexity(mesh: trimesh.Trimesh) -> float:
    """Volume of a watertight mesh / volume of its convex hull (1 = convex)."""
    hv = mesh.convex_hull.volume
    return float(mesh.volume / hv) if hv > 0 else 1.0


def convex_parts(mesh: trimesh.Trimesh, convex_ratio: float = 0.85, threshold: float = 0.05,
                 max_parts: int = 16, seed: int = 0) -> list[trimesh.Trimesh]:
    """Convex pieces for physics: [hull] for near-convex meshes, CoACD parts otherwise."""
    if convexity(mesh) >= convex_ratio:
        return [mesh.convex_hull]
    import coacd

    coacd.set_log_level("error")
    # input is already a watertight manifold (no preprocess); a coarser search than CoACD's defaults
    # gives the same parts on tabletop objects at ~1/5 of the time
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)), threshold=threshold,
                            max_convex_hull=max_parts, preprocess_mode="off", resolution=500, mcts_iterations=60,
                            mcts_nodes=10, seed=seed)
    out = []
    for v, f in parts:
        p = trimesh.Trimesh(np.asarray(v), np.asarray(f), process=True)
        if len(p.faces) >= 4:
            out.append(p.convex_hull)  # exact hulls: what the engine will use anyway
    return out or [mesh.convex_hull]


def mass_properties(mesh: trimesh.Trimesh, density: float) -> tuple[float, float]:
    """(volume m^3, mass kg) of a watertight mesh at `density` kg/m^3."""
    v = float(abs(mesh.volume))
    return v, v * density
