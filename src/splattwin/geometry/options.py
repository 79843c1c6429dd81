"""Options of the geometry stage (filtering, clustering, meshing, physics), one plain data object.

Units: metres, kilograms. Thresholds set to None are derived from the scene size (`scene_scale`, the
diagonal of the robust bounding box of all Gaussian centres) when the conversion starts. In an unscaled
twin (SfM units) every length (unit "m") is first multiplied by the frame's nominal metre and the
density divided by its cube (`resolved(..., length_scale)`, `splattwin.options.scale_lengths`), so each
threshold is the same share of the scene as in a metric twin; a metric twin uses them as written.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from splattwin.options import option


@dataclass
class GeometryOptions:
    """Knobs of the Gaussians -> collision geometry conversion (defaults follow the paper, section 3.3)."""

    # -- stage 1: attribute filtering ------------------------------------------------------------
    min_opacity: float = option(0.1, "drop Gaussians with opacity below this (haze, ghosts)")
    max_scale: float | None = option(None, "drop Gaussians whose largest scale exceeds this (none: max_scale_rel x "
                                     "scene size)", unit="m")
    max_scale_rel: float = option(0.01, "automatic max_scale as a share of the scene size (diagonal of the robust box)")
    max_aspect: float = option(5.0, "a needle has largest / middle scale above this (flat discs are fine) ...")
    needle_length: float = option(0.006, "... and its largest scale above this (shorter elongated splats line "
                                  "edges)", unit="m")
    max_flatness: float | None = option(None, "optional bound on largest / smallest scale (none: off)")
    # -- stage 2: connectivity pruning -------------------------------------------------------------
    dbscan_eps: float = option(0.02, "DBSCAN eps of the connectivity pruning (paper: 2 cm)", unit="m", aliases=("eps",))
    dbscan_min_samples: int = option(10, "DBSCAN min_samples", aliases=("min-samples",))
    dbscan_voxel: float | None = option(None, "voxel of the weighted DBSCAN on voxel centroids (none: eps / 4; 0: "
                                        "exact DBSCAN)", unit="m")
    rejoin_precision: float = option(0.9, "a DBSCAN cluster other than the largest is kept too when its splats, "
                                     "rendered alone, lie inside the object's 2D masks for this share (median over "
                                     "views: a part of the object the gaps of a sparse real capture cut off, not a "
                                     "floater; needs masks; 0: the largest cluster only, as the paper)")
    plane_distance: float = option(0.004, "RANSAC inlier distance for the table plane", unit="m")
    plane_iterations: int = option(500, "RANSAC iterations of the table plane fit")
    support_gap: float = option(0.02, "an obstacle cluster must come this close to the table", unit="m")
    foot_height: float = option(0.006, "object points this close to the table ...", unit="m")
    foot_margin: float = option(0.005, "... and this far outside the outline above them are table (foot_height 0: "
                                "off)", unit="m")
    obstacle_min_points: int = option(200, "smaller background clusters above the table are floaters")
    # -- stage 3: meshing --------------------------------------------------------------------------
    mesh_voxel: float = option(0.003, "finest voxel of the solid the surface points enclose", unit="m")
    mesh_voxel_rel: float = option(0.75, "the voxel is at least this times the 4th-neighbour spacing (sparse splats)")
    close_iterations: int = option(2, "morphological closing iterations (voxels) sealing gaps between samples")
    alpha: float | None = option(None, "alpha-shape radius (none: alpha_factors x point spacing)", unit="m")
    alpha_factors: tuple[float, ...] = option((1.5, 2.0, 3.0), "alpha radii in point spacings, tried in order until "
                                              "the outer shell is watertight")
    use_alpha: bool = option(True, "alpha shapes (--no-use-alpha: voxel remesh by marching cubes, faster)")
    alpha_max_points: int = option(16000, "objects with more points get a coarser voxel (the Delaunay cost grows with "
                                   "the points)")
    close_bottom: bool = option(True, "add the unseen footprint under an object resting on the table")
    fill_to_support: bool = option(True, "a resting object is solid from the table up to its seen surface")
    rest_gap: float = option(0.01, "an object whose lowest point is within this of the table rests on it", unit="m")
    foot_gap: float = option(0.05, "... and so does one up to this high with no other object under it (its foot "
                             "was not seen: nothing holds it in the air)", unit="m")
    float_gap: float = option(0.005, "a usable object whose lowest point ends up more than this above its support "
                              "(the table top, or an object or obstacle under it) is floating: warned and noted in "
                              "its problem (physics would drop it)", unit="m")
    obstacle_pad: float = option(0.01, "an unusable object is kept in the collision exports as the axis-aligned box "
                                 "of its labelled splats (their half-opaque extents, stray floaters left out) grown "
                                 "by this on every side", unit="m")
    densify: bool = option(True, "mesh each splat's alpha = surface_level ellipsoid, not only its centre")
    surface_level: float = option(0.5, "alpha iso-level of a splat taken as its surface (trained centres sit inside)")
    carve: bool = option(True, "drop splat-extent samples that a capture camera sees in front of the object's "
                         "rendered depth (free space; needs the cameras, see geometry.carving)")
    carve_tolerance: float = option(0.002, "a sample is free space when it is this far in front of the rendered depth",
                                    unit="m")
    carve_views: int = option(32, "at most this many cameras carve (spread evenly over the capture)")
    carve_depth: bool = option(True, "when the capture has measured depth (RGB-D) and the twin is metric, also drop "
                               "the points a depth camera sees clearly in front of the measured surface, inside "
                               "the object's eroded visible mask (see geometry.carving)")
    carve_depth_tolerance: float = option(0.002, "a point is free space when it lies this far (plus the noise "
                                          "term) in front of the measured depth (pose and registration error)",
                                          unit="m")
    carve_depth_noise: float = option(0.005, "... plus this times z^2 (z: the measured depth in m): the error of the "
                                      "median-filtered depth growing as a stereo camera's (a D435 reads about 0.01 m "
                                      "RMS at 1 m per pixel; the 5x5 median cuts uncorrelated noise to a quarter, so "
                                      "0.005 is twice that, or one sigma where the noise spans the window)")
    carve_depth_erode: int = option(2, "pixels the object's mask is eroded by before its depth is trusted (depth "
                                    "edges bleed, colour and depth are registered to a pixel or two)", unit="px")
    smooth_iterations: int = option(10, "Taubin smoothing of the mesh (removes the voxel staircase)")
    collision_faces: int = option(1500, "face budget of collision meshes", aliases=("faces",))
    visual_faces: int = option(20000, "face budget of visual meshes")
    # -- stage 4: physics --------------------------------------------------------------------------
    density: float = option(500.0, "mass = volume * density", unit="kg/m^3")
    convex_ratio: float = option(0.85, "convex decomposition when mesh volume / hull volume is below this")
    coacd_threshold: float = option(0.1, "CoACD concavity bound (relative to the object size)")
    coacd_faces: int = option(400, "CoACD runs on a copy decimated to this (its cost grows fast)")
    max_convex_parts: int = option(8, "at most this many convex parts per object")
    # -- bad input -----------------------------------------------------------------------------------
    min_points: int = option(50, "an object with fewer points after cleaning is unusable, unless its masks show "
                             "it whole (min_coverage)")
    min_points_whole: int = option(20, "an object its masks show whole (min_coverage) needs only this many points "
                                   "after cleaning (the robot-style capture's 2.5 cm cube keeps 48; 30 of them "
                                   "mesh it at F1@5 mm 0.93+)")
    min_coverage: float = option(0.5, "an object is whole when its cleaned splats, rendered alone, cover this share "
                                 "of its 2D masks (median over views; measured: whole objects 0.72-1.0, fragments "
                                 "0.01-0.36); below it one with min_points or more points is usable but flagged")
    coverage_views: int = option(8, "at most this many views with a mask of an object measure its silhouette "
                                 "coverage (0: off, the count alone decides)")
    min_thickness: float = option(0.002, "a cluster thinner than this (PCA extent) is degenerate", unit="m")
    # -- metrics -------------------------------------------------------------------------------------
    f1_threshold: float = option(0.005, "distance threshold of the F1 score against ground truth", unit="m")
    seed: int = option(0, "seed of RANSAC and CoACD")

    def resolved(self, scene_scale: float, length_scale: float = 1.0) -> "GeometryOptions":
        """Copy with the scene-size dependent defaults filled in. length_scale: frame units per metre of
        the lengths (1 in a metric twin; an unscaled twin's nominal metre, see the module docstring)."""
        from splattwin.options import scale_lengths

        d = asdict(scale_lengths(self, length_scale))
        if d["max_scale"] is None:
            d["max_scale"] = float(self.max_scale_rel * scene_scale)
        if d["dbscan_voxel"] is None:
            d["dbscan_voxel"] = d["dbscan_eps"] / 4.0
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


def scene_scale(means) -> float:
    """Diagonal (m) of the 1–99 percentile box of the points [N,3]: a size robust to floaters."""
    import numpy as np

    if len(means) == 0:
        return 1.0
    lo, hi = np.percentile(means, [1, 99], axis=0)
    return float(max(np.linalg.norm(hi - lo), 1e-3))
