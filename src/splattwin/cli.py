"""`splattwin` command line.

Each stage owns its sub-commands in `splattwin/<stage>/cli.py`, exposing `register(subparsers)`, which
adds parsers whose `func(args) -> int` runs the command. Exit codes: 0 success, 2 bad input
(`InputError`, message names the file and the problem), 1 internal error.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback

from splattwin import __version__
from splattwin.errors import InputError

# Order = order in `splattwin --help`.
STAGE_CLIS = [
    "splattwin.pipeline.cli",
    "splattwin.scene.cli",
    "splattwin.capture.cli",
    "splattwin.poses.cli",
    "splattwin.splat.cli",
    "splattwin.semantics.cli",
    "splattwin.geometry.cli",
    "splattwin.twin.cli",
    "splattwin.robot.cli",
    "splattwin.cluster.cli",
    "splattwin.playback.cli",
    "splattwin.report.cli",
    "splattwin.viewer.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="splattwin",
        description="Turn a few RGB photos of a tabletop into a planning-ready digital twin "
                    "(3D Gaussian Splatting, semantic objects, collision meshes, robot plans validated in MuJoCo).",
    )
    parser.add_argument("--version", action="version", version=f"splattwin {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in STAGE_CLIS:
        importlib.import_module(mod).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception:  # internal error: full traceback for the bug report
        traceback.print_exc()
        return 1


if __name__ == "__main__":
    sys.exit(main())
