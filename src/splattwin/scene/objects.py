"""Objects of the tabletop scene and their seeded, collision-free layout on the table.

World frame = table frame: z up, table top at z = 0, origin at the table centre, metres. Each object's
frame has its origin at the centre of its axis-aligned bounding box (in that frame) and z up; objects
rest on the table, so T_world_obj has a pure yaw rotation and translation z = extent_z / 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from splattwin.scene import textures as tx
from splattwin.transforms import pose_xyz_yaw

# Table top: [xmin, xmax, ymin, ymax] metres, and thickness (top at z = 0).
TABLE_EXTENT = (-0.45, 0.45, -0.55, 0.55)
TABLE_THICKNESS = 0.03
ROBOT_BASE_XY = np.array([-0.50, 0.0])
REACH = (0.30, 0.75)                      # metres from the robot base, horizontal
# Where footprints may lie: x0 >= -0.19 keeps every point >= 0.31 m from the base (so checking corners
# against the outer reach radius suffices), |y| <= 0.3 keeps objects in view of the scan.
PLACE_REGION = (-0.19, 0.26, -0.30, 0.30)
TARGET_FRAME_SIZE = 0.24                  # taped square for the hammer: side measured on the tape's centre line, m
TAPE_WIDTH = 0.018                        # width of the tape outlining the target frame, m
MIN_GAP = 0.035                           # free space between footprints, m (room for gripper fingers)

# Hammer geometry (object frame before centring: handle along +x from 0, lying on the table).
_HANDLE = (0.175, 0.025, 0.025)
_HEAD = (0.03, 0.08, 0.03)
_HEAD_X0 = 0.16


@dataclass
class SceneObject:
    """One object: name, label id (1..), segmenter prompt, shape kind, role, pose, size, mesh, texture."""

    name: str
    label: int
    prompt: str
    kind: str                      # "box" | "cylinder" | "compound"
    role: str                      # "obstacle+placement" | "graspable"
    extent: np.ndarray             # [3] bounding-box size in the object frame, m
    mesh_obj: trimesh.Trimesh      # object-frame mesh
    footprint: list[tuple[np.ndarray, np.ndarray]]  # object-frame 2D rectangles (centre [2], half-size [2])
    T_world_obj: np.ndarray = field(default_factory=lambda: np.eye(4))
    albedo: tx.Albedo | None = None

    @property
    def convex(self) -> bool:
        hull = self.mesh_obj.convex_hull
        return bool(self.mesh_obj.volume / hull.volume > 0.99)

    def mesh_world(self) -> trimesh.Trimesh:
        m = self.mesh_obj.copy()
        m.apply_transform(self.T_world_obj)
        return m

    def to_json(self) -> dict:
        return {"name": self.name, "label": self.label, "prompt": self.prompt, "kind": self.kind,
                "role": self.role, "T_world_obj": _round(self.T_world_obj), "extent": _round(self.extent),
                "mesh": f"meshes/{self.name}.ply", "convex": self.convex}


def _round(a) -> list:
    """JSON-ready list; float repr round-trips exactly, so what is recorded is what was rendered."""
    return np.asarray(a, dtype=np.float64).tolist()


def _box(extent: tuple[float, float, float], center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extent)
    m.apply_translation(center)
    return m


def make_objects(seed: int) -> list[SceneObject]:
    """The five objects, in label order, with poses still at the identity."""
    objs = []
    e = np.array([0.20, 0.15, 0.10])
    objs.append(SceneObject("cardboard_box", 1, "cardboard box", "box", "obstacle+placement", e, _box(e),
                            [(np.zeros(2), e[:2] / 2)], albedo=tx.cardboard_albedo(seed + 10, e)))
    e = np.array([0.08, 0.06, 0.05])
    objs.append(SceneObject("blue_box", 2, "blue box", "box", "graspable", e, _box(e),
                            [(np.zeros(2), e[:2] / 2)], albedo=tx.blue_box_albedo(seed + 20)))
    e = np.array([0.025, 0.025, 0.025])
    objs.append(SceneObject("yellow_cube", 3, "yellow cube", "box", "graspable", e, _box(e),
                            [(np.zeros(2), e[:2] / 2)], albedo=tx.yellow_cube_albedo(seed + 30)))
    # hammer: handle + head, boolean union (watertight), then centred on its bounding box
    handle = _box(_HANDLE, (_HANDLE[0] / 2, 0.0, _HANDLE[2] / 2))
    head = _box(_HEAD, (_HEAD_X0 + _HEAD[0] / 2, 0.0, _HEAD[2] / 2))
    ham = trimesh.boolean.union([handle, head], engine="manifold")
    lo, hi = ham.bounds
    c = (lo + hi) / 2
    ham.apply_translation(-c)
    e = hi - lo
    fp = [(np.array([_HANDLE[0] / 2 - c[0], 0.0]), np.array(_HANDLE[:2]) / 2),
          (np.array([_HEAD_X0 + _HEAD[0] / 2 - c[0], 0.0]), np.array(_HEAD[:2]) / 2)]
    objs.append(SceneObject("toy_hammer", 4, "toy hammer", "compound", "graspable", e, ham, fp,
                            albedo=tx.hammer_albedo(seed + 40, _HEAD_X0 - c[0])))
    r, h = 0.035, 0.16
    cyl = trimesh.creation.cylinder(radius=r, height=h, sections=48)
    objs.append(SceneObject("bottle", 5, "bottle", "cylinder", "graspable", np.array([2 * r, 2 * r, h]), cyl,
                            [(np.zeros(2), np.array([r, r]))], albedo=tx.bottle_albedo(seed + 50, r, h)))
    return objs


def table_mesh() -> trimesh.Trimesh:
    x0, x1, y0, y1 = TABLE_EXTENT
    return _box((x1 - x0, y1 - y0, TABLE_THICKNESS), ((x0 + x1) / 2, (y0 + y1) / 2, -TABLE_THICKNESS / 2))


# -- layout --------------------------------------------------------------------------------------------
# Plain-Python geometry on 4-corner lists: the sampler makes ~10^4 tiny tests, where numpy's per-call
# overhead dominates.
Quad = list  # [(x, y)] * 4, counter-clockwise


def _rect_corners(center, half, yaw: float) -> Quad:
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = float(center[0]), float(center[1])
    hx, hy = float(half[0]), float(half[1])
    return [(cx + c * lx - s * ly, cy + s * lx + c * ly)
            for lx, ly in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]


def _sat_overlap(a: Quad, b: Quad, gap: float) -> bool:
    """Separating-axis test of two convex quads, inflated by `gap` total: True if they come closer."""
    ca = (sum(p[0] for p in a) / 4, sum(p[1] for p in a) / 4)
    cb = (sum(p[0] for p in b) / 4, sum(p[1] for p in b) / 4)
    ra = max(math.hypot(p[0] - ca[0], p[1] - ca[1]) for p in a)
    rb = max(math.hypot(p[0] - cb[0], p[1] - cb[1]) for p in b)
    if math.hypot(ca[0] - cb[0], ca[1] - cb[1]) > ra + rb + gap:  # bounding circles apart
        return False
    for poly in (a, b):
        for i in range(4):
            ex, ey = poly[(i + 1) % 4][0] - poly[i][0], poly[(i + 1) % 4][1] - poly[i][1]
            n = math.hypot(ex, ey)
            ax, ay = -ey / n, ex / n
            pa = [p[0] * ax + p[1] * ay for p in a]
            pb = [p[0] * ax + p[1] * ay for p in b]
            if max(pa) + gap <= min(pb) or max(pb) + gap <= min(pa):
                return False
    return True


def footprint_world(obj: SceneObject, xy, yaw: float) -> list[Quad]:
    """The object's footprint rectangles in the world (table) plane for a pose (xy, yaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for ctr, half in obj.footprint:
        w = (c * ctr[0] - s * ctr[1] + xy[0], s * ctr[0] + c * ctr[1] + xy[1])
        out.append(_rect_corners(w, half, yaw))
    return out


def _admissible(quads: list[Quad]) -> bool:
    x0, x1, y0, y1 = PLACE_REGION
    bx, by = float(ROBOT_BASE_XY[0]), float(ROBOT_BASE_XY[1])
    for q in quads:
        for x, y in q:
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                return False
            # the farthest point of a convex polygon is a corner; the nearest is >= 0.31 m by PLACE_REGION
            if not REACH[0] <= math.hypot(x - bx, y - by) <= REACH[1]:
                return False
    return True


def sample_layout(objects: list[SceneObject], seed: int, marker_size: float = 0.08) -> dict:
    """Place the target frame, the marker's reserved square and every object, without overlaps.

    Deterministic for a given seed. Sets each object's `T_world_obj` and returns
    {"target_frame": {"center": [x, y, 0], "size": s}, "marker_xy": [x, y], "marker_yaw": yaw}.
    The marker square is reserved even when no marker is printed, so toggling it keeps the layout.
    """
    rng = np.random.default_rng([seed, 1])
    x0, x1, y0, y1 = PLACE_REGION
    for _attempt in range(200):
        placed: list[np.ndarray] = []
        # target frame: axis-aligned square, tape included
        ts = TARGET_FRAME_SIZE
        ok = False
        for _ in range(500):
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            q = _rect_corners(c, np.array([ts / 2 + 0.01, ts / 2 + 0.01]), 0.0)
            if _admissible([q]):
                ok = True
                break
        if not ok:
            continue
        target_c = c
        placed.append(q)
        success = True
        for obj in objects:
            for _ in range(2000):
                xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
                yaw = rng.uniform(-math.pi, math.pi)
                quads = footprint_world(obj, xy, yaw)
                if not _admissible(quads):
                    continue
                if any(_sat_overlap(qa, qb, MIN_GAP) for qa in quads for qb in placed):
                    continue
                break
            else:
                success = False
                break
            placed.extend(quads)
            obj.T_world_obj = pose_xyz_yaw(xy[0], xy[1], obj.extent[2] / 2, yaw)
        if not success:
            continue
        # marker (reserved even when not printed): flat on the table near the objects, so the scan sees it
        ms = marker_size * 1.25 + 0.01  # quiet zone + margin
        for _ in range(2000):
            c = np.array([rng.uniform(-0.26, 0.30), rng.uniform(-0.34, 0.34)])
            yaw_m = rng.uniform(-0.5, 0.5)
            q = _rect_corners(c, np.array([ms / 2, ms / 2]), yaw_m)
            if not any(_sat_overlap(q, p, 0.01) for p in placed):
                marker_c = c
                break
        else:
            continue
        if success:
            return {"target_frame": {"center": _round([target_c[0], target_c[1], 0.0]), "size": ts,
                                     "tape_width": TAPE_WIDTH},
                    "marker_xy": marker_c, "marker_yaw": float(yaw_m)}
    raise RuntimeError(f"could not lay out the scene for seed {seed}")  # pragma: no cover
