"""`splattwin view TWIN`: the web viewer."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="web viewer (viser): splats, labels, collision meshes, robot trajectory")
    p.add_argument("twin", type=Path, help="twin folder (with twin.json)")
    p.add_argument("--host", default="127.0.0.1", help="interface to serve on (default loopback only)")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080; the next free one when it "
                   "is taken)")
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    from splattwin.viewer.app import serve

    serve(args.twin, host=args.host, port=args.port, block=True)
    return 0
