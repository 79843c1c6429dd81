"""`splattwin plan ... --record DIR`: every validation run of a task as a LeRobot-layout episode.

The robot stage executes the nominal run and the perturbed trials (in a process pool) and keeps each
one's `Rollout` (robot/rollout.npz, robot/trials/<i>.rollout.npz, written atomically by the process that
ran it). Recording happens after, in this process, from those files: episode 0 is the nominal run,
episode i is trial i (its objects start where that trial perturbed them: the rollout's object poses are
the simulation's). Each episode is rendered photoreal from the twin's splats (`DynamicScene` +
`RobotSplats`) by a wrist camera (eye-in-hand, D435-like) and one scene camera, and written by
`episode.write_episode` (parquet + one MP4 per camera + meta).

Atomic as a whole: episodes are written into a staging folder beside DIR (`.<name>.recording`), which
replaces DIR only when every episode is there; a killed run leaves the staging folder, and the next run
keeps the episodes whose rollout (by content) and settings are unchanged (`record.json` in the staging
folder says which). DIR, when it exists, must be a dataset (meta/info.json) or empty: nothing else is
ever replaced.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.hashing import sha256_file
from splattwin.playback.cameras import EyeInHand, check_camera, resolve_camera

STATE_FILE = "record.json"


@dataclass
class RecordRun:
    """One run to record: its rollout file, the episode's task text and what to keep in its meta record."""

    rollout: Path
    task: str
    extra: dict


def staging_dir(dest: str | Path) -> Path:
    dest = Path(dest)
    return dest.parent / f".{dest.name}.recording"


def check_destination(dest: str | Path) -> Path:
    """DIR as given, or InputError when it exists and is neither empty nor a LeRobot dataset."""
    dest = Path(dest)
    if dest.exists():
        if not dest.is_dir():
            raise InputError("--record must name a folder, this is a file", dest)
        if any(dest.iterdir()) and not (dest / "meta" / "info.json").is_file():
            raise InputError("--record folder exists and is not a LeRobot dataset (no meta/info.json): "
                             "refusing to replace it", dest)
    return dest


class Recorder:
    """Renders rollouts of one twin into episodes. Built before the physics runs, so a twin without splats
    or a camera below the table is refused (InputError) before anything is computed or written.

    twin_dir: the twin; T_world_base [4,4]: the robot base the runs used; camera: scene camera spec
    (`resolve_camera`); width: pixels of both cameras; fps: episode frame rate (Hz)."""

    def __init__(self, twin_dir: str | Path, T_world_base: np.ndarray, camera: str = "capture:0",
                 width: int = 320, fps: float = 10.0):
        from splattwin.playback.compositor import PlaybackRenderer
        from splattwin.playback.robot import RobotSplats
        from splattwin.playback.scene import DynamicScene

        self.twin_dir = Path(twin_dir)
        self.fps = float(fps)
        self.scene = DynamicScene.load(self.twin_dir)       # InputError: no splats
        scene_cam = resolve_camera(camera, self.twin_dir, width=width)
        if isinstance(scene_cam, EyeInHand):
            raise InputError(f"--record-camera {camera!r} is an eye-in-hand camera; the wrist camera is always "
                             "recorded, give a world camera for the scene view")
        check_camera(scene_cam, self.scene.table_height, camera if str(camera).endswith((".yaml", ".yml")) else None)
        height = int(round(width * 3 / 4))
        self.cameras = {"wrist": EyeInHand(width=int(width), height=height), "scene": scene_cam}
        self.renderer = PlaybackRenderer(self.scene, RobotSplats.panda(np.asarray(T_world_base, float)))
        self.settings = {"fps": self.fps, "camera": str(camera), "width": int(width),
                         "scene_K": np.asarray(scene_cam.K).round(9).tolist(),
                         "scene_T_world_cam": np.asarray(scene_cam.T_world_cam).round(9).tolist(),
                         "base": np.asarray(T_world_base).round(9).tolist()}

    def record(self, dest: str | Path, runs: list[RecordRun], progress: bool = True) -> dict:
        """Write every run as episode 0.. into `dest` (replacing it atomically). Returns a summary."""
        from splattwin.playback.episode import write_episode
        from splattwin.robot.rollout import Rollout

        dest = check_destination(dest)
        stage = staging_dir(dest)
        state_path = stage / STATE_FILE
        state = _read_state(state_path) if stage.is_dir() else {}
        stale = [k for k in state.get("episodes", {}) if not k.isdigit() or int(k) >= len(runs)]
        if stale or state.get("settings") != json.loads(json.dumps(self.settings)):
            # other settings, or episodes of an earlier, longer run: start the staging folder afresh
            if stage.exists():
                shutil.rmtree(stage)
            state = {"settings": self.settings, "episodes": {}}
        stage.mkdir(parents=True, exist_ok=True)
        reused = 0
        for ep, run in enumerate(runs):
            digest = sha256_file(run.rollout)
            if state["episodes"].get(str(ep)) == digest and _has_episode(stage, ep):
                reused += 1
                continue
            rollout = Rollout.load(run.rollout)
            write_episode(stage, rollout, self.renderer, self.cameras, fps=self.fps, task=run.task,
                          episode_index=ep, progress=progress, extra=run.extra)
            state["episodes"][str(ep)] = digest
            io.write_json(state_path, state)
        (stage / STATE_FILE).unlink()
        _replace_dir(stage, dest)
        return {"path": str(dest), "episodes": len(runs), "reused": reused, "fps": self.fps,
                "cameras": {k: [c.width, c.height] for k, c in
                            ((k, self.cameras[k]) for k in self.cameras)}}


def recorder_for(twin_dir: str | Path, robot_out: str | Path, opts) -> Recorder:
    """The `Recorder` for `RobotOptions.record` (`opts`), with everything the recording needs checked
    before the physics runs: the destination, its place outside the robot output folder, the arm (only
    the Panda's Gaussians can be drawn), the twin's splats and the camera (InputError otherwise)."""
    from splattwin.paths import is_inside
    from splattwin.robot.world import BasePose

    check_destination(opts.record)
    if is_inside(opts.record, robot_out) or is_inside(robot_out, opts.record):
        raise InputError(f"--record must be outside the robot output folder {robot_out}", opts.record)
    if opts.robot_mjcf is not None:
        raise InputError("--record renders the Franka Panda's Gaussians; a user robot MJCF cannot be recorded "
                         "yet", opts.robot_mjcf)
    base = BasePose.for_twin(twin_dir, opts.base_pose)
    return Recorder(twin_dir, base.matrix(), camera=opts.record_camera, width=opts.record_width,
                    fps=opts.record_fps)


def record_result(recorder: Recorder, dest: str | Path, robot_out: str | Path, details: dict,
                  progress: bool = True) -> dict:
    """Write the nominal run and every trial of a robot stage result (`RobotResult.details`) into `dest`."""
    return recorder.record(dest, runs_of(robot_out, details, task_text(details["run"])), progress=progress)


def runs_of(robot_out: str | Path, results: dict, task: str) -> list[RecordRun]:
    """The nominal run and each trial of a robot stage result (`RobotResult.details`) as `RecordRun`s."""
    out = Path(robot_out)
    run = results["run"]
    runs = [RecordRun(out / "rollout.npz", task, {"run": "nominal", "seed": None, "success": bool(run.success),
                                                  "sigma_m": 0.0})]
    if not runs[0].rollout.is_file():
        raise InputError("the nominal run left no rollout to record", runs[0].rollout)
    trials = results.get("trials") or {}
    for i, r in enumerate(trials.get("results", [])):
        if "rollout" not in r:   # a crashed trial: nothing executed, nothing to record
            continue
        p = out / "trials" / r["rollout"]
        runs.append(RecordRun(p, task, {"run": f"trial {i + 1}", "seed": r.get("seed"), "success": bool(r["success"]),
                                        "sigma_m": trials.get("sigma"), "sigma_yaw_rad": trials.get("sigma_yaw")}))
    return runs


def task_text(run) -> str:
    """The episode's task in words, from the run's steps (a `RunResult`): "put blue_box on cardboard_box; ..."."""
    steps = [f"move {s.pick} to {s.goal}"
             for s in getattr(run, "steps", [])]
    return "; ".join(steps) or "pick and place"


def _has_episode(root: Path, ep: int) -> bool:
    from splattwin.playback.episode import read_jsonl

    try:
        return any(e.get("episode_index") == ep for e in read_jsonl(root / "meta" / "episodes.jsonl"))
    except InputError:
        return False


def _read_state(path: Path) -> dict:
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    try:   # bounded: the dataset folder may be someone else's (deep nesting raised RecursionError)
        d = read_json(path, max_bytes=MAX_RECORD_BYTES)
    except (InputError, OSError):
        return {}
    return d if isinstance(d, dict) and isinstance(d.get("episodes"), dict) else {}


def _replace_dir(src: Path, dest: Path) -> None:
    """Move the finished folder `src` to `dest` by renames in one parent folder: `dest` holds the old
    dataset or the new one, never a mixture (it is missing only between the two renames)."""
    old = None
    if dest.exists():
        old = io.temp_dir(dest.parent, dest.name + ".old")
        os.rename(dest, old / "dataset")
    os.rename(src, dest)
    io.fsync_path(dest.parent)
    if old is not None:
        shutil.rmtree(old)
