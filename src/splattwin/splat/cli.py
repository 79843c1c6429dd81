"""Sub-commands of the splat stage: `splattwin train` and `splattwin eval`."""

from __future__ import annotations

import argparse
from pathlib import Path

from splattwin.options import add_command, add_options, add_progress_flag, from_args
from splattwin.poses.options import HoldoutOptions
from splattwin.splat.config import DEVICES, TrainConfig


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "train", _train)
    p.add_argument("dataset", type=Path, help="dataset folder or file (any format `splattwin` reads)")
    p.add_argument("out", type=Path, help="output folder")
    add_options(p, TrainConfig)
    add_options(p, HoldoutOptions, prefix="holdout.", title="held-out views (kept out of training; see "
                                                        "splattwin.poses.holdout)")
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest checkpoint in OUT (refused, exit 2, when it was made with other "
                        "options or data)")
    p.add_argument("--max-frames", type=int, help="use at most this many frames of the dataset")

    e = add_command(sub, "eval", _eval)
    e.add_argument("splat", type=Path, help="training output folder or 3DGS .ply file")
    e.add_argument("--dataset", type=Path, required=True, help="dataset with (held-out) views")
    e.add_argument("--out", type=Path, default=None, help="output folder (default: <OUT>/eval or <ply dir>/eval)")
    e.add_argument("--resolution", type=int, help="as for train (default: the training one, recorded in train.json)")
    e.add_argument("--full-resolution", action="store_true", help="render at the full image size")
    e.add_argument("--device", choices=DEVICES, help="rasterizer device (default auto)")
    e.add_argument("--align-poses", action="store_true",
                   help="fit each held-out camera to its image first (for splats trained with --refine-poses)")
    add_progress_flag(e)


def _train(args: argparse.Namespace) -> int:
    """Train 3D Gaussians on a posed dataset (writes OUT/point_cloud.ply).

    Trains a 3D Gaussian Splatting model on DATASET (transforms.json, COLMAP, cameras.json, ...) and
    writes OUT/point_cloud.ply (standard 3DGS PLY), OUT/train.json and checkpoints."""
    from splattwin.capture import load_dataset
    from splattwin.splat.trainer import train

    from splattwin.frame_options import check_max_frames

    check_max_frames(args.max_frames)   # before anything is read (0 left no frame, -2 failed inside numpy)
    cfg = from_args(TrainConfig, args)
    from splattwin.lock import output_lock

    from splattwin.poses.holdout import apply_holdout

    from splattwin.capture.dataset import refuse_video

    refuse_video(args.dataset, "train")   # no poses: said before its frames would be extracted
    holdout = from_args(HoldoutOptions, args, prefix="holdout.")
    # the lock first: reading the dataset writes into OUT (a photo's transparent pixels get loss masks in
    # OUT/capture/frames/alpha_masks, as `build`'s TWIN/capture/frames), which another run may hold
    with output_lock(args.out):
        ds = load_dataset(args.dataset, max_frames=args.max_frames, frames_dir=args.out / "capture" / "frames")
        h = apply_holdout(ds, holdout)
        print(f"held-out views ({h.rule}): {', '.join(h.names) if h.names else 'none'}")
        res = train(ds, args.out, cfg, resume=args.resume)
    psnr = "unknown" if res.final_psnr is None else f"{res.final_psnr:.2f} dB"
    # wall_s: the training time of the result over the original run and resumes (see trainer)
    took = "training time unknown" if res.wall_s is None else f"{res.wall_s:.1f} s of training"
    if res.resumed_at_step is not None:
        took += (f" (resumed a finished run at step {res.resumed_at_step}: no step left)"
                 if res.resumed_at_step >= res.steps else f" (resumed at step {res.resumed_at_step})")
    print(f"{len(res.gaussians)} Gaussians, train PSNR {psnr}, {took} -> {res.ply_path}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    """Render held-out views: PSNR/SSIM and side-by-side images.

    Evaluates a trained splat (training folder OUT or a .ply) on DATASET's held-out views: PSNR and SSIM
    per view and mean (metrics.json) and side-by-side PNGs (ground truth | render | error)."""
    from splattwin.capture.dataset import refuse_video
    from splattwin.splat.eval import evaluate

    from splattwin.lock import output_lock
    from splattwin.paths import is_inside

    refuse_video(args.dataset, "eval")   # no poses: said before its frames would be extracted
    out = args.out
    if out is None:
        out = (args.splat if args.splat.is_dir() else args.splat.parent) / "eval"
    # one writer per folder (splattwin.lock): a training folder's lock when writing into it (a `train` still
    # running there holds it), else OUT's. Taken before the dataset is read: that writes loss masks for
    # transparent pixels into OUT/capture/frames/alpha_masks.
    with output_lock(args.splat if args.splat.is_dir() and is_inside(out, args.splat) else out):
        res = evaluate(args.splat, args.dataset, out, resolution=args.resolution, backend=args.device or "auto",
                       progress=args.progress, align_poses=args.align_poses,
                       full_resolution=args.full_resolution)
    for v in res.views:
        fix = f"  pose fit {v['pose_correction_deg']:.2f} deg / {_pose_length(v)}" if "pose_correction_deg" in v else ""
        print(f"{v['name']:>24s}  PSNR {v['psnr']:6.2f} dB  SSIM {v['ssim']:.4f}{fix}{_coverage_text(v)}")
    cov = {"covered_frac": res.mean_covered_frac, "psnr_covered": res.mean_psnr_covered,
           "psnr_uncovered": res.mean_psnr_uncovered}
    print(f"{'mean (' + res.split + ')':>24s}  PSNR {res.mean_psnr:6.2f} dB  SSIM {res.mean_ssim:.4f}"
          f"{_coverage_text(cov)}  -> {res.metrics_path}")
    return 0


def _pose_length(v: dict) -> str:
    """A view's pose correction (camera centre shift) in its unit: cm in metres; an unscaled dataset's
    SfM units said so (never as cm)."""
    if v.get("pose_correction_units", "m") == "m":
        return f"{100 * v.get('pose_correction', v.get('pose_correction_m', float('nan'))):.2f} cm"
    return f"{v['pose_correction']:.3g} units (SfM, unscaled)"


def _coverage_text(v: dict) -> str:
    """'  seen by the training views 78 % (PSNR 16.8 there, 13.0 elsewhere)' or '' without the figures."""
    import math

    frac = v.get("covered_frac")
    if frac is None or (isinstance(frac, float) and math.isnan(frac)):
        return ""
    fmt = lambda x: "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.1f}"  # noqa: E731
    return (f"  seen by the training views {100 * frac:.0f} % (PSNR {fmt(v.get('psnr_covered'))} there, "
            f"{fmt(v.get('psnr_uncovered'))} elsewhere)")
