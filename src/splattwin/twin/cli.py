"""Sub-commands of the twin stage: `splattwin export TWIN [--formats mjcf,urdf,moveit,gltf]`."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.errors import InputError
from splattwin.options import add_command, add_options, from_args
from splattwin.twin.options import FORMATS, ExportOptions


def _export(args: argparse.Namespace) -> int:
    """(Re-)export a twin folder for simulators and planners.

    Writes the twin's exports: MJCF (MuJoCo), URDF per object and scene, MoveIt 2 planning scene (.scene
    text + CollisionObject YAML), glTF binary. Files are replaced atomically. Prints the files written;
    twin.json keeps earlier exports only while their files exist."""
    from splattwin.lock import output_lock
    from splattwin.twin.build import write_exports
    from splattwin.twin.manifest import Manifest, warn_missing_obstacle_boxes

    twin = Path(args.twin)
    if not twin.is_dir():
        raise InputError("twin folder does not exist", twin)
    with output_lock(twin):
        manifest = Manifest.load(twin)
        warn_missing_obstacle_boxes(manifest, twin)   # an older twin.json: unusable objects left out silently
        opts = from_args(ExportOptions, args)
        formats = opts.resolve()
        if not manifest.frame.scaled:
            print("note: the twin is unscaled (SfM units, not metres): its exports are marked so in each file")
        if not formats:
            raise InputError("no export format given; choose from " + ", ".join(FORMATS), "--formats")
        written = write_exports(twin, manifest, formats, options=opts)
    for fmt, path in written.items():  # only what this run wrote (twin.json may list earlier exports too)
        print(f"{fmt:7s} {twin / path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "export", _export)
    p.add_argument("twin", metavar="TWIN", help="twin folder (contains twin.json)")
    add_options(p, ExportOptions)
