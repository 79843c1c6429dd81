"""Parallel-jaw grasp synthesis on an object's collision mesh.

Candidates (object frame, metres):
* top-down: approach along -z_obj, closing axis along one of the two horizontal principal axes, grasp
  centres spaced along the other axis, the pads `depth` below the local top surface;
* side: approach horizontally along a principal axis, closing along the other, at mid-height.

Each candidate is checked by ray casting onto the mesh (trimesh/embree): the two jaw rays along the
closing axis must hit surfaces whose normals lie within the friction cone of the closing direction
(antipodal), the width between the contacts must fit the opened gripper with clearance, and extra rays
over the pad area must find the same surface (no grasping a corner or an edge in mid-air).

Frames: T_obj_tcp maps TCP-frame points to the object frame. TCP frame: z = approach direction (out of
the hand, towards the object), y = closing axis (finger motion), x = y × z — the Panda hand's convention.
Ranking and IK/collision feasibility are in `rank_grasps` / `feasible_grasps` (execute.py calls them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FRICTION_CONE = math.atan(0.6)     # rad: half-angle accepted between contact normal and closing axis
PAD_HALF = 0.008                   # m, half-size of a Panda fingertip pad (rays over the pad area)
MIN_TCP_ABOVE_BOTTOM = 0.0145      # m: pads (±8.5 mm) stay >= 6 mm above the support surface
CLEARANCE = 0.008                  # m, opened jaw minus object width, per side total


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


def synthesize(vertices: np.ndarray, faces: np.ndarray, max_width: float = 0.08, spacing: float = 0.01,
               depth: float = 0.02, side: bool = True) -> list[Grasp]:
    """Antipodal parallel-jaw grasp candidates on a mesh (object frame), unranked except by geometry score.

    vertices [N,3], faces [M,3]: the collision mesh in the object frame (z up when resting).
    max_width: gripper opening (m); depth: how far the pad centres go below the local top (m).
    """
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=True)
    inter = mesh.ray
    V = np.asarray(mesh.vertices)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre = (lo + hi) / 2
    com = mesh.center_mass if mesh.is_watertight else centre
    a1, a2 = principal_axes_xy(mesh.convex_hull.vertices)
    reach = float(np.linalg.norm(hi - lo)) + 0.05
    out: list[Grasp] = []
    z_dn = np.array([0.0, 0.0, -1.0])

    def try_grasp(p: np.ndarray, approach: np.ndarray, closing: np.ndarray, kind: str) -> None:
        c = closing / np.linalg.norm(closing)
        origins = np.stack([p + c * reach, p - c * reach])
        hit, pts, nrm = _cast(inter, origins, np.stack([-c, c]), mesh)
        if not hit.all():
            return
        # contacts are the outermost surfaces along the closing axis (jaws come from outside)
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

    # top-down grasps
    for closing, along in ((a2, a1), (a1, a2)):
        ext = np.ptp(V @ along)
        n = max(1, int(ext / spacing))
        for s in np.linspace(-ext / 2 + 0.012, ext / 2 - 0.012, n) if ext > 0.03 else [0.0]:
            q = centre + along * s
            # local top: ray down at this xy
            hit, top, _ = _cast(inter, np.array([[q[0], q[1], hi[2] + 0.05]]), z_dn[None], mesh)
            if not hit[0]:
                continue
            z = max(top[0, 2] - depth, lo[2] + MIN_TCP_ABOVE_BOTTOM, (top[0, 2] + lo[2]) / 2)
            z = min(z, top[0, 2] - 0.004)
            p = np.array([q[0], q[1], z])
            for sign in (1, -1):
                try_grasp(p, z_dn, sign * closing, "top")
    if side:
        zc = max((lo[2] + hi[2]) / 2, lo[2] + 0.04)   # hand body needs room above the support
        if zc < hi[2] - 0.005:
            for approach_axis, closing in ((a1, a2), (a2, a1)):
                for sa in (1, -1):
                    for sc in (1, -1):
                        try_grasp(np.array([centre[0], centre[1], zc]), sa * approach_axis, sc * closing, "side")
    return out


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
