"""`splattwin build` (photos → validated twin) and `splattwin demo` (the same on the embedded scene)."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.pipeline.build import STAGES


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--iters", type=int, default=3000, help="splat training iterations (default 3000)")
    p.add_argument("--resolution", type=int, default=1, help="training image downscale 1/2/4/8 or target width")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto", help="rasterizer backend")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--kappa", type=float, default=1.5, help="semantic consensus strictness, tau = N/kappa")
    p.add_argument("--from", dest="from_stage", choices=STAGES, default=None, help="redo from this stage on")
    p.add_argument("--until", choices=STAGES, default=None, help="stop after this stage")
    p.add_argument("--trials", type=int, default=0, help="extra robot trials with perturbed object poses")
    p.add_argument("--sigma", type=float, default=0.005, help="object pose error of the trials: per-axis standard deviation of x and y (m); yaw "
                        "sigma / 0.1 m rad")
    p.add_argument("--no-frames", action="store_true", help="do not render robot execution frames")


def register(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("build", help="photos → planning-ready twin: poses, splats, semantics, geometry, export",
                       description="Run the whole pipeline. Finished stages are skipped on a re-run (their inputs "
                                   "and options are hashed); --from redoes from a stage; a killed run resumes.")
    b.add_argument("input", type=Path, help="dataset: image folder, video, transforms.json, COLMAP, cameras.json, "
                                            "BOP scene, or TUM pose list + intrinsics")
    b.add_argument("--out", type=Path, required=True, help="twin folder to write")
    b.add_argument("--prompt", default=None, help='open-vocabulary objects, e.g. "blue box. yellow cube. toy hammer"')
    b.add_argument("--masks", type=Path, default=None, help="2D masks instead of --prompt (PNG dirs, COCO RLE, polygons, "
                                                                  "BOP mask_visib, per-instance files)")
    b.add_argument("--poses", choices=("auto", "known", "sfm", "robot"), default="auto")
    b.add_argument("--robot-poses", type=Path, default=None, help="T_base_ee per image (JSON/YAML)")
    b.add_argument("--hand-eye", type=Path, default=None, help="T_ee_cam (JSON/YAML)")
    b.add_argument("--marker-size", type=float, default=None, help="ArUco marker side (m) for metric scale")
    b.add_argument("--up", default="auto", choices=("auto", "keep", "+z", "-z", "+y", "-y", "+x", "-x"),
                   help="known poses: the world axis pointing up (--up=-z, --up=+y, ...); auto finds it (cameras, table plane) and turns "
                        "z-down worlds z up; keep = trust the poses")
    b.add_argument("--task", default=None, help="robot task YAML to validate in physics ('default' = paper's task)")
    _common(b)
    b.set_defaults(func=_build)

    d = sub.add_parser("demo", help="the whole pipeline on the embedded tabletop scene, the three-step task "
                                    "in physics, and the HTML report")
    d.add_argument("--out", type=Path, default=Path("demo_out"))
    d.add_argument("--width", type=int, default=320)
    d.add_argument("--height", type=int, default=240)
    d.add_argument("--views", type=int, default=15)
    d.add_argument("--heldout", type=int, default=5)
    _common(d)
    d.set_defaults(func=_demo)


def _options(args: argparse.Namespace, **kw):
    from splattwin.pipeline.build import BuildOptions

    return BuildOptions(iters=args.iters, resolution=args.resolution, device=args.device, seed=args.seed,
                        kappa=args.kappa, trials=args.trials, sigma=args.sigma, render_frames=not args.no_frames, **kw)


def _build(args: argparse.Namespace) -> int:
    from splattwin.pipeline.build import build

    opts = _options(args, input=str(args.input), poses=args.poses,
                    robot_poses=str(args.robot_poses) if args.robot_poses else None,
                    hand_eye=str(args.hand_eye) if args.hand_eye else None, marker_size=args.marker_size, up=args.up,
                    masks=str(args.masks) if args.masks else None, prompt=args.prompt, task=args.task)
    ctx = build(args.out, opts, from_stage=args.from_stage, until=args.until)
    _print_headline(ctx)
    return _exit_code(ctx)


def _exit_code(ctx) -> int:
    """2 when the robot task could not run (bad input), 1 when it ran and failed, else 0."""
    robot = ctx.results.get("robot") or {}
    if robot.get("error"):
        return 2
    return 0 if robot.get("success", True) else 1


def _demo(args: argparse.Namespace) -> int:
    from splattwin.pipeline.build import build

    scene = {"seed": args.seed, "width": args.width, "height": args.height, "views": args.views, "heldout": args.heldout}
    opts = _options(args, scene=scene, poses="known", task="default")
    ctx = build(args.out, opts, from_stage=args.from_stage, until=args.until)
    _print_headline(ctx)
    return _exit_code(ctx)


def _print_headline(ctx) -> None:
    import json

    from rich.console import Console

    con = Console()
    r = ctx.results
    if "splats" in r and r["splats"]:
        s = r["splats"]
        con.print(f"reconstruction: {s['gaussians']} Gaussians, {s['split']} PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.4f}")
    fj = ctx.path("semantics/fusion.json")
    if fj.is_file():
        f = json.loads(fj.read_text())
        if f.get("miou_heldout") is not None:
            con.print(f"semantics: held-out mIoU {f['miou_heldout']:.3f}")
    gj = ctx.path("geometry_metrics.json")
    if gj.is_file():
        g = json.loads(gj.read_text())
        if g:
            con.print("geometry: F1@5mm " + ", ".join(f"{k} {v['f1']:.3f}" for k, v in g.items()))
    if r.get("robot", {}).get("error"):
        con.print(f"[red]robot task not run: {r['robot']['error']}[/]")
    elif r.get("robot"):
        con.print(f"robot task: {'[green]success[/]' if r['robot']['success'] else '[red]failure[/]'}")
    con.print(f"total {sum(ctx.timings.values()):.0f} s; twin: {ctx.out / 'twin.json'}")
    if r.get("report"):
        con.print(f"report: {ctx.out / r['report']['report'][1:]}")
