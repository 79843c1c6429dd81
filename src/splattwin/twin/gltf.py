"""glTF binary (GLB) of the twin's visual meshes (Unity, Blender, three.js), via trimesh.

One node per object (named by its export ID, `splattwin.names.export_id`; transform = T_world_obj, mesh
in the object frame, vertex colours from the splats), the table box, the background obstacles (node
`background_obstacles`, twin frame, as in URDF/MJCF/MoveIt) and each unusable object's obstacle box
(`obstacle_only`, translucent red: a material with alphaMode BLEND, alpha 0.5). glTF is y-up by convention; we keep the twin's z-up frame and put the
conversion on a root node `twin_z_up` so importers show the table horizontal. glTF lengths are metres
by spec: an unscaled twin says what its numbers are in the scene's extras.

Colours: glTF's COLOR_0 and baseColorFactor are *linear* (spec 3.7.2.1, 3.9.2); the splats' colours and
our display colours are sRGB, so they are converted (`linear_from_srgb`), else viewers show them washed
out. COLOR_0 is written as float (glTF allows float, normalised unsigned byte or short for it): linear
8-bit has 13 levels for sRGB 0..55, so a dark object's vertex colours came out posterised (sRGB 0..13 all
read as linear 0 or 1/255). Not 16-bit: trimesh 5.2 reads a normalised unsigned short COLOR_0 as raw
integers cast to bytes (wrong colours), floats in [0, 1] correctly. trimesh writes COLOR_0 as 8-bit only,
so the float colours travel as a custom vertex attribute (`COLOR_ATTRIBUTE`) that the tree post-processor
renames to COLOR_0. Every primitive carries unit NORMALs (without them viewers must shade flat, spec 3.7.2.1): smooth
on the visual meshes, per face on boxes and convex obstacle parts (unmerged vertices), and each
bufferView says whether it holds vertex or index data (`target`), as the Khronos validator asks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from splattwin import io
from splattwin.meshio import load_mesh
from splattwin.names import export_id
from splattwin.twin.manifest import Manifest, unscaled_note

# z-up twin -> y-up glTF: rotate -90 degrees about x
Y_UP_FROM_Z_UP = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=float)


OBSTACLE_RGBA = (230, 77, 77, 128)   # translucent red (alpha ~0.5, sRGB), as the report and the viewer draw them
TABLE_RGBA = (153, 128, 102, 255)    # sRGB
BACKGROUND_RGBA = (128, 128, 128, 255)  # sRGB
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963   # bufferView.target values (glTF 2.0, 5.11)


COLOR_ATTRIBUTE = "_color_linear"   # trimesh's name for a custom attribute; renamed COLOR_0 in the GLB


def linear_from_srgb(rgba, dtype=np.uint8) -> np.ndarray:
    """RGBA [...,4] with linear RGB (glTF's COLOR_0 / baseColorFactor) from uint8 sRGB RGBA (what the splats
    and our display colours are): the sRGB transfer function (IEC 61966-2-1); alpha is kept. dtype: uint8
    (0..255) or a float type (0..1: the dark sRGB levels stay distinct)."""
    if np.issubdtype(dtype, np.floating):
        full = 1.0
    else:
        full = float(np.iinfo(dtype).max)
    c = np.asarray(rgba, dtype=float) / 255.0
    rgb = c[..., :3]
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    out = np.concatenate([lin, c[..., 3:]], axis=-1) * full
    return out.astype(dtype) if full == 1.0 else np.round(out).astype(dtype)


def _set_colours(mesh: trimesh.Trimesh, srgb_rgba) -> None:
    """Give `mesh` the sRGB RGBA colours (one [4] for all vertices, or [V,4] uint8) as float32 linear
    colours in `COLOR_ATTRIBUTE`, and no trimesh vertex colours (those would be written as 8-bit COLOR_0)."""
    srgb = np.broadcast_to(np.asarray(srgb_rgba, dtype=np.uint8), (len(mesh.vertices), 4))
    mesh.visual = trimesh.visual.ColorVisuals(mesh=mesh)
    mesh.vertex_attributes[COLOR_ATTRIBUTE] = linear_from_srgb(srgb, np.float32)


def _flat(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh with one vertex per face corner, so its exported vertex normals are face normals (boxes and
    convex hulls would otherwise be shaded as if rounded)."""
    mesh = mesh.copy()
    mesh.unmerge_vertices()
    return mesh


def _set_buffer_view_targets(tree: dict) -> None:
    """tree_postprocessor of trimesh's glTF export: bufferView.target ARRAY_BUFFER for vertex attributes,
    ELEMENT_ARRAY_BUFFER for indices (the validator's BUFFER_VIEW_TARGET_MISSING)."""
    acc, views = tree.get("accessors", []), tree.get("bufferViews", [])
    for mesh in tree.get("meshes", []):
        for prim in mesh.get("primitives", []):
            attributes = prim.get("attributes", {})
            if COLOR_ATTRIBUTE in attributes:   # our float linear colours (0..1): COLOR_0
                attributes["COLOR_0"] = attributes.pop(COLOR_ATTRIBUTE)
            for a in prim.get("attributes", {}).values():
                views[acc[a]["bufferView"]]["target"] = ARRAY_BUFFER
            if "indices" in prim:
                views[acc[prim["indices"]]["bufferView"]]["target"] = ELEMENT_ARRAY_BUFFER


def obstacle_material():
    """The material of an obstacle-only box: red, alphaMode BLEND with alpha ~0.5 (trimesh stores colour
    factors as uint8: 128/255). glTF ignores a vertex colour's alpha under the default material (OPAQUE),
    so the translucency must come from a material."""
    return trimesh.visual.material.PBRMaterial(name="obstacle_only",
                                               baseColorFactor=linear_from_srgb(OBSTACLE_RGBA).tolist(),
                                               alphaMode="BLEND", doubleSided=True, metallicFactor=0.0,
                                               roughnessFactor=1.0)


def twin_scene(twin_dir: Path, manifest: Manifest, y_up: bool = True) -> trimesh.Scene:
    """trimesh Scene of the twin as the GLB holds it (module docstring): lengths in metres (twin frame
    units if unscaled), vertex colours linear float in `COLOR_ATTRIBUTE`; y_up: the root node `twin_z_up`
    turns the z-up twin frame into glTF's y-up one (else identity)."""
    scene = trimesh.Scene()
    # glTF lengths are metres by spec: an unscaled twin says what its numbers are (scene extras)
    scene.metadata["splattwin"] = {"units": manifest.frame.units, "scaled": bool(manifest.frame.scaled),
                                   "frame_source": manifest.frame.source,
                                   **({"note": unscaled_note(manifest.frame)} if not manifest.frame.scaled else {})}
    root = "twin_z_up"
    scene.graph.update(frame_to=root, frame_from=scene.graph.base_frame, matrix=Y_UP_FROM_Z_UP if y_up else np.eye(4))
    bg = manifest.background
    x0, x1, y0, y1 = bg.table_extent
    table = _flat(trimesh.creation.box(extents=[x1 - x0, y1 - y0, bg.table_thickness]))
    _set_colours(table, TABLE_RGBA)
    T = np.eye(4)
    T[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, bg.table_height - bg.table_thickness / 2]
    scene.add_geometry(table, node_name="table", geom_name="table", parent_node_name=root, transform=T)
    obstacles = [load_mesh(twin_dir / p, "background obstacle mesh", process=True) for p in bg.convex_parts[1:]]
    if obstacles:  # part 0 is the table box itself
        m = _flat(trimesh.util.concatenate(obstacles))
        _set_colours(m, BACKGROUND_RGBA)
        scene.add_geometry(m, node_name="background_obstacles", geom_name="background_obstacles",
                           parent_node_name=root, transform=np.eye(4))
    for o in manifest.objects:
        oid = export_id(o.name)
        if o.obstacle_only:
            box = _flat(trimesh.creation.box(extents=np.asarray(o.bbox_extent, dtype=float)))
            box.visual = trimesh.visual.TextureVisuals(material=obstacle_material())
            scene.add_geometry(box, node_name=oid, geom_name=oid, parent_node_name=root, transform=o.pose)
        elif o.usable and o.visual_mesh:
            m = load_mesh(twin_dir / o.visual_mesh, f"visual mesh of {o.name!r}", process=True)
            if m.visual.kind == "vertex":   # the splats' sRGB colours -> glTF's linear COLOR_0
                _set_colours(m, m.visual.vertex_colors)
            scene.add_geometry(m, node_name=oid, geom_name=oid, parent_node_name=root, transform=o.pose)
    return scene


def export_gltf(twin_dir: str | Path, manifest: Manifest, options=None) -> Path:
    """Write export/scene.glb (atomically)."""
    twin_dir = Path(twin_dir)
    path = twin_dir / "export" / "scene.glb"
    data = twin_scene(twin_dir, manifest).export(file_type="glb", include_normals=True,
                                                 tree_postprocessor=_set_buffer_view_targets)
    return io.write_bytes(path, data)
