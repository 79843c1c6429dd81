"""Reading triangle meshes named by files we did not write (twin.json, scene.json): a bad file is an
InputError naming it, never a library traceback.

`load_mesh(path)` is `trimesh.load(path, force="mesh")` after checks: the file exists and is at most
`limits.MAX_JSON_BYTES` large, a PLY header's element counts are bounded (`limits.check_ply_header`), and
the result is one triangle mesh with at least one face and finite vertices within `limits.MAX_POSITION` of
the origin (a finite 1e308 overflowed in the hull, volume and inertia computations after it: qhull errors). trimesh raises many
exception types (and sometimes returns an empty scene) for files that are not meshes; all become an
InputError.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.limits import MAX_ELEMENTS, MAX_JSON_BYTES, MAX_POSITION, check_file_size, check_ply_header

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


def load_mesh(path: str | Path, what: str = "mesh", process: bool = False):
    """A `trimesh.Trimesh` read from `path` (format from the suffix), checked (see module docstring)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file does not exist", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{what} must be one of {', '.join(MESH_SUFFIXES)} (got {path.suffix or 'no suffix'!r})",
                         path)
    check_file_size(path, MAX_JSON_BYTES, what)
    if path.suffix.lower() == ".ply":
        check_ply_header(path, what)
    try:
        m = trimesh.load(path, force="mesh", process=process)
    except Exception as e:  # noqa: BLE001 - trimesh and its parsers raise many types on malformed files
        raise InputError(f"not a readable {what} ({type(e).__name__}: {str(e)[:200]})", path) from None
    if not isinstance(m, trimesh.Trimesh):
        raise InputError(f"not a triangle {what} (read as {type(m).__name__})", path)
    if len(m.faces) == 0 or len(m.vertices) == 0:
        raise InputError(f"{what} has no triangles", path)
    if len(m.vertices) > MAX_ELEMENTS or len(m.faces) > MAX_ELEMENTS:
        raise InputError(f"{what} has more than {MAX_ELEMENTS} vertices or faces", path)
    if not np.all(np.isfinite(m.vertices)):
        raise InputError(f"{what} has NaN or infinite vertices", path)
    if np.abs(m.vertices).max() > MAX_POSITION:
        raise InputError(f"{what} has vertices more than {MAX_POSITION:g} from the origin", path)
    if m.faces.min() < 0 or m.faces.max() >= len(m.vertices):
        raise InputError(f"{what} has faces that index missing vertices", path)
    return m
