"""Sub-commands of the splat stage: `splattwin train` and `splattwin eval`."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

# Mirrors splattwin.splat.trainer.TrainConfig (not imported here: it pulls in torch, and every
# `splattwin --help` builds this parser); a test checks they agree.
TRAIN_DEFAULTS = SimpleNamespace(iters=3000, init_points=0, max_gaussians=0, checkpoint_every=500,
                                 pose_lr=5e-3, pose_start=0.0, depth_lambda=0.0,
                                 opacity_reg=0.0)


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    d = TRAIN_DEFAULTS
    p = sub.add_parser("train", help="train 3D Gaussians on a posed dataset (writes OUT/point_cloud.ply)",
                       description="Train a 3D Gaussian Splatting model on DATASET (transforms.json, COLMAP, "
                                   "cameras.json, ...) and write OUT/point_cloud.ply (standard 3DGS PLY), "
                                   "OUT/train.json and checkpoints.")
    p.add_argument("dataset", type=Path, help="dataset folder or file (any format `splattwin` reads)")
    p.add_argument("out", type=Path, help="output folder")
    p.add_argument("--iters", type=int, default=d.iters, help=f"training steps (default {d.iters})")
    p.add_argument("--resolution", type=int, default=1,
                   help="1/2/4/8 divide the image size, larger values are a target width in px, "
                        "-1 caps the width at 1600 (default 1)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="rasterizer device: cuda uses gsplat (default auto)")
    p.add_argument("--init", choices=["auto", "sfm", "depth", "random"], default="auto",
                   help="initial point cloud: dataset/SfM points, back-projected depth maps, or random "
                        "(default auto: the first available in that order)")
    p.add_argument("--init-points", type=int, default=d.init_points,
                   help="at most this many initial Gaussians (default 0: 24000 for 320x240 images, scaled "
                        "with the square root of the pixel count above)")
    p.add_argument("--sh-degree", type=int, default=3, choices=[0, 1, 2, 3], help="maximum SH degree")
    p.add_argument("--max-gaussians", type=int, default=d.max_gaussians,
                   help="cap on the Gaussian count (default 0: 28000 for 320x240 images, scaled with the "
                        "square root of the pixel count above)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                   help=f"steps between checkpoints (0: none; default {d.checkpoint_every})")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in OUT")
    p.add_argument("--refine-poses", action="store_true",
                   help="learn a per-camera SE(3) pose correction jointly (writes OUT/refined_poses.json)")
    p.add_argument("--pose-lr", type=float, default=d.pose_lr,
                   help=f"Adam learning rate of the pose corrections (default {d.pose_lr:g})")
    p.add_argument("--pose-start", type=float, default=d.pose_start,
                   help=f"fraction of the run before the poses start to move (default {d.pose_start:g})")
    p.add_argument("--depth-lambda", type=float, default=d.depth_lambda,
                   help="weight of a relative depth loss on frames with depth maps (default 0: off)")
    p.add_argument("--opacity-reg", type=float, default=d.opacity_reg,
                   help="weight of a mean-opacity penalty, as gsplat's opacity_reg (default 0: off; 0.05 gave "
                        "+0.27 dB / +0.009 SSIM on the embedded scene, ~15 %% slower)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most this many frames of the dataset")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)

    e = sub.add_parser("eval", help="render held-out views: PSNR/SSIM and side-by-side images",
                       description="Evaluate a trained splat (training folder OUT or a .ply) on DATASET's "
                                   "held-out views: PSNR and SSIM per view and mean (metrics.json) and "
                                   "side-by-side PNGs (ground truth | render | error).")
    e.add_argument("splat", type=Path, help="training output folder or 3DGS .ply file")
    e.add_argument("--dataset", type=Path, required=True, help="dataset with (held-out) views")
    e.add_argument("--out", type=Path, default=None, help="output folder (default: <OUT>/eval or <ply dir>/eval)")
    e.add_argument("--resolution", type=int, default=None, help="as for train (default: the training one)")
    e.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    e.add_argument("--align-poses", action="store_true",
                   help="fit each held-out camera to its image first (for splats trained with --refine-poses)")
    e.add_argument("--no-progress", action="store_true")
    e.set_defaults(func=_eval)


def _train(args: argparse.Namespace) -> int:
    from splattwin.capture import load_dataset
    from splattwin.splat.trainer import TrainConfig, train

    cfg = TrainConfig(iters=args.iters, resolution=args.resolution, device=args.device, init=args.init,
                      init_points=args.init_points, sh_degree=args.sh_degree, seed=args.seed,
                      checkpoint_every=args.checkpoint_every, refine_poses=args.refine_poses,
                      pose_lr=args.pose_lr, pose_start=args.pose_start, depth_lambda=args.depth_lambda,
                      opacity_reg=args.opacity_reg,
                      max_gaussians=args.max_gaussians, progress=not args.no_progress)
    ds = load_dataset(args.dataset, max_frames=args.max_frames)
    res = train(ds, args.out, cfg, resume=args.resume)
    print(f"{len(res.gaussians)} Gaussians, train PSNR {res.final_psnr:.2f} dB, {res.wall_s:.1f} s -> {res.ply_path}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from splattwin.splat.eval import evaluate

    out = args.out
    if out is None:
        out = (args.splat if args.splat.is_dir() else args.splat.parent) / "eval"
    res = evaluate(args.splat, args.dataset, out, resolution=args.resolution, backend=args.device,
                   progress=not args.no_progress, align_poses=args.align_poses)
    for v in res.views:
        fix = (f"  pose fit {v['pose_correction_deg']:.2f} deg / {100 * v['pose_correction_m']:.2f} cm"
               if "pose_correction_deg" in v else "")
        print(f"{v['name']:>24s}  PSNR {v['psnr']:6.2f} dB  SSIM {v['ssim']:.4f}{fix}")
    print(f"{'mean (' + res.split + ')':>24s}  PSNR {res.mean_psnr:6.2f} dB  SSIM {res.mean_ssim:.4f}  -> {res.metrics_path}")
    return 0
