"""The robot stage (`splattwin plan` and the pipeline): `run(RobotInputs, RobotOptions) -> RobotResult`.

Reads the twin folder and the task; validates the task in MuJoCo physics and writes OUT (default
TWIN/robot; `splattwin.robot.outputs`, the only writer of each): results.json, trials/, trajectories,
rollout.npz, playback.npz (what `splattwin view` plays), frames/; with `options.record` also each
trial's rollout (trials/<i>.rollout.npz), from which `splattwin.playback.record` renders the episodes
(this stage does not render them: playback is the layer above).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from splattwin.errors import InputError
from splattwin.robot.options import RobotOptions


@dataclass
class RobotInputs:
    twin_dir: Path      # twin folder (twin.json)
    out_dir: Path       # where the run's files go (TWIN/robot)


@dataclass
class RobotResult:
    results: Path                 # results.json
    success: bool                 # the nominal run succeeded (trials are reported in results.json)
    error: str | None = None      # why the task could not run on this twin (bad input), if it could not
    # why the real-robot files were refused although the plan ran: the trajectory leaves the named robot's
    # limits (`--joint-names fr3`), or an object moved from its twin pose before the robot acted (the run
    # does not validate the twin: `execute.unsettled`); `plan` and `build` exit 2 with it. A failed task
    # is `success` False, not this.
    export_error: str | None = None
    details: dict[str, Any] = field(default_factory=dict)   # run, trials, paths: for printing, not recorded


def run(inputs: RobotInputs, options: RobotOptions, *, progress: bool = True,
        record_errors: bool = False) -> RobotResult:
    """Plan and execute the task (options.task None or "default": the paper's task), then the trials.

    record_errors: an InputError of the task on this twin (e.g. an object whose geometry failed) is
    written to results.json and returned as `error` (the pipeline: the report says why) instead of raised."""
    from splattwin.robot.outputs import remove_previous, write_outputs
    from splattwin.robot.trials import TrialSpec, run_once, run_trials
    from splattwin.twin.manifest import Manifest, warn_missing_obstacle_boxes
    from splattwin.twin.mjcf import check_scaled

    options.validate()
    out = Path(inputs.out_dir)
    try:  # before the task: a twin in SfM units cannot be planned in at all (the message says how to scale it)
        manifest = Manifest.load(inputs.twin_dir)
        check_scaled(manifest, Path(inputs.twin_dir) / "twin.json")
        # an older twin.json: its unusable objects are not in the robot's world (no obstacle box yet)
        warn_missing_obstacle_boxes(manifest, inputs.twin_dir)
    except InputError as e:
        if not record_errors:
            raise
        return _error_result(out, e, options, Path(inputs.twin_dir))
    spec = TrialSpec.from_options(inputs.twin_dir, options)
    try:  # a naming that does not fit the arm fails before the run, not after it
        names = _export_names(spec, options)
    except InputError as e:
        if not record_errors:
            raise
        return _error_result(out, e, options, Path(inputs.twin_dir))
    t0 = time.perf_counter()
    try:
        # the earlier run's outputs go once the task is valid (a bad task leaves them), before this run
        # writes any: OUT then holds only this run's files (trials 1..N stay: resumed or rewritten)
        result, note, frames = run_once(spec, frame_dir=out / "frames" if options.render else None,
                                        keep_trajectories=True,
                                        on_valid=lambda: remove_previous(out, keep_trials=options.trials))
    except InputError as e:
        if not record_errors:
            raise
        return _error_result(out, e, options, Path(inputs.twin_dir))
    # trials land in OUT/trials/<i>.json: a killed run resumes them
    trials = None
    if options.trials > 0:
        from splattwin.executor import make_executor

        # a local pool or a Ray cluster (options.cluster); the outcomes depend only on the trials' seeds
        with make_executor(options.cluster, max_tasks=options.trials) as ex:
            trials = run_trials(spec, options.trials, options.sigma, progress=progress, out_dir=out,
                                resume=options.resume, sigma_yaw=options.sigma_yaw, executor=ex,
                                keep_rollouts=options.record is not None)
    from splattwin.options import to_dict

    paths, real_robot = write_outputs(out, spec, result, trials,
                                      render_note=(note or "") if options.render else "rendering disabled (--no-render)",
                                      frames=frames, wall_s=time.perf_counter() - t0, options=to_dict(options),
                                      names=names)
    # the plan ran, yet no real-arm files: outside the named robot's limits, or the scene moved before the
    # robot acted (a floating object: the run does not validate the twin); a failed task is neither
    export_error = (real_robot["reason"] if real_robot.get("limit_violations") or real_robot.get("not_at_rest")
                    else None)
    return RobotResult(results=paths["results"], success=bool(result.success), export_error=export_error,
                       details={"run": result, "trials": trials, "paths": paths, "real_robot": real_robot})


def _export_names(spec, options: RobotOptions):
    """The joint names and base frame of the exported files (`robot.export.export_names`)."""
    from splattwin.robot.export import export_names

    robot = spec.robot_model()
    return export_names(options.joint_names, robot.arm_joints, robot.root_body, spec.robot_mjcf is None,
                        base_frame=options.base_frame)


def _error_result(out: Path, e: InputError, options: RobotOptions, twin_dir: Path) -> RobotResult:
    """results.json saying why the task could not run, alone in OUT (no earlier run's files beside it)."""
    from splattwin import io
    from splattwin.robot.outputs import remove_previous, twin_digest

    remove_previous(out)
    path = io.write_json(out / "results.json", {"error": str(e), "task": options.task,
                                                "twin_digest": twin_digest(twin_dir)})
    return RobotResult(results=path, success=False, error=str(e))
