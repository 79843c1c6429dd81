"""MJCF export of a twin: the static table/background and one free body per usable object.

`build_spec(manifest, twin_dir)` returns an editable `mujoco.MjSpec` (used by the robot world, which adds
the arm); `add_twin(spec, manifest, twin_dir)` adds the twin into an existing spec (e.g. a robot's);
`export_mjcf(twin_dir, manifest)` writes TWIN/export/scene.xml with mesh paths relative to it.

Names: in scene.xml, object bodies are named by their export IDs (`splattwin.names.export_id`, as in
every export); `add_twin` names them by the objects' names unless export_ids=True (the robot world
looks them up by the task's names). An unusable object with an obstacle estimate (`obstacle_only`) is
a static body (no joint) holding its box `<id>/obstacle`: it collides, but cannot be moved or grasped.

Frames: the twin frame is MuJoCo's world frame (z up, table top at z = table_height). Object convex parts
are stored in the object frame, so each object body sits at `T_world_obj`.

Contact model (why): MuJoCo collides a mesh as its convex hull, hence one geom per convex part. Grasping
by friction needs condim 4 (torsional friction keeps a pinched object from spinning about the finger
axis), an elliptic friction cone with impratio 10 (less slip under squeeze) and stiffer-than-default
contacts (solref 0.01) so light objects do not sink into the table.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.names import export_id
from splattwin.transforms import mujoco_quat_wxyz_from_matrix
from splattwin.twin.manifest import Manifest, ObjectEntry, unscaled_note

log = logging.getLogger(__name__)

FRICTION = (1.0, 0.01, 0.0002)     # sliding, torsional (m), rolling (m)
CONDIM = 4
SOLREF = (0.01, 1.0)               # time constant (s), damping ratio
SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)
DEFAULT_DENSITY = 400.0            # kg/m^3 when the manifest has no mass (light packaging / wood)
TABLE_RGBA = (0.62, 0.52, 0.40, 1.0)
FLOOR_DEPTH = 0.75                 # m below the table top: a floor to catch dropped objects


def object_parts(obj: ObjectEntry, twin_dir: Path) -> list[Path]:
    """Absolute paths of an object's convex parts (falls back to the collision mesh as one part)."""
    rels = list(obj.convex_parts) or ([obj.collision_mesh] if obj.collision_mesh else [])
    paths = [Path(twin_dir) / r for r in rels]
    missing = [p for p in paths if not p.is_file()]
    if not paths or missing:
        raise InputError(f"object {obj.name!r} has no collision geometry ({'missing ' + str(missing[0]) if missing else 'no parts'})",
                         Path(twin_dir) / "twin.json")
    return paths


def _mesh_volume(path: Path) -> float:
    from splattwin.meshio import load_mesh

    m = load_mesh(path, "convex part")
    hull = m.convex_hull  # MuJoCo uses the hull of each part for mass and contact
    return float(abs(hull.volume))


def add_twin(spec, manifest: Manifest, twin_dir: str | Path, objects: list[str] | None = None,
             floor: bool = True, poses: dict[str, np.ndarray] | None = None, export_ids: bool = False) -> list[str]:
    """Add table, background and object bodies of the twin into `spec` (in place).

    objects: names to include (default: every usable object). poses: optional override of T_world_obj
    [4,4] per object (perturbed trials). Returns the names of the (free) object bodies added.
    Body names: objects by their name (export_ids=True: their export IDs); geoms `<name>/part_<k>`;
    table geom `table`. Obstacle-only objects (unusable, with an obstacle box) are always added, as
    static bodies with geom `<name>/obstacle`, and are not in the returned list.
    """
    import mujoco

    twin_dir = Path(twin_dir).resolve()
    opt = spec.option
    opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    opt.impratio = 10.0
    bg = manifest.background
    x0, x1, y0, y1 = bg.table_extent
    thick = float(bg.table_thickness)
    wb = spec.worldbody
    if not any(m.name == "twin_table" for m in spec.materials):
        spec.add_material(name="twin_table", rgba=list(TABLE_RGBA))
    table = wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX,
                        size=[(x1 - x0) / 2, (y1 - y0) / 2, thick / 2],
                        pos=[(x0 + x1) / 2, (y0 + y1) / 2, bg.table_height - thick / 2], material="twin_table")
    _contact(table)
    if floor:
        fl = wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
                         pos=[0, 0, bg.table_height - FLOOR_DEPTH * manifest.frame.length_scale()], rgba=[0.3, 0.3, 0.32, 1])
        _contact(fl)
    # part 0 is the table box itself (geometry.convert), already the `table` geom above: adding it again
    # doubled every table contact (box + mesh hull), and URDF, MoveIt and glTF skip it too
    for k, rel in enumerate(bg.convex_parts[1:], start=1):
        _mesh_volume(twin_dir / rel)  # a readable triangle mesh (InputError naming it otherwise)
        mesh = spec.add_mesh(name=f"background_part_{k}", file=str(twin_dir / rel))
        g = wb.add_geom(name=f"background/part_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name,
                        rgba=[0.5, 0.5, 0.5, 1])
        _contact(g)
    added = []
    for obj in manifest.objects:
        bname = export_id(obj.name) if export_ids else obj.name
        if obj.obstacle_only:  # where an unusable object stands: static, so planners and physics avoid it
            body = wb.add_body(name=bname, pos=obj.pose[:3, 3].tolist(),
                               quat=mujoco_quat_wxyz_from_matrix(obj.pose[:3, :3]).tolist())
            g = body.add_geom(name=f"{bname}/obstacle", type=mujoco.mjtGeom.mjGEOM_BOX,
                              size=(np.asarray(obj.bbox_extent, float) / 2).tolist(), rgba=[0.9, 0.3, 0.3, 0.5])
            _contact(g)
            continue
        if not obj.usable or (objects is not None and obj.name not in objects):
            continue
        T = np.asarray(poses[obj.name]) if poses and obj.name in poses else obj.pose
        parts = object_parts(obj, twin_dir)
        vols = [_mesh_volume(p) for p in parts]
        total = sum(vols)
        if total <= 0:
            raise InputError(f"object {obj.name!r} has zero-volume collision geometry", parts[0])
        mass = float(obj.mass) if obj.mass else DEFAULT_DENSITY * total
        density = mass / total
        body = wb.add_body(name=bname, pos=T[:3, 3].tolist(), quat=mujoco_quat_wxyz_from_matrix(T[:3, :3]).tolist())
        body.add_freejoint(name=f"{bname}/free")
        rgba = _colour(obj)
        for k, p in enumerate(parts):
            mesh = spec.add_mesh(name=f"{bname}_part_{k}", file=str(p.resolve()))
            g = body.add_geom(name=f"{bname}/part_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name,
                              density=density, rgba=rgba)
            _contact(g)
        added.append(bname)
    return added


def _contact(geom) -> None:
    geom.friction = list(FRICTION)
    geom.condim = CONDIM
    geom.solref = list(SOLREF)
    geom.solimp = list(SOLIMP)


COLOUR_WORDS = {"blue": (0.15, 0.35, 0.85), "yellow": (0.95, 0.82, 0.1), "red": (0.85, 0.15, 0.12),
                "green": (0.2, 0.7, 0.25), "orange": (0.95, 0.5, 0.1), "cardboard": (0.66, 0.5, 0.32),
                "hammer": (0.85, 0.25, 0.2), "bottle": (0.3, 0.6, 0.65), "white": (0.9, 0.9, 0.9),
                "black": (0.15, 0.15, 0.15)}


def _colour(obj: ObjectEntry) -> list[float]:
    """Display colour: from a colour word in the object's name/prompt, else a stable colour per label."""
    text = f"{obj.name} {obj.prompt}".lower()
    for word, rgb in COLOUR_WORDS.items():
        if word in text:
            return [*rgb, 1.0]
    rng = np.random.default_rng(int(obj.label) * 7919 + 1)
    return [*(0.25 + 0.7 * rng.random(3)).tolist(), 1.0]


def _xml_comment(text: str) -> str:
    from splattwin.twin.xmltext import comment_text

    return comment_text(text)


def check_scaled(manifest: Manifest, where: str | Path) -> None:
    """Robot planning and physics need metres: refuse an unscaled twin, saying how to give it scale."""
    if not manifest.frame.scaled:
        raise InputError(
            f"the twin is not metrically scaled (frame source {manifest.frame.source!r}, units "
            f"{manifest.frame.units!r}): a robot cannot plan in SfM units. Rebuild it with a metric scale: "
            "--known-length camera_height=M (mean camera height above the table, metres) or "
            "baseline@IMG_A,IMG_B=M (distance between two camera centres), --marker-size M (an ArUco marker "
            "in view), metric known poses (a dataset's transforms.json or --robot-poses with --hand-eye), "
            "or metric depth images with known poses", where)


def build_spec(manifest: Manifest, twin_dir: str | Path, unscaled_ok: bool = False, **kw):
    """A `mujoco.MjSpec` of the twin alone (table, background, objects). kw: see `add_twin`.
    unscaled_ok: build an unscaled twin's spec too (the export, marked unscaled; never for planning)."""
    import mujoco

    if not unscaled_ok:
        check_scaled(manifest, Path(twin_dir) / "twin.json")
    spec = mujoco.MjSpec()
    spec.modelname = "splattwin_twin"
    spec.option.timestep = 0.002
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.worldbody.add_light(name="top", pos=[0, 0, 2.0], dir=[0, 0, -1], type=int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL))
    add_twin(spec, manifest, twin_dir, **kw)
    return spec


def _relative_files(xml: str, out_dir: Path) -> str:
    """`xml` with every absolute `file` attribute made relative to `out_dir`. Parsed, not text-replaced:
    to_xml escapes the path (`&` -> `&amp;`), so a plain replace missed folders named with `&<'"`."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml)
    for el in root.iter():
        f = el.get("file")
        if f and Path(f).is_absolute():
            el.set("file", Path(os.path.relpath(f, out_dir)).as_posix())
    return ET.tostring(root, encoding="unicode") + "\n"


def export_mjcf(twin_dir: str | Path, manifest: Manifest | None = None, options=None) -> Path:
    """Write TWIN/export/scene.xml (mesh files referenced relative to it) and record it in the manifest."""
    twin_dir = Path(twin_dir).resolve()
    manifest = manifest or Manifest.load(twin_dir)
    spec = build_spec(manifest, twin_dir, unscaled_ok=True, export_ids=True)
    if not manifest.frame.scaled:
        spec.modelname = "splattwin_twin_unscaled"
    try:
        spec.compile()
    except ValueError as e:
        raise InputError(f"twin does not compile as MJCF: {e}", twin_dir / "twin.json") from e
    xml = _relative_files(spec.to_xml(), twin_dir / "export")
    notes = ["frame: the world frame is the twin frame (z up, metres unless marked unscaled); quaternions "
             "are w x y z (MJCF); bodies are named by the objects' export IDs (twin.json export_id)"]
    note = unscaled_note(manifest.frame)
    if note:
        notes.append(note)
    srcs = sorted({o.mass_source for o in manifest.objects if o.usable and o.mass_source})
    if any(o.usable for o in manifest.objects):
        notes.append("masses and inertias: " + ("; ".join(srcs) if srcs else
                     f"uniform density {DEFAULT_DENSITY:g} kg/m^3 over the convex parts"))
    obst = [export_id(o.name) for o in manifest.objects if o.obstacle_only]
    if obst:
        notes.append("obstacle-only (unusable objects; static padded boxes of their splats, estimates): "
                     + ", ".join(obst))
    j = xml.index(">", xml.index("<mujoco")) + 1   # comments right after the root element's opening tag
    xml = xml[:j] + "".join(f"\n  <!-- {_xml_comment(n)} -->" for n in notes) + xml[j:]
    out = io.write_text(twin_dir / "export" / "scene.xml", xml)
    manifest.exports["mjcf"] = "export/scene.xml"
    manifest.save(twin_dir)
    return out
