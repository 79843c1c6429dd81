"""Grasp and place-pose selection from the robot's belief of the object poses (geometry only: no IK,
no collision checks — `candidates.py` makes the selections feasible).

Grasp heights follow the support surface under the object (table or the object below it, from the
belief), not the object mesh's bottom: reconstructed objects sink a few mm into the table, and the
fingertips (which reach 8.9 mm beyond the Panda's TCP, measured from the model) must keep the planning
margin above the surface in the closed pose. The object below is found on the objects' collision meshes
(`footprint`: the union of their convex parts; an object without one, its bounding box): an object in the
free notch of an L-shaped one, or beside a hammer's handle, stands on the table.

Place targets: upright at the goal — centred on the support's top face (4 yaws aligned with the support),
released just above the highest point of the support's mesh under the object's footprint (`release_height`:
what it touches first, in the simulation too, whose collision geometry is the same convex parts), or in the
goal region (8 yaws, only those whose footprint fits), the one closest to the object's current yaw first.
Frames: T_world_obj [4,4] in the twin frame, metres, radians.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.robot import footprint as fp
from splattwin.robot import grasp as grasp_mod
from splattwin.robot.task import Step
from splattwin.transforms import pose_xyz_yaw, yaw_of
from splattwin.twin.manifest import Manifest

PLACE_CLEARANCE = 0.004  # m released above the support
REGION_MARGIN = 0.02     # m: a place yaw's footprint must fit the region with this much to spare
Belief = dict[str, np.ndarray]   # object name -> T_world_obj [4,4] the robot plans with
ShapeOf = Callable[[str], fp.Shape]   # object name -> its Shape (`footprint.Shapes`)


def _boxes(manifest: Manifest) -> ShapeOf:
    """Each object's bounding box as its Shape (no collision meshes at hand)."""
    return lambda name: fp.box_shape(manifest.object(name).bbox_extent)


def support_height(obj: str, belief: Belief, manifest: Manifest, shape: ShapeOf | None = None) -> float:
    """World z (m) of the surface under `obj` in the belief: the table top, or the top of another object
    whose footprint holds obj's centre and whose top there is below obj's centre. shape: each object's
    `footprint.Shape` (its collision mesh: an object in the free notch of an L-shaped one stands on the
    table, one on the low step of a stepped one on that step); None: their bounding boxes."""
    shape = shape or _boxes(manifest)
    T = belief[obj]
    z = float(manifest.background.table_height)
    for o, T_o in belief.items():
        if o == obj:
            continue
        top = fp.top_at(shape(o), T_o, T[:2, 3])
        if top is not None and top < T[2, 3]:
            z = max(z, top)
    return z


def release_height(support: str, obj: str, T_place: np.ndarray, belief: Belief, manifest: Manifest,
                   shape: ShapeOf | None = None) -> float:
    """World z (m) of the support's top under `obj` placed at T_place [4,4] (its x, y and yaw): the highest
    point of the support's mesh under obj's footprint there (`footprint.Posed.top_under`), what obj lowered
    onto it touches first; the support's bounding-box top over its centre where no mesh lies under it. The
    same for a box-shaped support; for a sloped, stepped or dented one, lower than its bounding-box top (the
    object was released from that much higher), for a mesh reaching above its box, higher."""
    shape = shape or _boxes(manifest)
    T_sup = belief[support]
    top = fp.Posed(shape(support), T_sup).top_under(fp.polygons(shape(obj), T_place))
    if top is None:
        ext = np.asarray(manifest.object(support).bbox_extent, float)
        top = float(T_sup[2, 3] + T_sup[2, 2] * ext[2] / 2)
    return top


def place_targets(step: Step, obj: str, belief: Belief, manifest: Manifest,
                  shape: ShapeOf | None = None) -> list[np.ndarray]:
    """Candidate T_world_obj [4,4] at the step's goal (upright, yaw variants), best first. On a support: at
    its centre (its bounding box's top face), PLACE_CLEARANCE above its mesh under obj's footprint at each yaw
    (`release_height`); shape: each object's `footprint.Shape` (None: their bounding boxes)."""
    T_now = belief[obj]
    ext = np.asarray(manifest.object(obj).bbox_extent, float)
    yaw_now = yaw_of(T_now)

    def wrap(a: float) -> float:
        return (a + math.pi) % (2 * math.pi) - math.pi

    if step.place_on is not None:
        T_sup = belief[step.place_on]
        sup_ext = np.asarray(manifest.object(step.place_on).bbox_extent, float)
        xyz = T_sup[:3, 3] + T_sup[:3, 2] * sup_ext[2] / 2
        yaw_sup = yaw_of(T_sup)
        yaws = sorted((yaw_sup + k * math.pi / 2 for k in range(4)), key=lambda y: abs(wrap(y - yaw_now)))
        out = []
        for y in yaws:
            T = pose_xyz_yaw(xyz[0], xyz[1], 0.0, y)
            T[2, 3] = release_height(step.place_on, obj, T, belief, manifest, shape) + ext[2] / 2 + PLACE_CLEARANCE
            out.append(T)
        return out
    reg = step.place_in
    xyz = reg.center.copy()
    z = manifest.background.table_height + ext[2] / 2 + PLACE_CLEARANCE
    yaws = [k * math.pi / 4 for k in range(8)]
    fits = []
    for y in yaws:
        c, s = abs(math.cos(y)), abs(math.sin(y))
        fx, fy = c * ext[0] + s * ext[1], s * ext[0] + c * ext[1]
        if fx <= reg.size[0] - REGION_MARGIN and fy <= reg.size[1] - REGION_MARGIN:
            fits.append(y)
    yaws = fits or yaws
    yaws.sort(key=lambda y: abs(wrap(y - yaw_now)))
    return [pose_xyz_yaw(xyz[0], xyz[1], z, y) for y in yaws]


class GraspSelector:
    """Ranked grasp candidates on an object's collision mesh for the surface it rests on in the belief.

    max_opening: gripper opening (m); tip_depth: how far the opened fingers reach beyond the TCP along
    the approach (m); floor_clearance: fingertips kept this far above the support (m). Candidates are
    synthesised once per (object, support height) and ranked for the current belief pose and base.
    """

    def __init__(self, manifest: Manifest, twin_dir: str | Path, T_world_base: np.ndarray, max_opening: float,
                 tip_depth: float, floor_clearance: float):
        self.manifest, self.twin_dir = manifest, Path(twin_dir)
        self.T_world_base = np.asarray(T_world_base, float)
        self.max_opening, self.tip_depth, self.floor_clearance = max_opening, tip_depth, floor_clearance
        self._cache: dict[tuple[str, float], list[grasp_mod.Grasp]] = {}
        self.shapes = fp.Shapes(manifest, self.twin_dir)   # footprints for the support under an object

    def synthesize(self, obj: str, belief: Belief) -> list[grasp_mod.Grasp]:
        """Unranked candidates (object frame) for the support under `obj` in the belief."""
        from splattwin.meshio import load_mesh

        T_obj = belief[obj]
        floor = support_height(obj, belief, self.manifest, self.shapes)
        floor_obj = round(floor - float(T_obj[2, 3]), 4)  # object frame (upright)
        key = (obj, floor_obj)
        if key not in self._cache:
            entry = self.manifest.object(obj)
            if not entry.collision_mesh:
                raise InputError(f"object {obj!r} has no collision mesh to grasp", self.twin_dir / "twin.json")
            # the checked loader: a bad PLY header or an empty OBJ in a received twin is an InputError naming it
            path = self.twin_dir / entry.collision_mesh
            mesh = load_mesh(path, f"collision mesh of object {obj!r}", process=True)
            v = np.asarray(mesh.vertices)
            if np.linalg.matrix_rank(v - v.mean(axis=0), tol=1e-9) < 3:  # qhull fails on it in synthesis
                raise InputError(f"collision mesh of object {obj!r} is flat (its vertices lie on a plane): "
                                 f"not a solid to grasp", path)
            self._cache[key] = grasp_mod.synthesize(
                mesh.vertices, mesh.faces, max_width=self.max_opening, floor=floor_obj,
                tip_depth=self.tip_depth, floor_clearance=self.floor_clearance)
        return self._cache[key]

    def ranked(self, obj: str, belief: Belief) -> list[grasp_mod.Grasp]:
        """Candidates best first for the object at its belief pose (`grasp.rank_grasps`)."""
        return grasp_mod.rank_grasps(self.synthesize(obj, belief), belief[obj], self.T_world_base)
