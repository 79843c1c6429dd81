"""Objects' footprints on the table plane, from their collision meshes: for the checks of a task (`task.TaskScene`)
and the planner's belief (what stands on what, `selection.support_height`; how high to release an object on
another, `selection.release_height`; which objects crowd a goal, `candidates.goal_neighbours`).

An object's `Shape` is its convex parts (twin.json `convex_parts`, else its `collision_mesh` as one part, as the
collision exports take them): vertices in the object frame (m). Posed at T_world_obj, its footprint is the union
of the parts' projections on the table plane (twin frame x, y): one convex polygon per part, so an L-shaped
object or a hammer (head and handle) leaves the free corners of its bounding box free. An object without a
usable mesh (an obstacle-only box, a usable object with no part, or no twin folder given) falls back to its
bounding box: `bbox_extent` centred on the object frame's origin, as one part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.twin.manifest import Manifest, ObjectEntry

EPS = 1e-9   # m: a point this close to a polygon counts as on it (the old box test was exact: d == 0)


@dataclass(frozen=True)
class Shape:
    """An object's geometry for the task checks: vertices [Ni, 3] of each convex part (object frame, m);
    from_mesh False when the one part is its bounding box (no usable collision mesh)."""

    parts: tuple[np.ndarray, ...]
    from_mesh: bool = True


def box_shape(extent) -> Shape:
    """The bounding box of `extent` [3] (m, object frame, centred on the origin) as a one-part Shape."""
    half = np.asarray(extent, float)[:3] / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * half
    return Shape((corners,), from_mesh=False)


def object_shape(obj: ObjectEntry, twin_dir: str | Path | None) -> Shape:
    """The Shape of a twin object: its convex parts read from `twin_dir` (paths confined to it, meshes
    checked by `meshio.load_mesh`: InputError naming the file), or its bounding box when it has no usable
    mesh (obstacle-only, no parts) or `twin_dir` is None."""
    from splattwin.meshio import load_mesh
    from splattwin.paths import confined

    rels = list(obj.convex_parts) or ([obj.collision_mesh] if obj.collision_mesh else [])
    if twin_dir is None or not obj.usable or not rels:
        return box_shape(obj.bbox_extent)
    where = Path(twin_dir) / "twin.json"
    parts = []
    for rel in rels:
        what = f"convex part of object {obj.name!r}"
        m = load_mesh(confined(twin_dir, rel, where, what), what)
        parts.append(np.asarray(m.vertices, float))
    return Shape(tuple(parts))


class Shapes:
    """The Shapes of a twin's objects by name (`object_shape`: convex parts read from twin_dir, else the
    bounding box), each read once; twin_dir None: every object's bounding box."""

    def __init__(self, manifest: Manifest, twin_dir: str | Path | None) -> None:
        self.manifest, self.twin_dir = manifest, twin_dir
        self._cache: dict[str, Shape] = {}

    def __call__(self, name: str) -> Shape:
        if name not in self._cache:
            self._cache[name] = object_shape(self.manifest.object(name), self.twin_dir)
        return self._cache[name]


def _posed(part: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Vertices [N, 3] (object frame) in the twin frame at T_world_obj [4, 4]."""
    T = np.asarray(T, float)
    return part @ T[:3, :3].T + T[:3, 3]


def _polygon(xy: np.ndarray) -> np.ndarray:
    """The convex hull of points xy [N, 2], counter-clockwise [K, 2]; a degenerate one (a line: a part seen
    edge-on) is its two extreme points [2, 2] (no area: only points on that segment are on it)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        a = xy[np.argmax(np.linalg.norm(xy - xy[0], axis=1))]
        b = xy[np.argmax(np.linalg.norm(xy - a, axis=1))]
        return np.array([a, b])


def _edges_distance(p: np.ndarray, poly: np.ndarray) -> float:
    """Distance (m) from the point p [2] to the closest edge of the closed polygon poly [K, 2]."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def _inside(p: np.ndarray, poly: np.ndarray) -> bool:
    """True if p [2] lies in the counter-clockwise convex polygon poly [K, 2] (within EPS of it counts)."""
    if len(poly) < 3:
        return _edges_distance(p, poly) <= EPS
    e = np.roll(poly, -1, axis=0) - poly
    cross = e[:, 0] * (p[1] - poly[:, 1]) - e[:, 1] * (p[0] - poly[:, 0])
    return bool(np.all(cross >= -EPS * np.linalg.norm(e, axis=1)))


def polygon_distance(xy, poly: np.ndarray) -> float:
    """Horizontal distance (m) from the point xy to the convex polygon poly [K, 2]; 0 inside or on it."""
    p = np.asarray(xy, float)[:2]
    return 0.0 if _inside(p, poly) else _edges_distance(p, poly)


INRADIUS_RAYS = 720   # directions (every 0.5 degrees) along which `inradius` measures the footprint about its centre


def _ray_intervals(poly: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_in, t_out) [A] of the rays from the origin along the unit directions d [A, 2] through the convex
    counter-clockwise polygon poly [K, 2] (m; t_in > t_out where a ray misses it)."""
    e = np.roll(poly, -1, axis=0) - poly                              # [K, 2] edges
    f0 = -(e[:, 0] * poly[:, 1] - e[:, 1] * poly[:, 0])               # cross(e, 0 - v) [K]: >= 0 inside
    df = d[:, None, 1] * e[None, :, 0] - d[:, None, 0] * e[None, :, 1]   # cross(e, d) [A, K]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -f0[None, :] / df
    t_in = np.max(np.where(df > 0, t, -np.inf), axis=1)
    t_out = np.min(np.where(df < 0, t, np.inf), axis=1)
    parallel_out = np.any((df == 0) & (f0[None, :] < 0), axis=1)     # along an edge line, outside it
    return np.where(parallel_out, np.inf, np.maximum(t_in, 0.0)), np.where(parallel_out, -np.inf, t_out)


def inradius(shape: Shape) -> float:
    """Radius (m) of the disc about the object frame's origin that the footprint of `shape` covers, upright,
    at any yaw: the distance from the origin to where the union of its parts' footprints ends, the least
    over INRADIUS_RAYS directions (parts that touch or overlap continue each other; beside a concave corner
    of the union a ray may end a little beyond it: 0.05 mm at 2.2 cm); 0 when the origin is on no part (an
    L's notch). A box's is half its shorter side."""
    polys = [p for p in polygons(shape, np.eye(4)) if len(p) >= 3]
    if not any(_inside(np.zeros(2), p) for p in polys):
        return 0.0
    a = np.linspace(0.0, 2 * np.pi, INRADIUS_RAYS, endpoint=False)
    d = np.column_stack([np.cos(a), np.sin(a)])
    spans = [_ray_intervals(p, d) for p in polys]
    reach = np.zeros(len(a))          # how far from the origin each ray is covered without a gap
    for _ in polys:                   # each pass may add one more part along a ray
        for t_in, t_out in spans:
            joins = (t_in <= reach + EPS) & (t_out > reach)
            reach = np.where(joins, t_out, reach)
    return float(reach.min())


def _part_top(V: np.ndarray, xy: np.ndarray) -> float:
    """Height (m) of the convex part with vertices V [N, 3] (twin frame) on the vertical line through xy,
    which its footprint holds: the lowest of its upward faces' planes there; the top of its vertices for a
    flat part (no volume)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        eq = ConvexHull(V).equations   # n . p + d <= 0 inside
    except (QhullError, ValueError):
        return float(V[:, 2].max())
    up = eq[:, 2] > 1e-9
    z = -(eq[up, 0] * xy[0] + eq[up, 1] * xy[1] + eq[up, 3]) / eq[up, 2]
    return float(np.clip(z.min(), V[:, 2].min(), V[:, 2].max()))


THICKEN = 1e-6   # m: a part without volume (a plate, a needle) is made this much thicker for its hull


def _hull_planes(V: np.ndarray) -> np.ndarray | None:
    """The convex hull of V [N, 3] as planes [F, 4] (n . p + d <= 0 inside, unit n); a part without volume (a
    plate, a needle) thickened by THICKEN across it first; None for no vertices."""
    from scipy.spatial import ConvexHull, QhullError

    if len(V) == 0:
        return None
    try:
        return ConvexHull(V).equations
    except (QhullError, ValueError):
        _, _, axes = np.linalg.svd(V - V.mean(axis=0), full_matrices=True)
        offsets = [s * THICKEN * a for a in axes for s in (-1, 1)]
        return ConvexHull(np.vstack([V + o for o in offsets])).equations


def _halfplanes(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A [M, 2], b [M]): the points p with A p <= b are the counter-clockwise convex polygon poly [K, 2] (a
    segment when K = 2, `_polygon`)."""
    if len(poly) >= 3:
        e = np.roll(poly, -1, axis=0) - poly   # inside: cross(e, p - v) >= 0
        return np.column_stack([e[:, 1], -e[:, 0]]), e[:, 1] * poly[:, 0] - e[:, 0] * poly[:, 1]
    a, b = poly[0], poly[-1]
    d = b - a
    n = np.array([-d[1], d[0]])
    return np.array([n, -n, -d, d]), np.array([n @ a, -(n @ a), -(d @ a), d @ b])


def _highest_over(planes: np.ndarray, poly: np.ndarray) -> np.ndarray | None:
    """x, y [2] of the highest point of the convex solid `planes` [F, 4] over the convex polygon poly [K, 2];
    None when the solid lies nowhere over it. A linear program (scipy HiGHS)."""
    from scipy.optimize import linprog

    A2, b2 = _halfplanes(poly)
    norm = np.maximum(np.linalg.norm(A2, axis=1), 1e-300)   # unit normals: the slack below is EPS metres
    A2, b2 = A2 / norm[:, None], b2 / norm
    A = np.vstack([planes[:, :3], np.column_stack([A2, np.zeros(len(A2))])])
    b = np.concatenate([-planes[:, 3], b2 + EPS])   # a polygon touching the part's edge meets it
    r = linprog([0.0, 0.0, -1.0], A_ub=A, b_ub=b, bounds=[(None, None)] * 3, method="highs")
    return np.asarray(r.x[:2], float) if r.status == 0 else None


class Posed:
    """A Shape at T_world_obj [4, 4]: its parts' vertices in the twin frame and their footprint polygons (twin
    frame x, y, m; one convex polygon per part, their union the footprint), computed once for many queries."""

    def __init__(self, shape: Shape, T: np.ndarray) -> None:
        self.parts = [_posed(p, T) for p in shape.parts]
        self.polygons = [_polygon(V[:, :2]) for V in self.parts]

    def distance(self, xy) -> float:
        """Horizontal distance (m) from the point xy (twin frame) to the footprint; 0 on it."""
        return min(polygon_distance(xy, poly) for poly in self.polygons)

    def top_at(self, xy) -> float | None:
        """Height (m, twin frame) of the top over the point xy: the highest of the parts whose footprint holds
        xy; None when none does (xy is off the footprint)."""
        p = np.asarray(xy, float)[:2]
        tops = [_part_top(V, p) for V, poly in zip(self.parts, self.polygons) if _inside(p, poly)]
        return max(tops) if tops else None

    def bottom(self) -> float:
        """Height (m, twin frame) of the lowest point."""
        return min(float(V[:, 2].min()) for V in self.parts)

    def top_under(self, polys: list[np.ndarray]) -> float | None:
        """Height (m, twin frame) of the highest point of the parts over the convex polygons polys [K, 2] (twin
        frame x, y: another object's footprint, `Posed.polygons`): the first point an object with that footprint,
        lowered from above, would touch; None when no part lies under them. Per part and polygon, a linear
        program (maximise z inside the part's hull and over the polygon); the height there as `top_at` says."""
        tops = []
        for V in self.parts:
            planes = _hull_planes(V)
            if planes is None:
                continue
            for poly in polys:
                xy = _highest_over(planes, poly)
                if xy is not None:
                    tops.append(_part_top(V, xy))
        return max(tops) if tops else None


def reach(shape: Shape) -> float:
    """Radius (m) of the disc about the object frame's origin that holds the footprint of `shape` upright at
    any yaw: the farthest of its parts' vertices from the vertical axis through the origin (a box's: half
    its footprint's diagonal)."""
    return max(float(np.linalg.norm(p[:, :2], axis=1).max(initial=0.0)) for p in shape.parts)


def polygons(shape: Shape, T: np.ndarray) -> list[np.ndarray]:
    """The footprint of `shape` posed at T_world_obj: one convex polygon (twin frame x, y, m) per part."""
    return Posed(shape, T).polygons


def distance(xy, shape: Shape, T: np.ndarray) -> float:
    """Horizontal distance (m) from the point xy (twin frame) to the footprint of `shape` at T; 0 on it."""
    return Posed(shape, T).distance(xy)


def top_at(shape: Shape, T: np.ndarray, xy) -> float | None:
    """Height (m, twin frame) of the top of `shape` posed at T over the point xy (`Posed.top_at`)."""
    return Posed(shape, T).top_at(xy)


def bottom(shape: Shape, T: np.ndarray) -> float:
    """Height (m, twin frame) of the lowest point of `shape` posed at T."""
    return Posed(shape, T).bottom()


WIDTH_ANGLE_STEP_DEG = 2.0   # closing directions sampled over a half turn (a 1 degree miss widens a run by 0.015 %)
WIDTH_SLICE_STEP = 0.005     # m between the horizontal cross-sections `narrowest_width` measures
MAX_WIDTH_LINES = 400        # lines per direction at most (3 mm apart up to 1.2 m across)


def _hull_edges(V: np.ndarray) -> np.ndarray | None:
    """The edges [E, 2] (vertex index pairs) of the convex hull of V [N, 3]; None for a flat or degenerate part."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        f = ConvexHull(V).simplices
    except (QhullError, ValueError):
        return None
    return np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]]), axis=1), axis=0)


def _section(V: np.ndarray, edges: np.ndarray, z: float) -> np.ndarray | None:
    """The cross-section at height z (object frame, m) of the convex part with vertices V [N, 3] and hull edges
    `edges` [E, 2]: a convex counter-clockwise polygon [K, 2] (x, y), or None when the plane misses the part or
    the section has no area (a plane through one vertex)."""
    a, b = V[edges[:, 0]], V[edges[:, 1]]
    cross = (a[:, 2] - z) * (b[:, 2] - z) <= 0.0
    a, b = a[cross], b[cross]
    dz = b[:, 2] - a[:, 2]
    flat = np.abs(dz) < 1e-12      # an edge lying in the plane: both its ends are on the section
    t = np.where(flat, 0.0, (z - a[:, 2]) / np.where(flat, 1.0, dz))
    pts = np.vstack([a[:, :2] + t[:, None] * (b[:, :2] - a[:, :2]), b[flat, :2]])
    poly = _polygon(pts) if len(pts) >= 3 else None
    return poly if poly is not None and len(poly) >= 3 else None


def _chords(poly: np.ndarray, c: np.ndarray, b: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
    """Where the lines {p: p.b_a = s_i} cross the convex counter-clockwise polygon poly [K, 2], along the unit
    directions c [A, 2] (b [A, 2]: c turned by +90 degrees; s [S], m): (lo, hi) [A, S] (lo = inf, hi = -inf
    where a line misses it) and the cosines [A, S] between c and the outward edge normals there (at lo: of
    -c, at hi: of c)."""
    q = np.roll(poly, -1, axis=0)
    e = q - poly
    n = np.column_stack([e[:, 1], -e[:, 0]]) / np.maximum(np.linalg.norm(e, axis=1), 1e-300)[:, None]  # outward (CCW)
    u0, u1, v0, v1 = b @ poly.T, b @ q.T, c @ poly.T, c @ q.T                 # [A, K]
    du = u1 - u0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (s[None, :, None] - u0[:, None, :]) / du[:, None, :]             # [A, S, K]
    hit = (t >= 0.0) & (t <= 1.0) & (du != 0.0)[:, None, :]
    v = v0[:, None, :] + t * (v1 - v0)[:, None, :]
    i_lo = np.argmin(np.where(hit, v, np.inf), axis=2)
    i_hi = np.argmax(np.where(hit, v, -np.inf), axis=2)
    any_hit = hit.any(axis=2)
    lo = np.where(any_hit, np.take_along_axis(v, i_lo[..., None], axis=2)[..., 0], np.inf)
    hi = np.where(any_hit, np.take_along_axis(v, i_hi[..., None], axis=2)[..., 0], -np.inf)
    nc = c @ n.T                                                              # [A, K]: cos(c, normal of edge k)
    return lo, hi, -np.take_along_axis(nc, i_lo, axis=1), np.take_along_axis(nc, i_hi, axis=1)


def _run_min(polys: list[np.ndarray], c: np.ndarray, b: np.ndarray, s: np.ndarray, cos_cone: float) -> float:
    """The shortest run of material (m) across the union of the convex polygons polys along the lines of
    `_chords` whose two ends face -c and +c within the cone (cosine cos_cone); inf when none does."""
    ch = [_chords(q, c, b, s) for q in polys]                                 # per part: lo, hi, cos_lo, cos_hi
    lo, hi, clo, chi = (np.stack([x[i] for x in ch], axis=-1) for i in range(4))   # [A, S, P]
    order = np.argsort(lo, axis=-1)                                          # the parts along each line
    lo, hi, clo, chi = (np.take_along_axis(x, order, axis=-1) for x in (lo, hi, clo, chi))
    run_lo, run_clo, run_hi, run_chi = lo[..., 0], clo[..., 0], hi[..., 0], chi[..., 0]
    best = math.inf

    def shortest(mask: np.ndarray) -> float:
        ok = mask & (run_hi > run_lo) & (run_clo >= cos_cone) & (run_chi >= cos_cone)
        return float((run_hi - run_lo)[ok].min()) if ok.any() else math.inf

    for j in range(1, len(polys)):
        there = np.isfinite(lo[..., j])                                       # part j crosses the line
        new = there & (lo[..., j] > run_hi + EPS)                             # after a gap: the run so far ends
        best = min(best, shortest(new))
        longer = there & ~new & (hi[..., j] > run_hi)
        run_lo, run_clo = np.where(new, lo[..., j], run_lo), np.where(new, clo[..., j], run_clo)
        run_hi, run_chi = np.where(new | longer, hi[..., j], run_hi), np.where(new | longer, chi[..., j], run_chi)
    return min(best, shortest(np.isfinite(run_lo)))


def narrowest_width(shape: Shape, cone: float | None = None, step: float | None = None) -> float | None:
    """The narrowest width (m) a parallel gripper would have to open to, to close on `shape` (object frame,
    upright): top and side grasps both close horizontally (`grasp.synthesize`), so over horizontal closing
    directions c (every WIDTH_ANGLE_STEP_DEG), horizontal cross-sections (every WIDTH_SLICE_STEP from bottom
    to top: a bottle's neck counts, not only its widest part) and lines along c (every `step`), the length of
    each run of material across the union of the parts (parts that touch or overlap continue each other)
    whose two ends face -c and +c within the friction cone `cone` (rad): the runs the jaws could hold
    (antipodal), as the synthesis' contact test wants. A box's is its shorter side, a disc's 0.86 of its
    diameter (cos of the 31 degree cone). None when no run qualifies (no pair of opposite faces at all).
    cone / step default to `grasp.FRICTION_CONE` and `grasp.SCAN_STEP`."""
    from splattwin.robot.grasp import FRICTION_CONE, SCAN_STEP

    cos_cone = math.cos(FRICTION_CONE if cone is None else cone)
    step = SCAN_STEP if step is None else step
    parts = [(V, e) for V, e in ((np.asarray(p, float), _hull_edges(np.asarray(p, float))) for p in shape.parts)
             if e is not None]
    if not parts:
        return None
    z_lo = min(float(V[:, 2].min()) for V, _ in parts)
    z_hi = max(float(V[:, 2].max()) for V, _ in parts)
    zs = (np.arange(z_lo + WIDTH_SLICE_STEP / 2, z_hi, WIDTH_SLICE_STEP) if z_hi - z_lo > WIDTH_SLICE_STEP
          else np.array([(z_lo + z_hi) / 2]))
    a = np.radians(np.arange(0.0, 180.0, WIDTH_ANGLE_STEP_DEG))
    c = np.column_stack([np.cos(a), np.sin(a)])
    b = np.column_stack([-np.sin(a), np.cos(a)])
    r = max(float(np.linalg.norm(V[:, :2], axis=1).max()) for V, _ in parts)
    step = max(step, 2 * r / MAX_WIDTH_LINES)        # bounds the [angles, lines, edges] arrays of a huge object
    s = np.arange(-r + step / 2, r, step)            # the lines: the same offsets from the origin at every angle
    best, last = math.inf, None
    for z in zs:
        polys = [q for q in (_section(V, e, float(z)) for V, e in parts) if q is not None]
        if not polys:
            continue
        if last is not None and len(last) == len(polys) and all(
                p.shape == q.shape and np.allclose(p, q, atol=1e-6) for p, q in zip(last, polys)):
            continue                                 # the same section as the slice below (a prism's sides)
        last = polys
        best = min(best, _run_min(polys, c, b, s, cos_cone))
    return None if math.isinf(best) else best
