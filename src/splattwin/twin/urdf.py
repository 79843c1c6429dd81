"""URDF export: one URDF per object and one for the scene.

Files go to TWIN/export/ (`scene.urdf`, `<export_id>.urdf`). Mesh filenames follow
`ExportOptions.urdf_uri`: relative to that folder by default ("../objects/box/visual.obj": simulators
and yourdfpy resolve it against the URDF file, and the twin folder can be moved as a whole), absolute
`file://` URIs, or `package://NAME/...` with the twin folder as the package root (ROS passes
robot_description as a string, so rviz / MoveIt need one of the URIs; they are percent-encoded as RFC
8089 / 3986 ask: see `percent_encoding_note`). Links and joints are named by
the objects' export IDs (`splattwin.names.export_id`: [A-Za-z0-9_]). The scene URDF roots at link
`world` = the twin frame (z up); the table, background obstacles and every usable object hang from it
on fixed joints at their poses (a URDF cannot express free bodies; simulators free them, planners
treat them as a snapshot). An unusable object with an obstacle estimate (`obstacle_only`) is a link
with its box only (no inertial: static). Masses and inertias are estimates (a comment says so).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from urllib.parse import quote, unquote
from xml.sax.saxutils import quoteattr

import numpy as np
import trimesh

from splattwin import io
from splattwin.meshio import load_mesh
from splattwin.names import export_id
from splattwin.paths import child
from splattwin.twin.manifest import Manifest, ObjectEntry, unscaled_note

log = logging.getLogger(__name__)
_FILENAME = re.compile(r'<mesh filename="([^"]*)"')


def _origin(T: np.ndarray) -> str:
    rpy = trimesh.transformations.euler_from_matrix(T, "sxyz")  # URDF rpy: fixed-axis x, y, z
    xyz = " ".join(f"{v:.6g}" for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{" ".join(f"{v:.6g}" for v in rpy)}"/>'


def _rel(twin_dir: Path, rel_path: str, from_dir: Path, uri: str = "relative") -> str:
    """A mesh's filename in the URDF (module docstring): `rel_path` is relative to the twin folder."""
    if uri == "file":
        return (Path(twin_dir).resolve() / rel_path).as_uri()   # percent-encodes spaces
    if uri.startswith("package://"):
        return f"{uri}/{quote(Path(rel_path).as_posix())}"
    return Path(os.path.relpath(twin_dir / rel_path, from_dir)).as_posix()


def _inertial(twin_dir: Path, o: ObjectEntry) -> str:
    mass = float(o.mass or 0.1)
    m = load_mesh(twin_dir / o.collision_mesh, f"collision mesh of {o.name!r}", process=True) if o.collision_mesh else None
    if m is not None and m.is_volume:
        m.density = mass / m.volume
        com, I = m.center_mass, m.moment_inertia
    else:  # a solid box of the bbox extent
        e = np.asarray(o.bbox_extent, dtype=float)
        com = np.zeros(3)
        I = np.diag(mass / 12.0 * np.array([e[1]**2 + e[2]**2, e[0]**2 + e[2]**2, e[0]**2 + e[1]**2]))
    T = np.eye(4)
    T[:3, 3] = com
    # shortest round-trip digits, not 6: rounding each element apart can break the triangle inequality
    # ixx + iyy >= izz of a thin object (a 0.1 mm card), which Gazebo, Drake and MuJoCo's URDF compiler refuse
    f = {k: repr(float(I[i, j])) for k, (i, j) in
         {"ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2), "izz": (2, 2)}.items()}
    return (f'<inertial>{_origin(T)}<mass value="{mass!r}"/>'
            f'<inertia ixx="{f["ixx"]}" ixy="{f["ixy"]}" ixz="{f["ixz"]}" iyy="{f["iyy"]}" '
            f'iyz="{f["iyz"]}" izz="{f["izz"]}"/></inertial>')


def object_link(twin_dir: Path, o: ObjectEntry, from_dir: Path, uri: str = "relative") -> str:
    """<link> of an object in its own frame: inertial, visual mesh, one collision per convex part; an
    obstacle-only object: its box as visual and collision, no inertial (a static link)."""
    parts = [f"<link name={quoteattr(export_id(o.name))}>"]
    if o.obstacle_only:
        box = " ".join(f"{v:.6g}" for v in o.bbox_extent)
        parts.append(f'<visual><geometry><box size="{box}"/></geometry></visual>'
                     f'<collision><geometry><box size="{box}"/></geometry></collision>')
    else:
        parts.append(_inertial(twin_dir, o))
    if o.visual_mesh:
        parts.append(f'<visual><geometry><mesh filename={quoteattr(_rel(twin_dir, o.visual_mesh, from_dir, uri))}/>'
                     f"</geometry></visual>")
    for p in (o.convex_parts or ([o.collision_mesh] if o.collision_mesh else [])):
        parts.append(f'<collision><geometry><mesh filename={quoteattr(_rel(twin_dir, p, from_dir, uri))}/>'
                     f"</geometry></collision>")
    parts.append("</link>")
    return "\n  ".join(parts)


def _comment(text: str) -> str:
    from splattwin.twin.xmltext import comment_text

    return "<!-- " + comment_text(text) + " -->\n"


def _note(manifest: Manifest | None, objects=None) -> str:
    """XML comment lines: the frame, an unscaled twin's note (URDF has no unit field: lengths are metres by
    spec), that masses are estimates, and the obstacle-only links."""
    if manifest is None:
        return ""
    out = _comment("frame: link world is the twin frame (z up; table top at z = table_height in twin.json); "
                   "each object link's origin is its object frame")
    note = unscaled_note(manifest.frame)
    if note:
        out += _comment(note)
    objects = manifest.objects if objects is None else objects
    srcs = sorted({o.mass_source for o in objects if o.usable and o.mass_source})
    if any(o.usable for o in objects):
        out += _comment("masses and inertias: " + ("; ".join(srcs) if srcs else
                                                                 "uniform density over the collision mesh"))
    obst = [export_id(o.name) for o in objects if o.obstacle_only]
    if obst:
        out += _comment("obstacle-only (unusable objects, static padded boxes of their splats, estimates): "
                        + ", ".join(obst))
    return out


def object_urdf(twin_dir: Path, o: ObjectEntry, out_dir: Path, manifest: Manifest | None = None,
                uri: str = "relative") -> str:
    return (f'<?xml version="1.0"?>\n{_note(manifest, [o])}<robot name={quoteattr(export_id(o.name))}>\n  '
            f'{object_link(twin_dir, o, out_dir, uri)}\n</robot>\n')


def scene_urdf(twin_dir: Path, manifest: Manifest, out_dir: Path, uri: str = "relative") -> str:
    bg = manifest.background
    x0, x1, y0, y1 = bg.table_extent
    box = f"{x1 - x0:.6g} {y1 - y0:.6g} {bg.table_thickness:.6g}"
    T_table = np.eye(4)
    T_table[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, bg.table_height - bg.table_thickness / 2]
    lines = ['<?xml version="1.0"?>', _note(manifest).rstrip(),
             '<robot name="splattwin_scene">', '  <link name="world"/>',
             f'  <link name="table"><visual><geometry><box size="{box}"/></geometry></visual>'
             f'<collision><geometry><box size="{box}"/></geometry></collision></link>',
             f'  <joint name="world_to_table" type="fixed"><parent link="world"/><child link="table"/>{_origin(T_table)}</joint>']
    obstacles = [p for p in bg.convex_parts[1:]]  # part 0 is the table box itself
    if obstacles:
        coll = "".join(f'<collision><geometry><mesh filename={quoteattr(_rel(twin_dir, p, out_dir, uri))}/>'
                       f'</geometry></collision>' for p in obstacles)
        lines += [f'  <link name="background_obstacles">{coll}</link>',
                  '  <joint name="world_to_background_obstacles" type="fixed"><parent link="world"/>'
                  '<child link="background_obstacles"/><origin xyz="0 0 0" rpy="0 0 0"/></joint>']
    for o in manifest.objects:
        if not (o.usable or o.obstacle_only):
            continue
        oid = export_id(o.name)
        lines.append("  " + object_link(twin_dir, o, out_dir, uri))
        lines.append(f'  <joint name={quoteattr("world_to_" + oid)} type="fixed"><parent link="world"/>'
                     f'<child link={quoteattr(oid)}/>{_origin(o.pose)}</joint>')
    lines.append("</robot>\n")
    return "\n".join(lines)


def encoded_characters(urdf_texts: list[str]) -> list[str]:
    """The characters that the URDFs' mesh URIs hold percent-encoded (space, non-ASCII, '%', '#', ...)."""
    chars = set()
    for text in urdf_texts:
        for fn in _FILENAME.findall(text):
            if "%" in fn:
                chars.update(c for c in unquote(fn) if quote(c, safe="/") != c)
    return sorted(chars)


def percent_encoding_note(uri: str, chars: list[str]) -> str:
    """Why the URIs hold %XX escapes and who reads them (the export's warning and the URDF's comment).

    RFC 8089 file: URIs (and package:// URIs, as URI references) percent-encode a space ('%20'), non-ASCII
    bytes, '%', '#', ... What the consumers do with them: ROS resource_retriever (ROS 1 and 2; what rviz and
    MoveIt load meshes through, and what these URIs are for) decodes them; yourdfpy (0.0.60, checked) strips
    'file://' or 'package://NAME/' and opens the rest as written, so '%20' stays and the mesh is not found
    (dropped silently); MuJoCo's URDF compiler (4.0, checked) opens no file:// URI, encoded or not; urdfdom
    only parses (its users resolve). Writing the characters raw would break the URI for ROS to please
    loaders that should read the relative filenames anyway, so the URIs stay encoded and the export says so.
    """
    shown = ", ".join(repr(c) if c != " " else "space" for c in chars[:6]) + (" ..." if len(chars) > 6 else "")
    where = "the twin folder's path or an object's folder name" if uri == "file" else "an object's folder name"
    return (f"the URDF mesh filenames ({uri} URIs) percent-encode characters of {where} ({shown}; e.g. a space "
            f"is '%20'), as RFC 8089/3986 require: ROS (resource_retriever: rviz, MoveIt) decodes them, but loaders "
            f"that open the path as written (yourdfpy) miss the meshes, and MuJoCo reads no file:// URI: for those "
            f"use the default relative filenames (--urdf-uri relative), or move the twin to a path of letters, "
            f"digits, '_', '-', '.' only")


def export_urdf(twin_dir: str | Path, manifest: Manifest, options=None) -> Path:
    """Write export/scene.urdf and export/<export_id>.urdf for every usable object (atomically). options:
    `ExportOptions` (urdf_uri). Returns scene.urdf. URI filenames with percent-encoded characters get a
    warning and a comment in each file (`percent_encoding_note`)."""
    from splattwin.twin.options import ExportOptions

    uri = (options or ExportOptions()).urdf_uri
    twin_dir = Path(twin_dir)
    out = twin_dir / "export"
    texts = {f"{export_id(o.name)}.urdf": object_urdf(twin_dir, o, out, manifest, uri)
             for o in manifest.objects if o.usable}
    texts["scene.urdf"] = scene_urdf(twin_dir, manifest, out, uri)
    chars = encoded_characters(list(texts.values())) if uri != "relative" else []
    if chars:
        note = percent_encoding_note(uri, chars)
        log.warning("%s: %s", out / "scene.urdf", note)
        head = '<?xml version="1.0"?>\n'
        texts = {k: head + _comment(note) + t[len(head):] if t.startswith(head) else t for k, t in texts.items()}
    for name, text in texts.items():
        if name != "scene.urdf":
            io.write_text(child(out, name), text)
    path = io.write_text(out / "scene.urdf", texts["scene.urdf"])
    io.remove_stale(out, set(texts), suffix=".urdf")   # an earlier build's object that is gone or now unusable
    return path
