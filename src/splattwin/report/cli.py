"""`splattwin report TWIN`: (re)write the twin's HTML report."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.options import add_options
from splattwin.report.options import ReportOptions


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write the twin's self-contained HTML report (TWIN/report/index.html)")
    p.add_argument("twin", type=Path, help="twin folder")
    add_options(p, ReportOptions)
    p.set_defaults(func=_report)


def _report(args: argparse.Namespace) -> int:
    from splattwin.errors import InputError
    from splattwin.options import from_args
    from splattwin.report.build import build_report

    from splattwin.lock import output_lock

    opts = from_args(ReportOptions, args)
    opts.validate()
    if not args.twin.is_dir():
        raise InputError("twin folder does not exist", args.twin)
    with output_lock(args.twin):
        print(f"report: {build_report(args.twin, options=opts)}")
    return 0
