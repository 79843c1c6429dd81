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
    plan = sub.choices.get("plan")   # registered below this layer (playback/cli.py), which may not import it
    if plan is not None:
        plan.add_argument("--no-report", action="store_true",
                          help="leave TWIN/report/index.html as it is (default: a twin that has a report gets it "
                               "re-written with this run's results, as `splattwin report TWIN` would)")
        plan.set_defaults(after_plan=refresh_after_plan)


def refresh_after_plan(args: argparse.Namespace, out: Path, seconds: float | None = None) -> Path | None:
    """After `splattwin plan` (inside its lock): re-write the twin's report so it shows this run's results,
    not the build's (the report reads TWIN/robot/results.json). The whole report, as `splattwin report
    TWIN` writes it (a task video of an unchanged rollout comes from its cache). Only a twin that has a
    report (a build made one), only when the run wrote TWIN/robot (an --out elsewhere is not what the
    report shows: said), not with --no-report. A report that cannot be written is a warning, not the
    plan's outcome. Returns its path or None. seconds: the plan run's (s); when it wrote TWIN/robot they
    are recorded (`build.record_plan_run`, also with --no-report) so that the report's timings table gives
    the robot row this run's seconds, not the build's robot stage's."""
    import logging

    from splattwin.console import console

    twin = Path(args.twin)
    page = twin / "report" / "index.html"
    wrote_twin_robot = Path(out).resolve() == (twin / "robot").resolve()
    if wrote_twin_robot and seconds is not None:
        from splattwin.report.build import record_plan_run
        from splattwin.runtime import peak_rss_gib

        record_plan_run(twin, seconds, peak_rss_gib())
    if getattr(args, "no_report", False) or not page.is_file():
        return None
    if not wrote_twin_robot:
        console().print(f"report: {page} not refreshed (it shows TWIN/robot; this run wrote {out})",
                        markup=False, highlight=False)
        return None
    from splattwin.report.build import build_report

    try:
        path = build_report(twin)
    except Exception as e:   # the plan's results are written; the report is a view of them
        logging.getLogger(__name__).warning("report not refreshed (%s: %s); run `splattwin report %s`",
                                            type(e).__name__, e, twin)
        return None
    console().print(f"report: {path} (refreshed with this run's results)", markup=False, highlight=False)
    return path


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
