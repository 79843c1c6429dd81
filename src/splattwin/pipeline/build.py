"""Photos → validated twin in one call: capture → poses → splats → semantics → geometry/export →
(robot validation) → report, with the stage runner's hashing, skipping and resume.

Layout of the output folder TWIN (the twin folder itself):

    TWIN/pipeline.json        stage keys, outputs, timings, peak memory
    TWIN/poses/               transforms.json, frame.json, poses_report.json, cameras.png
    TWIN/splat/               point_cloud.ply, checkpoints, eval/ (held-out PSNR/SSIM, side-by-sides)
    TWIN/semantics/           labels.npy, fusion.json, label maps, per-object splats
    TWIN/twin.json, objects/, background/, export/   (the twin, see splattwin.twin)
    TWIN/robot/               results.json, trajectories, frames, playback.npz   (with a task)
    TWIN/report/index.html    the self-contained report
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.pipeline.runner import Context, Stage, run_stages

log = logging.getLogger(__name__)

STAGES = ("scene", "poses", "splats", "semantics", "twin", "robot", "report")


@dataclass
class BuildOptions:
    """Everything a build depends on (recorded in the twin's manifest and used for stage hashing).

    input: dataset path (any layout `splattwin.capture.load_dataset` reads), or None with `scene` set.
    scene: options of the embedded scene to generate as input (the demo), as a dict for SceneOptions.
    poses: "auto" | "known" | "sfm" | "robot"; robot_poses / hand_eye: files; marker_size (m).
    masks: folder/file of 2D masks; prompt: open-vocabulary text ("blue box. yellow cube").
    iters / resolution / device / seed / max_gaussians: splat training (max_gaussians 0: scaled with the
        training image size, see `splattwin.splat.trainer.capacity`).
    kappa / fusion_iters: semantic fusion. task: robot task YAML ("default" for the paper's task, None: skip).
    """

    input: str | None = None
    scene: dict | None = None
    poses: str = "auto"
    robot_poses: str | None = None
    hand_eye: str | None = None
    marker_size: float | None = None
    masks: str | None = None
    prompt: str | None = None
    iters: int = 3000
    resolution: int = 1
    device: str = "auto"
    seed: int = 0
    max_gaussians: int = 0
    checkpoint_every: int = 500
    kappa: float = 1.5
    fusion_iters: int = 3
    task: str | None = None
    trials: int = 0
    sigma: float = 0.005
    render_frames: bool = True
    progress: bool = True
    extra: dict[str, Any] = field(default_factory=dict)


# -- stages ------------------------------------------------------------------------------------------
def _scene_stage(ctx: Context) -> dict:
    from splattwin.scene.generate import generate
    from splattwin.scene.options import SceneOptions

    opts = ctx.options["scene"]
    if opts is None:
        return {}
    generate(ctx.path("scene"), SceneOptions(**opts), progress=ctx.options["progress"])
    return {"dir": "@scene/scene.json"}


def _input_path(ctx: Context) -> Path:
    if ctx.options["scene"] is not None:
        return ctx.path("scene")
    return Path(ctx.options["input"])


def _scene_json(ctx: Context) -> Path:
    """Where an embedded scene's scene.json would be for this input (it may not exist)."""
    src = _input_path(ctx)
    return (src if src.is_dir() else src.parent) / "scene.json"


def _poses_stage(ctx: Context) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses.estimate import PoseOptions, estimate_poses

    o = ctx.options
    ds = load_dataset(_input_path(ctx))
    popts = PoseOptions(method=o["poses"], robot_poses=Path(o["robot_poses"]) if o["robot_poses"] else None,
                        hand_eye=Path(o["hand_eye"]) if o["hand_eye"] else None, marker_size=o["marker_size"],
                        work_dir=ctx.path("poses/sfm"), progress=o["progress"], seed=o["seed"])
    result = estimate_poses(ds, popts)
    result.save(ctx.path("poses"))
    return {"transforms": "@poses/transforms.json", "frame": "@poses/frame.json",
            "registered": result.stats.get("registered"), "total": result.stats.get("total")}


def _splat_stage(ctx: Context) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import TrainConfig, train

    o = ctx.options
    ds = load_dataset(ctx.path("poses/transforms.json"))
    cfg = TrainConfig(iters=o["iters"], resolution=o["resolution"], device=o["device"], seed=o["seed"],
                      max_gaussians=o["max_gaussians"], checkpoint_every=o["checkpoint_every"],
                      progress=o["progress"])
    # resume=True: a killed run continues from its last checkpoint inside this stage.
    res = train(ds, ctx.path("splat"), cfg, resume=True)
    ev = evaluate(res.ply_path, ds, out_dir=ctx.path("splat/eval"), progress=o["progress"])
    return {"ply": "@splat/point_cloud.ply", "psnr": ev.mean_psnr, "ssim": ev.mean_ssim, "split": ev.split,
            "gaussians": len(res.gaussians), "train_s": res.wall_s}


def _load_masks(ctx: Context):
    from splattwin.capture import load_dataset
    from splattwin.semantics.masks import load_masks, scene_masks, scene_objects

    o = ctx.options
    scene_json = _scene_json(ctx)
    objs = scene_objects(scene_json.parent) if scene_json.is_file() else None
    if o["masks"]:
        return load_masks(o["masks"], objects=objs)
    if o["prompt"]:
        from splattwin.semantics.segment import segment_images

        ds = load_dataset(ctx.path("poses/transforms.json"))
        return segment_images({f.name: f.image_path for f in ds.train()}, o["prompt"],
                              out_dir=ctx.path("semantics/masks2d"))
    if scene_json.is_file():  # the embedded scene: its simulated open-vocabulary segmenter
        ms = scene_masks(scene_json.parent, kind="noisy")
        # Only training views are fused: held-out views stay unseen for the metrics.
        train = {f.name for f in load_dataset(ctx.path("poses/transforms.json"), validate=False).train()}
        for d in (ms.masks, ms.scores, ms.sizes):
            for view in [v for v in d if v not in train]:
                del d[view]
        return ms
    raise InputError("no 2D masks: pass --masks DIR or --prompt 'blue box. yellow cube'")


def _semantics_stage(ctx: Context) -> dict:
    from splattwin.semantics.fusion import FusionOptions
    from splattwin.semantics.lift import fuse_to_dir

    from splattwin.capture import load_dataset
    from splattwin.splat.gaussians import Gaussians

    o = ctx.options
    ms = _load_masks(ctx)
    g = Gaussians.load_ply(ctx.path("splat/point_cloud.ply"))
    ds = load_dataset(ctx.path("poses/transforms.json"))
    res = fuse_to_dir(g, ds, ms,
                      ctx.path("semantics"), FusionOptions(kappa=o["kappa"], iters=o["fusion_iters"]),
                      progress=o["progress"])
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

    o = ctx.options
    g = Gaussians.load_ply(ctx.path("splat/point_cloud.ply"))
    labels = np.load(ctx.path("semantics/labels.npy"))
    objects = [tuple(x) for x in io.read_json(ctx.path("semantics/objects.json"))]
    frame = load_frame(ctx.path("poses/frame.json"))
    man = build_twin(g, labels, objects, ctx.out, frame=frame, cameras_path="poses/transforms.json",
                     progress=o["progress"])
    # Scene facts the robot task needs (goal regions) travel in the manifest's config.
    scene_json = _scene_json(ctx)
    if scene_json.is_file():
        scene = io.read_json(scene_json)
        if scene.get("target_frame"):
            man.config["target_frame"] = scene["target_frame"]
    man.config["build"] = {k: v for k, v in o.items() if k != "progress"}
    man.splats = man.splats or "splat/point_cloud.ply"
    man.labels = man.labels or "semantics/labels.npy"
    man.save(ctx.out)
    if scene_json.is_file():
        _geometry_fidelity(ctx, scene_json.parent)
    return {"manifest": "@twin.json"}


def _geometry_fidelity(ctx: Context, scene_dir: Path) -> None:
    """Chamfer / precision / recall / F1 @5 mm of each object's cleaned points vs the GT mesh."""
    import trimesh

    from splattwin.geometry.metrics import fidelity, sample_surface
    from splattwin.twin.manifest import Manifest

    man = Manifest.load(ctx.out)
    rows = {}
    for obj in man.objects:
        gt_path = scene_dir / "meshes" / f"{obj.name}.ply"
        if not obj.usable or not obj.visual_mesh or not gt_path.is_file():
            continue
        mesh = trimesh.load(ctx.out / obj.visual_mesh, force="mesh", process=False)
        mesh.apply_transform(obj.pose)
        pts = sample_surface(mesh, spacing=0.002)
        gt = sample_surface(trimesh.load(gt_path, force="mesh", process=False), spacing=0.002)
        f = fidelity(pts, gt, threshold=0.005)
        rows[obj.name] = asdict(f) if hasattr(f, "__dataclass_fields__") else dict(f)
    io.write_json(ctx.path("geometry_metrics.json"), rows)


def _robot_stage(ctx: Context) -> dict:
    o = ctx.options
    if not o["task"]:
        return {}
    from splattwin.robot.render import prefer_egl

    prefer_egl()
    from splattwin.robot.outputs import write_outputs
    from splattwin.robot.trials import TrialSpec, run_once, run_trials

    out = ctx.path("robot")
    spec = TrialSpec(twin_dir=str(ctx.out), task_path=None if o["task"] == "default" else o["task"], seed=o["seed"])
    try:
        result, note, frames = run_once(spec, frame_dir=out / "frames" if o["render_frames"] else None,
                                        keep_trajectories=True)
    except InputError as e:
        # The task cannot run on this twin (e.g. an object whose geometry failed): record why, so the
        # report still gets written and says it, and let the command exit 2 at the end.
        io.write_json(out / "results.json", {"error": str(e), "task": o["task"]})
        return {"results": "@robot/results.json", "success": False, "error": str(e)}
    # trials land in robot/trials/<i>.json: a killed build resumes them
    trials = run_trials(spec, o["trials"], o["sigma"], out_dir=out) if o["trials"] > 0 else None
    write_outputs(out, spec, result, trials, render_note=note or "", frames=frames, wall_s=result.wall_s)
    _write_playback(ctx, spec)
    return {"results": "@robot/results.json", "success": bool(result.success)}


def _write_playback(ctx: Context, spec) -> None:
    """Robot geometry posed along the executed trajectory, for the viewer (robot/playback.npz)."""
    from splattwin.robot.trajectory import Trajectory
    from splattwin.robot.world import build_world
    from splattwin.viewer.app import robot_track_from_mujoco, save_robot_track

    traj_path = ctx.path("robot/trajectory.json")
    if not traj_path.is_file():
        return
    traj = Trajectory.load_json(traj_path)
    world = build_world(ctx.out, base=spec.base)
    step = max(1, len(traj.t) // 300)  # ~300 poses are plenty for playback
    qpos = np.tile(world.data.qpos.copy(), (len(traj.t[::step]), 1))
    qpos[:, world.arm_qpos_adr] = traj.q[::step, : len(world.arm_qpos_adr)]
    track = robot_track_from_mujoco(world.model, qpos, traj.t[::step], bodies=world.robot_bodies)
    save_robot_track(track, ctx.path("robot/playback.npz"))


def _report_stage(ctx: Context) -> dict:
    from splattwin.report.build import build_report

    path = build_report(ctx.out, timings=ctx.timings, peak_rss_gib=ctx.peak_rss_gib)
    return {"report": f"@{path.relative_to(ctx.out).as_posix()}"}


def stages() -> list[Stage]:
    data = ("input", "scene", "poses", "robot_poses", "hand_eye", "marker_size", "seed")
    return [
        Stage("scene", _scene_stage, option_keys=("scene",)),
        Stage("poses", _poses_stage, option_keys=data, deps=("scene",)),
        Stage("splats", _splat_stage, option_keys=("iters", "resolution", "device", "seed", "max_gaussians"), deps=("poses",)),
        Stage("semantics", _semantics_stage, option_keys=("masks", "prompt", "kappa", "fusion_iters"), deps=("splats",)),
        Stage("twin", _twin_stage, option_keys=(), deps=("semantics",)),
        Stage("robot", _robot_stage, option_keys=("task", "trials", "sigma", "seed", "render_frames"), deps=("twin",)),
        # The report reads every stage's outputs; its key changes whenever any of them re-ran.
        Stage("report", _report_stage, option_keys=(), deps=("poses", "splats", "semantics", "twin", "robot")),
    ]


def build(out: str | Path, options: BuildOptions, from_stage: str | None = None, until: str | None = None) -> Context:
    """Run (or resume) the pipeline into the twin folder `out`. Returns the run context."""
    from rich.console import Console

    out = Path(out)
    if options.input is None and options.scene is None:
        raise InputError("nothing to build: give an input dataset")
    if options.input is not None and not Path(options.input).exists():
        raise InputError("input does not exist", options.input)
    con = Console(stderr=True)

    def on_stage(name: str, status: str) -> None:
        if status == "skip":
            con.print(f"[dim]· {name}: up to date, skipped[/]")
        elif status == "run":
            con.print(f"[bold cyan]▶ {name}[/]")

    ctx = Context(out=out, options=asdict(options))
    return run_stages(stages(), ctx, from_stage=from_stage, until=until, on_stage=on_stage)
