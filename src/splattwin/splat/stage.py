"""The splat stage as the pipeline runs it: `run(SplatInputs, TrainConfig) -> SplatResult`.

Reads the posed dataset (TWIN/poses/transforms.json); writes OUT/point_cloud.ply, OUT/train.json,
OUT/checkpoints/ (a killed run resumes from them; a checkpoint of other options or data is not resumed,
training starts over; with fresh=True, `build --from` this stage or an earlier one, training starts over
and the old checkpoints are removed) and OUT/eval/ (held-out PSNR/SSIM, side-by-side pictures).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from splattwin.splat.config import TrainConfig


@dataclass
class SplatInputs:
    transforms: Path   # posed dataset
    out_dir: Path      # the stage's folder (TWIN/splat)


@dataclass
class SplatResult:
    ply: Path          # standard 3DGS PLY (twin frame, metres)
    psnr: float        # mean over the evaluation split (dB)
    ssim: float
    split: str         # "heldout", or "train" when the dataset has no held-out views
    gaussians: int
    train_s: float


def run(inputs: SplatInputs, options: TrainConfig, *, progress: bool = True, fresh: bool = False) -> SplatResult:
    from splattwin.capture import load_dataset
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import train

    ds = load_dataset(inputs.transforms)
    res = train(ds, inputs.out_dir, replace(options, progress=progress), resume=not fresh,
                on_mismatch="restart")
    # the training folder (train.json): held-out views rendered at the training resolution by default
    ev = evaluate(inputs.out_dir, ds, out_dir=inputs.out_dir / "eval", progress=progress,
                  full_resolution=options.eval_full_resolution)
    return SplatResult(ply=res.ply_path, psnr=ev.mean_psnr, ssim=ev.mean_ssim, split=ev.split,
                       gaussians=len(res.gaussians), train_s=res.wall_s)
