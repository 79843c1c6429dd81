"""Pre-flight: the checks `build` runs before any stage, in seconds, so that a run that cannot succeed
stops (InputError, exit 2) before minutes of SfM and hours of training, with a message naming the file,
model or option:

- 2D masks (`--masks`, or without it a scene folder's own: the embedded scene's masks/noisy/, a robot-style
  BOP capture's mask_visib/) read and fit the capture's images (`semantics.stage.check_masks`); a build whose
  semantics stage would run with no masks at all (no --masks, no --prompt, no masks of the scene's own)
  stops here, not after SfM and training, and says how to build the splats alone (`--until splats`);
- `--prompt`: the segmentation models it needs (Grounding DINO + SAM, or SAM 3) are on this machine,
  all missing ones named with their hub ids (`semantics.models`);
- `--task`: the twin will be metric. An image folder or video posed by SfM is known only up to scale;
  without --known-length, --marker-size or --robot-poses the robot stage would refuse it after training;
- a video gives the poses stage at least 2 frames (none decodes, 1 frame, or --max-frames 1 with SfM:
  `check_video_frames`, naming the video);
- the task YAML parses;
- `--known-length` parses and the images it names (`baseline@IMG_A,IMG_B`, `camera_height@IMG`) are in the
  capture (`check_known_length`; the poses stage found a typo only after SfM);
- the training options lie in their ranges (`TrainConfig.check`, which the trainer runs again), when the
  splat stage will run;
- memory and disk for the capture at the training resolution and the Gaussian budget (`estimate`):
  refused only when clearly insufficient (the estimate above `REFUSE_FACTOR` times what is free), a
  warning when tight.

Reads image headers only (no decoding); a video is probed for its frame size and its first 2 frames
decoded, no more. Photos stored
rotated (EXIF Orientation) are the exception: their upright copies are written here, into the twin's
capture/frames/upright/, and the poses stage reuses them (`capture.orientation`).
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from splattwin.errors import InputError

log = logging.getLogger(__name__)

GIB = 2 ** 30
REFUSE_FACTOR = 1.5     # refuse when the estimate exceeds what is free by this factor ("clearly")
WARN_FACTOR = 0.8       # warn when the estimate exceeds this share of what is free
# Measured peaks (bench/real.py psnr_heldout_statue checks the estimate against a build's peak RSS):
BASE_PROCESS = 0.6 * GIB    # Python + torch + numba + open3d + mujoco + pycolmap imported: 0.43 GiB measured
SFM_BASE = 0.7 * GIB        # pycolmap worker process: SIFT at --max-image-size, matching (bench/real.py: <= 0.69)
BYTES_PER_GAUSSIAN = 2000   # params, grads, 2 Adam moments, densify statistics, per-view projections and
# autograd intermediates (bench/train.py: 0.45 GiB above the imports at 640x480 with 56k Gaussians)
RASTER_BYTES_PER_PIXEL = 800            # CPU rasterizer: per-pixel state, tile lists, backward buffers

@dataclass
class Estimate:
    """Bytes needed at peak (memory) and written (disk), with the parts that make them up."""

    memory: float
    disk: float
    parts: dict = field(default_factory=dict)

    def describe(self) -> str:
        return ", ".join(f"{k} {v / GIB:.2f} GiB" for k, v in self.parts.items())


def estimate(sizes: list[tuple[int, int]], train_sizes: list[tuple[int, int]], max_gaussians: int, sfm: bool,
             capture_bytes: int, max_image_size: int = 1600) -> Estimate:
    """Peak memory and disk of a build of views of `sizes` (w, h) trained at `train_sizes`, with at most
    `max_gaussians` (0: the trainer's default for the training size, `splat.resolution.capacity`), with
    SfM or not; `capture_bytes`: the capture's files (bundled into the twin: hard links where possible,
    copies at worst). SfM runs in its own process before training: the peak is the larger of the SfM
    phase (this process + the worker) and the training phase."""
    from splattwin.splat.resolution import capacity

    n = len(sizes)
    train_px = sum(w * h for w, h in train_sizes)
    if max_gaussians <= 0:
        max_gaussians = capacity(train_px / max(n, 1))[1]
    big = max((w * h for w, h in sizes), default=0)
    parts = {
        "process": BASE_PROCESS,
        "training images": train_px * 3 * 4 * 1.0,                  # float32 RGB in memory
        "decoding one image": big * 3 * 5,                           # uint8 + float32 while resizing
        "Gaussians": max_gaussians * BYTES_PER_GAUSSIAN,
        "rasterizer": max((w * h for w, h in train_sizes), default=0) * RASTER_BYTES_PER_PIXEL,
    }
    training = sum(parts.values())
    sfm_phase = 0.0
    if sfm:
        side = max_image_size or max((max(s) for s in sizes), default=0)
        parts["SfM"] = SFM_BASE + min(big, side * side) * 4 * 2
        sfm_phase = BASE_PROCESS + parts["decoding one image"] + parts["SfM"]
    memory = max(training, sfm_phase)
    disk = (capture_bytes + 2 * 3 * max_gaussians * 59 * 4     # bundle (copies at worst) + 2 checkpoints
            + max_gaussians * 62 * 4 * 2                        # PLYs (splat, objects)
            + train_px * 3                                      # label maps, eval pictures (PNG, uncompressed bound)
            + (n * 4096 * 140 + n * n * 4096 * 8 // 10 if sfm else 0)   # SfM database: features + matches
            + 200 * 2 ** 20)                                    # twin exports, report, robot outputs
    return Estimate(memory, disk, parts)


def available_memory() -> float:
    """Bytes of memory a new allocation can get now (MemAvailable + free swap)."""
    import psutil

    return float(psutil.virtual_memory().available + psutil.swap_memory().free)


def free_disk(path: Path) -> float:
    p = Path(path).resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    return float(shutil.disk_usage(p).free)


def check_resources(est: Estimate, out: Path, what: str) -> None:
    """InputError when memory or disk is clearly insufficient for `est`; a warning when tight."""
    mem, disk = available_memory(), free_disk(out)
    if est.memory > REFUSE_FACTOR * mem:
        raise InputError(f"not enough memory for {what}: needs about {est.memory / GIB:.1f} GiB ({est.describe()}) "
                         f"but {mem / GIB:.1f} GiB is free. Train at a lower resolution (--cpu-max-side, "
                         f"--resolution 2/4), lower --splat.max-gaussians, use fewer views, or free memory")
    if est.disk > REFUSE_FACTOR * disk:
        raise InputError(f"not enough disk space for {what}: needs about {est.disk / GIB:.1f} GiB but "
                         f"{disk / GIB:.1f} GiB is free here", out)
    if est.memory > WARN_FACTOR * mem:
        log.warning("memory is tight: about %.1f GiB needed (%s), %.1f GiB free", est.memory / GIB, est.describe(),
                    mem / GIB)
    if est.disk > WARN_FACTOR * disk:
        log.warning("disk space is tight in %s: about %.1f GiB needed, %.1f GiB free", out, est.disk / GIB, disk / GIB)


# -- scale -----------------------------------------------------------------------------------------
def unscaled_reason(poses, has_poses: bool, fmt: str | None, frame_json_beside: bool,
                    sfm_derived: bool = False, has_depth: bool = False) -> str | None:
    """Why the poses stage will produce an unscaled frame with these `PoseOptions`, or None when it will
    be metric (mirrors `splattwin.poses.estimate`: robot poses, a marker or a known length give scale; so
    does SfM on an RGB-D capture (its depth images) and so do known poses, except SfM output (a COLMAP
    model, a 3DGS cameras.json, a transforms.json from nerfstudio's COLMAP converters: `sfm_derived`)
    without a frame.json beside it; `--scale` overrides for known poses)."""
    if poses.robot_poses is not None or poses.marker_size is not None or poses.known_length is not None:
        return None
    method = poses.method
    if method == "auto":
        method = "known" if has_poses else "sfm"
    if method == "sfm":
        if has_depth and poses.scale_from_depth:
            return None   # the depth images give the scale (estimate._depth_scale; refused later if they disagree)
        return "structure from motion recovers the scene only up to an unknown scale"
    if method == "known" and poses.scale != "auto":
        return "--scale unscaled" if poses.scale == "unscaled" else None
    if method == "known" and not frame_json_beside:
        if fmt == "colmap":
            return "a COLMAP model is SfM output in arbitrary units"
        if fmt == "cameras.json":
            return "a 3DGS cameras.json is SfM output in arbitrary units"
        if sfm_derived:
            return "this transforms.json was written by nerfstudio's COLMAP converters: SfM output in arbitrary units"
    return None


SCALE_HELP = ("give the metric scale with one of: --known-length camera_height=0.45 (mean camera height above the "
              "table, m) or --known-length baseline@IMG_A,IMG_B=0.30 (distance between two camera centres, m); "
              "--marker-size 0.05 (an ArUco DICT_4X4_50 marker of that side in view); --robot-poses POSES.json "
              "(+ --hand-eye); or a capture with known metric poses (transforms.json, BOP or TUM RGB-D; --scale metric "
              "when known poses are in metres but taken as SfM output), or RGB-D images without poses. "
              "Without --task the twin is built unscaled")


# -- the whole pre-flight ---------------------------------------------------------------------------
def _raise(problems: list[InputError]) -> None:
    """Nothing for no problem; the problem itself for one; one InputError listing them all for several."""
    if len(problems) == 1:
        raise problems[0]
    if problems:
        lines = [f"  {i}. {e}" for i, e in enumerate(problems, 1)]
        raise InputError(f"pre-flight found {len(problems)} problems:\n" + "\n".join(lines))


def _runs(until: str | None, stage: str) -> bool:
    """Whether `stage` is among the stages a build with --until `until` runs."""
    from splattwin.pipeline.build import stages

    names = [s.name for s in stages()]
    return until is None or until not in names or names.index(stage) <= names.index(until)


def _video_sizes(path: Path, max_frames: int | None = None) -> list[tuple[int, int]]:
    """Frame sizes a video will give with --max-frames `max_frames` (probed, not decoded)."""
    from splattwin.frame_options import VIDEO_MAX_FRAMES

    from splattwin.capture.video import open_video

    max_frames = VIDEO_MAX_FRAMES if max_frames is None else max_frames
    c = open_video(path)
    try:
        s = c.streams.video[0]
        n = min(max_frames, s.frames or max_frames)
        return [(int(s.codec_context.width), int(s.codec_context.height))] * n
    finally:
        c.close()


def _decodable_frames(path: Path, want: int = 2) -> tuple[int, str | None]:
    """How many frames, up to `want`, the video decodes from its start, and the decoding error that stopped
    it (None when it ended or `want` were decoded). A stream's declared frame count is not enough: a damaged
    file declares 20 frames and decodes none."""
    from splattwin.capture.video import open_video

    c = open_video(path)
    n = 0
    try:
        for _ in c.decode(video=0):
            n += 1
            if n >= want:
                break
    except Exception as e:  # noqa: BLE001 - PyAV decode errors have many types
        return n, str(e)
    finally:
        c.close()
    return n, None


def check_video_frames(path: Path, max_frames: int | None, sfm: bool) -> None:
    """InputError naming the video when it cannot give the poses stage 2 frames: none decodes, or (with SfM)
    it or --max-frames gives only one. Decodes at most 2 frames (a video that pauses may still collapse
    to one frame after near-duplicates are skipped: the poses stage says so then)."""
    from splattwin.frame_options import VIDEO_MAX_FRAMES
    from splattwin.wording import plural

    n, err = _decodable_frames(path)
    if n == 0:
        raise InputError("gave no frame: " + (f"decoding failed at its first frame ({err})" if err else
                                              "the video has no frames"), path)
    wanted = VIDEO_MAX_FRAMES if max_frames is None else max_frames
    if sfm and min(n, wanted) < 2:
        why = (f"--max-frames {wanted}" if n >= 2 else "the video has 1 decodable frame"
               + (f"; decoding failed after it: {err}" if err else ""))
        raise InputError(f"gave {plural(min(n, wanted), 'frame')} ({why}); structure from motion needs >= 2", path)


def check_known_length(text: str, ds) -> None:
    """--known-length parses, and the images it names are in the capture `ds` (None: a video, not read
    here). The poses stage checked the names only after SfM: a typo in baseline@IMG_A,IMG_B cost the whole
    SfM run (a minute on the real cake) before "not among the registered images"."""
    from splattwin.poses.table import KnownLength

    try:
        kl = KnownLength.parse(text)
    except InputError as e:   # "known length kind 'height': ..." named neither the flag nor the value given
        if e.problem.startswith("--known-length"):
            raise
        raise InputError(f"--known-length {text!r}: {e.problem}") from e
    if ds is None or not kl.images:
        return
    known = {n for f in ds.frames for n in (f.name, f.image_path.name, f.image_path.stem)}
    missing = [n for n in kl.images if n not in known]
    if missing:
        some = ", ".join(sorted(f.image_path.name for f in ds.frames)[:4])
        raise InputError(f"--known-length {text!r}: no image named {', '.join(map(repr, missing))} in this "
                         f"capture (its images: {some}{', ...' if len(ds.frames) > 4 else ''}; give a file name "
                         f"with or without its suffix)", "--known-length")


def run_preflight(options, out: Path, input_path: Path | None, scene_dir: Path | None, frames_dir: Path,
                  until: str | None = None, progress: bool = True) -> dict:
    """All checks for `BuildOptions` `options` building into `out` (see module docstring). input_path:
    the capture (None for the embedded scene, generated later). until: the last stage that will run
    (None: all). progress: of a video's frame extraction (build --no-progress: none). Returns what it
    measured."""
    import time

    from splattwin.capture.dataset import VIDEO_SUFFIXES

    t0 = time.perf_counter()
    o = options
    info: dict = {}
    # every independent problem is collected, so one run names all of them (a user fixing the first and
    # re-running only to meet the second is what pre-flight is for)
    problems: list[InputError] = []
    if _runs(until, "splats"):  # option ranges the trainer would refuse only after the poses
        try:
            o.splat.check()
        except InputError as e:
            problems.append(e)
    # models first: needs no capture at all
    if o.semantics.prompt and not o.semantics.masks:
        from splattwin.semantics.segment import prompt_object_names

        try:
            prompt_object_names(o.semantics.prompt)  # the names the objects will get (reserved, unique, ASCII)
        except InputError as e:
            problems.append(e)
        from splattwin.semantics.models import missing_models_error

        err = missing_models_error(o.semantics.segment)
        if err is not None:
            problems.append(err)
    if o.robot.task and o.robot.task != "default":
        from splattwin.robot.task import load_task

        try:
            load_task(o.robot.task)  # the file parses as a task (bounded YAML); checked against the twin later
        except InputError as e:
            problems.append(e)
    if input_path is None:
        _raise(problems)
        return info
    if not (o.semantics.masks or o.semantics.prompt) and scene_dir is None and _runs(until, "semantics"):
        problems.append(InputError(
            "no 2D masks for the semantics stage (which objects are where): pass --masks DIR (mask images per "
            "view and object, BOP mask_visib, COCO JSON) or --prompt 'red mug. cereal box' (open-vocabulary "
            "segmentation); or build only the splats with --until splats", input_path))
    video = input_path.is_file() and input_path.suffix in VIDEO_SUFFIXES
    sfm = o.poses.method == "sfm" or (o.poses.method == "auto" and o.poses.robot_poses is None)
    if video:   # frames it will give: 0 or 1 fail in the poses stage with a message that names no video
        try:
            check_video_frames(input_path, o.poses.max_frames, sfm)
        except InputError as e:
            problems.append(e)
            _raise(problems)   # nothing below can read this video
    ds = None
    if not video or o.semantics.masks:
        from splattwin.capture import load_dataset

        # image headers only; nothing else works without (a video: its frames as the poses stage extracts them)
        ds = load_dataset(input_path, frames_dir=frames_dir, max_frames=o.poses.max_frames,
                          min_change=o.poses.min_change, progress=progress)
    if isinstance(o.poses.known_length, str) and _runs(until, "poses"):
        try:
            check_known_length(o.poses.known_length, ds)
        except InputError as e:
            problems.append(e)
    if o.robot.task:
        fmt = ds.meta.get("format") if ds is not None else "video"
        meta_path = Path(ds.meta.get("path", ds.root)) if ds is not None else input_path
        beside = (meta_path.parent if meta_path.is_file() else meta_path) / "frame.json"
        why = unscaled_reason(o.poses, bool(ds is not None and ds.has_poses), fmt, beside.is_file(),
                              sfm_derived=bool(ds is not None and ds.meta.get("sfm_derived")),
                              has_depth=bool(ds is not None and any(f.depth_path is not None for f in ds.frames)))
        if why is not None:
            problems.append(InputError(f"--task needs a metric twin, but this capture gives no scale ({why}): "
                                       f"{SCALE_HELP}", input_path))
    own_masks = (not (o.semantics.masks or o.semantics.prompt) and scene_dir is not None and ds is not None
                 and _runs(until, "semantics"))   # a scene folder's own masks (`scene_default_masks`)
    if o.semantics.masks or own_masks:
        from splattwin.semantics.stage import check_masks

        try:
            check_masks(o.semantics, ds.frames, scene_dir)
        except InputError as e:
            problems.append(e)
    _raise(problems)
    # resources at the training resolution
    from splattwin.splat.resolution import resolve

    sizes = (_video_sizes(input_path, o.poses.max_frames) if ds is None
             else [(f.camera.width, f.camera.height) for f in ds.frames])
    device = "cuda" if o.splat.device == "cuda" else "cpu"
    rule = resolve(o.splat.resolution, o.splat.cpu_max_side, device)
    train_sizes = [rule.size(w, h) for w, h in sizes]
    capture_bytes = 0
    if ds is not None:
        for f in ds.frames:
            for p in (f.image_path, f.depth_path, f.mask_path):
                if p is not None:
                    try:
                        capture_bytes += os.stat(p).st_size
                    except OSError:
                        pass
    else:
        capture_bytes = sum(w * h * 3 for w, h in sizes)
    has_poses = bool(ds is not None and ds.has_poses)
    sfm = sfm and (o.poses.method == "sfm" or not has_poses)
    est = estimate(sizes, train_sizes, o.splat.max_gaussians, sfm, capture_bytes, o.poses.max_image_size)
    check_resources(est, out, f"{len(sizes)} views trained at {rule.how.split(' (')[0]} with up to "
                              f"{int(est.parts['Gaussians'] // BYTES_PER_GAUSSIAN)} Gaussians")
    info.update(views=len(sizes), memory_gib=round(est.memory / GIB, 3), disk_gib=round(est.disk / GIB, 3),
                seconds=round(time.perf_counter() - t0, 3))
    log.info("pre-flight: %d views, about %.1f GiB memory and %.1f GiB disk needed (%.1f s)", len(sizes),
             est.memory / GIB, est.disk / GIB, info["seconds"])
    return info
