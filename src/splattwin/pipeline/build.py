"""Photos → validated twin in one call: capture → poses → splats → semantics → geometry/export →
(robot validation) → report, with the stage runner's hashing, skipping and resume.

Layout of the output folder TWIN (the twin folder itself):

    TWIN/pipeline.json        stage keys, outputs, timings, peak memory
    TWIN/.splattwin/          lock (one writer at a time), digests.json (input hash cache)
    TWIN/capture/frames/      frames extracted from a video input
    TWIN/poses/               transforms.json, frame.json, poses_report.json, cameras.png, and the capture's
                              images/, depth/, masks/, labels/ (hard links or copies: the twin is
                              self-contained and can be moved; where the capture was is recorded in
                              twin.json config.build, not needed afterwards)
    TWIN/splat/               point_cloud.ply, checkpoints, eval/ (held-out PSNR/SSIM, side-by-sides)
    TWIN/semantics/           labels.npy, fusion.json, label maps, per-object splats
    TWIN/twin.json, objects/, background/, export/   (the twin, see splattwin.twin)
    TWIN/robot/               results.json, trajectories, rollout.npz, playback.npz, frames   (with a task)
    TWIN/report/index.html    the self-contained report

Nothing is written outside TWIN. The whole build holds TWIN's lock (`splattwin.lock`): a second build
into the same folder exits 2 at once. Before any stage runs, inputs that can be checked cheaply are
(`preflight`: 2D masks against the images' sizes, the task YAML), so a bad mask file is reported
before hours of pose estimation and training, naming the file.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.options import to_dict
from splattwin.pipeline.options import STAGES, BuildOptions  # noqa: F401 - STAGES re-exported
from splattwin.pipeline.runner import Context, Stage, compute_keys, run_stages

log = logging.getLogger(__name__)


# -- stages ------------------------------------------------------------------------------------------
def _frames_dir(ctx: Context) -> Path:
    """Where a video input's frames are extracted (inside the twin: nothing is written outside it)."""
    return ctx.path("capture/frames")


def _load_input(ctx: Context, validate: bool = True):
    from splattwin.capture import load_dataset

    return load_dataset(_input_path(ctx), validate=validate, frames_dir=_frames_dir(ctx))


def _scene_stage(ctx: Context) -> dict:
    from splattwin.scene.generator import generate

    opts = ctx.config.scene
    if opts is None:
        return {}
    generate(ctx.path("scene"), opts, progress=ctx.progress)
    return {"dir": "@scene/scene.json"}


def _input_path(ctx: Context) -> Path:
    if ctx.config.scene is not None:
        return ctx.path("scene")
    return Path(ctx.config.input)


def _scene_json(ctx: Context) -> Path:
    """Where an embedded scene's scene.json would be for this input (it may not exist)."""
    src = _input_path(ctx)
    return (src if src.is_dir() else src.parent) / "scene.json"


def _poses_inputs(ctx: Context) -> dict:
    """The capture's files the poses stage reads (metadata, images, depth, masks, points), its frame.json
    prior, and the robot pose files: hashed by content for the stage key."""
    from splattwin.capture.dataset import VIDEO_SUFFIXES

    o = ctx.config.poses
    src = _input_path(ctx)
    out: dict = {"robot_poses": o.robot_poses, "hand_eye": o.hand_eye}
    if src.is_file() and src.suffix in VIDEO_SUFFIXES:
        out["capture"] = src
        return out
    if not src.exists():
        out["capture"] = src
        return out
    ds = _load_input(ctx, validate=False)
    files = []
    meta_path = ds.meta.get("path")
    if meta_path and ds.meta.get("format") in ("nerfstudio", "cameras.json", "colmap"):
        files.append(Path(meta_path))
        files.append((Path(meta_path).parent if Path(meta_path).is_file() else Path(meta_path)) / "frame.json")
    for f in ds.frames:
        files += [f.image_path, f.depth_path, f.mask_path, f.label_path]
    out["capture"] = files
    if ds.points_xyz is not None:
        rgb = b"" if ds.points_rgb is None else np.ascontiguousarray(ds.points_rgb).tobytes()
        out["points"] = np.ascontiguousarray(ds.points_xyz).tobytes() + rgb
    return out


def _poses_stage(ctx: Context) -> dict:
    from splattwin.poses.estimate import estimate_poses

    ds = _load_input(ctx)
    result = estimate_poses(ds, replace(ctx.config.poses, work_dir=ctx.path("poses/sfm"), progress=ctx.progress))
    result.save(ctx.path("poses"))
    return {"transforms": "@poses/transforms.json", "frame": "@poses/frame.json",
            "registered": result.stats.get("registered"), "total": result.stats.get("total")}


def _splat_stage(ctx: Context) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import train

    ds = load_dataset(ctx.path("poses/transforms.json"))
    cfg = replace(ctx.config.splat, progress=ctx.progress)
    # resume=True: a killed run continues from its last checkpoint inside this stage. A checkpoint of
    # another run (other options or data: this stage's key changed) is not resumed: training starts over.
    res = train(ds, ctx.path("splat"), cfg, resume=True, on_mismatch="restart")
    ev = evaluate(res.ply_path, ds, out_dir=ctx.path("splat/eval"), progress=ctx.progress)
    return {"ply": "@splat/point_cloud.ply", "psnr": ev.mean_psnr, "ssim": ev.mean_ssim, "split": ev.split,
            "gaussians": len(res.gaussians), "train_s": res.wall_s}


def _load_masks(ctx: Context, image_sizes: dict | None = None):
    """(MaskSet, the path its masks came from) for this build (`--masks`, `--prompt` or the embedded
    scene's segmenter). image_sizes: view -> (H, W), checked for every mask file as it is read."""
    from splattwin.capture import load_dataset
    from splattwin.semantics.masks import load_masks, scene_masks, scene_objects

    o = ctx.config.semantics
    scene_json = _scene_json(ctx)
    objs = scene_objects(scene_json.parent) if scene_json.is_file() else None
    if o.masks:
        return load_masks(o.masks, objects=objs, image_sizes=image_sizes), Path(o.masks)
    if o.prompt:
        from splattwin.semantics.segment import segment_images

        ds = load_dataset(ctx.path("poses/transforms.json"))
        out = ctx.path("semantics/masks2d")
        return segment_images({f.name: f.image_path for f in ds.train()}, o.prompt, o.segment, out_dir=out), out
    if scene_json.is_file():  # the embedded scene: its simulated open-vocabulary segmenter
        ms = scene_masks(scene_json.parent, kind="noisy")
        # Only training views are fused: held-out views stay unseen for the metrics.
        train = {f.name for f in load_dataset(ctx.path("poses/transforms.json"), validate=False).train()}
        for d in (ms.masks, ms.scores, ms.sizes):
            for view in [v for v in d if v not in train]:
                del d[view]
        return ms, scene_json.parent / "masks" / "noisy"
    raise InputError("no 2D masks: pass --masks DIR or --prompt 'blue box. yellow cube'")


def _semantics_inputs(ctx: Context) -> dict:
    o = ctx.config.semantics
    scene_json = _scene_json(ctx)
    out: dict = {"masks": o.masks, "scene.json": scene_json if scene_json.is_file() else None}
    if not o.masks and not o.prompt and scene_json.is_file():
        out["scene_masks"] = scene_json.parent / "masks" / "noisy"
    return out


def _semantics_stage(ctx: Context) -> dict:
    from splattwin.semantics.fusion import check_views
    from splattwin.semantics.lift import fuse_to_dir, views_for

    from splattwin.capture import load_dataset
    from splattwin.splat.gaussians import Gaussians

    o = ctx.config.semantics
    ds = load_dataset(ctx.path("poses/transforms.json"))
    ms, masks_from = _load_masks(ctx, {f.name: (f.camera.height, f.camera.width) for f in ds.frames})
    # checked here with the masks' path, so that a size or empty-mask error names it
    import warnings

    from splattwin.semantics.masks import MaskWarning

    with warnings.catch_warnings():  # fuse_to_dir warns about unmatched views itself
        warnings.simplefilter("ignore", MaskWarning)
        check_views(views_for(ds.train() or ds.frames, ms, masks_from, all_frames=ds.frames), ms, masks_from)
    g = Gaussians.load_ply(ctx.path("splat/point_cloud.ply"))
    res = fuse_to_dir(g, ds, ms, ctx.path("semantics"), o.fusion, renderer=o.renderer, label_maps=o.maps,
                      naive=o.naive, progress=ctx.progress, maps_renderer=o.maps_renderer)
    prompts = ms.prompts or {}
    objects = [[res.names[k], int(k), prompts.get(k, res.names[k].replace("_", " "))] for k in res.label_ids]
    io.write_json(ctx.path("semantics/objects.json"), objects)
    _semantic_metrics(ctx, res, ms, g, ds)
    return {"labels": "@semantics/labels.npy", "objects": "@semantics/objects.json"}


KAPPA_SWEEP = (2.0, 1.8, 1.5, 1.2, 1.0)


def _semantic_metrics(ctx: Context, res, ms, g, ds) -> None:
    """The paper's 3D projection consistency and ghost index, the κ sweep, and 2D masks | fused labels
    pictures, added to semantics/fusion.json and semantics/masks_vs_labels/."""
    from splattwin.capture import load_image, load_mask
    from splattwin.report.html import side_by_side
    from splattwin.semantics.lift import views_for
    from splattwin.semantics.metrics import ghost_index, projection_consistency
    from splattwin.semantics.render import colorize

    views = views_for(ds.train() or ds.frames, ms)
    sweep = [{"kappa": k, "consistency": projection_consistency(g.means, res.relabel(k), views, ms),
              "ghost_index": ghost_index(res, k)} for k in KAPPA_SWEEP]
    meta = io.read_json(ctx.path("semantics/fusion.json"))
    meta["consistency"] = projection_consistency(g.means, res.labels, views, ms)
    meta["ghost_index"] = ghost_index(res)
    meta["kappa_sweep"] = sweep
    io.write_json(ctx.path("semantics/fusion.json"), meta)
    for f in [fr for fr in ds.train() if fr.name in ms.sizes][:3]:
        h, w = ms.sizes[f.name]
        mask_map = np.zeros((h, w), np.int32)
        for k in sorted(ms.masks.get(f.name, {})):
            mask_map[ms.masks[f.name][k]] = k
        img = load_image(f.image_path)
        fused = load_mask(ctx.path(f"semantics/label_maps/raw/{f.name}.png")).astype(np.int32)
        pic = side_by_side([colorize(mask_map, res.names, img, legend=False), colorize(fused, res.names, img)])
        io.write_image(ctx.path(f"semantics/masks_vs_labels/{f.name}.png"), (pic * 255 + 0.5).astype(np.uint8))


def _twin_stage(ctx: Context) -> dict:
    from splattwin.poses.estimate import load_frame
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.build import build_twin

    o = ctx.config
    g = Gaussians.load_ply(ctx.path("splat/point_cloud.ply"))
    labels = np.load(ctx.path("semantics/labels.npy"))
    objects = [tuple(x) for x in io.read_json(ctx.path("semantics/objects.json"))]
    frame = load_frame(ctx.path("poses/frame.json"))
    man = build_twin(g, labels, objects, ctx.out, frame=frame, cameras_path="poses/transforms.json",
                     options=o.geometry, formats=o.export.resolve(frame.scaled, "export.formats"),
                     progress=ctx.progress)
    # Scene facts the robot task needs (goal regions) travel in the manifest's config.
    scene_json = _scene_json(ctx)
    if scene_json.is_file():
        scene = io.read_json(scene_json)
        if scene.get("target_frame"):
            man.config["target_frame"] = scene["target_frame"]
    # references to the inputs (absolute paths), recorded but never needed by report/view/plan/export
    man.config["build"] = resolved_config(o)
    man.splats = man.splats or "splat/point_cloud.ply"
    man.labels = man.labels or "semantics/labels.npy"
    man.save(ctx.out)
    if scene_json.is_file():
        _geometry_fidelity(ctx, scene_json.parent)
    return {"manifest": "@twin.json"}


def _geometry_fidelity(ctx: Context, scene_dir: Path) -> None:
    """Chamfer / precision / recall / F1 @5 mm of each object's cleaned points vs the GT mesh."""
    from splattwin.geometry.metrics import fidelity, sample_surface
    from splattwin.meshio import load_mesh
    from splattwin.twin.manifest import Manifest

    man = Manifest.load(ctx.out)
    rows = {}
    for obj in man.objects:
        gt_path = scene_dir / "meshes" / f"{obj.name}.ply"
        if not obj.usable or not obj.visual_mesh or not gt_path.is_file():
            continue
        mesh = load_mesh(ctx.out / obj.visual_mesh, f"visual mesh of {obj.name!r}")
        mesh.apply_transform(obj.pose)
        pts = sample_surface(mesh, spacing=0.002)
        gt = sample_surface(load_mesh(gt_path, "ground-truth mesh"), spacing=0.002)
        f = fidelity(pts, gt, threshold=0.005)
        rows[obj.name] = asdict(f) if hasattr(f, "__dataclass_fields__") else dict(f)
    io.write_json(ctx.path("geometry_metrics.json"), rows)


def resolved_config(options: BuildOptions) -> dict:
    """The options as recorded in twin.json: every option, path options made absolute (references to the
    inputs, never needed by report/view/plan/export)."""
    from splattwin.options import specs

    def absolute(obj):
        kw = {}
        for spec in specs(type(obj)):
            v = getattr(obj, spec.name)
            if spec.nested is not None and v is not None:
                kw[spec.name] = absolute(v)
            elif spec.meta.get("path") and v not in (None, "", "default"):
                kw[spec.name] = type(v)(Path(v).resolve()) if isinstance(v, Path) else str(Path(v).resolve())
        return replace(obj, **kw)

    return to_dict(absolute(options))


def _twin_inputs(ctx: Context) -> dict:
    scene_json = _scene_json(ctx)
    return {"scene.json": scene_json if scene_json.is_file() else None}


def _robot_inputs(ctx: Context) -> dict:
    from splattwin.robot.task import default_task_path

    task = ctx.config.robot.task
    return {"task": None if not task else (default_task_path() if task == "default" else Path(task))}


def _robot_stage(ctx: Context) -> dict:
    o = ctx.config.robot
    if not o.task:
        return {}
    from splattwin.robot.render import prefer_egl

    prefer_egl()
    from splattwin.robot.outputs import write_outputs
    from splattwin.robot.trials import TrialSpec, run_once, run_trials

    out = ctx.path("robot")
    spec = TrialSpec.from_options(ctx.out, o)
    try:
        result, note, frames = run_once(spec, frame_dir=out / "frames" if o.render else None,
                                        keep_trajectories=True)
    except InputError as e:
        # The task cannot run on this twin (e.g. an object whose geometry failed): record why, so the
        # report still gets written and says it, and let the command exit 2 at the end.
        io.write_json(out / "results.json", {"error": str(e), "task": o.task})
        return {"results": "@robot/results.json", "success": False, "error": str(e)}
    # trials land in robot/trials/<i>.json: a killed build resumes them
    trials = run_trials(spec, o.trials, o.sigma, workers=o.workers, out_dir=out, resume=o.resume,
                        sigma_yaw=o.sigma_yaw) if o.trials > 0 else None
    # robot/rollout.npz and robot/playback.npz (the viewer's track) are written by the robot package
    write_outputs(out, spec, result, trials, render_note=note or "", frames=frames, wall_s=result.wall_s)
    return {"results": "@robot/results.json", "success": bool(result.success)}


def _report_stage(ctx: Context) -> dict:
    from splattwin.report.build import build_report

    path = build_report(ctx.out, timings=ctx.timings, peak_rss_gib=ctx.peak_rss_gib)
    return {"report": f"@{path.relative_to(ctx.out).as_posix()}"}


def stages() -> list[Stage]:
    """The pipeline. Each stage's key hashes its own sub-config of BuildOptions (`option_keys`), less the
    path options, which are hashed by content instead (each stage's `inputs`); each stage's `code` lists
    the packages whose source is part of its key (see `splattwin.pipeline.runner`)."""
    return [
        Stage("scene", _scene_stage, option_keys=("scene",), code=("splattwin.scene",)),
        Stage("poses", _poses_stage, option_keys=("scene", "poses"), deps=("scene",), inputs=_poses_inputs,
              code=("splattwin.capture", "splattwin.poses")),
        Stage("splats", _splat_stage, option_keys=("splat",), deps=("poses",),
              code=("splattwin.splat", "splattwin.capture")),
        Stage("semantics", _semantics_stage, option_keys=("semantics",), deps=("splats",),
              inputs=_semantics_inputs, code=("splattwin.semantics", "splattwin.capture")),
        Stage("twin", _twin_stage, option_keys=("geometry", "export"), deps=("semantics",), inputs=_twin_inputs,
              code=("splattwin.geometry", "splattwin.twin", "splattwin.meshio")),
        Stage("robot", _robot_stage, option_keys=("robot",), deps=("twin",),
              inputs=_robot_inputs, code=("splattwin.robot", "splattwin.twin")),
        # The report reads every stage's outputs; its key changes whenever any of them re-ran.
        Stage("report", _report_stage, option_keys=(), deps=("poses", "splats", "semantics", "twin", "robot"),
              code=("splattwin.report", "splattwin.viewer")),
    ]


def preflight(ctx: Context) -> None:
    """Checks of the inputs that need no earlier stage, before any runs (see module docstring)."""
    o = ctx.config
    if o.input is not None and o.scene is None and o.semantics.masks:
        ds = _load_input(ctx)
        sizes = {f.name: (f.camera.height, f.camera.width) for f in ds.frames}
        ms, where = _load_masks(ctx, sizes)
        ms.validate(None, where)  # an empty set or an object that is in no view
        known = [v for v in ms.views if v in sizes]
        if not known:
            raise InputError(f"no mask view matches an image of the input (masks: {', '.join(ms.views[:5])}...; "
                             f"images: {', '.join(sorted(sizes)[:5])}...)", where)
    if o.robot.task and o.robot.task != "default":
        from splattwin.robot.task import load_task

        load_task(o.robot.task)  # the file parses as a task (bounded YAML); checked against the twin later


def _context(out: str | Path, options: BuildOptions, progress: bool = True) -> Context:
    return Context(out=Path(out), options=to_dict(options, "key"), config=options, progress=progress)


def stage_keys(out: str | Path, options: BuildOptions) -> dict[str, str]:
    """{stage: key} for `options` and the inputs as they are now (nothing runs, nothing is written)."""
    return compute_keys(stages(), _context(out, options))


def check_inputs(options: BuildOptions) -> None:
    """InputError, before anything runs, for an input or an option's file that does not exist."""
    if options.input is None and options.scene is None:
        raise InputError("nothing to build: give an input dataset")
    if options.input is not None and options.scene is not None:
        raise InputError("give either an input dataset or scene options (the embedded scene), not both")
    if options.input is not None and not Path(options.input).exists():
        raise InputError("input does not exist", options.input)
    for flag, v in (("--masks", options.semantics.masks), ("--robot-poses", options.poses.robot_poses),
                    ("--hand-eye", options.poses.hand_eye), ("--robot.robot-mjcf", options.robot.robot_mjcf)):
        if v is not None and not Path(v).exists():
            raise InputError(f"{flag} does not exist", v)
    task = options.robot.task
    if task not in (None, "default") and not Path(task).is_file():
        raise InputError("task file not found", task)
    options.robot.validate()


def build(out: str | Path, options: BuildOptions, from_stage: str | None = None, until: str | None = None,
          progress: bool = True) -> Context:
    """Run (or resume) the pipeline into the twin folder `out`. Returns the run context.
    progress: progress bars of every stage (not an option of the result: no stage key depends on it)."""
    from rich.console import Console

    from splattwin.lock import output_lock

    out = Path(out)
    check_inputs(options)
    con = Console(stderr=True)

    def on_stage(name: str, status: str) -> None:
        if status == "skip":
            con.print(f"[dim]· {name}: up to date, skipped[/]")
        elif status == "run":
            con.print(f"[bold cyan]▶ {name}[/]")

    ctx = _context(out, options, progress)
    with output_lock(out):
        preflight(ctx)
        return run_stages(stages(), ctx, from_stage=from_stage, until=until, on_stage=on_stage)
