"""`splattwin build` (photos → validated twin) and `splattwin demo` (the same on the embedded scene).

Every stage option is a flag here, generated from the stage's options dataclass (`--splat.depth-lambda`,
`--semantics.fusion.kappa`, ...; the common ones also have short names: `--iters`, `--kappa`, `--task`),
and can come from a config file (`--config twin.yaml`, nested like the flags); flags override the file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.options import add_config_flag, add_options, given, load_config, merge

# demo: steps of the object refinement (`splattwin.playback.refine`). Demo twin of seed 0 trained
# antialiased, moved objects' PSNR after the three-step task (bench/photoreal.py, held-out views): 21.03 dB
# without, 21.66 with 800 or 1500 steps (4x budget), 21.64 with an 8x budget; 800 steps ~100 s on 2 busy cores
DEMO_REFINE_ITERS = 800


def add_build_flags(p: argparse.ArgumentParser, demo: bool = False) -> None:
    """The flags of `build` (and `demo`, and `batch`): config file, --seed, --from/--until, --no-progress, and
    every stage option generated from `BuildOptions` (read back with `resolve_options`)."""
    from splattwin.pipeline.options import STAGES, BuildOptions

    add_config_flag(p)
    p.add_argument("--seed", type=int, help="seed of every stage (sets each --<stage>.seed)")
    p.add_argument("--from", dest="from_stage", choices=STAGES,
                   help="redo this stage and every later one from scratch (splats: retrained, checkpoints not resumed)")
    p.add_argument("--until", choices=STAGES, help="stop after this stage")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    add_options(p, BuildOptions, build=True, exclude=("input",) if demo else ("input", "scene"))


def register(sub: argparse._SubParsersAction) -> None:
    # a short usage: argparse's own lists all ~200 generated flags, burying an error message under them
    b = sub.add_parser("build", usage="%(prog)s [INPUT] --out TWIN [--config FILE.yaml] [--from STAGE] [--until STAGE] "
                                      "[--no-progress] [--STAGE.OPTION VALUE ...] (all options: --help)",
                       help="photos → planning-ready twin: poses, splats, semantics, geometry, export",
                       description="Run the whole pipeline. Finished stages are skipped on a re-run (their inputs "
                                   "and options are hashed); --from redoes from a stage; a killed run resumes. "
                                   "Options: flags, or a YAML file (--config) nested like them; flags win.")
    b.add_argument("input", type=Path, nargs="?", help="dataset: image folder, video, transforms.json, COLMAP, "
                                                       "cameras.json, BOP scene, or TUM pose list + intrinsics (or "
                                                       "`input:` in the config file)")
    b.add_argument("--out", type=Path, help="twin folder to write (required)")
    add_build_flags(b)
    b.set_defaults(func=_build)

    d = sub.add_parser("demo", usage="%(prog)s [--out TWIN] [--config FILE.yaml] [--from STAGE] [--until STAGE] "
                                     "[--STAGE.OPTION VALUE ...] (all options: --help)",
                       help="the whole pipeline on the embedded tabletop scene, the three-step task "
                                    "in physics, and the HTML report")
    d.add_argument("--out", type=Path, default=Path("demo_out"), help="twin folder to write (default demo_out)")
    add_build_flags(d, demo=True)
    d.set_defaults(func=_demo)


def resolve_options(args: argparse.Namespace, demo: bool = False):
    """BuildOptions of a command line: the demo's or the built-in defaults, then the config file, then
    --seed, then the flags given."""
    from splattwin.pipeline.options import BuildOptions
    from splattwin.playback.options import RefineOptions
    from splattwin.poses.options import PoseOptions
    from splattwin.robot.options import RobotOptions
    from splattwin.scene.options import SceneOptions
    from splattwin.splat.config import TrainConfig

    opts = BuildOptions()
    if demo:  # the embedded scene as input, its poses as known, the paper's task
        # splats trained antialiased and the objects refined (bench/photoreal.py on seed 0: held-out 32.01 ->
        # 34.10 dB from the mode, 36.31 with its low-pass at Mip-Splatting's 0.1 instead of 0.3; moved
        # objects after the task 20.99 -> 21.66 dB from mode and refinement)
        opts = BuildOptions(scene=SceneOptions(), poses=PoseOptions(method="known"), robot=RobotOptions(task="default"),
                            splat=TrainConfig(rasterize_mode="antialiased"), refine=RefineOptions(iters=DEMO_REFINE_ITERS))
    if args.config is not None:
        opts = load_config(args.config, BuildOptions, base=opts)
    if args.seed is not None:
        opts = opts.with_seed(args.seed)
    opts = merge(opts, given(args, BuildOptions))
    if not demo and getattr(args, "input", None) is not None:
        opts = merge(opts, {"input": str(args.input)})
    return opts


def _run(args: argparse.Namespace, demo: bool) -> int:
    from splattwin.errors import InputError
    from splattwin.options import absolute_paths, print_yaml, to_dict
    from splattwin.pipeline.build import build

    opts = resolve_options(args, demo)
    if args.print_config:
        print_yaml(to_dict(absolute_paths(opts), "config"))
        return 0
    if args.out is None:
        raise InputError("--out TWIN is required: the twin folder to write")
    if not demo and opts.input is None:
        raise InputError("no input: give the dataset (splattwin build INPUT --out TWIN) or `input:` in --config")
    ctx = build(args.out, opts, from_stage=args.from_stage, until=args.until, progress=args.progress)
    _print_headline(ctx)
    return _exit_code(ctx)


def _build(args: argparse.Namespace) -> int:
    return _run(args, demo=False)


def _demo(args: argparse.Namespace) -> int:
    return _run(args, demo=True)


def _exit_code(ctx) -> int:
    """2 when the robot task could not run (bad input) or ran but its real-arm files were refused (outside
    the named robot's limits, or objects moved before the robot acted: `plan` exits 2 alike), 1 when it ran
    and failed, else 0."""
    robot = ctx.results.get("robot") or {}
    if robot.get("error") or robot.get("export_error"):
        return 2
    return 0 if robot.get("success", True) else 1


def _gt_placement(twin_json: Path) -> str:
    """How the ground truth was placed for the figures (twin.json config.ground_truth, `twin.stage.gt_alignment`),
    as a suffix of the summary's geometry line; "" when not recorded."""
    from splattwin.errors import InputError
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    try:   # bounded; deep nesting or bad JSON leaves the suffix out rather than a traceback after the build
        gt = read_json(twin_json, max_bytes=MAX_RECORD_BYTES).get("config", {}).get("ground_truth") or {}
    except (InputError, OSError, AttributeError):
        return ""
    how = gt.get("placement") if isinstance(gt, dict) else None
    if how == "robot_base":
        off = gt.get("global_offset_m")
        return (" (ground truth placed by scene.json's robot base" + (f"; twin objects {off * 1000:.1f} mm off it on "
                "average" if isinstance(off, (int, float)) else "") + ")")
    if how == "centre_fit":
        return " (ground truth aligned by object centres: shape only, a global offset is not measured)"
    return ""


def _record(path: Path) -> dict | None:
    """A stage's JSON record for the headline, or None when it is missing, unreadable, over the record limit or
    not an object. Up-to-date stages are skipped, so these may be files of a received twin, not this run's."""
    from splattwin import io

    doc = io.read_record(path)
    return doc if isinstance(doc, dict) else None


def _robot_line(ctx) -> str:
    """The headline's robot line: the task's outcome in simulation and whether the real-arm files were
    written (robot/program.json named), else why not (results.json `real_robot`), said once."""
    from rich.markup import escape

    rec = ctx.results["robot"]
    res = _record(ctx.path("robot/results.json")) or {}
    real = res.get("real_robot") if isinstance(res.get("real_robot"), dict) else {}
    if rec.get("success") and not rec.get("export_error") and real.get("written"):
        prog = ctx.path("robot/program.json")
        return (f"robot task: [green]success[/]; real arm: {escape(str(prog))} (arm phases and blocking gripper "
                f"actions)")
    head = ("[red]success in simulation, but no files for the real arm[/]" if rec.get("success")
            else "[red]failure[/], no files for the real arm")
    why = rec.get("export_error") or real.get("reason")
    return f"robot task: {head}" + (f": {escape(str(why))}" if why else "")


def _total(ctx) -> str:
    """What this run took, wall clock (pre-flight and report included). ctx.timings of skipped stages are
    their earlier runs' seconds: a fully skipped re-run (0.3 s) used to print their sum. Beside it the
    report's one stage-time figure (`report.build.stage_time_sum`: the stages' recorded seconds without
    the report's), named as the report names it: the two totals differed unexplained (68 s here, 48.5 s
    there). Without a run time (a context not made by run_stages): that figure alone."""
    from splattwin.report.build import stage_time_sum

    stages = stage_time_sum(ctx.timings)
    if ctx.wall_s is None:
        return f"stage time, sum {stages:.1f} s"
    took = f"{ctx.wall_s:.1f} s" if ctx.wall_s < 10 else f"{ctx.wall_s:.0f} s"
    n = len(ctx.skipped)
    if n == 0 and "report" not in ctx.timings:
        # --until before the report (`--until splats`, the build of a capture without masks): it said
        # "pre-flight and report included" though no report was written
        return (f"total {took} wall clock, pre-flight included (stage time, sum: {stages:.1f} s; no report: "
                f"stopped before it, `splattwin report {ctx.out}` writes one)")
    if n == 0:
        return (f"total {took} wall clock, pre-flight and report included (the report's stage time, sum: "
                f"{stages:.1f} s)")
    if n == len(ctx.timings):
        return (f"total {took} wall clock (all {n} stages up to date, skipped; the report's stage time, sum: "
                f"{stages:.1f} s, is the runs' that made them)")
    return (f"total {took} wall clock ({n} of {len(ctx.timings)} stages up to date, skipped: "
            f"{', '.join(ctx.skipped)}; the report's stage time, sum: {stages:.1f} s, counts them at their "
            f"earlier runs' seconds)")


def _not_run_after(ctx) -> str:
    """"stages semantics..report" : the stages after the last one this run ran or found up to date."""
    from splattwin.pipeline.options import STAGES

    done = [i for i, n in enumerate(STAGES) if n in ctx.results]
    later = list(STAGES[(max(done) + 1) if done else 0:])
    if not later:
        return "no stage"
    return f"stage {later[0]}" if len(later) == 1 else f"stages {later[0]}..{later[-1]}"


def _print_headline(ctx) -> None:
    import json

    from splattwin.console import console
    from splattwin.wording import plural

    con = console()
    r = ctx.results
    if "splats" in r and r["splats"]:
        s = r["splats"]
        masked = ""
        # held-out figures over the pixels the capture's loss masks keep (metrics.json loss_masks)
        lm = (_record(ctx.path("splat/eval/metrics.json")) or {}).get("loss_masks")
        masked = " (over loss-masked pixels)" if isinstance(lm, dict) and lm.get("applied") else ""
        con.print(f"reconstruction: {s['gaussians']} Gaussians, {s['split']} PSNR {s['psnr']:.2f} dB, "
                  f"SSIM {s['ssim']:.4f}{masked}")
    # only stages this run ran or found up to date (ctx.results): after `--until splats` the semantics and
    # twin of an earlier build are still on disk, but nothing vouches that they match the new splats
    fj = ctx.path("semantics/fusion.json")
    f = _record(fj) if "semantics" in r else None
    if f:
        if f.get("miou_heldout") is not None:
            con.print(f"semantics: held-out mIoU {f['miou_heldout']:.3f}")
        elif f.get("miou_heldout_masks") is not None:
            n = len(f.get('miou_heldout_masks_views', []))
            con.print(f"semantics: held-out mIoU {f['miou_heldout_masks']:.3f} against the 2D masks of "
                      f"{plural(n, 'held-out view')} (not used by the fusion)")
    gj = ctx.path("geometry_metrics.json")
    g = _record(gj) if "twin" in r else None
    if g:
            con.print("geometry: F1@5mm " + ", ".join(f"{k} {v['f1']:.3f}" for k, v in g.items())
                      + _gt_placement(ctx.out / "twin.json"), highlight=False)
    if r.get("robot", {}).get("error"):
        con.print(f"[red]robot task not run: {r['robot']['error']}[/]")
    elif r.get("robot"):
        con.print(_robot_line(ctx), highlight=False)
    twin = ctx.out / "twin.json"
    # --until before the twin stage: name the folder, not a twin.json that is not there (or is an earlier
    # build's: kept, with the later stages' caches, for the next run to resume from)
    if "twin" in r and twin.is_file():
        where = f"twin: {twin}"
    elif twin.is_file():
        later = _not_run_after(ctx)
        where = (f"outputs in {ctx.out} (twin.json there is from an earlier build: "
                 f"{later} did not run this time; run build again without --until to update it)")
    else:
        where = f"outputs in {ctx.out} (no twin.json: stopped before the twin stage)"
    con.print(f"{_total(ctx)}; {where}")
    if r.get("report"):
        con.print(f"report: {ctx.out / r['report']['report'][1:]}")
