"""The splat stage as the pipeline runs it: `run(SplatInputs, TrainConfig) -> SplatResult`.

Reads the posed dataset (TWIN/poses/transforms.json); writes OUT/point_cloud.ply, OUT/train.json,
OUT/checkpoints/ (a killed run resumes from them; a checkpoint of other options or data is not resumed,
training starts over; with fresh=True, `build --from` this stage or an earlier one, training starts over
and the old checkpoints are removed), OUT/trained_on.json (what the splats were trained on: when only the
frame changed since, e.g. the same build given --known-length, they are moved into the new frame instead of
trained again, `splattwin.splat.rescale`) and OUT/eval/ (held-out PSNR/SSIM, side-by-side pictures).

With pose refinement (`refine_poses`) the held-out views are evaluated with their poses aligned to their
images first (the splats fixed: `eval.evaluate(align_poses=True)`; the training poses were corrected, the
held-out ones, which share their errors, were not): metrics.json records the aligned figure as the headline
and the as-given one beside it. OUT/refined_poses.json then holds the refined training poses and the aligned
held-out ones (`splattwin.splat.refined_poses`), which the later stages read instead of the capture's
(poses/transforms.json is kept as it is); `SplatResult.refined_poses` names it. Without refinement there is
no such file and evaluation uses the poses as given.
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
    # with pose refinement: the refined training poses and aligned held-out ones (OUT/refined_poses.json), and
    # the held-out PSNR at the poses as given (psnr is then the aligned figure)
    refined_poses: Path | None = None
    psnr_as_given: float | None = None


def _units(transforms: Path) -> str:
    """The posed dataset's frame units for the log: "metres", or "" (an unscaled frame or none recorded)."""
    from splattwin.errors import InputError
    from splattwin.poses.twin_frame import frame_beside

    try:
        frame = frame_beside(transforms)
    except InputError:
        return ""
    return "metres" if frame is not None and frame.scaled else ""


def run(inputs: SplatInputs, options: TrainConfig, *, progress: bool = True, fresh: bool = False) -> SplatResult:
    from splattwin.capture import load_dataset
    from splattwin.splat import refined_poses, rescale
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import train

    ds = load_dataset(inputs.transforms)
    moved = None if fresh else rescale.try_rescale(ds, inputs.out_dir, options, _units(inputs.transforms))
    if moved is None:
        res = train(ds, inputs.out_dir, replace(options, progress=progress), resume=not fresh,
                    on_mismatch="restart")
        ply, gaussians, train_s = res.ply_path, len(res.gaussians), res.wall_s
    else:   # only the frame changed (e.g. --known-length given): the trained splats moved into it
        ply, gaussians, train_s = inputs.out_dir / "point_cloud.ply", moved.gaussians, moved.train_s
    rescale.record(inputs.out_dir, ds, options)
    # the training folder (train.json): held-out views rendered at the training resolution by default
    # with pose refinement the held-out poses are aligned first (module docstring)
    align = bool(options.refine_poses)
    ev = evaluate(inputs.out_dir, ds, out_dir=inputs.out_dir / "eval", progress=progress,
                  full_resolution=options.eval_full_resolution, align_poses=align,
                  align_reason="the training refined its poses (--splat.refine-poses)" if align else None)
    refined = None
    if align:
        refined = refined_poses.add_heldout(inputs.out_dir, ev.aligned_T_world_cam or {})
    return SplatResult(ply=ply, psnr=ev.mean_psnr, ssim=ev.mean_ssim, split=ev.split,
                       gaussians=gaussians, train_s=train_s, refined_poses=refined,
                       psnr_as_given=ev.mean_psnr_as_given if align else None)
