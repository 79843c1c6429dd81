"""MoveIt 2 planning scene export.

- `export/moveit/scene.scene`: the text format of `PlanningScene::saveGeometryToStream` that RViz's
  "Import" reads: scene name; per object "* id", object pose (x y z / qx qy qz qw), shape count, per shape
  the geometric_shapes text (`box` + sizes, or `mesh` + "V F" + vertices + triangles), shape pose, colour
  "r g b a"; then the subframe count; "." ends the file.
- `export/moveit/collision_objects.yaml`: a YAML list of moveit_msgs/msg/CollisionObject (header,
  id, pose, meshes/mesh_poses or primitives/primitive_poses, operation ADD = 0), ready to publish.
Objects carry their collision mesh in the object frame with the object pose; the table is a box; an
unusable object with an obstacle estimate (`obstacle_only`) is its box. Ids are the objects' export IDs
(`splattwin.names.export_id`, as in every export). Frame: every pose is in the twin frame, named by
`frame_id` (default `twin`, `ExportOptions.moveit_frame`; not `world`, which stock Panda MoveIt configs
put at the robot base); the YAML says so in its header, and the `.scene` format (no comments, poses in
the planning frame) only through twin.json's export_files. Quaternions are x y z w in both.
`*_boxes.*` variants give each object as its gravity-aligned box proxy (for fast planners).
`parse_scene` reads the text format back (for tests and tools).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from splattwin import io
from splattwin.meshio import load_mesh
from splattwin.errors import InputError
from splattwin.names import export_id
from splattwin.transforms import (pose_from_pos_quat_wxyz, quat_wxyz_from_matrix, quat_wxyz_from_xyzw,
                                  quat_xyzw_from_wxyz)
from splattwin.twin.manifest import Manifest, unscaled_note

ADD = 0
BOX = 1  # shape_msgs/SolidPrimitive.BOX
TWIN_FRAME = "twin"  # default frame_id of the exported poses: the twin frame


@dataclass
class Shape:
    kind: str                      # "box" | "mesh"
    T_obj_shape: np.ndarray        # [4,4]
    size: np.ndarray | None = None  # box sides (m)
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    color: tuple = (0.0, 0.0, 0.0, 0.0)


@dataclass
class SceneObject:
    id: str
    T_world_obj: np.ndarray
    shapes: list = field(default_factory=list)


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    """File boundary: MoveIt scene files and messages order quaternions xyzw."""
    return quat_xyzw_from_wxyz(quat_wxyz_from_matrix(R, canonical=False))


def _pose_T(xyz, q_xyzw) -> np.ndarray:
    return pose_from_pos_quat_wxyz(np.asarray(xyz, dtype=float), quat_wxyz_from_xyzw(q_xyzw))


def scene_objects(twin_dir: Path, manifest: Manifest, boxes: bool = False) -> list[SceneObject]:
    """The collision world of the twin: table (box) + background obstacles + usable objects + the obstacle
    boxes of unusable ones (`obstacle_only`). Ids: export IDs.

    boxes=True: each object is its gravity-aligned box proxy (T_world_obj, bbox_extent) instead of its
    collision mesh — what fast planners want."""
    bg = manifest.background
    x0, x1, y0, y1 = bg.table_extent
    T_table = np.eye(4)
    T_table[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, bg.table_height - bg.table_thickness / 2]
    objs = [SceneObject("table", T_table, [Shape("box", np.eye(4), size=np.array([x1 - x0, y1 - y0, bg.table_thickness]),
                                                   color=(0.6, 0.5, 0.4, 1.0))])]
    obstacles = bg.convex_parts[1:]
    if obstacles:
        shapes = []
        for p in obstacles:
            m = load_mesh(twin_dir / p, "background obstacle mesh", process=True)
            shapes.append(Shape("mesh", np.eye(4), vertices=np.asarray(m.vertices), faces=np.asarray(m.faces),
                                color=(0.5, 0.5, 0.5, 1.0)))
        objs.append(SceneObject("background_obstacles", np.eye(4), shapes))
    for o in manifest.objects:
        if o.obstacle_only:  # an unusable object still stands there: its padded box
            objs.append(SceneObject(export_id(o.name), o.pose, [Shape("box", np.eye(4), size=np.asarray(
                o.bbox_extent, dtype=float), color=(0.9, 0.3, 0.3, 0.5))]))
            continue
        if not o.usable or not o.collision_mesh:
            continue
        color = (0.8, 0.8, 0.8, 1.0)
        if o.visual_mesh and (twin_dir / o.visual_mesh).is_file():
            vis = load_mesh(twin_dir / o.visual_mesh, f"visual mesh of {o.name!r}", process=True)
            vc = getattr(vis.visual, "vertex_colors", None)
            if vc is not None and len(vc):
                color = tuple(float(c) for c in np.asarray(vc, float).mean(axis=0) / 255.0)
        if boxes:
            shape = Shape("box", np.eye(4), size=np.asarray(o.bbox_extent, dtype=float), color=color)
        else:
            m = load_mesh(twin_dir / o.collision_mesh, f"collision mesh of {o.name!r}", process=True)
            shape = Shape("mesh", np.eye(4), vertices=np.asarray(m.vertices), faces=np.asarray(m.faces), color=color)
        objs.append(SceneObject(export_id(o.name), o.pose, [shape]))  # ids are whitespace-free tokens
    return objs


def _pose_text(T: np.ndarray) -> str:
    q = _quat_xyzw(T[:3, :3])
    return f"{T[0,3]:.9g} {T[1,3]:.9g} {T[2,3]:.9g}\n{q[0]:.9g} {q[1]:.9g} {q[2]:.9g} {q[3]:.9g}\n"


def scene_text(objs: list[SceneObject], name: str = "splattwin") -> str:
    out = [f"{name}\n"]
    for o in objs:
        out.append(f"* {o.id}\n")
        out.append(_pose_text(o.T_world_obj))
        out.append(f"{len(o.shapes)}\n")
        for s in o.shapes:
            if s.kind == "box":
                out.append(f"box\n{s.size[0]:.9g} {s.size[1]:.9g} {s.size[2]:.9g}\n")
            else:
                out.append(f"mesh\n{len(s.vertices)} {len(s.faces)}\n")
                out.append("".join(f"{v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n" for v in s.vertices))
                out.append("".join(f"{f[0]} {f[1]} {f[2]}\n" for f in s.faces))
            out.append(_pose_text(s.T_obj_shape))
            out.append(" ".join(f"{c:.6g}" for c in s.color) + "\n")
        out.append("0\n")  # no subframes
    out.append(".\n")
    return "".join(out)


def parse_scene(text: str, where: str | Path = "scene.scene") -> tuple[str, list[SceneObject]]:
    """Read the MoveIt `.scene` text format (new format: with object poses and subframes)."""
    lines = text.splitlines()
    if not lines:
        raise InputError("empty .scene file", where)
    name = lines[0].strip()
    toks = " ".join(lines[1:]).split()
    pos = 0

    def take(n=1):
        nonlocal pos
        if pos + n > len(toks):
            raise InputError("truncated .scene file", where)
        v = toks[pos:pos + n]
        pos += n
        return v

    def pose():
        xyz = [float(v) for v in take(3)]
        q = [float(v) for v in take(4)]
        return _pose_T(xyz, q)

    objs = []
    while True:
        (marker,) = take()
        if marker == ".":
            return name, objs
        if marker != "*":
            raise InputError(f"unknown marker {marker!r} in .scene file", where)
        (oid,) = take()
        o = SceneObject(oid, pose())
        for _ in range(int(take()[0])):
            (kind,) = take()
            if kind == "box":
                s = Shape("box", np.eye(4), size=np.array([float(v) for v in take(3)]))
            elif kind == "mesh":
                nv, nf = (int(v) for v in take(2))
                V = np.array([float(v) for v in take(3 * nv)]).reshape(nv, 3)
                F = np.array([int(v) for v in take(3 * nf)]).reshape(nf, 3)
                s = Shape("mesh", np.eye(4), vertices=V, faces=F)
            else:
                raise InputError(f"unsupported shape {kind!r} in .scene file", where)
            s.T_obj_shape = pose()
            s.color = tuple(float(v) for v in take(4))
            o.shapes.append(s)
        for _ in range(int(take()[0])):
            take()
            pose()
        objs.append(o)


def _pose_msg(T: np.ndarray) -> dict:
    q = _quat_xyzw(T[:3, :3])
    return {"position": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
            "orientation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}}


def collision_object_msgs(objs: list[SceneObject], frame_id: str = TWIN_FRAME) -> list[dict]:
    """moveit_msgs/msg/CollisionObject as plain dicts (ROS 2 field names)."""
    msgs = []
    for o in objs:
        m = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": frame_id}, "id": o.id,
             "pose": _pose_msg(o.T_world_obj), "type": {"key": "", "db": ""},
             "primitives": [], "primitive_poses": [], "meshes": [], "mesh_poses": [], "planes": [],
             "plane_poses": [], "subframe_names": [], "subframe_poses": [], "operation": ADD}
        for s in o.shapes:
            if s.kind == "box":
                m["primitives"].append({"type": BOX, "dimensions": [float(v) for v in s.size]})
                m["primitive_poses"].append(_pose_msg(s.T_obj_shape))
            else:
                m["meshes"].append({"triangles": [{"vertex_indices": [int(i) for i in f]} for f in s.faces],
                                    "vertices": [{"x": float(v[0]), "y": float(v[1]), "z": float(v[2])} for v in s.vertices]})
                m["mesh_poses"].append(_pose_msg(s.T_obj_shape))
        msgs.append(m)
    return msgs


def pose_from_msg(p: dict) -> np.ndarray:
    """[4,4] from a geometry_msgs/Pose dict."""
    o = p["orientation"]
    return _pose_T([p["position"][k] for k in "xyz"], [o["x"], o["y"], o["z"], o["w"]])


def export_moveit(twin_dir: str | Path, manifest: Manifest, frame_id: str | None = None, options=None) -> Path:
    """Write export/moveit/{scene.scene, collision_objects.yaml} (collision meshes) and
    {scene_boxes.scene, collision_objects_boxes.yaml} (box proxies), atomically. Returns scene.scene.
    frame_id: the poses' frame (default: options.moveit_frame, `twin`)."""
    import yaml

    from splattwin.twin.options import ExportOptions

    frame_id = frame_id or (options or ExportOptions()).moveit_frame
    twin_dir = Path(twin_dir)
    out = twin_dir / "export" / "moveit"
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # libyaml: ~10x faster on mesh-sized lists
    note = unscaled_note(manifest.frame)
    # the .scene text format has no comments: an unscaled twin says so in the scene's name
    unscaled = "" if note is None else "_unscaled"
    for boxes, suffix in ((True, "_boxes"), (False, "")):
        objs = scene_objects(twin_dir, manifest, boxes=boxes)
        io.write_text(out / f"collision_objects{suffix}.yaml",
                      ("" if note is None else f"# {note}\n")
                      + f"# frame_id {frame_id}: the twin frame (z up; table top at z = table_height in twin.json), not "
                      f"the robot base: publish a transform to it. Quaternions x y z w; lengths in "
                      f"{'metres' if note is None else 'UNSCALED units'}\n"
                      + yaml.dump(collision_object_msgs(objs, frame_id), Dumper=dumper, default_flow_style=None,
                                  sort_keys=False, width=1 << 20))
        path = io.write_text(out / f"scene{suffix}.scene", scene_text(objs, "splattwin" + suffix + unscaled))
    return path
