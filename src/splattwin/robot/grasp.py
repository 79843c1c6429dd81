"""Parallel-jaw grasp synthesis on an object's collision mesh.

Candidates (object frame, metres):
* top-down: approach along -z_obj, closing axis along one of the two horizontal principal axes. Grasp
  stations are spaced along the other axis; at each station a row of downward rays across the closing
  axis finds the runs of material (a handle off the box's centre line, a hammer head) and the jaws are
  centred on each run that fits the gripper. The pads go `depth` below the run's top, but never so low
  that the fingertips (which reach `tip_depth` beyond the TCP) come closer than `floor_clearance` to the
  support surface `floor` (the planner's margin must hold against the table in the closed pose);
* side: approach horizontally along a principal axis, closing along the other, at mid-height.

Each candidate is checked by ray casting onto the mesh (trimesh): the two jaw rays start where the opened
pads are (±max_width/2 along the closing axis) and must hit surfaces facing them whose normals lie within
the friction cone of the closing direction (antipodal; a pad that would land on material finds a back
face and is rejected), the width between the contacts must fit the opened gripper with clearance, and
extra rays over the pad area must find the same surface (no grasping a corner or an edge in mid-air).

Frames: T_obj_tcp maps TCP-frame points to the object frame. TCP frame: z = approach direction (out of
the hand, towards the object), y = closing axis (finger motion), x = y × z — the Panda hand's convention.
Ranking is `rank_grasps`; selection for a support surface is in selection.py, IK/collision feasibility in
candidates.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FRICTION_CONE = math.atan(0.6)     # rad: half-angle accepted between contact normal and closing axis
PAD_HALF = 0.008                   # m, half-size of a Panda fingertip pad (rays over the pad area)
TIP_DEPTH = 0.009                  # m: Panda finger geometry beyond the TCP along the approach (8.9 mm)
FLOOR_CLEARANCE = 0.0065           # m: fingertips above the support: 5 mm planning margin + 1.5 mm
MIN_GRIP_DEPTH = 0.004             # m: the TCP (pad centre) at least this far below the local top
SCAN_STEP = 0.003                  # m between the downward rays that find material runs at a station
CLEARANCE = 0.008                  # m, opened jaw minus object width, per side total
MAX_OPENING = 0.08                 # m: the Panda hand's full finger gap, when no robot model says otherwise


@dataclass
class Grasp:
    """One parallel-jaw grasp. T_obj_tcp [4,4]; width m between contacts; kind 'top' | 'side'."""

    T_obj_tcp: np.ndarray
    width: float
    kind: str
    score: float
    contacts: np.ndarray            # [2,3] object frame

    def T_world_tcp(self, T_world_obj: np.ndarray) -> np.ndarray:
        return np.asarray(T_world_obj) @ self.T_obj_tcp


def _frame(approach: np.ndarray, closing: np.ndarray, p: np.ndarray) -> np.ndarray:
    z = approach / np.linalg.norm(approach)
    y = closing - z * (closing @ z)
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, 0] = np.cross(y, z)
    T[:3, 1] = y
    T[:3, 2] = z
    T[:3, 3] = p
    return T


def principal_axes_xy(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal axes (long, short) [3] of the minimum-area footprint rectangle of vertices V [N,3].

    The minimum-area rectangle (not PCA) so that a square footprint still yields face-aligned axes.
    """
    import trimesh

    T, ext = trimesh.bounds.oriented_bounds_2D(np.asarray(V)[:, :2])
    R = np.asarray(T)[:2, :2].T          # columns: rectangle axes in the object frame
    i = int(np.argmax(ext))
    a1 = np.array([*R[:, i], 0.0])
    a2 = np.array([*R[:, 1 - i], 0.0])
    return a1 / np.linalg.norm(a1), a2 / np.linalg.norm(a2)


def _cast(intersector, origins: np.ndarray, dirs: np.ndarray, mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits of rays: (hit [R] bool, points [R,3], normals [R,3])."""
    locs, ray_idx, tri_idx = intersector.intersects_location(origins, dirs, multiple_hits=False)
    hit = np.zeros(len(origins), bool)
    pts = np.zeros((len(origins), 3))
    nrm = np.zeros((len(origins), 3))
    hit[ray_idx] = True
    pts[ray_idx] = locs
    nrm[ray_idx] = mesh.face_normals[tri_idx]
    return hit, pts, nrm


def synthesize(vertices: np.ndarray, faces: np.ndarray, max_width: float = MAX_OPENING, spacing: float = 0.01,
               depth: float = 0.02, side: bool = True, floor: float | None = None, tip_depth: float = TIP_DEPTH,
               floor_clearance: float = FLOOR_CLEARANCE, com: np.ndarray | None = None) -> list[Grasp]:
    """Antipodal parallel-jaw grasp candidates on a mesh (object frame), unranked except by geometry score.

    vertices [N,3], faces [M,3]: the collision mesh in the object frame (z up when resting).
    max_width: gripper opening (m); depth: how far the pad centres go below the local top (m).
    floor: z (object frame, m) of the surface the object rests on; default the mesh's bottom.
    tip_depth: how far the finger geometry reaches beyond the TCP along the approach (m).
    floor_clearance: fingertips of top grasps stay this far above `floor` (m).
    com: centre of mass [3] for scoring (default: the mesh's, or its bounding-box centre if not watertight).
    """
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=True)
    inter = mesh.ray
    V = np.asarray(mesh.vertices)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = (lo + hi) / 2
    if com is None:
        com = mesh.center_mass if mesh.is_watertight else centre
    com = np.asarray(com, float)
    floor = float(lo[2]) if floor is None else max(float(floor), float(lo[2]))
    a1, a2 = principal_axes_xy(mesh.convex_hull.vertices)
    out: list[Grasp] = []
    z_dn = np.array([0.0, 0.0, -1.0])

    def try_grasp(p: np.ndarray, approach: np.ndarray, closing: np.ndarray, kind: str) -> None:
        c = closing / np.linalg.norm(closing)
        # the jaw rays start at the opened pads: material between them is grasped, material under a pad
        # makes the ray start inside and hit a back face (rejected by the friction-cone test below)
        origins = np.stack([p + c * max_width / 2, p - c * max_width / 2])
        hit, pts, nrm = _cast(inter, origins, np.stack([-c, c]), mesh)
        if not hit.all():
            return
        width = float((pts[0] - pts[1]) @ c)
        if not (0.004 < width <= max_width - CLEARANCE):
            return
        if nrm[0] @ c < math.cos(FRICTION_CONE) or -(nrm[1] @ c) < math.cos(FRICTION_CONE):
            return
        # pad-area check: rays offset over the pad must hit the surface at about the same width
        a = approach / np.linalg.norm(approach)
        b = np.cross(c, a)
        offs = [s * PAD_HALF * u for u in (a, b) for s in (-1, 1)]
        o2 = np.concatenate([origins + o for o in offs])
        d2 = np.concatenate([np.stack([-c, c])] * len(offs))
        h2, p2, n2 = _cast(inter, o2, d2, mesh)
        if h2.mean() < 0.75:
            return
        w2 = [((p2[2 * k] - p2[2 * k + 1]) @ c) for k in range(len(offs)) if h2[2 * k] and h2[2 * k + 1]]
        if not w2 or max(abs(np.array(w2) - width)) > 0.01:
            return
        mid = (pts[0] + pts[1]) / 2
        T = _frame(approach, c, mid)
        off_com = float(np.linalg.norm((mid - com) - a * ((mid - com) @ a)))
        score = (1.0 if kind == "top" else 0.6) - 2.0 * off_com - 0.5 * width / max_width
        out.append(Grasp(T, width, kind, score, pts.copy()))

    # top-down grasps: stations along one axis, jaws centred on each material run across the other
    z_min = floor + tip_depth + floor_clearance
    for closing, along in ((a2, a1), (a1, a2)):
        u, v = V @ along, V @ closing
        ext = float(np.ptp(u))
        inset = PAD_HALF + 0.004
        n = max(1, int(ext / spacing))
        stations = np.linspace(u.min() + inset, u.max() - inset, n) if ext > 0.03 else [float(u.mean())]
        ts = np.arange(v.min() + SCAN_STEP / 2, v.max(), SCAN_STEP)
        for s in stations:
            xy = along[None, :2] * s + closing[None, :2] * ts[:, None]
            origins = np.column_stack([xy, np.full(len(ts), hi[2] + 0.05)])
            hit, top, _ = _cast(inter, origins, np.broadcast_to(z_dn, origins.shape), mesh)
            for r0, r1 in _runs(hit):
                if (r1 - r0 - 1) * SCAN_STEP > max_width - CLEARANCE:
                    continue            # wider than the opened gripper at this station
                t_mid = (ts[r0] + ts[r1 - 1]) / 2
                z_top = float(top[r0:r1, 2].max())
                z = max(z_top - depth, (z_top + floor) / 2, z_min)
                if z > z_top - MIN_GRIP_DEPTH:
                    continue            # too flat to grip above the support with the fingertips clear
                q = along * s + closing * t_mid
                p = np.array([q[0], q[1], z])
                for sign in (1, -1):
                    try_grasp(p, z_dn, sign * closing, "top")
    if side:
        zc = max((lo[2] + hi[2]) / 2, floor + 0.04)   # hand body needs room above the support
        if zc < hi[2] - 0.005:
            for approach_axis, closing in ((a1, a2), (a2, a1)):
                for sa in (1, -1):
                    for sc in (1, -1):
                        try_grasp(np.array([centre[0], centre[1], zc]), sa * approach_axis, sc * closing, "side")
    return out


def too_wide(name: str, width: float | None, opening: float) -> str | None:
    """Why no grasp can hold object `name` whose narrowest width (m; `footprint.narrowest_width`, None: not
    known) leaves no room in the gripper opened to `opening` (m): the synthesis wants the width at most the
    opening less CLEARANCE. None when it fits."""
    if width is None or width <= opening - CLEARANCE:
        return None
    room = "" if width > opening else f"; a grasp needs {CLEARANCE * 100:.1f} cm of it as clearance"
    return (f"object {name!r} is too wide for the gripper: its narrowest width is {width * 100:.1f} cm "
            f"(the gripper opens {opening * 100:.1f} cm{room})")


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges [i, j) of consecutive True entries of a 1-D bool array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def rank_grasps(grasps: list[Grasp], T_world_obj: np.ndarray, T_world_base: np.ndarray) -> list[Grasp]:
    """Order candidates for a robot: top grasps whose approach points down in the world, near the
    centre of mass, with the hand's x axis pointing away from the robot base (the Panda's natural wrist)."""
    T_world_obj = np.asarray(T_world_obj)
    base_xy = np.asarray(T_world_base)[:2, 3]
    scored = []
    for g in grasps:
        T = T_world_obj @ g.T_obj_tcp
        approach = T[:3, 2]
        if g.kind == "top" and approach[2] > -math.cos(math.radians(30)):
            continue  # object tipped over: its "top" is not up any more
        if g.kind == "side" and abs(approach[2]) > math.sin(math.radians(30)):
            continue
        radial = T[:2, 3] - base_xy
        radial /= max(np.linalg.norm(radial), 1e-9)
        # the Panda's home pose has the closing axis (TCP y) along the radial direction: wrist mid-range
        natural = float(T[:2, 1] @ radial) if g.kind == "top" else float(T[:2, 2] @ radial)
        scored.append((g.score + 0.3 * natural, g))
    scored.sort(key=lambda t: -t[0])
    return [g for _, g in scored]
