"""3DGS training loop: one view per step, Adam, (1-l) L1 + l D-SSIM, SH warm-up, densification by a
strategy object (`splattwin.splat.strategy`; default: 3DGS adaptive density control on
`TrainConfig.densify_config()`), optional pose refinement, atomic checkpoints and exact resume.

Loss masks: a frame's nerfstudio `mask_path` (0 = ignore the pixel) is loaded with its view (`load_views`,
`TrainView.mask`); the ignored pixels are 0 in render and photo before L1 and D-SSIM (`TrainView.masked`,
splatfacto's rule), so they add no loss, gradient or densification statistics; train.json's `loss_masks`.

Determinism: every random choice comes from seeded generators (view order, split samples, init), whose
states are checkpointed together with parameters, Adam moments, densification statistics and the step,
so a run resumed from a checkpoint reproduces the uninterrupted run (on the CPU backend).

Outputs in OUT: point_cloud.ply (standard 3DGS), train.json (config, statistics), refined_poses.json
(with --refine-poses), train_curves.png (PSNR and Gaussian count), checkpoints/ckpt_XXXXXX.safetensors
(tensors + plain data, never a pickle: `splattwin.splat.checkpoint`; the two newest are kept).

Outputs record the run's figures in strict JSON (no NaN): train.json's train_loss/train_psnr are the moving
averages at the final step (checkpointed, so a resumed run, even one with no step left, reports the run's
own figures; null only when unknown) and wall_s is the training time of the result: the time spent in
the steps that led to it, summed over the original run and every resume (steps redone after a kill
counted once; null when resumed from a checkpoint that predates this record). resumed_at_step names
the checkpoint's step when the run resumed one.

Resume: a checkpoint is resumed only when it was made with the same training options, the same
densification strategy and the same training data (view names, cameras and image contents, recorded as a digest). Otherwise the run does
not silently continue someone else's or an older run: with on_mismatch="error" (`splattwin train
--resume`) it stops with an InputError saying what differs; with on_mismatch="restart" (`splattwin
build`, whose stage key already says the inputs changed) it says why, removes the stale checkpoints
and starts over. Pickled checkpoints of earlier versions (`ckpt_*.pt`) are never loaded.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from splattwin.capture import Camera, Dataset, Frame, load_dataset, load_image
from splattwin.errors import InputError
from splattwin.io import write_json
from splattwin.limits import check_pixels
from splattwin.runtime import torch_threads
from splattwin.splat import appearance
from splattwin.splat import checkpoint as ckpt_io
from splattwin.splat import extras
from splattwin.splat.config import TrainConfig
from splattwin.splat.depth_loss import depth_loss  # noqa: F401  (also re-exported: trainer.depth_loss)
from splattwin.splat.gaussians import Gaussians
from splattwin.splat.init import initial_gaussians, poses_points_source, scene_center_and_scale
from splattwin.splat.losses import photometric_loss, psnr_from_mse
from splattwin.splat.model import GaussianModel
from splattwin.splat import refined_poses
from splattwin.splat.pose_refine import PoseCorrection
from splattwin.splat.rasterize import backend_device, rasterization, resolve_backend
from splattwin.splat.resolution import Resolution, capacity, describe_sizes, resolve as resolve_resolution
from splattwin.splat.robust import masked_target, transient_sheet
from splattwin.splat.strategy import DefaultStrategy, Strategy

log = logging.getLogger(__name__)

CKPT_DIR = "checkpoints"


@dataclass
class TrainView:
    """A training image in memory and its camera at training resolution."""

    name: str
    image: torch.Tensor  # [H,W,3] float32 in [0,1]
    camera: Camera
    depth: torch.Tensor | None = None  # [H,W] float32 z-depth in m, inf where unknown (with depth=True)
    # the frame's nerfstudio loss mask (`mask_path`) at this size: [H,W,1] float32, 1 where the pixel is
    # trained on and evaluated, 0 where it is ignored; None: every pixel counts
    mask: torch.Tensor | None = None

    def masked(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(img, photo) with the ignored pixels set to 0 in both, as splatfacto masks its loss: L1 and SSIM
        then see no difference there and send no gradient from them. Unchanged without a mask."""
        if self.mask is None:
            return img, self.image
        return img * self.mask, self.image * self.mask


@dataclass
class TrainResult:
    """What `train` / `Trainer.run` return (OUT/point_cloud.ply and train.json hold the same).

    gaussians: the trained splats (`Gaussians`, the dataset's world frame, metres when its poses are metric);
    ply_path: where they were written; steps: optimiser steps done; wall_s: training seconds over the run and
    its resumes (None: a resumed checkpoint did not record it); final_loss / final_psnr (dB): moving averages
    at the last step; init_method: how the Gaussians were initialised; history: per-logging-step records;
    refined_T_world_cam: view name -> refined camera-to-world [4,4] (pose refinement on), else None;
    resumed_at_step: the checkpoint's step when the run resumed one."""

    gaussians: Gaussians
    ply_path: Path
    steps: int
    wall_s: float | None   # training time of the result over the original run and resumes (see module doc)
    final_loss: float | None   # moving averages at the final step; None when unknown
    final_psnr: float | None
    init_method: str
    history: list[dict]
    refined_T_world_cam: dict[str, list] | None = None
    resumed_at_step: int | None = None   # the checkpoint's step when the run resumed one


# The low-pass is the config's (`TrainConfig.filter_eps2d`, px^2 at the training size) and 1/4^level of it
# at coarse levels, so a coarse level renders every Gaussian as the training size does, only sampled on a
# coarser grid (with 0.3 coarse px^2, sub-pixel Gaussians learnt at 1/4 size were dilated 16x more than at
# full size, and the model kept that bias: -0.4 dB held-out on the embedded scene)
MIN_LEVEL_SIDE = 32  # coarse levels keep at least this many pixels on the short side (SSIM needs 11)


AUTO_DOWNSCALE_MIN_SIDE = 300  # coarse-to-fine by default only for images at least this large (short side)
AUTO_COARSEST_SIDE = 120  # ... down to levels at least this large


def auto_downscales(short_side: int) -> int:
    """Default coarse levels for training images whose short side is `short_side` px: 0 below 300 px
    (320x240 lost 0.1-0.2 dB held-out with any coarse phase), else the most halvings, up to 2, that keep
    the coarsest level >= 120 px (360 px: 1, 480 px: 2). See TrainConfig for the measurements."""
    if short_side < AUTO_DOWNSCALE_MIN_SIDE:
        return 0
    k = 0
    while k < 2 and short_side / 2 ** (k + 1) >= AUTO_COARSEST_SIDE:
        k += 1
    return k


def resolution_level(step: int, iters: int, num_downscales: int, downscale_every: float) -> int:
    """Coarse-to-fine level of `step` (0-based): the image is rendered at 1/2^level of the training size.
    Level num_downscales for the first round(downscale_every * iters) steps, one less after each further
    such block, 0 (full size) from num_downscales blocks on."""
    if num_downscales <= 0 or downscale_every <= 0:
        return 0
    block = max(1, int(round(downscale_every * iters)))
    return max(0, num_downscales - step // block)


def downscale_view(view: TrainView, factor: int) -> TrainView:
    """`view` at 1/factor of its size: image area-averaged (PIL box filter, as `load_views`), depth map
    nearest-sampled, camera intrinsics scaled; a loss mask keeps a coarse pixel only when every fine pixel
    of its box is kept (the box average of the photo holds the ignored pixels' colours otherwise)."""
    from PIL import Image

    from splattwin.capture import resize_nearest

    cam = view.camera.scaled(1.0 / factor)
    img = view.image.detach().cpu().numpy()
    small = np.stack([np.asarray(Image.fromarray(img[..., c]).resize((cam.width, cam.height), Image.BOX))
                      for c in range(img.shape[2])], -1)  # float32 per channel: no 8-bit rounding
    depth = None
    if view.depth is not None:
        depth = torch.from_numpy(np.ascontiguousarray(resize_nearest(view.depth.cpu().numpy(), cam.width, cam.height)))
    mask = None
    if view.mask is not None:
        m = np.asarray(Image.fromarray(view.mask[..., 0].detach().cpu().numpy()).resize((cam.width, cam.height),
                                                                                          Image.BOX))
        mask = torch.from_numpy(np.ascontiguousarray((m >= 1.0 - 1e-4)[..., None], dtype=np.float32))
    return TrainView(view.name, torch.from_numpy(np.ascontiguousarray(small, dtype=np.float32)), cam, depth, mask)


def training_scale(width: int, resolution: int) -> float:
    """Scale factor applied to an image of `width` px for the 3DGS `-r` convention (see TrainConfig)."""
    return Resolution(resolution).scale(width, width)


def load_views(frames: list[Frame], resolution: int | Resolution = 1, depth: bool = False,
               depth_scale: float | None = None, masks: bool = True) -> list[TrainView]:
    """Images of `frames` as tensors, resized (PIL area filter) to the training resolution (a 3DGS `-r`
    value or a resolved `splattwin.splat.resolution.Resolution`); with depth=True also their depth maps
    (frames without one get None). A photo with lens distortion is first resampled to its pinhole camera
    (`splattwin.capture.undistort.pinhole_for`): the views' cameras are ideal pinholes.

    masks: also the frames' nerfstudio loss masks (`Frame.mask_path`, `capture.dataset.load_loss_mask`),
    taken through the same undistortion and resize by nearest pixel (`TrainView.mask`); depth is unknown
    (inf) where the mask ignores the pixel."""
    from PIL import Image

    from splattwin.capture import load_depth, resize_nearest
    from splattwin.capture.dataset import load_loss_mask
    from splattwin.capture.undistort import pinhole_for, undistort_image

    views = []
    zooms = []  # focal scale of each undistorted photo's pinhole camera
    for f in frames:
        img = load_image(f.image_path)
        if img.shape[:2] != (f.camera.height, f.camera.width):
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but its camera says "
                             f"{f.camera.width}x{f.camera.height}", f.image_path)
        # the rasterizer draws pinhole images: a distorted photo is resampled once to its pinhole camera
        try:
            pin = pinhole_for(f.camera)
        except InputError as e:  # a lens model no photo was taken with: name the photo
            raise InputError(e.problem, e.path or f.image_path) from None
        if pin is not f.camera:
            img = undistort_image(img, f.camera, pin)
            zooms.append(pin.fx / f.camera.fx)
        s = (resolution if isinstance(resolution, Resolution) else Resolution(resolution)).scale(
            pin.width, pin.height)
        cam = pin
        if abs(s - 1.0) > 1e-9:
            cam = pin.scaled(s)
            # a target width far above the photo's would upsample it to gigapixels
            check_pixels(cam.width, cam.height, f.image_path, "view at the training resolution")
            pil = Image.fromarray((img * 255 + 0.5).astype(np.uint8)).resize((cam.width, cam.height), Image.BOX)
            img = np.asarray(pil, dtype=np.float32) / 255.0
        keep = None
        if masks and f.mask_path is not None:
            keep = load_loss_mask(f.mask_path, (f.camera.width, f.camera.height))
            if pin is not f.camera:
                keep = undistort_image(keep.astype(np.uint8), f.camera, pin, nearest=True) > 0
            if keep.shape != (cam.height, cam.width):
                keep = resize_nearest(keep, cam.width, cam.height)
            if not keep.any():
                log.warning("%s: the loss mask ignores every pixel of this view", f.mask_path)
        d = None
        if depth and f.depth_path is not None:
            dm = load_depth(f.depth_path, depth_scale, size=(f.camera.width, f.camera.height))  # fits a smaller map
            if dm.shape != (f.camera.height, f.camera.width):
                raise InputError(f"depth map is {dm.shape[1]}x{dm.shape[0]} but its camera says "
                                 f"{f.camera.width}x{f.camera.height}", f.depth_path)
            if pin is not f.camera:
                dm = undistort_image(dm, f.camera, pin, nearest=True)
            if dm.shape != (cam.height, cam.width):
                dm = resize_nearest(dm, cam.width, cam.height)
            dm = np.where(np.isfinite(dm) & (dm > 0), dm, np.inf).astype(np.float32)
            if keep is not None:
                dm[~keep] = np.inf
            d = torch.from_numpy(np.ascontiguousarray(dm))
        m = None if keep is None else torch.from_numpy(np.ascontiguousarray(keep[..., None], dtype=np.float32))
        views.append(TrainView(f.name, torch.from_numpy(np.ascontiguousarray(img)), cam, d, m))
    if zooms:
        log.info("%d of %d photos have lens distortion: undistorted to pinhole cameras (focal x%.4f to x%.4f)",
                 len(zooms), len(frames), min(zooms), max(zooms))
    return views


def plot_history(history: list[dict], path: str | Path, width: int = 640, height: int = 240) -> Path:
    """PNG of the training curves: PSNR (blue, left half) and Gaussian count (green, right half) vs step."""
    from PIL import Image, ImageDraw

    from splattwin.io import write_image

    img = Image.new("RGB", (width, height), "white")
    d = ImageDraw.Draw(img)
    half = width // 2
    steps = [h["step"] for h in history] or [0]
    for k, (key, colour, x0) in enumerate((("psnr", (30, 90, 200), 0), ("n", (30, 150, 60), half))):
        vals = [float(h[key]) for h in history if math.isfinite(float(h[key]))]
        d.rectangle([x0 + 40, 20, x0 + half - 10, height - 30], outline=(160, 160, 160))
        d.text((x0 + 45, 4), "train PSNR (dB)" if key == "psnr" else "Gaussians", fill=colour)
        if len(vals) < 2:
            continue
        lo, hi = min(vals), max(vals)
        hi = hi if hi > lo else lo + 1
        d.text((x0 + 2, 20), f"{hi:.0f}", fill=(0, 0, 0))
        d.text((x0 + 2, height - 40), f"{lo:.0f}", fill=(0, 0, 0))
        d.text((x0 + half - 60, height - 25), f"step {steps[-1]}", fill=(0, 0, 0))
        pts = [(x0 + 40 + (half - 50) * (h["step"] - steps[0]) / max(steps[-1] - steps[0], 1),
                height - 30 - (height - 50) * (float(h[key]) - lo) / (hi - lo))
               for h in history if math.isfinite(float(h[key]))]
        d.line(pts, fill=colour, width=2)
    return write_image(path, np.asarray(img))


# Options that change what a run computes: a checkpoint made with other values is not resumed. Left out:
# progress, checkpoint_every (bookkeeping) and device/backend (the same computation on other hardware).
_RUN_NEUTRAL = ("progress", "checkpoint_every", "device", "backend", "eval_full_resolution")


def checkpoint_files(out_dir: Path) -> list[Path]:
    """The run's checkpoints in OUT/checkpoints, oldest first (the newest is resumed)."""
    return sorted((out_dir / CKPT_DIR).glob(f"ckpt_*{ckpt_io.SUFFIX}"))


def _latest_checkpoint(out_dir: Path) -> Path | None:
    legacy = sorted((out_dir / CKPT_DIR).glob(f"ckpt_*{ckpt_io.LEGACY_SUFFIX}"))
    if legacy:
        log.warning("ignoring %d pickled checkpoint(s) in %s (e.g. %s): pickles can run code and are never "
                    "loaded; only %s checkpoints are resumed", len(legacy), out_dir / CKPT_DIR, legacy[-1].name,
                    ckpt_io.SUFFIX)
    ckpts = checkpoint_files(out_dir)
    return ckpts[-1] if ckpts else None


def run_options(cfg: TrainConfig) -> dict:
    """The options a checkpoint must share with the run that resumes it (JSON-normalised)."""
    import json

    d = {k: v for k, v in cfg.to_dict().items() if k not in _RUN_NEUTRAL}
    return json.loads(json.dumps(d, default=str))


def data_digest(views: list[TrainView]) -> str:
    """SHA-256 of what the run trains on: view names, sizes, intrinsics, poses, image (and depth) pixels."""
    import hashlib

    h = hashlib.sha256()
    for v in views:
        c = v.camera
        h.update(v.name.encode("utf-8", "surrogateescape") + b"\0")
        h.update(np.asarray([c.width, c.height], np.int64).tobytes())
        h.update(np.ascontiguousarray(c.K, np.float64).tobytes())
        h.update(np.ascontiguousarray(c.T_world_cam, np.float64).tobytes())
        h.update(np.ascontiguousarray(v.image.detach().cpu().numpy()).tobytes())
        if v.depth is not None:
            h.update(np.ascontiguousarray(v.depth.detach().cpu().numpy()).tobytes())
        if v.mask is not None:
            h.update(b"loss mask\0" + np.ascontiguousarray(v.mask.detach().cpu().numpy()).tobytes())
    return h.hexdigest()


# run options set by no flag but derived from others, by what a user knows them as
_DERIVED = {"densify_cfg": "the densification schedule (scaled to --iters)"}


def options_diff(old: dict, new: dict, keys: list[str], shown: int = 4) -> str:
    """`keys` (run options that differ between a checkpoint, `old`, and this run, `new`) as a user set
    them: `--iters 300 (checkpoint) vs 400 (this run)`, the flags first (the densification schedule, derived
    from --iters, led the message with a 600-character dict); derived settings as a short note after them,
    or, when nothing else differs, by the entries that differ."""
    from splattwin.errors import short_repr
    from splattwin.options import flag_name, specs

    by_name = {sp.name: sp for sp in specs(TrainConfig)}
    flags = [k for k in keys if k in by_name and by_name[k].meta.get("cli", True)]
    derived = [k for k in keys if k not in flags]

    def pair(name: str, a, b) -> str:
        return f"{name} {short_repr(a)} (checkpoint) vs {short_repr(b)} (this run)"

    parts = []
    for k in flags[:shown]:
        sp = by_name[k]
        build = "" if sp.meta.get("build_alias") else f" (build: --splat.{flag_name(sp)})"
        parts.append(pair(f"--{flag_name(sp)}", old.get(k), new.get(k)) + build)
    if len(flags) > shown:
        parts.append(f"and {len(flags) - shown} more")
    text = ", ".join(parts)
    if derived and flags:
        return text + f"; derived from them: {', '.join(_DERIVED.get(k, k) for k in derived)}"
    for k in derived:
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            sub = [x for x in sorted(set(a) | set(b)) if a.get(x) != b.get(x)]
            inner = ", ".join(pair(x, a.get(x), b.get(x)) for x in sub[:shown])
            more = f" and {len(sub) - shown} more" if len(sub) > shown else ""
            parts.append(f"{_DERIVED.get(k, k)}: {inner}{more}")
        else:
            parts.append(pair(_DERIVED.get(k, k), a, b))
    return ", ".join(parts)


def _moving_average(avg: float, x: float) -> float:
    """The training curve's moving average (0.9 old + 0.1 new; NaN: none yet) after the step figure x. A
    non-finite x leaves it unchanged: one view whose loss mask ignores every pixel (PSNR +inf: mse 0) made
    the PSNR average +inf for the rest of the run (train.json's train_psnr null, the curve empty)."""
    if not math.isfinite(x):
        return avg
    return x if math.isnan(avg) else 0.9 * avg + 0.1 * x


class CheckpointMismatch(InputError):
    """A checkpoint that was made by another run (other options or data): not resumed."""


class TrainingDiverged(RuntimeError):
    """Training produced NaN or infinite values (a non-finite loss, or non-finite model parameters): the
    run stops at once and saves nothing non-finite, so its newest checkpoint stays resumable. Not an
    `InputError`: the inputs were valid when loaded (the CLI reports it as an internal error, exit 1)."""


class Trainer:
    """Holds the state of one training run; `run()` trains (or resumes) to `cfg.iters`.

    strategy: how the Gaussians are densified/pruned (`splattwin.splat.strategy`); default
    `DefaultStrategy(cfg.densify_config())`, or no densification with `cfg.densify=False`."""

    def __init__(self, dataset: Dataset | str | Path, out_dir: str | Path, cfg: TrainConfig | None = None,
                 strategy: Strategy | None = None):
        self.cfg = cfg or TrainConfig()
        if not isinstance(dataset, Dataset):   # a path, as `evaluate` and `fuse_to_dir` take (a str failed deep inside)
            from splattwin.capture.dataset import refuse_video

            refuse_video(dataset, "train")
            # transparent pixels' loss masks (`capture.images.mask_transparent_pixels`) go into the output
            dataset = load_dataset(dataset, frames_dir=Path(out_dir) / "capture" / "frames")
        self.dataset = dataset
        self.out_dir = Path(out_dir)
        self.cfg.check()
        # --appearance auto: on when the poses stage measured differing exposures (appearance.decide)
        self.exposure, exposure_path = appearance.exposure_record(dataset)
        self.appearance_record = appearance.decide(self.cfg.appearance, self.exposure, exposure_path)
        self.cfg = replace(self.cfg, appearance=self.appearance_record["mode"])
        self.frames = dataset.train()
        if not self.frames:
            raise InputError("dataset has no training frames", dataset.root)
        if not dataset.has_poses:
            raise InputError("dataset has no camera poses; estimate them first (splattwin poses)", dataset.root)
        self.backend = resolve_backend(self.cfg.backend or self.cfg.device)
        self.device = backend_device(self.backend)
        self.resolution = resolve_resolution(self.cfg.resolution, self.cfg.cpu_max_side, self.device.type)
        self.views = load_views(self.frames, self.resolution, depth=self.cfg.depth_lambda > 0,
                                depth_scale=dataset.depth_scale)
        log.info("training at %s (%s)", describe_sizes([(v.camera.width, v.camera.height) for v in self.views]),
                 self.resolution.how)
        n_masked = sum(v.mask is not None for v in self.views)
        if n_masked:
            log.info("loss masks (mask_path): %d of %d training views; their ignored pixels are left out of the "
                     "loss", n_masked, len(self.views))
        self.data_digest = data_digest(self.views)
        self.scene_center, self.scene_scale = scene_center_and_scale([v.camera for v in self.views])
        if self.cfg.init_points <= 0 or self.cfg.max_gaussians <= 0:  # 0: scaled with the image size
            init, cap = capacity(float(np.mean([v.camera.width * v.camera.height for v in self.views])))
            self.cfg = replace(self.cfg, init_points=self.cfg.init_points if self.cfg.init_points > 0 else init,
                               max_gaussians=self.cfg.max_gaussians if self.cfg.max_gaussians > 0 else cap)
        self.cfg, self.profile = self.cfg.resolved(len(self.views))
        if self.profile:
            log.info("%s", self.profile)
        self.dcfg = self.cfg.densify_config()
        if strategy is None:
            strategy = DefaultStrategy(self.dcfg) if self.cfg.densify else Strategy()
        self.strategy = strategy
        self.sh_interval = self.cfg.sh_interval or max(1, self.cfg.iters // 10)
        dev = self.device
        for v in self.views:
            v.image = v.image.to(dev)
            v.depth = None if v.depth is None else v.depth.to(dev)
            v.mask = None if v.mask is None else v.mask.to(dev)
        self.viewmats = torch.tensor(np.stack([v.camera.T_cam_world for v in self.views]), dtype=torch.float32,
                                     device=dev)
        # coarse-to-fine: views and intrinsics per level (level k: 1/2^k of the training size)
        short = min(min(v.camera.width, v.camera.height) for v in self.views)
        if self.cfg.num_downscales < 0:
            self.cfg = replace(self.cfg, num_downscales=auto_downscales(short))
        n_levels = 1 + max(0, min(self.cfg.num_downscales, int(math.log2(max(short / MIN_LEVEL_SIDE, 1.0)))))
        self.levels = [self.views] + [[downscale_view(v, 2**k) for v in self.views] for k in range(1, n_levels)]
        for views in self.levels[1:]:
            for v in views:
                v.image = v.image.to(dev)
                v.depth = None if v.depth is None else v.depth.to(dev)
                v.mask = None if v.mask is None else v.mask.to(dev)
        self.Ks_levels = [torch.tensor(np.stack([v.camera.K for v in views]), dtype=torch.float32, device=dev)
                          for views in self.levels]
        self.Ks = self.Ks_levels[0]
        self.bg = torch.tensor([self.cfg.background], dtype=torch.float32, device=dev)
        self.step = 0
        self.history: list[dict] = []
        self.init_method = ""
        # moving averages of the loss and PSNR, and the training seconds behind the current state: both
        # checkpointed, so that a resumed run logs and reports what the uninterrupted run would have
        self.ema_loss, self.ema_psnr = math.nan, math.nan
        self.train_s: float | None = 0.0   # None: resumed from a checkpoint that did not record it
        self._run_t0: float | None = None  # perf_counter() when this process's steps began

    # -- state ------------------------------------------------------------------------------------
    def _fresh_state(self) -> None:
        cfg = self.cfg
        g, self.init_method = initial_gaussians(
            cfg.init, self.frames, self.dataset.points_xyz, self.dataset.points_rgb,
            depth_scale=self.dataset.depth_scale, sh_degree=cfg.sh_degree, max_points=cfg.init_points,
            seed=cfg.seed, stereo_points=cfg.init_stereo, progress=cfg.progress,
            points_source=poses_points_source(self.dataset))
        torch.manual_seed(cfg.seed)
        g = extras.with_background_sphere(g, cfg, self.views, self.scene_center, self.scene_scale)
        self.model = GaussianModel.from_gaussians(g, max_sh_degree=cfg.sh_degree, lrs=cfg.lrs,
                                                  scene_scale=self.scene_scale, device=self.device,
                                                  scene_center=torch.tensor(self.scene_center))
        self.strategy_state = self.strategy.initialize_state(self.model)
        self.split_gen = torch.Generator().manual_seed(cfg.seed)
        self.view_gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.drop_gen = torch.Generator().manual_seed(cfg.seed + 2)
        self.order: list[int] = []
        self.poses = PoseCorrection(len(self.views), cfg.pose_lr, self.device) if cfg.refine_poses else None
        self.appearance, self.bg_model = extras.make(cfg, self.views, self.device, self._appearance_init())
        self.step = 0
        self.history = []
        self.ema_loss, self.ema_psnr = math.nan, math.nan
        self.train_s = 0.0

    def elapsed_s(self) -> float | None:
        """Training seconds behind the current state: the checkpoint's plus this process's so far."""
        if self.train_s is None:
            return None
        return self.train_s + (time.perf_counter() - self._run_t0 if self._run_t0 is not None else 0.0)

    def state_dict(self) -> dict:
        return {"step": self.step, "model": self.model.state_dict(), "densify": self.strategy_state,
                "strategy": self.strategy.describe(),
                "split_gen": self.split_gen.get_state(), "view_gen": self.view_gen.get_state(),
                "drop_gen": self.drop_gen.get_state(), "order": list(self.order),
                "poses": self.poses.state_dict() if self.poses else None,
                "history": list(self.history), "init_method": self.init_method,
                "ema": [self.ema_loss, self.ema_psnr], "train_s": self.elapsed_s(),
                "appearance": self.appearance.state_dict() if self.appearance else None,
                "bg_model": self.bg_model.state_dict() if self.bg_model else None,
                "torch_rng": torch.get_rng_state(), "config": self.cfg.to_dict(),
                "run_options": run_options(self.cfg), "data_digest": self.data_digest,
                "view_names": [v.name for v in self.views]}

    def check_resumable(self, sd: dict, where: Path) -> None:
        """CheckpointMismatch naming what differs when `sd` was made by another run (see module doc)."""
        if not isinstance(sd.get("run_options"), dict) or not isinstance(sd.get("data_digest"), str):
            raise CheckpointMismatch("checkpoint does not record its run's options and data", where)
        if sd.get("view_names") != [v.name for v in self.views]:
            raise CheckpointMismatch("checkpoint was made with different training views", where)
        old, new = sd["run_options"], run_options(self.cfg)
        # an option the checkpoint does not record is newer than it: that run had the option's default
        # behaviour (options are added with a default that keeps what came before)
        old = {**{k: v for k, v in run_options(TrainConfig()).items() if k not in old}, **old}
        diff = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
        if diff:
            raise CheckpointMismatch(f"checkpoint was made with other options: {options_diff(old, new, diff)}",
                                     where)
        if sd["data_digest"] != self.data_digest:
            raise CheckpointMismatch("checkpoint was made with other training data (images, cameras or poses "
                                     "changed)", where)
        # (checkpoints before strategy objects: the strategy followed from the options compared above)
        if "strategy" in sd and sd["strategy"] != self.strategy.describe():
            name = sd["strategy"].get("name") if isinstance(sd["strategy"], dict) else sd["strategy"]
            raise CheckpointMismatch(f"checkpoint was made with another densification strategy ({name!r}, "
                                     f"this run: {self.strategy.name!r} or other options)", where)

    def check_state(self, sd: dict, where: Path) -> None:
        """InputError naming the checkpoint when its state is not one this run could have saved: a received
        checkpoint of NaN parameters resumed silently into an all-NaN point_cloud.ply, and a bad order,
        step, shape or history failed deep inside training (exit 1)."""
        from splattwin.limits import MAX_ELEMENTS
        from splattwin.splat.model import PARAM_NAMES

        def bad(what: str) -> InputError:
            return InputError(f"checkpoint state is inconsistent: {what}", where)

        def whole(v) -> bool:
            return isinstance(v, int) and not isinstance(v, bool)

        step = sd.get("step")
        if not whole(step) or not 0 <= step <= self.cfg.iters:
            raise bad(f"step {str(step)[:40]} is not in [0, {self.cfg.iters}] (the run's --iters)")
        order = sd.get("order")
        if (not isinstance(order, list) or len(order) > len(self.views)
                or not all(whole(i) and 0 <= i < len(self.views) for i in order)):
            raise bad(f"order must list view indices in [0, {len(self.views)})")
        history = sd.get("history")
        if not isinstance(history, list) or len(history) > step + 1 or not all(
                isinstance(h, dict) and whole(h.get("step"))
                and all(isinstance(h.get(k), (int, float)) and not isinstance(h.get(k), bool)
                        for k in ("loss", "psnr", "n")) for h in history):
            raise bad("history must be a list of {step, loss, psnr, n} records")
        model = sd.get("model")
        params = model.get("params") if isinstance(model, dict) else None
        if not isinstance(params, dict) or not all(isinstance(params.get(k), torch.Tensor) for k in PARAM_NAMES):
            raise bad(f"model parameters {', '.join(PARAM_NAMES)} are missing")
        n = params["means"].shape[0] if params["means"].ndim else -1
        want = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3)}
        for k in PARAM_NAMES:
            t = params[k]
            shape = tuple(t.shape)
            ok = shape == want[k] if k in want else (t.ndim == 3 and shape[0] == n and shape[2] == 3
                                                      and shape[1] + 1 in (1, 4, 9, 16))
            if not 0 <= n <= MAX_ELEMENTS or not ok or not t.is_floating_point():
                raise bad(f"parameter {k} has shape {shape} (dtype {t.dtype}) for {n} Gaussians")
            if not bool(torch.isfinite(t).all()):
                raise bad(f"parameter {k} holds NaN or infinite values")
        # the learnt corrections beside the Gaussians (per-view appearance, background, pose corrections): NaN
        # gains made every render NaN ("training diverged", blaming the learning rates), NaN poses resumed silently
        for part in ("appearance", "bg_model", "poses"):
            st = sd.get(part)
            for k, v in (st.items() if isinstance(st, dict) else ()):
                if k.startswith("optimizer"):
                    continue
                for t in (v if isinstance(v, (list, tuple)) else [v]):
                    if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
                        raise bad(f"{part} state {k} holds NaN or infinite values")
        opt = model.get("optimizers")
        if isinstance(opt, dict):
            for k, o in opt.items():
                states = o.get("state") if isinstance(o, dict) else None
                for st in (states.values() if isinstance(states, dict) else []):
                    for name, v in (st.items() if isinstance(st, dict) else []):
                        if (isinstance(v, torch.Tensor) and v.ndim and k in params
                                and tuple(v.shape) != tuple(params[k].shape)):
                            raise bad(f"optimizer state {k}.{name} has shape {tuple(v.shape)}, the parameter "
                                      f"{tuple(params[k].shape)}")

    def load_state_dict(self, sd: dict) -> None:
        if sd["view_names"] != [v.name for v in self.views]:
            raise InputError("checkpoint was made with different training views; start a new run "
                             "(without --resume) or use the original dataset", self.out_dir)
        self.model = GaussianModel.from_state_dict(sd["model"], self.device)
        self.strategy_state = self.strategy.load_state(sd["densify"], self.model)
        self.split_gen = torch.Generator()
        self.split_gen.set_state(sd["split_gen"])
        self.view_gen = torch.Generator()
        self.view_gen.set_state(sd["view_gen"])
        self.drop_gen = torch.Generator()
        self.drop_gen.set_state(sd["drop_gen"])
        self.order = list(sd["order"])
        self.poses = None
        if sd["poses"] is not None:
            self.poses = PoseCorrection(len(self.views), self.cfg.pose_lr, self.device)
            self.poses.load_state_dict(sd["poses"])
        elif self.cfg.refine_poses:
            raise InputError("--refine-poses differs from the checkpointed run; start a new run", self.out_dir)
        self.appearance, self.bg_model = extras.make(self.cfg, self.views, self.device, self._appearance_init())
        extras.load_state(self.appearance, self.bg_model, sd)
        self.history = list(sd["history"])
        self.init_method = sd["init_method"]
        # checkpoints from before these records: the averages restart, the training time is unknown
        ema = sd.get("ema")
        self.ema_loss, self.ema_psnr = (float(ema[0]), float(ema[1])) if ema is not None else (math.nan, math.nan)
        self.train_s = float(sd["train_s"]) if sd.get("train_s") is not None else None
        torch.set_rng_state(sd["torch_rng"])
        self.step = int(sd["step"])

    def _nonfinite_params(self) -> str:
        """Which model parameters hold NaN or infinite values, for an error message ("" when none): name,
        how many Gaussians, the first one's row."""
        parts = []
        with torch.no_grad():
            for k, t in self.model.params.items():
                bad = ~torch.isfinite(t).reshape(t.shape[0], -1).all(dim=1)
                n = int(bad.sum())
                if n:
                    parts.append(f"{k} ({n} of {t.shape[0]} Gaussians, first at row {int(bad.nonzero()[0, 0])})")
        return ", ".join(parts)

    def _diverged(self, what: str) -> TrainingDiverged:
        ckpts = checkpoint_files(self.out_dir)
        keep = (f"the newest checkpoint, {ckpts[-1]}, is finite" if ckpts else "no checkpoint was saved")
        return TrainingDiverged(f"training diverged: {what}; stopped (nothing non-finite is saved: {keep}). "
                                f"Lower the learning rates, or report it with the command and data")

    def check_finite(self) -> None:
        """TrainingDiverged if a model parameter is NaN or infinite. Called before every checkpoint and after
        the last step: the CPU rasterizer silently skips Gaussians with non-finite geometry, so such a
        parameter leaves the loss finite and would otherwise surface only when the splat is written."""
        bad = self._nonfinite_params()
        if bad:
            raise self._diverged(f"non-finite model parameters after step {self.step}: {bad}")

    def save_checkpoint(self) -> Path:
        # never write a non-finite state: `check_state` refuses it on --resume, and only the 2 newest
        # checkpoints are kept, so non-finite ones would replace the last good ones
        self.check_finite()
        path = self.out_dir / CKPT_DIR / f"ckpt_{self.step:06d}{ckpt_io.SUFFIX}"
        ckpt_io.save(path, self.state_dict())
        for old in checkpoint_files(self.out_dir)[:-2]:
            old.unlink()
        return path

    def load_checkpoint(self, path: Path) -> None:
        """Resume from `path` (tensors + plain data only); CheckpointMismatch when another run made it."""
        sd = ckpt_io.load(path)
        self.check_resumable(sd, path)
        self.check_state(sd, path)
        try:
            self.load_state_dict(sd)
        except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as e:
            raise InputError(f"checkpoint state is inconsistent ({type(e).__name__}: {str(e)[:200]})", path) from None

    # -- one step ---------------------------------------------------------------------------------
    def _next_view(self) -> int:
        if not self.order:
            self.order = torch.randperm(len(self.views), generator=self.view_gen).tolist()
        return self.order.pop(0)

    def sh_degree_at(self, step: int) -> int:
        return min(step // self.sh_interval, self.cfg.sh_degree)

    def level_at(self, step: int) -> int:
        """Coarse-to-fine level of `step` (index into self.levels; see `resolution_level`)."""
        lvl = resolution_level(step, self.cfg.iters, self.cfg.num_downscales, self.cfg.downscale_every)
        return min(lvl, len(self.levels) - 1)

    def render(self, idx: int, sh_degree: int | None = None, render_mode: str = "RGB", level: int = 0,
               drop: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """Render training view `idx` with the current model: ([H,W,3 or 4], [H,W,1], meta), at
        coarse-to-fine `level` (0: the training size); drop: fraction of Gaussians hidden at random."""
        v = self.levels[level][idx]
        act = self.model.activated()
        if drop > 0:   # DropGaussian (TrainConfig.drop_rate): a random subset, opacity-compensated
            keep = torch.rand(act["opacities"].shape, generator=self.drop_gen) >= drop
            act = {**act, "opacities": act["opacities"] * keep.to(act["opacities"]) / (1.0 - drop)}
        viewmat = self.viewmats[idx:idx + 1]
        if self.poses is not None and self.step >= self.cfg.pose_start * self.cfg.iters:
            viewmat = self.poses.apply(viewmat, [idx])
        colors, alphas, meta = rasterization(
            act["means"], act["quats"], act["scales"], act["opacities"], act["sh"], viewmat,
            self.Ks_levels[level][idx:idx + 1], v.camera.width, v.camera.height,
            sh_degree=self.sh_degree_at(self.step) if sh_degree is None else sh_degree,
            backgrounds=self.bg, render_mode=render_mode, backend=self.backend,
            rasterize_mode=self.cfg.rasterize_mode, eps2d=self.cfg.filter_eps2d() / 4**level)
        return colors[0], alphas[0], meta

    def train_step(self) -> dict:
        cfg = self.cfg
        self.model.set_step(self.step, cfg.iters)
        idx = self._next_view()
        level = self.level_at(self.step)
        view = self.levels[level][idx]
        gt, gt_depth = view.image, view.depth
        use_depth = cfg.depth_lambda > 0 and gt_depth is not None
        drop = cfg.drop_rate * self.step / cfg.iters
        img, alpha, meta = self.render(idx, render_mode="RGB+ED" if use_depth else "RGB", level=level, drop=drop)
        if use_depth:
            img, depth = img[..., :3], img[..., 3]
        img, extra_loss = extras.apply(self.appearance, self.bg_model, img, alpha, idx, self.Ks_levels[level][idx],
                                       self.viewmats[idx], self.bg[0])
        # the loss mask (nerfstudio mask_path): ignored pixels 0 in render and photo alike, so they add
        # nothing to L1 or D-SSIM and send no gradient (nor densification statistics: those are the means2d
        # gradients of this loss); views without one are not copied
        img_l, target = view.masked(img)
        masked = 0.0
        if cfg.robust_quantile > 0 and self.step >= cfg.robust_start * cfg.iters:
            target, outliers = masked_target(img_l, target, cfg.robust_quantile)
            masked = float(outliers.float().mean())
        loss = photometric_loss(img_l, target, cfg.ssim_lambda) + extra_loss
        if use_depth:
            loss = loss + cfg.depth_lambda * depth_loss(depth, alpha[..., 0], gt_depth, cfg.depth_mode)
        if cfg.opacity_reg > 0:  # gsplat's opacity_reg: mean opacity, fewer semi-transparent layers
            loss = loss + cfg.opacity_reg * torch.sigmoid(self.model.params["opacities"]).mean()
        s = self.step + 1
        loss_value = float(loss.detach())
        if not math.isfinite(loss_value):
            # before backward and the optimizer step: one NaN colour poisons the pixels it covers, then every
            # gradient there, and Adam writes NaN into every Gaussian those pixels see (the run went on to
            # its end with nothing drawn right, then failed to save)
            bad = self._nonfinite_params()
            raise self._diverged(f"the loss of step {s} (view {view.name!r}) is {loss_value}"
                                 + (f"; non-finite model parameters: {bad}" if bad else ""))
        cam = view.camera  # at this step's coarse-to-fine level: means2d gradients are in its pixels
        hook_info = {**meta, "width": cam.width, "height": cam.height, "view": idx, "iters": cfg.iters,
                     "generator": self.split_gen}
        self.strategy.step_pre_backward(self.model, self.strategy_state, s, hook_info)
        loss.backward()
        self.model.step()
        self.model.zero_grad()
        extras.step(self.appearance, self.bg_model, idx)
        if self.poses is not None and s > self.cfg.pose_start * cfg.iters:  # after an optional warm-up
            self.poses.step([idx])
            if not self.order:
                # once per pass over the views, not every step: applied every step this (first-order)
                # removal kept the poses from converging (8 views of a fixed scene, 1.5 deg error:
                # 1.4 deg left after 150 passes, vs 0.04 deg when applied once per pass)
                self.poses.remove_common_motion(self.viewmats)
        sq = (img.detach() - gt) ** 2
        if view.mask is None:
            psnr = psnr_from_mse(float(sq.mean()))
        else:  # NaN (not measured) for a view whose mask ignores every pixel: mse 0 / 1 gave +inf
            kept = view.mask.sum()
            psnr = psnr_from_mse(float((sq * view.mask).sum() / (3 * kept))) if kept > 0 else math.nan
        info = {"step": s, "loss": loss_value, "psnr": psnr}
        stats = self.strategy.step_post_backward(self.model, self.strategy_state, s, hook_info)
        info.update(stats, n=len(self.model), densified=bool(stats))
        if cfg.robust_quantile > 0:
            info["masked"] = masked
        self.step = s
        return info

    # -- the loop ---------------------------------------------------------------------------------
    def run(self, resume: bool = False, callback: Callable[[dict], None] | None = None,
            on_mismatch: str = "error") -> TrainResult:
        """Train to `cfg.iters` steps (continuing from the newest checkpoint with resume=True).

        on_mismatch: what a checkpoint made by another run (other options or data) does: "error" raises
        CheckpointMismatch (exit 2), "restart" logs why, deletes the stale checkpoints and starts over.
        The caller's global torch random state is restored afterwards (the run seeds it with cfg.seed)."""
        if on_mismatch not in ("error", "restart"):
            raise ValueError(f"on_mismatch must be 'error' or 'restart', got {on_mismatch!r}")
        # A fresh run seeds torch's global generator (what a strategy drawing from it relies on); forked, so
        # that a notebook's own torch.rand after training is what it would have been without it.
        devices = [self.device.index or 0] if self.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            return self._run(resume, callback, on_mismatch)

    def _run(self, resume: bool, callback: Callable[[dict], None] | None, on_mismatch: str) -> TrainResult:
        ckpt = _latest_checkpoint(self.out_dir) if resume else None
        resumed_at = None
        if ckpt is not None:
            try:
                self.load_checkpoint(ckpt)
                resumed_at = self.step
                log.info("resumed from %s (step %d)", ckpt, self.step)
            except CheckpointMismatch as e:
                if on_mismatch == "error":
                    raise CheckpointMismatch(f"{e.problem}; not resumed. Start a new run (without --resume, or "
                                             f"into another folder) or resume with the original options and "
                                             f"data", e.path) from None
                log.warning("%s: %s; starting over (the stale checkpoints are removed)", e.path, e.problem)
                for old in checkpoint_files(self.out_dir):
                    old.unlink()
                ckpt = None
        if ckpt is None:
            if resume:
                log.info("no checkpoint in %s: starting from scratch", self.out_dir / CKPT_DIR)
            # checkpoints of an earlier run in this folder are stale now: left there, the newest (say a
            # finished run's step 200) would outrank this run's and a later --resume would continue it
            stale = checkpoint_files(self.out_dir)
            if stale:
                log.info("starting over: removing %d checkpoint(s) of an earlier run in %s", len(stale),
                         self.out_dir / CKPT_DIR)
                for old in stale:
                    old.unlink()
            self._fresh_state()
        self._run_t0 = time.perf_counter()
        # CPU backend: the heavy work is in numba kernels; torch only does small element-wise ops and
        # Adam. Its thread pool competing with numba's made steps ~1.7x slower on 2 busy cores (idle:
        # equal). One torch thread for the loop only; the caller's count is restored afterwards.
        with torch_threads(1) if self.backend == "cpu" else contextlib.nullcontext():
            self._loop(callback)
        wall = self.elapsed_s()
        self._run_t0 = None
        return self._write_outputs(wall, *self._final_figures(), resumed_at)

    def _final_figures(self) -> tuple[float | None, float | None]:
        """The moving averages at the final step; from the history's last entry (that step's, rounded)
        when a checkpoint predating the averages was resumed with nothing left to do; else None."""
        if math.isfinite(self.ema_loss) and math.isfinite(self.ema_psnr):
            return self.ema_loss, self.ema_psnr
        last = self.history[-1] if self.history else None
        if last is not None and last.get("step") == self.step:
            ok = lambda x: float(x) if x is not None and math.isfinite(float(x)) else None  # noqa: E731
            return ok(last.get("loss")), ok(last.get("psnr"))
        return None, None

    def _loop(self, callback: Callable[[dict], None] | None) -> None:
        """Steps to cfg.iters, updating the moving averages self.ema_loss / self.ema_psnr."""
        from splattwin.interrupt import DeferredInterrupt
        from splattwin.progress import Progress

        cfg = self.cfg
        with Progress(cfg.iters, "train", unit="it", enabled=cfg.progress, initial=self.step) as bar, \
                DeferredInterrupt("this training step") as interrupt:
            while self.step < cfg.iters:
                info = self.train_step()
                ema_loss = self.ema_loss = _moving_average(self.ema_loss, info["loss"])
                ema_psnr = self.ema_psnr = _moving_average(self.ema_psnr, info["psnr"])
                if self.step % 10 == 0 or self.step == cfg.iters or info["densified"]:
                    self.history.append({"step": self.step, "loss": round(ema_loss, 6),
                                         "psnr": round(ema_psnr, 3), "n": info["n"]})
                    bar.set_postfix(loss=f"{ema_loss:.4f}", psnr=f"{ema_psnr:.2f}", gaussians=info["n"])
                bar.update(1)
                if cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
                if callback is not None:
                    callback(info)
                if interrupt.requested:   # Ctrl-C: the step is complete, so the state is consistent
                    if cfg.checkpoint_every:
                        path = self.save_checkpoint()
                        log.warning("interrupted at step %d: saved %s; run again with --resume to continue "
                                    "(build: run it again)", self.step, path)
                    raise KeyboardInterrupt
        self.check_finite()  # a clear error here, not a "non-finite means" when the splat is written
        if cfg.checkpoint_every and self.step % cfg.checkpoint_every != 0:
            self.save_checkpoint()  # so that --resume on a finished run does no work

    def _write_transients(self) -> dict:
        """The transient masks of the final model on every training view: OUT/transients.png (the photos with
        what the loss leaves out tinted red) and each view's masked share (for train.json)."""
        photos, masks = [], []
        with torch.no_grad():
            for idx, v in enumerate(self.views):
                img, alpha, _ = self.render(idx)
                img, _ = extras.apply(self.appearance, self.bg_model, img, alpha, idx, self.Ks[idx],
                                      self.viewmats[idx], self.bg[0])
                _, out = masked_target(*v.masked(img), self.cfg.robust_quantile)
                photos.append(v.image.cpu().numpy())
                masks.append(out.cpu().numpy())
        names = [v.name for v in self.views]
        sheet = transient_sheet(photos, masks, names, self.out_dir / "transients.png")
        return {"quantile": self.cfg.robust_quantile, "start": self.cfg.robust_start, "image": sheet.name,
                "masked_share": {n: round(float(m.mean()), 4) for n, m in zip(names, masks)}}

    def _appearance_init(self) -> np.ndarray | None:
        """The colour corrections' starting gains [V,3] (None when the correction is off): the poses stage's
        measured gains of the training views (`appearance.initial_gains`); the source goes into train.json."""
        if self.cfg.appearance == "off":
            return None
        gains, rec = appearance.initial_gains(self.exposure, [v.name for v in self.views],
                                              self.appearance_record.get("source"))
        self.appearance_record.update(rec)
        return gains

    def _loss_mask_record(self) -> dict | None:
        """train.json's record of the nerfstudio loss masks applied (None: no training view has one): the
        views masked and the share of each one's pixels the loss ignored."""
        masked = [v for v in self.views if v.mask is not None]
        if not masked:
            return None
        return {"applied": True, "views": len(masked), "of": len(self.views),
                "ignored_share": {v.name: round(1.0 - float(v.mask.mean()), 4) for v in masked},
                "protocol": "pixels a frame's mask_path sets to 0 are 0 in render and photo before L1 and D-SSIM "
                            "(as splatfacto): no loss, no gradient from them"}

    def _heldout_record(self) -> dict:
        """The hold-out this splat was trained without: the dataset's rule and, always, the views
        (transforms.json keeps the views in its frames' split, not in its rule record), so `eval` can
        tell them from the training views whatever split the dataset it is given has."""
        rec = self.dataset.meta.get("heldout")
        rec = dict(rec) if isinstance(rec, dict) else {}
        rec["views"] = [f.name for f in self.dataset.heldout()]
        return rec

    def _write_outputs(self, wall: float | None, loss: float | None, psnr: float | None,
                       resumed_at: int | None = None) -> TrainResult:
        g = self.model.to_gaussians()
        from splattwin.splat.eval import remove_evaluation   # (eval imports this module)

        # the held-out metrics and pictures of the splats this file replaces (`splattwin train` into a built
        # twin): the report would show them as this model's; the build's splats stage, or `eval`, writes new ones
        if remove_evaluation(self.out_dir / "eval"):
            log.info("removed %s: the held-out metrics and pictures of the earlier splats (run `splattwin eval` "
                     "for these)", self.out_dir / "eval")
        ply = g.save_ply(self.out_dir / "point_cloud.ply")
        refined = None
        if self.poses is not None:
            from splattwin.capture import invert_se3
            T_cw = self.poses.corrected(np.stack([v.camera.T_cam_world for v in self.views]))
            refined = {v.name: invert_se3(T).tolist() for v, T in zip(self.views, T_cw)}
            refined_poses.write(self.out_dir, refined)
        elif (self.out_dir / refined_poses.FILE).exists():
            # a stale one from an earlier run with refinement: the later stages would project with its poses
            (self.out_dir / refined_poses.FILE).unlink()
        extras.write(self.out_dir, self.appearance, self.bg_model, [v.name for v in self.views])
        plot_history(self.history, self.out_dir / "train_curves.png")
        transients = self._write_transients() if self.cfg.robust_quantile > 0 else None
        if transients is None and (self.out_dir / "transients.png").exists():
            (self.out_dir / "transients.png").unlink()   # a stale one from an earlier run with the masks
        write_json(self.out_dir / "train.json", obj={
            "dataset": str(self.dataset.root), "config": self.cfg.to_dict(), "strategy": self.strategy.describe(),
            "backend": self.backend, "resolution": self.resolution.record(),
            "heldout": self._heldout_record(),
            "profile": self.profile or "dense (defaults)",
            "init_method": self.init_method, "steps": self.step, "gaussians": len(g),
            "wall_s": None if wall is None else round(wall, 3), "resumed_at_step": resumed_at,
            "train_loss": loss, "train_psnr": psnr, "scene_scale": self.scene_scale,
            "views": [{"name": v.name, "width": v.camera.width, "height": v.camera.height} for v in self.views],
            "transients": transients, "loss_masks": self._loss_mask_record(),
            "appearance": ({**self.appearance_record, "gauge": self.appearance.gauge()} if self.appearance is not None
                           else self.appearance_record),
            "history": self.history})
        return TrainResult(g, ply, self.step, wall, loss, psnr, self.init_method, self.history, refined, resumed_at)


def train(dataset: Dataset | str | Path, out_dir: str | Path, cfg: TrainConfig | None = None, resume: bool = False,
          callback: Callable[[dict], None] | None = None, on_mismatch: str = "error",
          strategy: Strategy | None = None) -> TrainResult:
    """Train 3D Gaussians on `dataset`'s training frames (a `Dataset` or a path `load_dataset` reads); writes
    OUT/point_cloud.ply (see module doc). strategy: densification (`splattwin.splat.strategy`; default from cfg, see `Trainer`)."""
    return Trainer(dataset, out_dir, cfg, strategy).run(resume=resume, callback=callback, on_mismatch=on_mismatch)
