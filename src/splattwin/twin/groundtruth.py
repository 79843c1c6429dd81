"""A twin built directly from the embedded scene's ground-truth meshes (no reconstruction).

`twin_from_scene(scene_dir, out_dir)` reads scene.json + meshes/<object>.ply (world frame) and writes a
regular twin folder (twin.json, objects/<name>/{visual,collision}.obj, parts/part_*.obj in the object
frame), so the robot stage can be tested and benchmarked "on the ground-truth meshes" and compared with
a reconstructed twin of the same scene.

Convex parts: objects flagged `convex` in scene.json get their convex hull; others are decomposed with
CoACD (MuJoCo collides each mesh geom as its hull, so a hammer needs several parts).
Frame: the scene's world frame = table frame (z up, table top at z = 0), metric (`ground_truth`).
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.meshio import load_mesh
from splattwin.names import object_name
from splattwin.paths import child, confined
from splattwin.poses.twin_frame import TwinFrame
from splattwin.twin.manifest import Background, Manifest, ObjectEntry

log = logging.getLogger(__name__)

DENSITY = {"cardboard_box": 150.0}   # kg/m^3 by object kind/name; hollow packaging is light
DEFAULT_DENSITY = 400.0
COACD_THRESHOLD = 0.05
MAX_PARTS = 12


def _load_scene(scene_dir: Path) -> dict:
    path = scene_dir / "scene.json"
    scene = io.read_json(path, missing="no scene.json here: not an embedded scene folder")
    if not isinstance(scene, dict):
        raise InputError(f"scene.json must hold a JSON object, got {type(scene).__name__}", path)
    if not isinstance(scene.get("objects"), list) or not scene["objects"]:
        raise InputError("scene.json lists no objects", path)
    for i, o in enumerate(scene["objects"]):   # a prompt is text: it names the object in reports and segmentation
        if isinstance(o, dict) and "prompt" in o and not (isinstance(o["prompt"], str) and len(o["prompt"]) <= 200):
            raise InputError(f"object {i + 1}'s prompt must be text of at most 200 characters, got "
                             f"{type(o['prompt']).__name__}", path)
    return scene


def load_scene_gt(scene_dir: str | Path) -> tuple[list, dict]:
    """(objects [(name, label, prompt)], GT world meshes {name: Trimesh}) of an embedded scene folder."""
    scene_dir = Path(scene_dir)
    where = scene_dir / "scene.json"
    sc = _load_scene(scene_dir)
    try:
        objects = [(object_name(o["name"], where), int(o["label"]), o.get("prompt", "")) for o in sc["objects"]]
        meshes = {name: load_mesh(confined(scene_dir, o["mesh"], where), process=True)
                  for (name, _, _), o in zip(objects, sc["objects"])}
    except (KeyError, TypeError, ValueError, AttributeError) as e:   # an entry without name/label/mesh, or not an object
        raise InputError(f"malformed scene.json objects ({type(e).__name__}: {e})", where) from None
    return objects, meshes


def _write_obj(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    import trimesh

    with io.atomic_path(path) as tmp:
        trimesh.Trimesh(V, F, process=False).export(tmp, file_type="obj")


def convex_parts(V: np.ndarray, F: np.ndarray, convex: bool, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex decomposition: [(V_k [n,3], F_k [m,3])]. Hull for convex shapes, CoACD otherwise."""
    import trimesh

    if convex:
        h = trimesh.Trimesh(V, F, process=True).convex_hull
        return [(np.asarray(h.vertices), np.asarray(h.faces))]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int64)),
                            threshold=COACD_THRESHOLD, max_convex_hull=MAX_PARTS, seed=seed)
    out = []
    for pv, pf in parts:
        h = trimesh.Trimesh(pv, pf, process=True).convex_hull
        if h.volume > 1e-9:
            out.append((np.asarray(h.vertices), np.asarray(h.faces)))
    return out


def twin_from_scene(scene_dir: str | Path, out_dir: str | Path) -> Manifest:
    """Build the ground-truth twin of an embedded scene into `out_dir`; returns its saved manifest.

    Re-running is cheap: an object whose mesh hash matches the existing twin's record is not decomposed again.
    """
    import trimesh

    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    scene = _load_scene(scene_dir)
    old, old_digest = {}, {}
    if (out_dir / "twin.json").is_file():
        try:
            prev_manifest = Manifest.load(out_dir)
            old = {o.name: o for o in prev_manifest.objects}
            old_digest = prev_manifest.config.get("gt_mesh_digest", {})
        except InputError:
            pass
    objects, digests = [], {}
    for o in scene["objects"]:
        name = o["name"]
        if name == "table":
            continue
        name = object_name(name, scene_dir / "scene.json")
        mesh_path = confined(scene_dir, o.get("mesh", f"meshes/{name}.ply"), scene_dir / "scene.json",
                             f"mesh of object {name!r}")
        if not mesh_path.is_file():
            raise InputError(f"mesh of object {name!r} missing", mesh_path)
        digest = hashlib.sha256(mesh_path.read_bytes()).hexdigest()[:16]
        try:
            T_world_obj = np.asarray(o["T_world_obj"], dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise InputError(f"object {name!r}: T_world_obj must be a 4x4 matrix", scene_dir / "scene.json") from None
        odir = child(child(out_dir, "objects"), name)
        prev = old.get(name)
        rel = lambda p: p.relative_to(out_dir).as_posix()  # noqa: E731
        digests[name] = digest
        if prev is not None and old_digest.get(name) == digest and prev.convex_parts \
                and all((out_dir / p).is_file() for p in prev.convex_parts):
            entry = prev
            entry.T_world_obj = T_world_obj.tolist()
        else:
            m = load_mesh(mesh_path, f"mesh of object {name!r}")
            V_world = np.asarray(m.vertices, np.float64)
            V = (V_world - T_world_obj[:3, 3]) @ T_world_obj[:3, :3]   # world -> object frame
            F = np.asarray(m.faces, np.int64)
            _write_obj(odir / "visual.obj", V, F)
            _write_obj(odir / "collision.obj", V, F)
            parts = convex_parts(V, F, bool(o.get("convex", False)))
            part_paths = []
            for k, (pv, pf) in enumerate(parts):
                p = odir / "parts" / f"part_{k:03d}.obj"
                _write_obj(p, pv, pf)
                part_paths.append(rel(p))
            tm = trimesh.Trimesh(V, F, process=True)
            volume = float(abs(tm.volume)) if tm.is_watertight else float(tm.convex_hull.volume)
            density = DENSITY.get(o.get("kind", ""), DENSITY.get(name, DEFAULT_DENSITY))
            entry = ObjectEntry(
                name=name, label=int(o.get("label", len(objects) + 1)), prompt=o.get("prompt", name.replace("_", " ")),
                T_world_obj=T_world_obj.tolist(), bbox_extent=[float(x) for x in o.get("extent", np.ptp(V, axis=0))],
                mass=density * volume, volume=volume, visual_mesh=rel(odir / "visual.obj"),
                collision_mesh=rel(odir / "collision.obj"), convex_parts=part_paths, usable=bool(part_paths),
                problem=None if part_paths else "convex decomposition produced no parts",
            )
        objects.append(entry)
    t = scene.get("table", {})
    ext = t.get("extent", [-0.5, 0.5, -0.4, 0.4])
    manifest = Manifest(
        frame=TwinFrame(source="ground_truth", scaled=True, scale_uncertainty_rel=0.0,
                        description=f"embedded scene {scene_dir} world frame (table top z = 0)"),
        objects=objects,
        background=Background(table_height=0.0, table_extent=[float(x) for x in ext],
                              table_thickness=float(t.get("thickness", 0.03))),
        config={"source": "ground_truth", "scene": str(scene_dir.resolve()),
                "target_frame": scene.get("target_frame"), "seed": scene.get("seed"),
                "gt_mesh_digest": digests},   # cache key: unchanged meshes are not decomposed again
    )
    manifest.save(out_dir)
    return manifest
