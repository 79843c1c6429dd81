"""Sub-commands of the twin stage: `splattwin export TWIN [--formats mjcf,urdf,moveit,gltf]`."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.errors import InputError


def _formats(text: str) -> tuple[str, ...]:
    from splattwin.twin.build import FORMATS

    fmts = tuple(f.strip().lower() for f in text.split(",") if f.strip())
    bad = [f for f in fmts if f not in FORMATS]
    if bad or not fmts:
        raise InputError(f"unknown export format(s) {', '.join(bad) or '(none)'}; choose from {', '.join(FORMATS)}",
                         "--formats")
    return fmts


def _export(args: argparse.Namespace) -> int:
    from splattwin.lock import output_lock
    from splattwin.twin.build import default_formats, export_twin
    from splattwin.twin.manifest import Manifest

    twin = Path(args.twin)
    if not twin.is_dir():
        raise InputError("twin folder does not exist", twin)
    with output_lock(twin):
        manifest = Manifest.load(twin)
        if args.formats is None:
            formats = default_formats(manifest.frame)
            if len(formats) < 4:
                print(f"note: mjcf export skipped: the twin is unscaled (frame source {manifest.frame.source!r}); "
                      f"physics needs metres")
        else:
            formats = _formats(args.formats)
        m = export_twin(twin, manifest, formats)
    for fmt, path in m.exports.items():
        print(f"{fmt:7s} {twin / path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    p = sub.add_parser("export", help="(re-)export a twin folder for simulators and planners",
                       description="Write the twin's exports: MJCF (MuJoCo), URDF per object and scene, MoveIt 2 "
                                   "planning scene (.scene text + CollisionObject YAML), glTF binary. Files are "
                                   "replaced atomically.")
    p.add_argument("twin", metavar="TWIN", help="twin folder (contains twin.json)")
    p.add_argument("--formats", default=None,
                   help="comma-separated subset of mjcf,urdf,moveit,gltf (default: all; an unscaled twin gets "
                        "no mjcf)")
    p.set_defaults(func=_export)
