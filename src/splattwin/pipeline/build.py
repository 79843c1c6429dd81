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

The pipeline only wires the stages and records them: each stage is `splattwin.<stage>.stage.run(inputs,
options) -> result` (typed dataclasses), reads its own sub-config of `BuildOptions`, and is the only writer
of its artifacts (docs/ARCHITECTURE.md lists them). Nothing is written outside TWIN. The whole build holds
TWIN's lock (`splattwin.lock`): a second build into the same folder exits 2 at once. Before any stage
runs, inputs that can be checked cheaply are (`preflight`, `splattwin.pipeline.preflight`: 2D masks
against the images' sizes, the prompt's segmentation weights, a metric scale when a task is given, the
task YAML, memory and disk), so a bad mask file is reported before hours of pose estimation and
training, naming the file.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from splattwin.errors import InputError
from splattwin.options import absolute_paths, to_dict
from splattwin.pipeline.options import STAGES, BuildOptions  # noqa: F401 - STAGES re-exported
from splattwin.pipeline.runner import Context, Stage, compute_keys, run_stages

log = logging.getLogger(__name__)
stage_log = logging.getLogger(__name__ + ".stages")   # "▶ splat" lines of build(progress=False)


def record(result: Any, out: Path) -> dict[str, Any]:
    """A stage result as pipeline.json records it: files inside the twin as "@relative/path" (the runner
    checks they still exist before skipping the stage), plain values as they are."""
    rec: dict[str, Any] = {}
    for f in dataclasses.fields(result):
        v = getattr(result, f.name)
        if isinstance(v, Path):
            rec[f.name] = "@" + Path(v).resolve().relative_to(Path(out).resolve()).as_posix()
        elif v is None or isinstance(v, (str, int, float, bool)):
            rec[f.name] = v
    return rec


# -- where each stage's inputs are -------------------------------------------------------------------
def _input_path(ctx: Context) -> Path:
    """The capture: the given dataset, or the embedded scene generated into TWIN/scene."""
    return ctx.path("scene") if ctx.config.scene is not None else Path(ctx.config.input)


def _scene_dir(ctx: Context) -> Path | None:
    """The folder of an embedded scene's ground truth (scene.json) for this input, if it is one: the input
    folder, or the folder of an input file (a scene's transforms.json). Never for a video: its frames
    (frame_00000, ...) are not the scene's views, so a scene's masks saved beside it could match none of
    them, and the pre-flight took the video for a scene with masks of its own (the semantics stage then
    failed on them after SfM and training)."""
    from splattwin.capture.dataset import is_video

    src = _input_path(ctx)
    if src.is_file() and is_video(src):
        return None
    d = src if src.is_dir() else src.parent
    return d if (d / "scene.json").is_file() else None


def _poses_inputs(ctx: Context):
    from splattwin.poses.stage import PosesInputs

    # a video's frames are extracted inside the twin: nothing is written outside it
    return PosesInputs(capture=_input_path(ctx), out_dir=ctx.path("poses"), frames_dir=ctx.path("capture/frames"))


def _refined_poses(ctx: Context) -> Path | None:
    """The splat stage's refined_poses.json when it refined the poses (`--splat.refine-poses`), else None: the
    later stages then project with those cameras instead of poses/transforms.json's (`splattwin.splat.
    refined_poses`; the splat stage removes a stale one, so a build without refinement reads the capture's)."""
    from splattwin.splat.refined_poses import path_in

    return path_in(ctx.path("splat")) if ctx.config.splat.refine_poses else None


def _semantics_inputs(ctx: Context):
    from splattwin.semantics.stage import SemanticsInputs

    return SemanticsInputs(transforms=ctx.path("poses/transforms.json"), splats=ctx.path("splat/point_cloud.ply"),
                           out_dir=ctx.path("semantics"), scene_dir=_scene_dir(ctx), refined_poses=_refined_poses(ctx))


# -- the stages: wiring only ------------------------------------------------------------------------
def _scene(ctx: Context) -> dict:
    from splattwin.scene.stage import SceneInputs, run

    if ctx.config.scene is None:
        return {}
    return record(run(SceneInputs(ctx.path("scene")), ctx.config.scene, progress=ctx.progress), ctx.out)


def _poses(ctx: Context) -> dict:
    from splattwin.poses.stage import run

    return record(run(_poses_inputs(ctx), ctx.config.poses, progress=ctx.progress), ctx.out)


def _poses_files(ctx: Context) -> dict:
    from splattwin.poses.stage import input_files

    return input_files(_poses_inputs(ctx), ctx.config.poses)


def _check_task_scale(ctx: Context) -> None:
    """--task needs a metric twin: when the poses came out unscaled although the pre-flight expected a scale
    (the depth images gave none: `splattwin.poses.depth_scale`), stop before training, not at the robot
    stage after every other stage's work."""
    if not ctx.config.robot.task:
        return
    from splattwin.pipeline.preflight import SCALE_HELP
    from splattwin.poses.twin_frame import load_frame

    frame_json = ctx.path("poses/frame.json")
    if frame_json.is_file() and not load_frame(frame_json).scaled:
        why = ""
        report = ctx.path("poses/poses_report.json")
        if report.is_file():
            from splattwin.limits import MAX_RECORD_BYTES, read_json

            rep = read_json(report, "poses report", MAX_RECORD_BYTES)
            err = rep.get("depth_scale", {}).get("error") if isinstance(rep, dict) and isinstance(
                rep.get("depth_scale"), dict) else None
            why = f" (no scale from the depth images: {err})" if isinstance(err, str) else ""
        raise InputError(f"--task needs a metric twin, but the poses came out unscaled{why}; nothing was trained: "
                         f"{SCALE_HELP}", frame_json)


def _splats(ctx: Context) -> dict:
    from splattwin.splat.stage import SplatInputs, run

    _check_task_scale(ctx)
    inputs = SplatInputs(transforms=ctx.path("poses/transforms.json"), out_dir=ctx.path("splat"))
    # --from splats (or earlier): retrain from scratch, never resume the finished run's checkpoints
    return record(run(inputs, ctx.config.splat, progress=ctx.progress, fresh="splats" in ctx.fresh), ctx.out)


def _semantics(ctx: Context) -> dict:
    from splattwin.semantics.stage import run

    # --from semantics (or earlier): segment every view again, never reuse the saved prompt masks
    return record(run(_semantics_inputs(ctx), ctx.config.semantics, progress=ctx.progress,
                      fresh="semantics" in ctx.fresh), ctx.out)


def _semantics_files(ctx: Context) -> dict:
    from splattwin.semantics.stage import input_files

    return input_files(_semantics_inputs(ctx), ctx.config.semantics)


def _twin(ctx: Context) -> dict:
    from splattwin.twin.options import TwinOptions
    from splattwin.twin.stage import TwinInputs, run

    masks = _stage_masks(ctx)
    inputs = TwinInputs(splats=ctx.path("splat/point_cloud.ply"), labels=ctx.path("semantics/labels.npy"),
                        objects=ctx.path("semantics/objects.json"), frame=ctx.path("poses/frame.json"),
                        twin_dir=ctx.out, cameras="poses/transforms.json", scene_dir=_scene_dir(ctx),
                        config=resolved_config(ctx.config), masks=masks, refined_poses=_refined_poses(ctx))
    options = TwinOptions(geometry=ctx.config.geometry, export=ctx.config.export)
    result = record(run(inputs, options, progress=ctx.progress), ctx.out)
    if ctx.config.refine.iters > 0:
        # the moved objects' splats trained again on the training photos (twin.json then points to them)
        from splattwin.capture import load_dataset
        from splattwin.playback.refine import refine_objects

        from splattwin.splat.refined_poses import apply

        ds = apply(load_dataset(ctx.path("poses")), _refined_poses(ctx))
        if ctx.config.refine.mask_lambda <= 0:
            masks = None
        elif masks is None:  # the semantics stage's 2D masks (prompt masks: its saved ones), strictly
            from splattwin.semantics.stage import load_stage_masks

            masks, _ = load_stage_masks(ctx.config.semantics, ds.frames, _scene_dir(ctx),
                                        ctx.path("semantics") / "masks2d")
        refine_objects(ctx.out, ds.train(), ctx.config.refine, resolution=ctx.config.splat.resolution,
                       cpu_max_side=ctx.config.splat.cpu_max_side, progress=ctx.progress, masks=masks)
    return result


def _stage_masks(ctx: Context):
    """The 2D masks the semantics stage fused (`semantics.stage.load_stage_masks`: --masks, the prompt's
    saved masks in semantics/masks2d, or the embedded scene's training views), for the objects'
    silhouette coverage; None with a warning when they cannot be read now (the twin is then built
    without the check: its objects are judged by their splat count alone)."""
    from splattwin.capture import load_dataset
    from splattwin.semantics.stage import load_stage_masks

    sem = ctx.config.semantics
    try:
        if sem.prompt and not sem.masks:  # the masks the semantics stage segmented and saved; never segment here
            from splattwin.semantics.masks import load_masks

            saved = ctx.path("semantics") / "masks2d"
            return load_masks(saved) if (saved / "masks.json").is_file() else None
        frames = load_dataset(ctx.path("poses/transforms.json"), validate=False, require_images=False).frames
        masks, _ = load_stage_masks(sem, frames, _scene_dir(ctx), ctx.path("semantics") / "masks2d")
        return masks
    except InputError as e:
        log.warning("2D masks not read (%s): objects judged by their splat count alone, no silhouette coverage", e)
        return None


def _twin_files(ctx: Context) -> dict:
    d = _scene_dir(ctx)
    return {"scene.json": d / "scene.json" if d is not None else None}


def _robot(ctx: Context) -> dict:
    from splattwin.robot.stage import RobotInputs, run

    if not ctx.config.robot.task:
        _drop_stale_robot(ctx)
        return {}
    opts = ctx.config.robot
    if "robot" in ctx.fresh:  # --from robot (or earlier): run every trial again, reuse none
        opts = replace(opts, resume=False)
    recorder = None
    if opts.record is not None:   # `--robot.record DIR`: checked before the physics runs, as `plan --record`
        from splattwin.playback.record import recorder_for

        recorder = recorder_for(ctx.out, ctx.path("robot"), opts)
    res = run(RobotInputs(ctx.out, ctx.path("robot")), opts, progress=ctx.progress, record_errors=True)
    if recorder is not None and res.details:
        from splattwin.playback.record import record_result

        record_result(recorder, opts.record, ctx.path("robot"), res.details, progress=ctx.progress)
    return record(res, ctx.out)


def _drop_stale_robot(ctx: Context) -> None:
    """No task this run, and the robot stage runs because the twin changed (or --from): results of a
    `splattwin plan` run by hand on an earlier twin (another object, other meshes) would be shown by the
    report and played by `render` as this twin's, so they go (`robot.outputs.remove_previous`: our own
    file names only). Results made on this very twin (a deterministic rebuild) stay."""
    from splattwin.robot.outputs import remove_previous, stale_results

    out = ctx.path("robot")
    if out.is_symlink() or not (out / "results.json").is_file():
        return
    why = stale_results(ctx.out)
    if why is None:
        return
    remove_previous(out)
    log.warning("removed the robot results in %s: %s", out, why)


def _robot_files(ctx: Context) -> dict:
    from splattwin.robot.task import default_task_path

    task = ctx.config.robot.task
    files = {"task": None if not task else (default_task_path() if task == "default" else Path(task))}
    if task and ctx.config.robot.robot_mjcf is None:
        # the default arm's model folder (MJCF + meshes): an updated Menagerie copy re-runs the trials
        from splattwin.errors import InputError
        from splattwin.robot.assets import panda_model_path

        try:
            files["robot_model"] = panda_model_path().parent
        except InputError:
            pass  # no model offline: the robot stage itself reports it
    return files


def _report(ctx: Context) -> dict:
    from splattwin.report.stage import ReportInputs, run

    return record(run(ReportInputs(ctx.out, dict(ctx.timings), dict(ctx.peak_rss_gib), list(ctx.skipped))), ctx.out)


def stages() -> list[Stage]:
    """The pipeline. Each stage's key hashes its own sub-config of BuildOptions (`option_keys`), less the
    path options, which are hashed by content instead (each stage's `inputs`); each stage's `code` lists
    the packages whose source is part of its key (see `splattwin.pipeline.runner`)."""
    return [
        Stage("scene", _scene, option_keys=("scene",), code=("splattwin.scene",)),
        Stage("poses", _poses, option_keys=("scene", "poses"), deps=("scene",), inputs=_poses_files,
              code=("splattwin.capture", "splattwin.poses")),
        Stage("splats", _splats, option_keys=("splat",), deps=("poses",),
              code=("splattwin.splat", "splattwin.capture")),
        Stage("semantics", _semantics, option_keys=("semantics",), deps=("splats",), inputs=_semantics_files,
              code=("splattwin.semantics", "splattwin.capture")),
        Stage("twin", _twin, option_keys=("geometry", "export", "refine"), deps=("semantics",), inputs=_twin_files,
              code=("splattwin.geometry", "splattwin.twin", "splattwin.meshio", "splattwin.playback.refine",
                    "splattwin.playback.scene", "splattwin.playback.holes")),
        Stage("robot", _robot, option_keys=("robot",), deps=("twin",), inputs=_robot_files,
              code=("splattwin.robot", "splattwin.twin")),
        # The report reads every stage's outputs; its key changes whenever any of them re-ran.
        Stage("report", _report, option_keys=(), deps=("poses", "splats", "semantics", "twin", "robot"),
              code=("splattwin.report", "splattwin.playback.view_model")),
    ]


def resolved_config(options: BuildOptions) -> dict:
    """The options as recorded in twin.json: every option, path options made absolute (references to the
    inputs, never needed by report/view/plan/export)."""
    return to_dict(absolute_paths(options))


def preflight(ctx: Context, until: str | None = None) -> dict:
    """Checks of the inputs that need no earlier stage, before any runs (`splattwin.pipeline.preflight`:
    masks, segmentation weights, a metric scale for --task, memory and disk)."""
    from splattwin.pipeline.preflight import run_preflight

    o = ctx.config
    return run_preflight(o, ctx.out, _input_path(ctx) if o.scene is None else None, _scene_dir(ctx),
                         ctx.path("capture/frames"), until=until, progress=ctx.progress)


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
    options.poses.check()   # --max-frames / --min-change, SfM's limits, ..., before the pre-flight extracts anything


def check_output(out: Path, options: BuildOptions) -> None:
    """InputError when the twin folder `out` is the capture's own folder (the input folder, or the folder of an
    input file such as its transforms.json): the twin's stage folders and records would be written among the
    photos, its pictures read back as photos in sub-folders, and removing the twin would remove the capture.
    A twin folder inside the capture's folder (`cake/twin`) is fine: the capture is read from its top level."""
    if options.input is None:
        return
    src = Path(options.input)
    if src.is_file() and src.suffix.lower() in {".json", ".txt"}:   # a dataset file: its folder is the capture
        src = src.parent
    if src.is_dir() and out.resolve() == src.resolve():
        raise InputError(f"the twin would be built into the capture's own folder {src}: give an --out folder "
                         f"apart from it (e.g. {src / 'twin'} or {src.parent / (src.name + '_twin')})", out)


def build(out: str | Path, options: BuildOptions, from_stage: str | None = None, until: str | None = None,
          progress: bool = True) -> Context:
    """Run (or resume) the pipeline into the twin folder `out`. Returns the run context.
    progress: progress bars of every stage and the stage lines ("▶ splat") on stderr; False: nothing printed,
    the stage lines logged (logger splattwin.pipeline.build.stages, INFO). Not an option of the result: no stage key
    depends on it."""
    from splattwin.console import console

    from splattwin.lock import output_lock

    out = Path(out)
    check_inputs(options)
    check_output(out, options)
    con = console(stderr=True)

    def on_stage(name: str, status: str) -> None:
        line = {"skip": f"· {name}: up to date, skipped", "run": f"▶ {name}"}.get(status)
        if line is None:
            return
        if name == "robot" and status == "run" and not options.robot.task:
            # the stage only tidies then: a bare "▶ robot" read as if the arm had been tried on the twin
            line += ": no --task, nothing planned (splattwin plan TWIN --task FILE validates one)"
        if progress:
            con.print(line, style="dim" if status == "skip" else "bold cyan", markup=False, highlight=False)
        else:   # a script, a notebook, a batch worker: through the logger, not printed
            stage_log.info(line)

    ctx = _context(out, options, progress)
    t0 = time.perf_counter()
    created = not out.exists()
    with output_lock(out):
        try:
            preflight(ctx, until)
            run_stages(stages(), ctx, from_stage=from_stage, until=until, on_stage=on_stage)
        except BaseException:
            if created:
                _unwind(out)
            raise
    ctx.wall_s = time.perf_counter() - t0   # with the pre-flight
    return ctx


# What a build writes before any stage writes outputs of its own: the runner's records and the capture's
# extracted video frames / upright photo copies (derived, seconds to redo).
_BOOKKEEPING = {"pipeline.json", "capture", ".splattwin"}
_STATE_FILES = {"lock", "digests.json"}


def _unwind(out: Path) -> None:
    """A build that failed (bad input, Ctrl-C) in a folder it created, before any stage wrote outputs of its
    own: remove what it wrote, so that `output_lock` removes the folder (README: "a command that fails
    before writing anything removes the output folder it created"). The lock removed only a folder holding
    nothing but the lock, so a video refused in the poses stage (1 frame, no decodable frame, an unknown
    --heldout-views name) left pipeline.json, digests.json and the frames behind. A folder where a stage
    has begun its work (poses/ with SfM's database, a generated scene/) is kept: a re-run resumes it."""
    try:
        names = {p.name for p in out.iterdir()}
        state = out / ".splattwin"
        if not names <= _BOOKKEEPING or (state.is_dir() and not {p.name for p in state.iterdir()} <= _STATE_FILES):
            return
        if (out / "capture").is_symlink():
            return
        shutil.rmtree(out / "capture", ignore_errors=True)
        (out / "pipeline.json").unlink(missing_ok=True)
        (state / "digests.json").unlink(missing_ok=True)
    except OSError:   # no permission, or something appeared meanwhile: leave it
        pass
