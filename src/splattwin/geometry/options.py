"""Options of the geometry stage (filtering, clustering, meshing, physics), one plain data object.

Units: metres, kilograms. Thresholds set to None are derived from the scene size (`scene_scale`, the
diagonal of the robust bounding box of all Gaussian centres) when the conversion starts.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np


@dataclass
class GeometryOptions:
    """Knobs of the Gaussians -> collision geometry conversion (defaults follow the paper, section 3.3)."""

    # -- stage 1: attribute filtering ------------------------------------------------------------
    min_opacity: float = 0.1            # drop alpha < min_opacity (haze, ghosts)
    max_scale: float | None = None      # drop Gaussians whose largest scale exceeds this (m); None: auto
    max_scale_rel: float = 0.01         # auto max_scale = max_scale_rel * scene_scale
    max_aspect: float = 5.0             # needle: largest / middle scale above this (flat discs are fine)
    needle_length: float = 0.006        # ... and largest scale above this (m): shorter elongated splats line edges
    max_flatness: float | None = None   # optional bound on largest / smallest scale (None: off)
    # -- stage 2: connectivity pruning -------------------------------------------------------------
    dbscan_eps: float = 0.02            # m (paper: 2 cm)
    dbscan_min_samples: int = 10
    dbscan_voxel: float | None = None   # voxel for weighted DBSCAN on voxel centroids; None: eps / 4; 0: exact
    plane_distance: float = 0.004       # RANSAC inlier distance for the table plane (m)
    plane_iterations: int = 500
    support_gap: float = 0.02           # an obstacle cluster must come this close to the table (m)
    foot_height: float = 0.006          # object points this close to the table ...
    foot_margin: float = 0.005          # ... and this far outside the outline above them are table (0 height: off)
    obstacle_min_points: int = 200      # smaller background clusters above the table are floaters
    # -- stage 3: meshing --------------------------------------------------------------------------
    mesh_voxel: float = 0.003           # finest voxel of the solid the surface points enclose (m)
    mesh_voxel_rel: float = 0.75        # voxel at least this x the 4th-neighbour spacing (sparse splats)
    close_iterations: int = 2           # morphological closing (voxels) sealing gaps between samples
    alpha: float | None = None          # alpha-shape radius (m); None: alpha_factors * point spacing
    alpha_factors: tuple = (1.5, 2.0, 3.0)   # tried in order until the outer shell is watertight
    use_alpha: bool = True              # False: voxel remesh (marching cubes) directly
    alpha_max_points: int = 8000        # coarser voxel for bigger objects (Delaunay cost ~ points)
    close_bottom: bool = True           # add the unseen footprint under an object resting on the table
    fill_to_support: bool = True        # a resting object is solid from the table up to its seen surface
    rest_gap: float = 0.01              # an object whose lowest point is within this of the table rests on it (m)
    densify: bool = True                # mesh each splat's alpha = surface_level ellipsoid, not only its centre
    surface_level: float = 0.5          # alpha iso-level of a splat taken as its surface (trained centres sit inside)
    smooth_iterations: int = 10         # Taubin smoothing of the mesh (removes the voxel staircase)
    collision_faces: int = 1500         # face budget of collision meshes
    visual_faces: int = 20000           # face budget of visual meshes
    # -- stage 4: physics --------------------------------------------------------------------------
    density: float = 500.0              # kg/m^3 for mass = volume * density
    convex_ratio: float = 0.85          # mesh volume / hull volume below this -> convex decomposition
    coacd_threshold: float = 0.1       # CoACD concavity bound (relative to the object size)
    coacd_faces: int = 400              # CoACD runs on a copy decimated to this (its cost grows fast)
    max_convex_parts: int = 8
    # -- bad input -----------------------------------------------------------------------------------
    min_points: int = 50                # fewer points after cleaning -> object unusable
    min_thickness: float = 0.002        # a cluster thinner than this (PCA extent, m) is degenerate
    # -- metrics -------------------------------------------------------------------------------------
    f1_threshold: float = 0.005         # m
    seed: int = 0

    def resolved(self, scene_scale: float) -> "GeometryOptions":
        """Copy with the scene-size dependent defaults filled in."""
        d = asdict(self)
        if d["max_scale"] is None:
            d["max_scale"] = float(self.max_scale_rel * scene_scale)
        if d["dbscan_voxel"] is None:
            d["dbscan_voxel"] = self.dbscan_eps / 4.0
        d["alpha_factors"] = tuple(d["alpha_factors"])
        return GeometryOptions(**d)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["alpha_factors"] = list(d["alpha_factors"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "GeometryOptions":
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if "alpha_factors" in kw:
            kw["alpha_factors"] = tuple(kw["alpha_factors"])
        return cls(**kw)


def scene_scale(means: np.ndarray) -> float:
    """Diagonal (m) of the 1–99 percentile box of the points [N,3]: a size robust to floaters."""
    if len(means) == 0:
        return 1.0
    lo, hi = np.percentile(means, [1, 99], axis=0)
    return float(max(np.linalg.norm(hi - lo), 1e-3))
