"""`splattwin sweep TWIN --out DIR ...` and `splattwin batch CAPTURE... --out DIR ...`.

Every flag is generated from an options dataclass (`splattwin.options.add_options`), none is written
here with a default: the sweep's own (`SweepOptions`: grid values, trials per cell, masks), the trials'
task, robot and planner (`RobotOptions`, the robot stage's), the build flags of `batch` (`BuildOptions`,
the same as `splattwin build`), and where the tasks run (`ExecutorOptions`: `--executor`,
`--ray-address`, `--max-retries`, `--workers`, also spelled `--cluster.*`).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from splattwin.cluster.options import BatchOptions, SweepOptions
from splattwin.options import add_options, add_progress_flag

# the robot stage's options a sweep's trials take from the command line (sigma is a grid parameter here)
SWEEP_ROBOT_FLAGS = ("task", "base_pose", "robot_mjcf", "tcp_site", "in_hand", "planner", "seed")


def register(sub: argparse._SubParsersAction) -> None:
    from splattwin.pipeline.cli import add_build_flags
    from splattwin.robot.options import RobotOptions

    s = sub.add_parser(
        "sweep", help="parameter grid over a twin (kappa, fusion rounds, cleaning options, sigma), each cell "
                      "validated by trials; one results table",
        description="Re-run semantic fusion, geometry cleaning and Monte-Carlo trials of the task for every cell "
                    "of a parameter grid over a built twin. Each value list is comma-separated; the grid is their "
                    "product. Parameters map by field name onto FusionOptions (fusion.*), GeometryOptions "
                    "(geometry.*) and the robot stage's trials (trials.sigma, trials.sigma_yaw, trials.planner, "
                    "trials.in_hand). Options not swept are those the twin was built with (its twin.json), "
                    "the trials' task, base pose and planner included unless given here. Writes OUT/sweep.csv, "
                    "OUT/sweep.json, OUT/sweep.png and prints the table; a re-run resumes. Exit code 0 when "
                    "every cell ran, 1 when a cell could not run, 2 on bad input.")
    s.add_argument("twin", type=Path, help="twin folder built by `splattwin build` / `demo` (with twin.json)")
    s.add_argument("--out", type=Path, required=True, help="sweep folder to write")
    add_options(s, SweepOptions)
    add_options(s, RobotOptions, include=SWEEP_ROBOT_FLAGS)
    add_progress_flag(s)
    s.set_defaults(func=run_sweep_cli)

    b = sub.add_parser(
        "batch", help="build many captures (one twin each) on the executor; one summary CSV/HTML",
        description="Run `splattwin build` for every capture into OUT/<name>/ (reconstruction as one task, on a GPU "
                    "when the cluster has one; the rest of the build as a second task), then write OUT/summary.csv, "
                    "OUT/summary.html and OUT/batch.json with each capture's figures and failures. A failed "
                    "capture is reported, not fatal; a re-run resumes every capture. The build flags are those "
                    "of `splattwin build` (inside a batch task the robot stage's trials run on a local pool of "
                    "the task's CPUs). Exit code 0 when every capture was built, 1 when some failed, 2 on bad "
                    "input.")
    b.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE",
                   help="datasets: image folders, videos, transforms.json, COLMAP, cameras.json, BOP scenes or TUM "
                        "pose lists + intrinsics")
    b.add_argument("--out", type=Path, required=True, help="folder of the twins and the summary")
    add_options(b, BatchOptions)
    add_build_flags(b)
    b.set_defaults(func=run_batch_cli)


def _grid(opts: SweepOptions) -> dict[str, list]:
    from splattwin.cluster import params as P
    from splattwin.errors import InputError

    grid: dict[str, list] = {}

    def put(name: str, values: list) -> None:
        if name in grid:
            raise InputError(f"sweep parameter {name} given twice")
        grid[name] = values

    for value, name in ((opts.kappa, "fusion.kappa"), (opts.fusion_iters, "fusion.iters"), (opts.sigma, "trials.sigma")):
        if value is not None:
            put(name, P.parse_values(name, value))
    for text in opts.clean:
        n, vals = P.parse_assignment(text if text.startswith("geometry.") else f"geometry.{text}")
        put(n, vals)
    for text in opts.param:
        put(*P.parse_assignment(text))
    if not grid:
        raise InputError("nothing to sweep: give --kappa, --fusion-iters, --clean, --sigma or --param")
    return grid


def run_sweep_cli(args: argparse.Namespace) -> int:
    from splattwin.cluster.sweep import SweepSpec, print_table, run_sweep, trial_options
    from splattwin.errors import InputError
    from splattwin.executor import make_executor
    from splattwin.options import from_args, given, merge
    from splattwin.robot.options import RobotOptions
    from splattwin.robot.trials import TrialSpec
    from splattwin.twin.manifest import Manifest

    opts = from_args(SweepOptions, args)
    opts.validate()
    grid = _grid(opts)
    if not (args.twin / "twin.json").is_file():
        from splattwin.twin.manifest import no_twin_yet

        raise InputError("not a twin folder (no twin.json)" + no_twin_yet(args.twin), args.twin)
    # the trials as the twin was built (its resolved config), the flags given here on top
    # (only the robot flags this command has: --sigma, --trials and --cluster.* are the sweep's own)
    given_robot = {k: v for k, v in given(args, RobotOptions).items() if k in SWEEP_ROBOT_FLAGS}
    robot = merge(trial_options(args.twin, Manifest.load(args.twin)), given_robot)
    robot.validate()
    if robot.task not in (None, "default") and not Path(robot.task).is_file():
        raise InputError("task file not found", robot.task)
    # sigma: the trials' pose error when the grid does not vary it
    trial = replace(TrialSpec.from_options(args.twin, robot), sigma=robot.sigma, sigma_yaw=robot.sigma_yaw)
    spec = SweepSpec(twin=args.twin, grid=grid, trials=opts.trials, masks=opts.masks, scene=opts.scene, trial=trial)
    with make_executor(opts.cluster) as ex:
        summary = run_sweep(spec, args.out, ex, progress=args.progress, resume=opts.resume)
    print_table(summary, summary.get("outputs"))
    return 1 if any(r.get("error") for r in summary["cells"]) else 0


def run_batch_cli(args: argparse.Namespace) -> int:
    from splattwin.cluster.batch import print_summary, run_batch
    from splattwin.errors import InputError
    from splattwin.executor import make_executor
    from splattwin.options import from_args
    from splattwin.pipeline.cli import resolve_options

    opts = from_args(BatchOptions, args)
    opts.validate()
    if args.from_stage:
        # a retried task would redo the stage again and again: redo a capture with `splattwin build --from`
        raise InputError("--from is not supported by batch (a retried task would redo the stage again); "
                         "use `splattwin build CAPTURE --out OUT/NAME --from STAGE` for one capture")
    build = resolve_options(args)
    if args.print_config:
        from splattwin.options import absolute_paths, print_yaml, to_dict

        print_yaml(to_dict(absolute_paths(build), "config"))
        return 0
    with make_executor(opts.cluster, cpus_per_task=opts.cpus_per_build, max_tasks=len(args.captures)) as ex:
        summary = run_batch(args.captures, args.out, build, ex, cpus=opts.cpus_per_build, gpus=opts.gpus_per_build,
                            until=args.until, progress=args.progress)
    print_summary(summary)
    return 0 if summary["failed"] == 0 else 1
