"""`splattwin sweep TWIN ...` and `splattwin batch CAPTURE... --out DIR`, and the executor flags they share
with `splattwin plan` (`--executor local|ray`, `--ray-address`, `--max-retries`)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from splattwin.cluster.executor import ADDRESS_ENV, DEFAULT_MAX_RETRIES, EXECUTORS

DEFAULT_SIGMA = 0.005   # m, the trials' pose error when the grid does not vary it (as `splattwin plan`)


def add_executor_args(p: argparse.ArgumentParser) -> None:
    """The flags that pick where tasks run (the command keeps its own --workers)."""
    g = p.add_argument_group("where the tasks run")
    g.add_argument("--executor", choices=EXECUTORS, default=None,
                   help="local: a process pool on this machine (the default unless a Ray address is given); ray: "
                        "a Ray cluster (pip install 'splattwin[ray]'), a local one unless --ray-address or $%s "
                        "names one" % ADDRESS_ENV)
    g.add_argument("--ray-address", default=None, metavar="ADDRESS",
                   help="Ray cluster to run on: 'auto' (the cluster this node belongs to), HOST:6379, or "
                        "ray://HOST:10001 (default: $%s; either implies --executor ray). Twins and outputs must be on "
                        "a filesystem every node mounts at the same path" % ADDRESS_ENV)
    g.add_argument("--max-retries", type=int, default=DEFAULT_MAX_RETRIES,
                   help=f"times a task is run again after its worker process died (default {DEFAULT_MAX_RETRIES})")


def executor_choice(executor: str | None, ray_address: str | None) -> tuple[str, str | None]:
    """(kind, address) from --executor / --ray-address / $SPLATTWIN_RAY_ADDRESS: an address (flag or
    environment) means Ray unless --executor local says otherwise; no address with ray: a local Ray."""
    env = os.environ.get(ADDRESS_ENV) or None
    if executor == "local":
        return "local", ray_address            # make_executor refuses an explicit --ray-address with local
    if executor == "ray" or ray_address or env:
        return "ray", ray_address or env
    return "local", None


def executor_from_args(args: argparse.Namespace, workers: int | None = None):
    """The Executor the flags ask for (the caller closes it)."""
    from splattwin.cluster.executor import make_executor

    kind, address = executor_choice(args.executor, args.ray_address)
    return make_executor(kind, address=address, workers=workers, max_retries=args.max_retries)


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "sweep", help="parameter grid over a twin (kappa, fusion rounds, cleaning options, sigma), each cell "
                      "validated by trials; one results table",
        description="Re-run semantic fusion, geometry cleaning and Monte-Carlo trials of the task for every cell "
                    "of a parameter grid over a built twin. Each value list is comma-separated; the grid is their "
                    "product. Parameters map by field name onto FusionOptions (fusion.*), GeometryOptions "
                    "(geometry.*) and the trials (trials.sigma, trials.sigma_yaw, trials.planner, trials.in_hand). "
                    "Writes OUT/sweep.csv, OUT/sweep.json, OUT/sweep.png and prints the table; a re-run resumes. "
                    "Exit code 0 when every cell ran, 1 when a cell could not run, 2 on bad input.")
    s.add_argument("twin", type=Path, help="twin folder built by `splattwin build` / `demo` (with twin.json)")
    s.add_argument("--out", type=Path, required=True, help="sweep folder to write")
    s.add_argument("--kappa", default=None, help="fusion.kappa values, e.g. 1.2,1.5,2.0 (consensus tau = N/kappa)")
    s.add_argument("--fusion-iters", default=None, help="fusion.iters values (refinement rounds), e.g. 1,3")
    s.add_argument("--clean", action="append", default=[], metavar="NAME=V1,V2",
                   help="a geometry cleaning option (GeometryOptions field) and its values, e.g. "
                        "min_opacity=0.05,0.1 or dbscan_eps=0.01,0.02 (repeatable)")
    s.add_argument("--sigma", default=None,
                   help="trials.sigma values: per-axis standard deviation of the objects' x/y error (m), e.g. "
                        "0.003,0.005,0.01 (default %g)" % DEFAULT_SIGMA)
    s.add_argument("--param", action="append", default=[], metavar="TARGET.FIELD=V1,V2",
                   help="any other sweep parameter, e.g. fusion.depth_tol=0.01,0.02 or trials.sigma_yaw=0.02,0.05")
    s.add_argument("--trials", type=int, default=20, help="trials per cell (default 20)")
    s.add_argument("--task", type=Path, default=None, help="task YAML (default: the paper's three steps)")
    s.add_argument("--masks", type=Path, default=None,
                   help="2D masks for the fusion cells (default: the ones the twin carries: its embedded scene or "
                        "semantics/masks2d)")
    s.add_argument("--scene", type=Path, default=None,
                   help="embedded-scene folder with ground truth for F1 (default TWIN/scene when present)")
    s.add_argument("--base-pose", default="-0.5,0,0,0", help="robot base x,y,z,yaw (m, rad)")
    s.add_argument("--planner", default="RRTConnect")
    s.add_argument("--seed", type=int, default=0, help="trials use seeds seed+1 .. seed+N in every cell")
    s.add_argument("--workers", type=int, default=None,
                   help="local: processes (default CPU count); ray without an address: CPUs of the local Ray")
    s.add_argument("--no-resume", action="store_true", help="redo every cell (default: reuse finished work)")
    add_executor_args(s)
    s.set_defaults(func=run_sweep_cli)

    b = sub.add_parser(
        "batch", help="build many captures (one twin each) on the executor; one summary CSV/HTML",
        description="Run `splattwin build` for every capture into OUT/<name>/ (reconstruction as one task, on a GPU "
                    "when the cluster has one; the rest of the build as a second task), then write OUT/summary.csv, "
                    "OUT/summary.html and OUT/batch.json with each capture's figures and failures. A failed "
                    "capture is reported, not fatal; a re-run resumes every capture. Exit code 0 when every "
                    "capture was built, 1 when some failed, 2 on bad input.")
    b.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE",
                   help="datasets: image folders, videos, transforms.json, COLMAP or cameras.json")
    b.add_argument("--out", type=Path, required=True, help="folder of the twins and the summary")
    b.add_argument("--prompt", default=None, help='open-vocabulary objects, e.g. "blue box. yellow cube. toy hammer"')
    b.add_argument("--poses", choices=("auto", "known", "sfm", "robot"), default="auto")
    b.add_argument("--marker-size", type=float, default=None, help="ArUco marker side (m) for metric scale")
    b.add_argument("--task", default=None, help="robot task YAML to validate on every twin ('default' = paper's task)")
    b.add_argument("--cpus-per-build", type=float, default=2.0,
                   help="CPUs each build task reserves on a Ray node and the threads it uses (default 2)")
    b.add_argument("--gpus-per-build", type=float, default=None,
                   help="GPUs of each reconstruction task (default: 1 when the Ray cluster has GPUs, else 0)")
    b.add_argument("--workers", type=int, default=1,
                   help="local: builds at once (default 1: a build uses every core); ray without an address: "
                        "CPUs of the local Ray")
    from splattwin.pipeline.cli import _common   # the same build flags as `splattwin build`

    _common(b)
    add_executor_args(b)
    b.set_defaults(func=run_batch_cli)


def _grid(args: argparse.Namespace) -> dict[str, list]:
    from splattwin.cluster import params as P
    from splattwin.errors import InputError

    grid: dict[str, list] = {}

    def put(name: str, values: list) -> None:
        if name in grid:
            raise InputError(f"sweep parameter {name} given twice")
        grid[name] = values

    for flag, name in (("kappa", "fusion.kappa"), ("fusion_iters", "fusion.iters"), ("sigma", "trials.sigma")):
        v = getattr(args, flag)
        if v is not None:
            put(name, P.parse_values(name, v))
    for text in args.clean:
        n, vals = P.parse_assignment(text if text.startswith("geometry.") else f"geometry.{text}")
        put(n, vals)
    for text in args.param:
        put(*P.parse_assignment(text))
    if not grid:
        raise InputError("nothing to sweep: give --kappa, --fusion-iters, --clean, --sigma or --param")
    return grid


def run_sweep_cli(args: argparse.Namespace) -> int:
    from splattwin.robot.render import prefer_egl

    prefer_egl()
    from splattwin.cluster.sweep import SweepSpec, print_table, run_sweep
    from splattwin.errors import InputError
    from splattwin.robot.trials import TrialSpec
    from splattwin.robot.world import BasePose

    grid = _grid(args)
    if args.task is not None and not args.task.is_file():
        raise InputError("task file not found", args.task)
    spec = SweepSpec(twin=args.twin, grid=grid, trials=args.trials, masks=args.masks, scene=args.scene,
                     trial=TrialSpec(twin_dir=str(args.twin), task_path=str(args.task) if args.task else None,
                                     base=BasePose.parse(args.base_pose), seed=args.seed, planner=args.planner,
                                     sigma=DEFAULT_SIGMA))
    with executor_from_args(args, args.workers) as ex:
        summary = run_sweep(spec, args.out, ex, resume=not args.no_resume)
    print_table(summary, summary.get("outputs"))
    return 1 if any(r.get("error") for r in summary["cells"]) else 0


def run_batch_cli(args: argparse.Namespace) -> int:
    from splattwin.cluster.batch import print_summary, run_batch
    from splattwin.errors import InputError
    from splattwin.pipeline.cli import _options

    if args.cpus_per_build <= 0:
        raise InputError(f"--cpus-per-build must be > 0, got {args.cpus_per_build}")
    if args.from_stage:
        # a retried task would redo the stage again and again: redo a capture with `splattwin build --from`
        raise InputError("--from is not supported by batch (a retried task would redo the stage again); "
                         "use `splattwin build CAPTURE --out OUT/NAME --from STAGE` for one capture")
    opts = _options(args, poses=args.poses, marker_size=args.marker_size, prompt=args.prompt, task=args.task)
    with executor_from_args(args, args.workers) as ex:
        summary = run_batch(args.captures, args.out, opts, ex, cpus=args.cpus_per_build, gpus=args.gpus_per_build,
                            until=args.until)
    print_summary(summary)
    return 0 if summary["failed"] == 0 else 1
