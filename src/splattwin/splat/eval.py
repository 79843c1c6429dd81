"""`splattwin eval`: render held-out views of a trained splat, PSNR and SSIM per view and mean,
side-by-side pictures (ground truth | render | error heat map) and a metrics JSON.

Views are rendered at the training resolution when a training folder (with train.json) or its
point_cloud.ply is given (the rule train.json records, `splattwin.splat.resolution`: a photo trained at
640 px on the CPU is evaluated at 640 px), else at the dataset's image size; `full_resolution=True` (`build
--eval-full-resolution`) renders at the full image size, `resolution=` at another 3DGS `-r` value.
metrics.json records the size used (`eval_resolution`) and the held-out views and their rule
(`heldout`). The background is the training background (black by default). The held-out views are the
ones train.json names when the dataset has them (`splattwin train --heldout-*` applies its hold-out to
the dataset it reads, so the dataset's own split may differ), else the dataset's; a view the splat was
trained on is never evaluated as held-out (`_heldout_split`). Without any held-out view the training
frames are evaluated instead (and flagged so).

Photos with lens distortion (SfM's SIMPLE_RADIAL) are compared undistorted, at their pinhole camera
(`capture.undistort.pinhole_for`, as they were trained; 3DGS evaluates on COLMAP-undistorted images too).

`align_poses=True` (`--align-poses`) first fits each held-out camera to its image with the splat fixed
(`pose_refine.align_camera`, InstantSplat's protocol): for models trained with pose refinement, whose
scene sits slightly off the input frame and whose held-out poses share the training poses' errors without
their correction. The metrics JSON then records the correction of every view, and both figures: `mean_psnr`
/ `mean_ssim` (the headline, `headline: "aligned"`) at the aligned poses, `mean_psnr_as_given` /
`mean_ssim_as_given` at the poses as given. The splat stage (`build`) evaluates this way by default when
the training refined its poses (`--splat.refine-poses`); without refinement the poses are used as given.

A learnt background (`TrainConfig.background_mode`, saved in the training folder's extras.safetensors, or
passed as `background_model=`) is composited behind the splats. Held-out views are rendered without a
colour correction (identity: `psnr`); every view also gets the appearance-protocol figures
(`appearance.heldout_corrected_psnr`: an affine colour fit on the left half of the image, PSNR on the
right half before/after it), so runs with and without `--appearance` compare on both.

Loss masks: a frame's nerfstudio `mask_path` (0 = ignore the pixel: people, the capture rig, sky) is
applied to its held-out view as in training (`trainer.load_views`): PSNR over the kept pixels only, SSIM
on both images with the ignored pixels set to 0 and its map averaged over the windows centred on kept
pixels (`metrics.masked_ssim`), and the appearance-protocol and coverage figures over the kept pixels.
The error map shows ignored pixels grey; metrics.json's `loss_masks` names the masked views (null: none).

Coverage (`training_coverage`): each held-out view also reports the share of its pixels whose rendered
surface point lies inside some training camera's image, and PSNR over those and over the rest. A sparse
sweep's end views are extrapolations (statue: 22.5 % of the held-out pixels lie in no training view); the
split tells a blur of what the photos saw from content they never held.
"""

from __future__ import annotations

import dataclasses

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from splattwin.capture import Dataset, Frame, load_dataset
from splattwin.capture.undistort import pinhole_for
from splattwin.errors import InputError
from splattwin.paths import LinkOutside, own_file
from splattwin.io import write_image, write_json
from splattwin.splat import metrics
from splattwin.splat.appearance import heldout_corrected_psnr
from splattwin.splat.config import filter_for, trained_filter
from splattwin.splat.losses import psnr_from_mse
from splattwin.splat.gaussians import Gaussians
from splattwin.splat.pose_refine import align_camera, pose_errors
from splattwin.splat.resolution import AUTO, FULL, MAX_SIDE, MIN_SIDE, Resolution, describe_sizes, resolve
from splattwin.splat.trainer import load_views

log = logging.getLogger(__name__)


@dataclass
class EvalResult:
    """What `evaluate` returns (OUT/eval/metrics.json holds the same): per-view and mean PSNR (dB) / SSIM of
    the renders against the photos of one split, and how they were compared (resolution, held-out rule,
    coverage by the training cameras, right-half colour-corrected PSNR). Field notes inline."""

    views: list[dict]          # {name, psnr, ssim, image[, pose_correction_deg, pose_correction, pose_correction_units
    #                            (, pose_correction_m: metric datasets only)]}
    mean_psnr: float
    mean_ssim: float
    split: str                 # "heldout" | "train"
    metrics_path: Path | None = None
    eval_resolution: dict | None = None  # {"mode", "how", "sizes", "full_sizes", "scale"} (metrics.json)
    heldout: dict | None = None          # {"views", "rule", "source"[, "every"]} (metrics.json)
    mean_psnr_right_plain: float = float("nan")      # right half, as rendered
    mean_psnr_right_corrected: float = float("nan")  # right half, affine colour fitted on the left half
    mean_covered_frac: float = float("nan")   # share of held-out pixels some training camera saw (see coverage)
    mean_psnr_covered: float = float("nan")   # PSNR over those pixels
    # align_poses only: the figures at the poses as given (mean_psnr / mean_ssim are the aligned ones), and the
    # held-out cameras as aligned (T_world_cam by view name)
    mean_psnr_as_given: float | None = None
    mean_ssim_as_given: float | None = None
    aligned_T_world_cam: dict | None = None
    mean_psnr_uncovered: float = float("nan")  # and over the rest (content no training photo holds)


def _coverage_means(rows: list[dict]) -> dict:
    """{"covered_frac", "psnr_covered", "psnr_uncovered"} over the views (PSNRs pooled by pixel count through
    their MSEs), None where no view has the figure."""
    got = [r for r in rows if "covered_frac" in r]
    if not got:
        return {"covered_frac": None, "psnr_covered": None, "psnr_uncovered": None}
    out = {"covered_frac": float(np.mean([r["covered_frac"] for r in got]))}
    for k, frac in (("psnr_covered", lambda r: r["covered_frac"]), ("psnr_uncovered", lambda r: 1 - r["covered_frac"])):
        parts = [(frac(r), 10 ** (-r[k] / 10)) for r in got if r.get(k) is not None]
        wsum = sum(f for f, _ in parts)
        out[k] = psnr_from_mse(sum(f * m for f, m in parts) / wsum) if parts and wsum > 0 else None
    return out


UNSEEN_TINT = np.array([40, 110, 255], np.uint8)  # error-map pixels no training camera saw (blended 50 %)
IGNORED_GREY = np.array([128, 128, 128], np.uint8)  # error-map pixels a loss mask ignores (not measured)


def side_by_side(gt: np.ndarray, render: np.ndarray, unseen: np.ndarray | None = None,
                 ignored: np.ndarray | None = None) -> np.ndarray:
    """[H, 3W + 8, 3] uint8: ground truth | render | error heat map, 4-px white gaps. unseen: [H,W] bool,
    pixels tinted blue in the error map (content no training photo holds, `training_coverage`); ignored:
    [H,W] bool, pixels shown grey in the error map (a loss mask leaves them out of the metrics)."""
    h = gt.shape[0]
    gap = np.full((h, 4, 3), 255, np.uint8)
    u8 = lambda a: (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    err = metrics.error_heatmap(render, gt)
    if unseen is not None and unseen.any():
        err[unseen] = ((err[unseen].astype(np.uint16) + UNSEEN_TINT) // 2).astype(np.uint8)
    if ignored is not None and ignored.any():
        err[ignored] = IGNORED_GREY
    return np.concatenate([u8(gt), gap, u8(render), gap, err], axis=1)


def training_coverage(depth: np.ndarray, alpha: np.ndarray, camera, train_cameras, T_cam_world=None,
                      min_alpha: float = 0.5) -> np.ndarray:
    """[H,W] bool: the held-out pixels whose surface point (the render's expected z-depth `depth` [H,W], m,
    where `alpha` [H,W] > min_alpha) lies inside the image of at least one training camera (in front of it).

    A frustum test, not an occlusion test: an upper bound on what the training photos saw. A sparse sweep's
    end views are extrapolations; the uncovered part is content no training photo holds, which no method
    can reconstruct, so its PSNR is reported apart (`evaluate`). camera: the held-out `Camera` (its K at the
    render's size); T_cam_world overrides its pose; train_cameras: `Camera`s at any size."""
    h, w = depth.shape
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"depth map is {w}x{h} but the camera is {camera.width}x{camera.height}")
    T_cw = camera.T_cam_world if T_cam_world is None else T_cam_world
    p_cam = camera.pixel_rays() * depth[..., None]
    T_wc = np.linalg.inv(T_cw)
    p_world = p_cam @ T_wc[:3, :3].T + T_wc[:3, 3]
    seen = np.zeros((h, w), bool)
    for c in train_cameras:
        q = c.world_to_cam(p_world)
        z = q[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (q @ c.K.T)[..., :2] / z[..., None]
        seen |= (z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 0] < c.width) & (uv[..., 1] >= 0) & (uv[..., 1] < c.height)
    return seen & (alpha > min_alpha) & (depth > 0)


def _shade(g, camera, T_cw, with_depth: bool, bg, background_model, backend, mode, eps2d):
    """(image [H,W,3] as evaluated, the raw render, alpha) of `camera` (at T_cw when given)."""
    from splattwin.splat.rendering import render

    rendered, alpha = render(g, camera, mode="RGB+ED" if with_depth else "RGB",
                             background=tuple(bg) if background_model is None else (0.0, 0.0, 0.0),
                             backend=backend, T_cam_world=T_cw, rasterize_mode=mode, eps2d=eps2d)
    img = np.clip(rendered[..., :3], 0.0, 1.0) if background_model is None else rendered[..., :3].copy()
    if background_model is not None:
        T = camera.T_cam_world if T_cw is None else T_cw
        with torch.no_grad():
            img = background_model.composite(
                torch.from_numpy(img), torch.from_numpy(alpha)[..., None],
                torch.tensor(camera.K, dtype=torch.float32),
                torch.linalg.inv(torch.tensor(T, dtype=torch.float32))).clamp(0, 1).numpy()
    return img, rendered, alpha


def _masked_psnr(img: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float | None:
    """`metrics.masked_psnr`, None (JSON null) for an empty mask."""
    p = metrics.masked_psnr(img, gt, mask)
    return None if np.isnan(p) else p


def _or_none(x: float) -> float | None:
    return None if x is None or np.isnan(x) else x


def _mean(rows: list[dict], key: str) -> float:
    """Mean of the views' `key` over the views that have it (a view whose loss mask ignores every pixel has
    no figure); NaN when none has."""
    vals = [r[key] for r in rows if r.get(key) is not None and not np.isnan(r[key])]
    return float(np.mean(vals)) if vals else float("nan")


def resolve_ply(path: str | Path) -> tuple[Path, dict]:
    """A PLY path and the training record (train.json, or {}) from a training folder or a PLY file.
    A training folder's own point_cloud.ply given by its path gets the folder's record too: the same
    splat, so the same held-out views and resolution."""
    path = Path(path)
    if path.is_file() and path.name == "point_cloud.ply" and (path.parent / "train.json").is_file():
        path = path.parent
    if path.is_dir():
        ply = path / "point_cloud.ply"
        if not ply.is_file() and (path / "splat" / "point_cloud.ply").is_file():
            # a twin folder given as README's `eval OUT` reads to a user of `build --out OUT`
            raise InputError(f"a twin folder (splattwin build's output), not a training folder: its splats are "
                             f"in splat/; evaluate them with `splattwin eval {path / 'splat'} --dataset "
                             f"{path / 'poses'}`", path)
        if not ply.is_file():
            raise InputError("no point_cloud.ply in this folder (train first: splattwin train)", path)
        own_file(path, ply, "point_cloud.ply")   # a training folder's own files, not a link out of it
        rec = own_file(path, path / "train.json", "train.json")
        return ply, (training_record(rec) if rec.is_file() else {})
    if not path.is_file():
        raise InputError("splat file or training folder does not exist", path)
    return path, {}


def training_record(path: Path) -> dict:
    """train.json of a training folder, checked before anything is sized from it: a training folder may
    come from someone else, and its recorded resolution sets the size of every rendered view (a target
    width of 100000 px took 23 GB). InputError naming the file."""
    from splattwin.limits import MAX_RECORD_BYTES, number, read_json

    info = read_json(path, max_bytes=MAX_RECORD_BYTES)
    if not isinstance(info, dict):
        raise InputError("malformed training record: expected a JSON object", path)
    for k in ("config", "resolution", "heldout"):
        if info.get(k) is not None and not isinstance(info[k], dict):
            raise InputError(f"malformed training record: {k} must be a JSON object", path)
    # the views trained on and held out decide which views are evaluated as held-out (_heldout_split)
    rows = info.get("views")
    if rows is not None and not (isinstance(rows, list) and all(
            isinstance(r, dict) and isinstance(r.get("name"), str) for r in rows)):
        raise InputError("malformed training record: views must be a list of objects with a name", path)
    held = (info.get("heldout") or {}).get("views")
    if held is not None and not (isinstance(held, list) and all(isinstance(n, str) for n in held)):
        raise InputError("malformed training record: heldout views must be a list of view names", path)
    cfg = info.get("config") or {}
    rec = info.get("resolution")
    rules = [("resolution", rec.get("resolution")), ("max_side", rec.get("max_side"))] if rec else []
    rules += [("config resolution", cfg.get("resolution")), ("config cpu_max_side", cfg.get("cpu_max_side"))]
    for what, v in rules:
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, int):
            raise InputError(f"training record: {what} must be a whole number, got {type(v).__name__}", path)
        try:
            if what.endswith("max_side"):
                if not MIN_SIDE <= v <= MAX_SIDE:
                    raise InputError(f"--cpu-max-side must be in [{MIN_SIDE}, {MAX_SIDE}] px, got {v}")
            elif v != AUTO:
                Resolution(v).scale(100, 100)  # the rule the CLI applies to --resolution
        except InputError as e:
            raise InputError(f"training record: {what}: {e.problem}", path) from None
    try:
        trained_filter(cfg or None)
    except ValueError as e:
        raise InputError(f"config: {e}", path) from None
    if cfg.get("background") is not None:
        bg = cfg["background"]
        if not isinstance(bg, (list, tuple)) or len(bg) != 3:
            raise InputError("training record: config background must be 3 numbers", path)
        for x in bg:
            number(x, path, "config background", 0.0, 1.0)
    return info


def _earlier_images(out: Path) -> list[str]:
    """The comparison images an earlier evaluation into `out` wrote, as its metrics.json lists them: plain
    .png file names only ([] without a readable metrics.json)."""
    from splattwin import io

    prev = io.read_record(out / "metrics.json")
    rows = prev.get("views") if isinstance(prev, dict) else None
    names = [r.get("image") for r in (rows if isinstance(rows, list) else []) if isinstance(r, dict)]
    return [n for n in names if isinstance(n, str) and n.endswith(".png") and n == Path(n).name
            and not n.startswith(".")]


def _remove_earlier_images(out: Path, keep: set[str]) -> None:
    """Remove the comparison images an earlier evaluation into `out` listed in its metrics.json that this one
    did not write (a view held out then and trained on now kept its old picture beside the new ones). Only
    plain file names that metrics.json listed go, never anything else in the folder."""
    from splattwin.io import remove_files

    remove_files(out, [n for n in _earlier_images(out) if n not in keep])


def remove_evaluation(out: str | Path) -> list[Path]:
    """Remove an evaluation's files from its folder `out` (`TRAINING/eval`): the comparison images its
    metrics.json lists, then metrics.json, then the folder when nothing else is left in it. For the splats
    they measured being replaced (`train` into a built twin): the report showed that PSNR and those
    pictures as the new model's. Nothing else in the folder goes. Returns the files removed."""
    from splattwin.io import remove_files

    out = Path(out)
    if out.is_symlink() or not (out / "metrics.json").is_file():
        return []
    return remove_files(out, _earlier_images(out) + ["metrics.json"], empty_folder=True)


def _heldout_split(ds: Dataset, info: dict) -> tuple[list[Frame], list[Frame], dict]:
    """(held-out frames, the frames the splat was trained on, the hold-out record) of `ds` for the
    training record `info` (train.json, {} for a bare PLY).

    The training record decides: `splattwin train --heldout-*` splits the dataset it reads in memory, so
    the dataset's own split (e.g. the poses stage's default every 8th view) may name views this splat was
    trained on. The views train.json holds out are evaluated when the dataset has them, and no view it
    trained on is ever reported as held-out."""
    rec = info.get("heldout") if isinstance(info.get("heldout"), dict) else None
    rows = info.get("views") if isinstance(info.get("views"), list) else []
    trained = {str(r["name"]) for r in rows if isinstance(r, dict) and "name" in r}
    frames, held = ds.heldout(), dict(ds.meta.get("heldout") or rec or {})
    named = {str(n) for n in rec["views"]} if rec and isinstance(rec.get("views"), list) else set()
    listed = [f for f in ds.frames if f.name in named and f.name not in trained]
    if listed:
        if {f.name for f in listed} != {f.name for f in frames} and frames:
            log.info("evaluating the views held out in training (%s: %s), not the dataset's split (%s)",
                     rec.get("rule", "train.json"), ", ".join(f.name for f in listed),
                     ", ".join(f.name for f in frames))
        frames, held = listed, dict(rec)
    seen = [f.name for f in frames if f.name in trained]
    if seen:
        log.warning("%s: trained on by this splat, so not evaluated as held-out", ", ".join(seen))
        frames = [f for f in frames if f.name not in trained]
    # a record naming none of these frames: trained on another capture, the dataset's training views stand in
    train_frames = [f for f in ds.frames if f.name in trained] or ds.train()
    return frames, train_frames, held


def dataset_units(ds: Dataset) -> str:
    """The length unit of the dataset's poses: its frame.json's (the poses stage writes one beside
    transforms.json: "m" or "unscaled"); without one a COLMAP model is unscaled (SfM units) and other
    known poses are taken as metres, as the poses stage takes them."""
    from splattwin.poses.twin_frame import UNSCALED_UNITS, frame_beside

    try:
        frame = frame_beside(ds.meta.get("path", ds.root))
    except LinkOutside:   # a link out of the poses folder is bad input, not a bad frame
        raise
    except InputError as e:
        log.warning("%s; pose corrections in the dataset's units, taken as unscaled", e)
        return UNSCALED_UNITS
    if frame is not None:
        return frame.units
    return UNSCALED_UNITS if ds.meta.get("format") == "colmap" else "m"


def _eval_resolution(info: dict, resolution: int | None, full_resolution: bool) -> tuple[Resolution, str]:
    """(the rule, its name for metrics.json): an explicit `resolution` (a 3DGS `-r` value; 0 = auto as on
    the CPU), the full size, or the training resolution train.json recorded (older train.json: its
    config's `resolution`; nothing recorded: full size)."""
    cfg = info.get("config", {}) if isinstance(info.get("config"), dict) else {}
    if resolution is not None:
        return resolve(int(resolution), int(cfg.get("cpu_max_side", 640)), "cpu"), "given"
    if full_resolution:
        return FULL, "full"
    # the training size, never above the photo's own: a held-out photo upsampled holds nothing more, and a
    # received train.json's target width would otherwise size every view up to the pixel limit
    rec = Resolution.from_record(info.get("resolution"))
    if rec is not None:
        return dataclasses.replace(rec, max_scale=1.0), "training"
    r = cfg.get("resolution")
    if isinstance(r, int) and r != 0:
        return Resolution(r, None, f"--resolution {r}", max_scale=1.0), "training"
    return FULL, "full"


def evaluate(splat: str | Path | Gaussians, dataset: Dataset | str | Path, out_dir: str | Path | None = None,
             resolution: int | None = None, background=None, backend: str = "auto",
             progress: bool = True, rasterize_mode: str | None = None, eps2d: float | None = None,
             align_poses: bool = False, align_iters: int = 300, full_resolution: bool = False,
             background_model=None, align_reason: str | None = None) -> EvalResult:
    """Evaluate a splat (training folder, PLY path, or `Gaussians`) on the dataset's held-out views
    (see the module docstring for the resolution). background_model: a learnt
    `background.BackgroundModel` to composite (default: the one saved beside the PLY, if any).
    rasterize_mode, eps2d: the rasterizer's mode and low-pass (px^2); None: as train.json records them (bare
    Gaussians: classic, and a mode's default low-pass)."""
    from splattwin.progress import track

    from splattwin.capture.dataset import refuse_video
    from splattwin.splat import extras

    if not isinstance(dataset, Dataset):
        refuse_video(dataset, "eval")
    info: dict = {}
    if isinstance(splat, Gaussians):
        g = splat
    else:
        ply, info = resolve_ply(splat)
        g = Gaussians.load_ply(ply)
        if background_model is None:
            background_model = extras.read_background(ply.parent)
    if g.sh_degree > 3:
        log.warning("SH degree %d: rendering with the first 3 degrees", g.sh_degree)
        g = g.with_sh_degree(3)
    # transparent pixels' loss masks (`capture.images.mask_transparent_pixels`) go into the output
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(
        dataset, frames_dir=None if out_dir is None else Path(out_dir) / "capture" / "frames")
    if not ds.has_poses:
        raise InputError("dataset has no camera poses to render from (photos or a video: give the posed dataset "
                         "the poses stage wrote, a twin's poses/ folder, or run splattwin poses first)", ds.root)
    frames, train_frames, held = _heldout_split(ds, info)
    split = "heldout"
    if not frames:
        log.warning("dataset has no held-out frames: evaluating the training frames (not a generalisation test)")
        frames, split = train_frames, "train"
    cfg = info.get("config", {})
    rule, mode_res = _eval_resolution(info, resolution, full_resolution)
    bg = background if background is not None else cfg.get("background", (0.0, 0.0, 0.0))
    # the mode and low-pass the splats were trained with (train.json); bare Gaussians: the mode's default
    trained: tuple[str, float | None] = ("classic", None)
    if cfg:
        try:
            trained = trained_filter(cfg)
        except ValueError as e:
            raise InputError(f"config: {e}", ply.parent / "train.json") from None
    mode, low_pass = filter_for(trained, rasterize_mode or None)
    eps2d = low_pass if eps2d is None else float(eps2d)
    views = load_views(frames, rule)
    sizes = [(v.camera.width, v.camera.height) for v in views]
    full = [(f.camera.width, f.camera.height) for f in frames]
    eval_res = {"mode": mode_res, "how": rule.how, "sizes": describe_sizes(sizes),
                "full_sizes": describe_sizes(full), "scale": round(min(w / fw for (w, _), (fw, _) in zip(sizes, full)), 6)}
    log.info("evaluating %d %s views at %s (%s)", len(views), split, eval_res["sizes"], mode_res)
    held = {k: held[k] for k in ("source", "rule", "every") if k in held}
    held["views"] = [f.name for f in frames] if split == "heldout" else []
    out = Path(out_dir) if out_dir is not None else None
    # the training photos' pinhole cameras: what the splats were fitted to (undistorted, `load_views`)
    train_cams = [pinhole_for(f.camera) for f in train_frames] if split == "heldout" else []
    units = dataset_units(ds)
    rows, aligned_poses = [], {}
    for v in track(views, "eval", unit="view", enabled=progress):
        gt = v.image.numpy()
        T_cw, extra = None, {}
        if align_poses:
            T_cw = align_camera(g, v.camera, gt, iters=align_iters, background=tuple(bg), backend=backend,
                                rasterize_mode=mode, eps2d=eps2d)
            rot, centre = pose_errors(T_cw[None], v.camera.T_cam_world[None])
            extra = {"pose_correction_deg": float(rot[0]), "pose_correction": float(centre[0]),
                     "pose_correction_units": units}
            if units == "m":  # the older key, kept for its readers; never written for a length that is no metre
                extra["pose_correction_m"] = float(centre[0])
        # the expected depth for the coverage test comes from the same pass as the colours
        with_depth = split == "heldout" and bool(train_cams)
        img, rendered, alpha = _shade(g, v.camera, T_cw, with_depth, bg, background_model, backend, mode, eps2d)
        # the frame's loss mask: only its kept pixels are measured (module doc)
        keep = None if v.mask is None else v.mask[..., 0].numpy() > 0.5
        if align_poses:  # the figures at the pose as given too (the metrics record both, the aligned is the headline)
            plain = _shade(g, v.camera, None, False, bg, background_model, backend, mode, eps2d)[0]
            extra.update(psnr_as_given=metrics.psnr(plain, gt) if keep is None else _masked_psnr(plain, gt, keep),
                         ssim_as_given=metrics.ssim(plain, gt) if keep is None
                         else _or_none(metrics.masked_ssim(plain, gt, keep)))
            aligned_poses[v.name] = np.linalg.inv(T_cw)
        if keep is None:
            row = {"name": v.name, "psnr": metrics.psnr(img, gt), "ssim": metrics.ssim(img, gt), **extra,
                   **heldout_corrected_psnr(img, gt)}
        else:
            row = {"name": v.name, "psnr": _masked_psnr(img, gt, keep),
                   "ssim": _or_none(metrics.masked_ssim(img, gt, keep)),
                   "ignored_frac": round(1.0 - float(keep.mean()), 6), **extra,
                   **{k: _or_none(x) for k, x in heldout_corrected_psnr(img, gt, mask=keep).items()}}
        seen = None
        if with_depth:
            seen = training_coverage(rendered[..., 3], alpha, v.camera, train_cams, T_cam_world=T_cw)
            if keep is None:
                row.update(covered_frac=float(seen.mean()), psnr_covered=_masked_psnr(img, gt, seen),
                           psnr_uncovered=_masked_psnr(img, gt, ~seen))
            elif keep.any():
                row.update(covered_frac=float(seen[keep].mean()), psnr_covered=_masked_psnr(img, gt, seen & keep),
                           psnr_uncovered=_masked_psnr(img, gt, ~seen & keep))
        if out is not None:
            row["image"] = f"{v.name}.png"
            write_image(out / row["image"], side_by_side(gt, img, None if seen is None else ~seen,
                                                         None if keep is None else ~keep))
        rows.append(row)
    mean_psnr, mean_ssim = _mean(rows, "psnr"), _mean(rows, "ssim")
    masked_views = [v.name for v in views if v.mask is not None]
    if masked_views:
        log.info("loss masks: %d of %d evaluated views measured over their kept pixels only", len(masked_views),
                 len(views))
    cov = _coverage_means(rows)
    result = EvalResult(rows, mean_psnr, mean_ssim, split, eval_resolution=eval_res, heldout=held,
                        mean_psnr_right_plain=_mean(rows, "psnr_right_plain"),
                        mean_psnr_right_corrected=_mean(rows, "psnr_right_corrected"),
                        **{f"mean_{k}": (float("nan") if x is None else x) for k, x in cov.items()})
    poses_rec = {"poses": "as given"}
    if align_poses:
        result.aligned_T_world_cam = aligned_poses
        result.mean_psnr_as_given, result.mean_ssim_as_given = _mean(rows, "psnr_as_given"), _mean(rows, "ssim_as_given")
        poses_rec = {"poses": "aligned (test-time pose fit)", "headline": "aligned",
                     "mean_psnr_aligned": mean_psnr, "mean_ssim_aligned": mean_ssim,
                     "mean_psnr_as_given": result.mean_psnr_as_given, "mean_ssim_as_given": result.mean_ssim_as_given,
                     "pose_protocol": "mean_psnr / mean_ssim (the headline) with each held-out camera first fitted to "
                                      "its image with the splats fixed; *_as_given at the dataset's poses"
                                      + (f" ({align_reason})" if align_reason else "")}
    if out is not None:
        _remove_earlier_images(out, {r["image"] for r in rows})
        result.metrics_path = write_json(out / "metrics.json", {
            "split": split, "mean_psnr": mean_psnr, "mean_ssim": mean_ssim, "n_views": len(rows),
            "mean_psnr_right_plain": result.mean_psnr_right_plain,
            "mean_psnr_right_corrected": result.mean_psnr_right_corrected,
            "appearance_protocol": "psnr_right_*: right half of each view; corrected = affine colour fitted "
                                   "on its left half (ridge towards identity)",
            **poses_rec, "units": units,
            **{f"mean_{k}": x for k, x in cov.items()},
            "coverage_protocol": "covered = held-out pixels whose rendered surface point lies inside some training "
                                 "camera's image (frustum test, occlusion ignored); psnr_covered / psnr_uncovered "
                                 "over those and the other pixels (pooled over the views)",
            "gaussians": len(g), "resolution": rule.resolution, "eval_resolution": eval_res, "heldout": held,
            # photos with lens distortion are compared undistorted, at their pinhole cameras (load_views)
            "undistorted_views": [f.name for f in frames if f.camera.dist is not None],
            # nerfstudio loss masks (mask_path): which views were measured over their kept pixels only
            "loss_masks": {"applied": True, "views": masked_views,
                           "protocol": "pixels a frame's mask_path sets to 0 are left out: PSNR over the kept "
                                       "pixels; SSIM with the ignored pixels 0 in both images, its map averaged "
                                       "over windows centred on kept pixels; psnr_right_* and coverage over the "
                                       "kept pixels"} if masked_views else None,
            "views": rows,
            "legend": "images: ground truth | render | |error| heat map (black 0 -> white >= 0.25; tinted blue: "
                      "pixels no training camera saw; grey: pixels a loss mask ignores)"})
    return result
