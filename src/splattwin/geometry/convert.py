"""Labelled Gaussians -> clean, planning-ready geometry per object and for the background.

The functional core of the geometry stage: `clean_indices` (stages 1-2 for one configuration, also used
by the ablation), `object_geometry` (stages 3-4 for one object) and `convert` (everything, with
per-stage timings). Object results are in the object frame (centre of the yaw-only OBB, z up);
background results in the twin frame. Nothing is written here (see `splattwin.twin.build`).
"""

from __future__ import annotations

import logging
import time
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from splattwin.geometry.carving import depth_views, free_space_mask
from splattwin.geometry.clustering import Plane, dbscan_labels, foot_bleed_mask, largest_cluster, split_background
from splattwin.geometry.completeness import Coverage, consistent_clusters, coverage
from splattwin.geometry.filtering import FilterStats, attribute_mask
from splattwin.geometry.meshing import (add_bottom, downsample, ellipsoid_samples, level_radii, point_spacing, simplify,
                                        smooth, solid_mesh)
from splattwin.geometry.metrics import Fidelity, fidelity, mesh_fidelity, sample_surface
from splattwin.geometry.options import GeometryOptions, scene_scale
from splattwin.geometry.physics import convex_parts, convexity, mass_properties, yaw_obb

log = logging.getLogger(__name__)

CONFIGS = ("raw", "attribute", "cluster", "full")  # the four ablation configurations (paper Table 5)


class ObjectUnusableWarning(UserWarning):
    """An object's geometry could not be built; the twin marks it usable=False with the problem."""


class FloatingObjectWarning(UserWarning):
    """A usable object's mesh ends above its support (`GeometryOptions.float_gap`): the twin records the
    problem; physics drops it at the start and planners see it hovering."""


class IncompleteObjectWarning(UserWarning):
    """An object's splats cover little of its 2D masks (maybe a fragment of it): it stays usable (it has
    `min_points` points), and the twin records the problem; check it before a robot relies on it."""


@dataclass
class ObjectGeometry:
    """Geometry of one object. Meshes in the object frame; T_world_obj [4,4] places them in the twin frame."""

    name: str
    label: int
    prompt: str = ""
    usable: bool = True
    problem: str | None = None
    indices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # kept Gaussians
    T_world_obj: np.ndarray = field(default_factory=lambda: np.eye(4))
    extent: np.ndarray = field(default_factory=lambda: np.zeros(3))
    visual: trimesh.Trimesh | None = None
    collision: trimesh.Trimesh | None = None
    parts: list = field(default_factory=list)
    volume: float | None = None
    mass: float | None = None
    convexity: float | None = None
    mesh_method: str | None = None
    alpha: float | None = None
    coverage: Coverage | None = None  # its cleaned splats vs its 2D masks (geometry.completeness); None: no masks
    # points (centres and ellipsoid samples) dropped as free space by the measured depth (geometry.carving),
    # out of depth_points; None: not carved against measured depth (no depth views of it, or carve_depth off)
    depth_carved: int | None = None
    depth_points: int | None = None
    depth_views: int = 0
    # an unusable object's obstacle estimate (`obstacle_box`): T_world_obj (translation only) and extent give
    # the padded axis-aligned box of its labelled splats; False with no splats at all
    obstacle: bool = False


@dataclass
class BackgroundGeometry:
    """Static environment in the twin frame: table box + obstacles."""

    indices: np.ndarray
    plane: Plane | None
    table_height: float
    table_extent: list
    table_thickness: float
    collision: trimesh.Trimesh | None
    parts: list
    n_obstacles: int = 0
    obstacles: list = field(default_factory=list)  # [Trimesh] each obstacle's mesh on the table (twin frame)
    default_reason: str | None = None  # why the table is the assumed default (`default_table`), None when found


@dataclass
class Conversion:
    """The result of converting labelled Gaussians to planning geometry (`convert`): one `ObjectGeometry`
    per object, the background's (`BackgroundGeometry`, None when not built), the attribute filter's
    statistics, the resolved options and per-step timings (s)."""

    objects: list[ObjectGeometry]
    background: BackgroundGeometry | None
    filter_stats: FilterStats
    options: GeometryOptions
    timings: dict
    # why the meshes were not carved against measured depth (no depth in the capture, an unscaled twin,
    # carve_depth off, no masks); None: they were, where an object had depth views (its depth_carved)
    depth_skipped: str | None = None


def clean_indices(g, labels: np.ndarray, label: int, opts: GeometryOptions, attribute: bool = True,
                  cluster: bool = True, attr_keep: np.ndarray | None = None, masks: list | None = None) -> np.ndarray:
    """Indices of the Gaussians of `label` that survive the chosen cleaning (opts must be resolved).
    masks: [(Camera, mask)] of the object: DBSCAN clusters besides the largest that lie inside them are
    kept too (`GeometryOptions.rejoin_precision`, `completeness.consistent_clusters`)."""
    idx = np.flatnonzero(labels == label)
    if attribute:
        keep = attr_keep if attr_keep is not None else attribute_mask(g.opacities, g.scales, opts)[0]
        idx = idx[keep[idx]]
    if cluster and len(idx):
        if not masks or opts.rejoin_precision <= 0:
            return idx[largest_cluster(g.means[idx], opts.dbscan_eps, opts.dbscan_min_samples, opts.dbscan_voxel)]
        cid = dbscan_labels(g.means[idx], opts.dbscan_eps, opts.dbscan_min_samples, opts.dbscan_voxel)
        ids, counts = np.unique(cid[cid >= 0], return_counts=True)
        if len(ids) == 0:
            return idx[:0]
        by_size = np.argsort(-counts, kind="stable")   # ties: the lowest id first, as largest_cluster
        order, sizes = ids[by_size], counts[by_size]
        # the largest always; of the rest those of at least min_samples splats, the 32 largest at most
        rest = [int(k) for k, n in zip(order[1:], sizes[1:]) if n >= opts.dbscan_min_samples][:32]
        kept = [int(order[0])] + consistent_clusters(g.subset(idx), cid, masks, rest, opts.rejoin_precision,
                                                     max_views=max(opts.coverage_views, 1))
        idx = idx[np.isin(cid, kept)]
    return idx


def coverage_text(cov: Coverage) -> str:
    """How much of an object's masks its splats cover, in words (problem texts, warnings)."""
    return (f"its splats cover {cov.recall:.0%} of its 2D masks' silhouettes (median over {cov.views} "
            f"view{'s' if cov.views != 1 else ''})")


def _problem(points: np.ndarray, opts: GeometryOptions, cov: Coverage | None = None) -> str | None:
    """Why the cleaned points [N,3] make no usable object, or None. The count floor is `min_points`, or
    `min_points_whole` when the silhouette coverage `cov` shows the object whole (`min_coverage`): a
    small whole object keeps few splats, a fragment of a large one covers a small share of its masks."""
    n = len(points)
    whole = cov is not None and cov.recall >= opts.min_coverage
    if n < min(opts.min_points_whole, opts.min_points):
        return f"too few points after cleaning ({n} < {min(opts.min_points_whole, opts.min_points)})"
    if n < opts.min_points and not whole:
        if cov is None:
            return f"too few points after cleaning ({n} < {opts.min_points})"
        return (f"too few points after cleaning ({n} < {opts.min_points}) and not whole: {coverage_text(cov)}, "
                f"below {opts.min_coverage:.0%} (likely a fragment of the object)")
    c = points - points.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False) / np.sqrt(n)  # std along principal axes
    if 4 * sv[0] < opts.min_thickness:
        return f"degenerate cluster: all points within {4 * sv[0] * 1000:.1f} mm (single point)"
    if 4 * sv[2] < opts.min_thickness:
        return f"degenerate cluster: flat (thickness {4 * sv[2] * 1000:.1f} mm < {opts.min_thickness * 1000:.1f} mm)"
    return None


def _vertex_colors(vertices_world: np.ndarray, means: np.ndarray, colors: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    _, nn = cKDTree(means).query(vertices_world, workers=-1)
    rgb = np.clip(colors[nn] * 255.0, 0, 255).astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)


def _stands_on_other(points: np.ndarray, others: np.ndarray | None, support_z: float, margin: float,
                     min_points: int = 10) -> bool:
    """True when at least `min_points` of `others` [M,3] (what else could hold it up: the other objects'
    centres, points on the background's obstacles) lie under this object's points [N,3]: inside its
    footprint (xy convex hull), above the table (support_z + margin) and below its lowest point + margin:
    it may stand on them rather than on the table."""
    if others is None or len(others) < min_points:
        return False
    from scipy.spatial import Delaunay
    from scipy.spatial import QhullError

    z_low = float(points[:, 2].min())
    cand = others[(others[:, 2] > support_z + margin) & (others[:, 2] < z_low + margin)]
    if len(cand) < min_points:
        return False
    try:
        hull = Delaunay(points[:, :2])
    except (QhullError, ValueError):  # a degenerate footprint (a line of points): nothing stands on it
        return False
    return int((hull.find_simplex(cand[:, :2]) >= 0).sum()) >= min_points


def object_geometry(g, indices: np.ndarray, name: str, label: int, opts: GeometryOptions, prompt: str = "",
                    timings: dict | None = None, support_z: float | None = None, cameras: list | None = None,
                    other_points: np.ndarray | None = None, masks: list | None = None,
                    measured=None) -> ObjectGeometry:
    """Stages 3-4 for one object from its cleaned Gaussians `g[indices]`. Never raises on bad data:
    returns usable=False with `problem` and emits ObjectUnusableWarning.

    support_z: height of the table top (twin frame). Table splats labelled as the object around its
    foot are dropped (`clustering.foot_bleed_mask`). Nothing physical lies below it, so points under it
    (reconstruction noise) are dropped, and an object resting on it gets its unseen bottom closed
    exactly at the table instead of a few millimetres inside it (which would make a gripper reaching
    for a small object graze the table, and make the object pop up in physics).

    cameras: the capture cameras (twin frame). With `opts.carve`, splat-extent samples that one of them
    sees in front of the object's rendered depth are dropped (`geometry.carving`); None: no carving.
    measured: [(Camera, sensor depth [H,W] m)] of this object, or a function returning them, called only
    when it is meshed (`carving.measured_views`: the capture's measured depth inside its eroded visible
    mask, inf elsewhere). With `opts.carve_depth`, the points (centres and samples) that these views see
    clearly in front of the measured surface are dropped (`carve_depth_tolerance` + `carve_depth_noise` x
    z^2, voted over the views), unless that would drop more than half of them (depth and poses disagree:
    a warning, nothing dropped). None: not done.
    other_points: [M,3] the other objects' cleaned centres and points on the background's obstacles. An
    object whose lowest point is more than `rest_gap` but at most `foot_gap` above the table rests on it
    unless some of these lie under it (it may stand on them): a downward robot sweep sees little of an
    object's lower sides, and its lowest splats can be 2 cm up (a box whose mesh then stopped there,
    hollow: F1@5 mm 0.42)."""
    timings = timings if timings is not None else defaultdict(float)
    indices = np.asarray(indices, dtype=np.int64)
    if support_z is not None and opts.foot_height > 0:
        indices = indices[foot_bleed_mask(g.means[indices], support_z, opts.foot_height, opts.foot_margin)]
    out = ObjectGeometry(name=name, label=int(label), prompt=prompt, indices=indices)
    pts = g.means[indices]
    if masks and len(indices) >= min(opts.min_points_whole, opts.min_points) and opts.coverage_views > 0:
        t0 = time.perf_counter()
        out.coverage = coverage(g.subset(indices), masks, max_views=opts.coverage_views)
        timings["coverage"] += time.perf_counter() - t0
    problem = _problem(pts, opts, out.coverage)
    if problem is None:
        t0 = time.perf_counter()
        pitch = max(opts.mesh_voxel, opts.mesh_voxel_rel * point_spacing(pts, k=4))
        if opts.densify:  # the splats' half-opaque extents, not just their centres (see ellipsoid_samples)
            sub = g.subset(indices)
            samples = ellipsoid_samples(pts, sub.rotation_matrices(), sub.scales,
                                        level_radii(sub.opacities, opts.surface_level))
            if opts.carve and cameras and opts.carve_views > 0:
                t1 = time.perf_counter()
                views = depth_views(sub, cameras, max_views=opts.carve_views)
                samples = samples[~free_space_mask(samples, views, opts.carve_tolerance)]
                timings["carve"] += time.perf_counter() - t1
            pts = np.concatenate([pts, samples])
        if opts.carve_depth and measured is not None:
            t1 = time.perf_counter()
            views = measured() if callable(measured) else measured
            if views:
                pts = _carve_measured(pts, views, opts, name, out)
            timings["carve_depth"] += time.perf_counter() - t1
        mpts = downsample(pts, pitch / 2)
        z_floor = None
        if support_z is not None:
            above = mpts[mpts[:, 2] >= support_z]
            mpts = above if len(above) >= 4 else mpts
            gap = mpts[:, 2].min() - support_z
            if gap < opts.rest_gap or (gap < opts.foot_gap
                                       and not _stands_on_other(mpts, other_points, support_z, opts.rest_gap)):
                z_floor = support_z
        if opts.close_bottom:
            mpts = add_bottom(mpts, pitch / 2, z_floor=z_floor)
        box = yaw_obb(mpts)
        T_obj_world = np.linalg.inv(box.T_world_box)
        local = mpts @ T_obj_world[:3, :3].T + T_obj_world[:3, 3]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            floor = None if (z_floor is None or not opts.fill_to_support) else z_floor + T_obj_world[2, 3]
            res = solid_mesh(local, pitch, opts.alpha, opts.alpha_factors, opts.close_iterations,
                             opts.use_alpha, name=name, max_points=opts.alpha_max_points, floor_z=floor)
        for w in caught:
            warnings.warn(w.message, stacklevel=2)
        mesh = smooth(res.mesh, opts.smooth_iterations)
        if floor is not None:  # smoothing rounds the bottom edge a little below the table: nothing is there
            v = np.array(mesh.vertices)
            v[:, 2] = np.maximum(v[:, 2], floor)
            mesh = trimesh.Trimesh(v, mesh.faces, process=False)
        visual = simplify(mesh, opts.visual_faces)
        vw = visual.vertices @ box.T_world_box[:3, :3].T + box.T_world_box[:3, 3]
        visual = trimesh.Trimesh(visual.vertices, visual.faces, vertex_colors=_vertex_colors(vw, g.means[indices], g.colors[indices]),
                                 process=False)
        collision = simplify(mesh, opts.collision_faces)
        # re-centre on the collision mesh's own box (same yaw), so the box proxy encloses it exactly
        lo, hi = collision.bounds
        c = (lo + hi) / 2
        collision.apply_translation(-c)
        visual.apply_translation(-c)
        T_world_obj = box.T_world_box.copy()
        T_world_obj[:3, 3] += box.T_world_box[:3, :3] @ c
        timings["mesh"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        thin = float(np.min(hi - lo))
        if thin < pitch:  # a sliver (e.g. a tetrahedron of a few points): no physics engine can give it inertia
            problem = (f"its mesh collapsed to a sliver {thin:.3g} thick (less than the mesh pitch {pitch:.3g}): "
                       f"too few or too scattered points")
        elif not collision.is_watertight:  # simplify() guarantees this; keep the invariant explicit
            problem = "collision mesh is not watertight"
        else:
            out.parts = convex_parts(simplify(collision, opts.coacd_faces), opts.convex_ratio, opts.coacd_threshold,
                                     opts.max_convex_parts, opts.seed)
            out.volume, out.mass = mass_properties(collision, opts.density)
            out.convexity = convexity(collision)
        timings["decompose"] += time.perf_counter() - t0
        out.T_world_obj, out.extent = T_world_obj, hi - lo
        out.visual, out.collision, out.mesh_method, out.alpha = visual, collision, res.method, res.alpha
    if problem is not None:
        out.usable, out.problem = False, problem
        out.visual = out.collision = None
        out.parts = []
        warnings.warn(ObjectUnusableWarning(f"object {name!r} (label {label}): {problem}"), stacklevel=2)
    elif out.coverage is not None and out.coverage.recall < opts.min_coverage:
        # enough points to build it, but little of what the photos show: usable (whole objects under crude
        # masks measured 0.72), flagged
        out.problem = (f"possibly incomplete: {coverage_text(out.coverage)}, below {opts.min_coverage:.0%} "
                       f"(a fragment of the object, or masks larger than it); check its mesh")
        warnings.warn(IncompleteObjectWarning(f"object {name!r} (label {label}): {out.problem}"), stacklevel=2)
    return out


MEASURED_VOTE = 0.5  # a point is free when at least half the depth views that see it (not behind) say so
MEASURED_MAX_DROP = 0.5  # more than this share dropped: measured depth and twin disagree (scale, poses)


def _carve_measured(pts: np.ndarray, measured: list, opts: GeometryOptions, name: str,
                    out: ObjectGeometry) -> np.ndarray:
    """pts [N,3] (twin frame, m) less those the measured depth views see as free space (see
    `object_geometry`); records the counts on `out`."""
    free = free_space_mask(pts, measured, opts.carve_depth_tolerance, opts.carve_depth_noise, MEASURED_VOTE)
    out.depth_views, out.depth_points = len(measured), len(pts)
    n = int(free.sum())
    if n > MEASURED_MAX_DROP * len(pts):
        log.warning("object %r: the measured depth sees %d of its %d points as free space (> %.0f %%): depth and "
                    "twin disagree (depth scale, poses, or masks of another object?); not carved against it",
                    name, n, len(pts), 100 * MEASURED_MAX_DROP)
        out.depth_carved = 0
        return pts
    out.depth_carved = n
    return pts[~free]


def scene_bounds(means: np.ndarray, grow: float = 1.0) -> np.ndarray:
    """[2,3] lower/upper corner of the scene: the 1-99 percentile box of the points `means` [N,3] (robust
    to floaters, as `options.scene_scale`) grown by `grow` times its diagonal on every side. What stands
    in the scene lies well inside; a stray splat far out does not."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    if len(means) == 0:
        return np.array([[-np.inf] * 3, [np.inf] * 3])
    lo, hi = np.percentile(means, [1, 99], axis=0)
    d = grow * max(float(np.linalg.norm(hi - lo)), 1e-3)
    return np.stack([lo - d, hi + d])


def obstacle_box(r: ObjectGeometry, points: np.ndarray, opts: GeometryOptions, support_z: float | None,
                 half_extent: np.ndarray | None = None, within: np.ndarray | None = None) -> None:
    """Give unusable `r` its obstacle estimate in place: the axis-aligned box (twin frame) that holds every
    one of its labelled splats that survive the attribute filter, centres `points` [N,3] each grown by its
    own `half_extent` [N,3] along the axes (`splat_half_extents`: the splat's half-opaque ellipsoid, so a
    few splats of a small object still bound it; None: centres alone), then by `obstacle_pad` on every
    side. Why: the real object stands there whatever its reconstruction's quality; a keep-out volume
    smaller than it (a 2 cm box for a 2.5 cm cube: its centres cut, the 2 % per side trimmed) lets a
    robot sweep through it. Stray floaters are not trimmed by percentile (that cut real extremities)
    but left out as parts: with 20 points or more, only the groups that hold at least 10 % of them (the
    largest always) count, a group being the points chained through touching cells of side `dbscan_eps`
    (`main_parts`): points within `dbscan_eps` of each other are always in one group, a floater up to about
    3.5 x `dbscan_eps` (2 sqrt(3), cell diagonals) from the rest may join it, one farther never does. (Exact
    chaining at `dbscan_eps`, DBSCAN with min_samples 1, gave boxes up to 2.7 cm tighter per side on the
    embedded scene's synthetic splats, still holding the objects, but took 3-7 x as long there and its
    neighbour lists grow with density: 10 s and +0.5 GiB for 100k splats on one box, against 0.45 s.) Points under
    the table are noise; a box ending within `foot_gap` of the table reaches down to it (what stands
    there rests on the table). within: [2,3] corners of the scene (`scene_bounds`): points outside are
    strays whatever their number (with fewer than 20 points no part is left out, and one splat 900 km
    away made a 900 km box); None: no bound. No points: nothing is set (r.obstacle stays False)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    h = np.zeros_like(points) if half_extent is None else np.asarray(half_extent, dtype=np.float64).reshape(-1, 3)
    if within is not None:
        inside = np.all((points >= within[0]) & (points <= within[1]), axis=1)
        if not inside.all():
            log.warning("object %r: %d of its %d labelled splats lie far outside the scene and are left out of its "
                        "obstacle box", r.name, int((~inside).sum()), len(points))
            points, h = points[inside], h[inside]
    if support_z is not None:
        above = points[:, 2] >= support_z
        if above.any():
            points, h = points[above], h[above]
    if len(points) == 0:
        return
    if len(points) >= 20:
        keep = main_parts(points, opts.dbscan_eps if opts.dbscan_eps > 0 else max(opts.obstacle_pad, 1e-9))
        points, h = points[keep], h[keep]
    lo, hi = (points - h).min(axis=0), (points + h).max(axis=0)
    lo, hi = lo - opts.obstacle_pad, hi + opts.obstacle_pad
    if support_z is not None:
        lo[2] = max(lo[2], support_z)
        if lo[2] - support_z <= opts.foot_gap:
            lo[2] = support_z
        hi[2] = max(hi[2], lo[2] + 2 * opts.obstacle_pad)
    T = np.eye(4)
    T[:3, 3] = (lo + hi) / 2
    r.T_world_obj, r.extent, r.obstacle = T, hi - lo, True


def splat_half_extents(g, idx: np.ndarray, opts: GeometryOptions) -> np.ndarray:
    """[len(idx),3] half-extents along the twin axes of the Gaussians `g[idx]`: of each one's alpha =
    `surface_level` ellipsoid (`level_radii`, the surface the meshing uses), at least its 1-sigma one (a
    keep-out volume errs large), sigmas capped at `max_scale` (a haze splat of an unfiltered fallback must
    not make a wall)."""
    sub = g.subset(np.asarray(idx))
    s = np.asarray(sub.scales, dtype=np.float64)
    if opts.max_scale is not None:
        s = np.minimum(s, opts.max_scale)
    radius = np.maximum(level_radii(sub.opacities, opts.surface_level), 1.0)
    R = sub.rotation_matrices()
    return radius[:, None] * np.sqrt(np.einsum("nij,nj->ni", R ** 2, s ** 2))   # sqrt of the covariance's diagonal


def main_parts(points: np.ndarray, link: float, min_share: float = 0.1) -> np.ndarray:
    """[N] bool: the points in the groups that hold at least `min_share` of them (the largest group
    always). A group: points chained through cells of side `link` that touch (26-neighbourhood), so two
    points within `link` of each other are always in one group; one up to 2 sqrt(3) x `link` (~3.5 x) from
    the rest may join it (its cell touches theirs), one farther than that never does. Sparse (occupied cells
    only): a far floater costs nothing, and the cost does not grow with the points' density as exact
    single linkage at `link` (DBSCAN, min_samples 1) does."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keys = np.floor(np.asarray(points, dtype=np.float64) / link).astype(np.int64)
    cells, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = np.asarray(inv).reshape(-1)
    index = {tuple(c): i for i, c in enumerate(cells.tolist())}
    offsets = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)]
    rows, cols = [], []
    for a, (x, y, z) in enumerate(cells.tolist()):
        for i, j, k in offsets:
            b = index.get((x + i, y + j, z + k))
            if b is not None:
                rows.append(a)
                cols.append(b)
    n = len(cells)
    _, comp_of_cell = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                           directed=False)
    comp = comp_of_cell[inv]
    counts = np.bincount(comp)
    keep = (counts >= min_share * len(points)) | (counts == counts.max())
    return keep[comp]


def flag_floating(results: list[ObjectGeometry], support_z: float | None, opts: GeometryOptions,
                  obstacle_meshes: list | None = None, units: str = "m") -> None:
    """Note in `problem` (and warn) each usable object whose collision mesh's lowest point lies more than
    `float_gap` above its support: the highest of the table top (support_z) and the other objects' and
    obstacles' surfaces under its footprint (xy hull) up to its lowest point + float_gap. Nothing to
    compare with when the table plane is unknown (support_z None)."""
    if support_z is None:
        return
    from scipy.spatial import Delaunay, QhullError

    def world(r, v):
        return v @ r.T_world_obj[:3, :3].T + r.T_world_obj[:3, 3]

    surfaces = {id(r): world(r, np.asarray(trimesh.sample.sample_surface(r.collision, 2000, seed=opts.seed)[0]))
                for r in results if r.usable and r.collision is not None and r.collision.area > 0}
    for r in results:  # an unusable object's obstacle box holds up what stands on it too
        if r.obstacle:
            c, e = r.T_world_obj[:3, 3], r.extent
            g = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 8)] * 2), -1).reshape(-1, 2)
            surfaces[id(r)] = np.column_stack([c[:2] + g * e[:2], np.full(len(g), c[2] + e[2] / 2)])
    obstacles = [np.asarray(trimesh.sample.sample_surface(m, 2000, seed=opts.seed)[0])
                 for m in (obstacle_meshes or []) if m.area > 0]
    for r in results:
        if not r.usable or r.collision is None:
            continue
        v = world(r, np.asarray(r.collision.vertices))
        z_low = float(v[:, 2].min())
        support, what = support_z, "the table top"
        others = [p for k, p in surfaces.items() if k != id(r)] + obstacles
        if others:
            pts = np.concatenate(others)
            pts = pts[(pts[:, 2] > support_z) & (pts[:, 2] <= z_low + opts.float_gap)]
            try:
                inside = Delaunay(v[:, :2]).find_simplex(pts[:, :2]) >= 0 if len(pts) else np.zeros(0, bool)
            except (QhullError, ValueError):
                inside = np.zeros(len(pts), bool)
            if inside.any():
                support, what = float(pts[inside, 2].max()), "the object or obstacle under it"
        gap = z_low - support
        if gap > opts.float_gap:
            note = (f"floating: its lowest point is {gap:.3g} {units} above {what} (more than float_gap "
                    f"{opts.float_gap:.3g} {units}); physics drops it at the start and planners see it hovering. "
                    f"Check its mesh (a longer training, or a --geometry.foot-gap above the gap fills it down to "
                    f"the table)")
            r.problem = note if not r.problem else f"{r.problem}; {note}"
            warnings.warn(FloatingObjectWarning(f"object {r.name!r} (label {r.label}): {note}"), stacklevel=2)


DEFAULT_TABLE_EXTENT = (-0.5, 0.5, -0.4, 0.4)  # m: the table assumed when none is found (xmin, xmax, ymin, ymax)
NEAR_FIELD = 2.0  # background farther than this x the cameras' depth to the objects (from every camera) is far field


def near_field_mask(points: np.ndarray, cameras: list | None, object_points: np.ndarray | None,
                    factor: float = NEAR_FIELD) -> np.ndarray | None:
    """Keep-mask [N] of points [N,3] within `factor` x the viewing depth of some capture camera, the
    viewing depth being the median over cameras of the median depth of the objects' points each sees.
    The far field (the sparse-view background sphere at 3 scene scales, a room's floor and walls) is no
    table, but it can outnumber the table's splats many times over and take the plane fit. None (keep
    everything) without cameras or objects to measure the depth against."""
    if not cameras or object_points is None or len(object_points) < 10:
        return None
    from scipy.spatial import cKDTree

    from splattwin.poses.table import viewing_depth

    depth = viewing_depth(cameras, object_points)
    if depth is None:
        return None
    centres = np.array([np.asarray(c.center, dtype=np.float64).reshape(3) for c in cameras])
    dist, _ = cKDTree(centres).query(points)
    return dist <= factor * depth


def default_table(object_points: np.ndarray | None, length_scale: float = 1.0, margin: float = 0.1
                  ) -> list[float]:
    """[xmin, xmax, ymin, ymax] of the table assumed when none was found: `DEFAULT_TABLE_EXTENT` (m, x
    length_scale) centred under the objects' points, grown to their footprint plus `margin` (m): a user
    expects the objects on the table, not off its edge (the origin of an SfM frame can be anywhere)."""
    half = np.array([DEFAULT_TABLE_EXTENT[1], DEFAULT_TABLE_EXTENT[3]]) * length_scale
    if object_points is None or len(object_points) == 0:
        return [float(-half[0]), float(half[0]), float(-half[1]), float(half[1])]
    lo, hi = np.percentile(object_points[:, :2], [1, 99], axis=0)
    c = (lo + hi) / 2
    half = np.maximum(half, (hi - lo) / 2 + margin * length_scale)
    return [float(c[0] - half[0]), float(c[0] + half[0]), float(c[1] - half[1]), float(c[1] + half[1])]


def _table_box(extent, h: float, thickness: float) -> trimesh.Trimesh:
    x0, x1, y0, y1 = extent
    table = trimesh.creation.box(extents=[x1 - x0, y1 - y0, thickness])
    table.apply_translation([(x0 + x1) / 2, (y0 + y1) / 2, h - thickness / 2])
    return table


TABLE_UNDER_MARGIN = 0.02  # m: how far the table reaches beyond the footprint of an object standing on it


def _footprint(r: ObjectGeometry) -> tuple[np.ndarray, float] | None:
    """(xy [2,2] lower/upper corner, lowest z) of an object's collision geometry in the twin frame: its
    collision mesh, or an unusable object's obstacle box; None when it has neither."""
    if r.usable and r.collision is not None and len(r.collision.vertices):
        v = np.asarray(r.collision.vertices) @ r.T_world_obj[:3, :3].T + r.T_world_obj[:3, 3]
        return np.stack([v[:, :2].min(axis=0), v[:, :2].max(axis=0)]), float(v[:, 2].min())
    if r.obstacle:
        c, e = np.asarray(r.T_world_obj)[:3, 3], np.asarray(r.extent)
        return np.stack([c[:2] - e[:2] / 2, c[:2] + e[:2] / 2]), float(c[2] - e[2] / 2)
    return None


def table_under_objects(bg: BackgroundGeometry, results: list[ObjectGeometry], reach: float, margin: float,
                        within: np.ndarray | None = None) -> list[str]:
    """Grow the table top of `bg` in place so that it reaches `margin` beyond the footprint (xy box of the
    collision geometry) of every object whose lowest point is within `reach` of it: the photos show those
    objects at rest on the table, so the table is under them. Its extent comes from the table splats,
    and they can stop short of an object: behind it (occluded), beyond the views, or sparse (SfM's few
    hundred seed points at a low iteration count). A 20 x 15 cm box at the far edge of the splats
    (`scene generate --robot-capture bop` without poses, SfM + depth scale, 800 iterations) hung
    15 cm over the table's edge and fell 74 cm to the floor at physics start. The table box, the
    background's collision mesh and its first convex part (the table) are rebuilt. within: [2,3] corners
    of the scene (`scene_bounds`): the table is not grown under an unusable object's obstacle box (an
    estimate) reaching beyond them; None: no bound. Returns the names of the objects it was grown under
    (empty: unchanged)."""
    x0, x1, y0, y1 = (float(v) for v in bg.table_extent)
    grown = []
    for r in results:
        fp = _footprint(r)
        if fp is None or fp[1] > bg.table_height + reach:
            continue
        if (within is not None and not r.usable
                and (np.any(fp[0][0] < within[0][:2]) or np.any(fp[0][1] > within[1][:2]))):
            log.warning("table not grown under %r: its obstacle box (an estimate) reaches far beyond the scene",
                        r.name)
            continue
        lo, hi = fp[0][0] - margin, fp[0][1] + margin
        if lo[0] < x0 or lo[1] < y0 or hi[0] > x1 or hi[1] > y1:
            grown.append(r.name)
            x0, y0 = min(x0, float(lo[0])), min(y0, float(lo[1]))
            x1, y1 = max(x1, float(hi[0])), max(y1, float(hi[1]))
    if not grown:
        return []
    log.info("table top grown under %s (their footprints reach beyond the table splats): x %.3g..%.3g, y %.3g..%.3g "
             "-> x %.3g..%.3g, y %.3g..%.3g", ", ".join(grown), *bg.table_extent, x0, x1, y0, y1)
    bg.table_extent = [x0, x1, y0, y1]
    table = _table_box(bg.table_extent, bg.table_height, bg.table_thickness)
    bg.parts = [table] + list(bg.parts[1:])
    bg.collision = trimesh.util.concatenate([table] + list(bg.obstacles))
    return grown


def background_geometry(g, indices: np.ndarray, opts: GeometryOptions, table_thickness: float = 0.03,
                        plane: Plane | None = None, length_scale: float = 1.0,
                        object_points: np.ndarray | None = None) -> BackgroundGeometry:
    """Table plane + obstacles from the (attribute-filtered) background Gaussians `g[indices]` (twin frame).
    plane: the table plane when the frame already defines it (see `split_background`). When no table
    splats are found the table is `default_table` (under `object_points`, lengths x length_scale) at
    the plane's height (0 without one), and `default_reason` says why."""
    pts = g.means[indices]
    if len(pts) < max(opts.min_points, 3):
        h = float(-plane.d / plane.normal[2]) + 0.0 if plane is not None else 0.0  # + 0.0: never -0
        ext = default_table(object_points, length_scale)
        return BackgroundGeometry(indices=np.zeros(0, np.int64), plane=plane, table_height=h, table_extent=ext,
                                  table_thickness=table_thickness, collision=_table_box(ext, h, table_thickness),
                                  parts=[_table_box(ext, h, table_thickness)],
                                  default_reason=f"too few background splats near the cameras ({len(pts)})")
    split = split_background(pts, opts.dbscan_eps, opts.dbscan_min_samples, opts.dbscan_voxel, opts.plane_distance,
                             opts.plane_iterations, opts.support_gap, opts.obstacle_min_points, opts.seed, plane=plane)
    n_table = int(split.table.sum())
    if n_table < opts.min_points:  # a few connected splats are no table top (the cake's 12 spanned 2 x 50 mm)
        split.table[:] = False
    tp = pts[split.table]
    h = float(np.median(tp[:, 2])) if len(tp) else float(-split.plane.d / split.plane.normal[2]) + 0.0
    if plane is None and not len(tp):
        h = 0.0  # a fitted plane without table splats is no evidence of the table's height
    if len(tp) and opts.densify:  # the top of the splats' half-opaque ellipsoids, like the objects' surfaces
        t = np.asarray(indices)[split.table]
        R = g.subset(t).rotation_matrices()
        sigma_z = np.sqrt(np.sum((R[:, 2, :] * g.scales[t]) ** 2, axis=1))  # std along world z
        h = float(np.median(tp[:, 2] + level_radii(g.opacities[t], opts.surface_level) * sigma_z))
    reason = None
    # the lengths in the reason (twin.json background.table_default, shown by the report) in the frame's
    # units: bare numbers read as metres in an unscaled twin (as `convert` names them)
    unit = "m" if length_scale == 1.0 else "frame units"
    if len(tp):
        x0, x1 = np.percentile(tp[:, 0], [0.2, 99.8])
        y0, y1 = np.percentile(tp[:, 1], [0.2, 99.8])
        extent = [float(x0), float(x1), float(y0), float(y1)]
        if object_points is not None and len(object_points):
            # objects stand on the table: a patch of table splats beside them (a plain cloth elsewhere,
            # the cake's 5 cm patch 2.5 units away) is part of it, not all of it
            lo, hi = np.percentile(object_points[:, :2], [1, 99], axis=0)
            cx, cy = (lo + hi) / 2
            if not (extent[0] <= cx <= extent[1] and extent[2] <= cy <= extent[3]):
                under = default_table(object_points, length_scale)
                reason = (f"the {len(tp)} table splats found (x {extent[0]:.3g}..{extent[1]:.3g}, y {extent[2]:.3g}.."
                          f"{extent[3]:.3g} {unit}) are not under the objects: the table is extended under them")
                extent = [min(extent[0], under[0]), max(extent[1], under[1]), min(extent[2], under[2]),
                          max(extent[3], under[3])]
    else:
        extent = default_table(object_points, length_scale)
        reason = (f"{int((np.abs(split.plane.signed_distance(pts)) <= 2 * opts.plane_distance).sum())} background "
                  f"splats within {2 * opts.plane_distance:.3g} {unit} of the "
                  f"{'frame' if plane is not None else 'fitted'} table plane, the largest connected group (DBSCAN eps "
                  f"{opts.dbscan_eps:.3g} {unit}) {n_table} of them "
                  f"(< {opts.min_points}): the table top is too sparse or not in the splats")
    table = _table_box(extent, h, table_thickness)
    parts = [table]
    meshes = [table]
    n_obs = int(split.obstacle_ids.max() + 1) if split.obstacles.any() else 0
    for k in range(n_obs):
        op = downsample(pts[split.obstacle_ids == k], opts.mesh_voxel)
        op = add_bottom(op, opts.mesh_voxel, z_floor=h) if opts.close_bottom else op
        res = solid_mesh(op, opts.mesh_voxel, opts.alpha, opts.alpha_factors, opts.close_iterations, opts.use_alpha,
                         name=f"background obstacle {k}", max_points=opts.alpha_max_points)
        m = simplify(smooth(res.mesh, opts.smooth_iterations), opts.collision_faces)
        meshes.append(m)
        parts.extend(convex_parts(simplify(m, opts.coacd_faces), opts.convex_ratio, opts.coacd_threshold,
                                  opts.max_convex_parts, opts.seed))
    return BackgroundGeometry(indices=np.asarray(indices)[split.keep], plane=split.plane, table_height=h,
                              table_extent=extent, table_thickness=table_thickness,
                              collision=trimesh.util.concatenate(meshes), parts=parts, n_obstacles=n_obs,
                              obstacles=meshes[1:], default_reason=reason)


def convert(g, labels: np.ndarray, objects: list, opts: GeometryOptions | None = None, background: bool = True,
            table_thickness: float = 0.03, progress: bool = True, length_scale: float = 1.0,
            cameras: list | None = None, table_plane: Plane | None = None, masks: dict | None = None,
            measured=None, scene_size: float | None = None) -> Conversion:
    """Full conversion. g: Gaussians [N]; labels [N] int (0 = background); objects: [(name, label, prompt)].
    scene_size: size (m, the diagonal of the robust box, `options.scene_scale`) of the scene the Gaussians come
    from, which sets the automatic `max_scale` (`max_scale_rel` x it); None: measured on `g`. Give the whole
    scene's (`scene_scale(all_gaussians.means)`) when `g` is a part of it (one object's Gaussians): measured on
    one object, max_scale shrinks to about a millimetre and the attribute filter drops the object (logged).
    length_scale: frame units per metre of the options' lengths and of table_thickness (m): 1 in a
    metric twin, the frame's nominal metre in an unscaled one (`TwinFrame.length_scale`).
    cameras: [Camera] of the capture in the twin frame, for the free-space carving of the object
    meshes (`GeometryOptions.carve`) and for the background's near field (`near_field_mask`); None:
    neither. table_plane: the table plane when the frame defines it (a table frame: z = 0), else fitted.
    masks: {label: [(Camera, bool mask [H,W])]}, the cameras (twin frame) with a 2D mask of that object:
    each object's silhouette coverage (`geometry.completeness`) decides with its splat count whether it
    is whole (`GeometryOptions.min_coverage`); None: no masks, the count alone decides.
    measured: label -> [(Camera, sensor depth [H,W] m)] (`carving.measured_views` of that object), for
    carving against the capture's measured depth (`GeometryOptions.carve_depth`); called for an object
    when it is meshed (its depth maps are read then; the time counts as carve_depth); None: no measured
    depth."""
    from splattwin.progress import Progress

    from splattwin.errors import require_type
    from splattwin.splat.gaussians import Gaussians

    # a PLY path passed here was taken for Gaussians: "labels has 0 entries for 10 Gaussians" (len of the path)
    require_type(g, Gaussians, "g", "(splattwin.splat.Gaussians; from a file: Gaussians.load_ply)")
    opts = opts or GeometryOptions()
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(g):
        from splattwin.errors import InputError

        raise InputError(f"labels has {len(labels)} entries for {len(g)} Gaussians")
    objects = check_objects(objects)
    timings: dict = defaultdict(float)
    t0 = time.perf_counter()
    size = scene_scale(g.means) if scene_size is None else float(scene_size)
    if not (np.isfinite(size) and size >= 0):
        raise ValueError(f"scene_size must be a finite size >= 0 (m), got {scene_size!r}")
    opts = opts.resolved(size, length_scale)
    table_thickness = table_thickness * length_scale
    keep, stats = attribute_mask(g.opacities, g.scales, opts)
    _log_oversized(g, labels, objects, keep, opts, size, scene_size is None)
    timings["filter"] = time.perf_counter() - t0
    # where the scene is: an unusable object's obstacle box holds no splat beyond it, and the table is not
    # grown under a box beyond twice as far (a box holds its splats' extents and a pad beyond its points)
    near_scene, far_scene = scene_bounds(g.means, 1.0), scene_bounds(g.means, 2.0)
    results = []
    with Progress(len(objects) + int(background), "geometry", unit="part", enabled=progress) as bar:
        t1 = time.perf_counter()
        cleaned = {int(obj[1]): clean_indices(g, labels, obj[1], opts, attr_keep=keep,
                                              masks=(masks or {}).get(int(obj[1])) if opts.coverage_views > 0 else None)
                   for obj in objects}
        timings["cluster"] += time.perf_counter() - t1
        obj_idx = [i for i in cleaned.values() if len(i)]
        obj_pts = g.means[np.concatenate(obj_idx)] if obj_idx else None
        # Background first: its table height is the support plane the objects are clipped to.
        bg = None
        if background:
            bar.set_description("geometry: background")
            t1 = time.perf_counter()
            bidx = np.flatnonzero((labels == 0) & keep)
            near = near_field_mask(g.means[bidx], cameras, obj_pts)
            if near is not None:
                log.info("background: %d of %d splats in the cameras' near field (the rest is far field, no table)",
                         int(near.sum()), len(bidx))
                bidx = bidx[near]
            bg = background_geometry(g, bidx, opts, table_thickness, plane=table_plane, length_scale=length_scale,
                                     object_points=obj_pts)
            if bg.default_reason is not None:
                x0, x1, y0, y1 = bg.table_extent
                log.warning("table assumed (%s): the twin's table is x %.3g..%.3g, y %.3g..%.3g at z %.3g, under "
                            "the objects; check its placement", bg.default_reason, x0, x1, y0, y1, bg.table_height)
            timings["background"] = time.perf_counter() - t1
            bar.update(1)
        support_z = bg.table_height if bg is not None and bg.plane is not None else None
        # what an object may stand on besides the table: the other objects and the background's obstacles
        # (a plate under a cake), each obstacle as points on its mesh
        obstacle_pts = [np.asarray(trimesh.sample.sample_surface(m, 2000, seed=opts.seed)[0])
                        for m in (bg.obstacles if bg is not None else []) if m.area > 0]
        for obj in objects:
            name, label, prompt = (tuple(obj) + ("",))[:3]
            bar.set_description(f"geometry: {name}")
            idx = cleaned[int(label)]
            others = [g.means[i] for lab, i in cleaned.items() if lab != int(label) and len(i)] + obstacle_pts
            if not np.any(labels == label):
                r = ObjectGeometry(name=name, label=int(label), prompt=prompt, usable=False,
                                   problem=f"missing label: no Gaussian carries label {label}")
                warnings.warn(ObjectUnusableWarning(f"object {name!r}: {r.problem}"), stacklevel=2)
            else:
                r = object_geometry(g, idx, name, label, opts, prompt, timings, support_z=support_z, cameras=cameras,
                                    other_points=np.concatenate(others) if others else None,
                                    masks=(masks or {}).get(int(label)),
                                    measured=(lambda lab=int(label): measured(lab)) if measured is not None else None)
            if not r.usable:  # its splats still say where the real object stands: an obstacle for planners
                mine = np.flatnonzero((labels == label) & keep)
                mine = mine if len(mine) else np.flatnonzero(labels == label)
                obstacle_box(r, g.means[mine], opts, bg.table_height if bg is not None else support_z,
                             half_extent=splat_half_extents(g, mine, opts), within=near_scene)
            results.append(r)
            bar.update(1)
        bar.set_description("geometry")
    if bg is not None:  # the objects stand on the table: it reaches under them wherever its splats stop short
        table_under_objects(bg, results, opts.foot_gap, TABLE_UNDER_MARGIN * length_scale, within=far_scene)
    flag_floating(results, support_z, opts, bg.obstacles if bg is not None else None,
                  units="m" if length_scale == 1.0 else "frame units")
    timings["total"] = time.perf_counter() - t0
    return Conversion(objects=results, background=bg, filter_stats=stats, options=opts, timings=dict(timings),
                      depth_skipped=None if measured is not None else "no measured depth given")


def ablation(g, labels: np.ndarray, objects: list, gt_meshes: dict, opts: GeometryOptions | None = None,
             table_height: float | None = 0.0, spacing: float = 0.002, length_scale: float = 1.0
             ) -> dict[str, dict[str, Fidelity]]:
    """Paper Table 5: {config: {object name: Fidelity}} of the cleaned Gaussian centres vs GT meshes
    (world frame) for the configurations raw, attribute, cluster, full. length_scale: see `convert`."""
    opts = (opts or GeometryOptions()).resolved(scene_scale(g.means), length_scale)
    keep = attribute_mask(g.opacities, g.scales, opts)[0]
    out: dict[str, dict[str, Fidelity]] = {c: {} for c in CONFIGS}
    for obj in objects:
        name, label = obj[0], obj[1]
        if name not in gt_meshes:
            continue
        gt = sample_surface(gt_meshes[name], spacing, seed=opts.seed, drop_supported=table_height)
        for c in CONFIGS:
            idx = clean_indices(g, labels, label, opts, attribute=c in ("attribute", "full"),
                                cluster=c in ("cluster", "full"), attr_keep=keep)
            out[c][name] = fidelity(g.means[idx], gt, opts.f1_threshold)
    return out


def check_objects(objects, where: str | Path | None = None) -> list[tuple[str, int, str]]:
    """`convert`'s and `build_twin`'s objects as [(name, label, prompt)]: each a (name, label[, prompt])
    sequence or a {"name", "label"[, "prompt"]} mapping, the label a whole number in [1, MAX_LABEL] (0 is background;
    label images are 16-bit, and twin.json refuses more), names and labels unique. InputError naming the
    entry otherwise (a dict used to give a bare KeyError: 1), before anything is built or written."""
    from splattwin.errors import InputError, short_repr
    from splattwin.semantics.masks import MAX_LABEL_ID as MAX_LABEL

    if isinstance(objects, (str, bytes, dict)) or not hasattr(objects, "__iter__"):
        raise InputError(f"objects must be a list of (name, label, prompt), got {type(objects).__name__}", where)
    out: list[tuple[str, int, str]] = []
    for i, o in enumerate(objects):
        if isinstance(o, dict):
            if "name" not in o or "label" not in o:
                raise InputError(f"object {i} {short_repr(o)} needs 'name' and 'label' (objects are (name, label, "
                                 f"prompt))", where)
            name, label, prompt = o["name"], o["label"], o.get("prompt", "")
        elif isinstance(o, (list, tuple)) and len(o) in (2, 3):
            name, label, prompt = (*o, "")[:3]
        else:
            raise InputError(f"object {i} must be (name, label, prompt), got {short_repr(o)}", where)
        if not isinstance(name, str) or not name:
            raise InputError(f"object {i}: the name must be non-empty text, got {short_repr(name)}", where)
        if (isinstance(label, (bool, np.bool_)) or not isinstance(label, (int, np.integer))
                or not 1 <= label <= MAX_LABEL):
            raise InputError(f"object {short_repr(name)}: the label must be a whole number >= 1 (0 is background) and "
                             f"<= {MAX_LABEL} (label images are 16-bit), got {short_repr(label)}", where)
        out.append((name, int(label), "" if prompt is None else str(prompt)))
    for k, what in ((0, "name"), (1, "label")):
        seen = [o[k] for o in out]
        dup = next((v for v in seen if seen.count(v) > 1), None)
        if dup is not None:
            raise InputError(f"objects: the {what} {dup!r} is used twice", where)
    return out


def _log_oversized(g, labels: np.ndarray, objects: list, keep: np.ndarray, opts: GeometryOptions, size: float,
                   measured: bool) -> None:
    """Warn for each object whose splats the attribute filter drops for the most part as larger than
    `max_scale`: with the automatic max_scale measured on the Gaussians given, that is one object's Gaussians
    passed alone (its own size sets the bound), and the object then ends "too few points after cleaning"."""
    if opts.max_scale is None:
        return
    largest = np.asarray(g.scales).max(axis=1)
    for obj in objects:
        name, label = obj[0], int(obj[1])
        mine = labels == label
        n = int(mine.sum())
        big = int((mine & ~keep & (largest > opts.max_scale)).sum())
        if n and big > n // 2:
            how = (f"max_scale_rel {opts.max_scale_rel:g} x the size {size:.3g} of the Gaussians given: pass "
                   f"convert(..., scene_size=scene_scale(whole_scene.means)) when they are a part of a scene, or "
                   f"GeometryOptions(max_scale=...)") if measured else "from scene_size"
            log.warning("object %r: the attribute filter drops %d of its %d splats as larger than max_scale %.3g "
                        "(%s)", name, big, n, opts.max_scale, how)


def conversion_fidelity(conv: Conversion, gt_meshes: dict, threshold: float = 0.005) -> dict[str, Fidelity]:
    """{object name: Fidelity} of each usable object's visual mesh, placed in the twin frame, against its
    GT mesh (world = twin frame); objects without a GT mesh are skipped, unusable ones score zero."""
    out = {}
    for o in conv.objects:
        if o.name not in gt_meshes:
            continue
        if not o.usable or o.visual is None:
            out[o.name] = Fidelity(chamfer=float("inf"), precision=0.0, recall=0.0, f1=0.0, n_points=0)
            continue
        m = o.visual.copy()
        m.apply_transform(o.T_world_obj)
        out[o.name] = mesh_fidelity(m, gt_meshes[o.name], threshold)
    return out
