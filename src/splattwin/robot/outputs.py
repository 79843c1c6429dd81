"""Artifacts of a validation run, written atomically under OUT (default TWIN/robot):

    results.json                 task, base pose and frame, exported joint names, per-step results, the
                                 servos' tracking error (`tracking_error`), trials summary (sigma per axis,
                                 its definition, sigma_yaw), notes
    trials/<i>.json              each finished perturbed trial (reused by a re-run with the same key)
    trials/<i>.rollout.npz       its rollout, kept when the run is recorded (`plan --record`); both written
                                 by the trial's worker (`trials.run_trials`), the rollout first
    trajectory.json / .csv       the whole executed timeline for the real robot, 100 Hz: every motion with
                                 the settle hold after it and the gripper holds (it lasts as long as the
                                 validated run, rollout.npz), the gripper commands (open / grasp: width,
                                 speed, force, epsilon), the exported joint names (`--joint-names`) and their
                                 map to the simulated ones; JSON also units, robot, base pose, start state
    trajectory.ros2.yaml         the same as trajectory_msgs/JointTrajectory (frame_id "")
    trajectory.goal.ros2.yaml    the same as a control_msgs/action/FollowJointTrajectory goal
    gripper.ros2.yaml            the gripper commands as franka_msgs/action/Grasp / Move goals with times
    base_transform.yaml          T_twin_base as geometry_msgs/TransformStamped (+ static_transform_publisher)
    moveit/collision_objects.yaml, moveit/scene.scene
                                 the twin's collision world in the robot base frame (`export.py`)
    segments/<label>.json        each servo command separately (transit, approach, lift, transfer, ...: the
                                 motion and its hold; close / open: the gripper hold)
    rollout.npz                  what physics did, every control step (`rollout.Rollout`: full qpos, arm and
                                 gripper measured and commanded, object poses, task step)
    playback.npz                 the robot's visual geometry posed along the rollout, for `splattwin view`
                                 (`track.RobotTrack`; this module is its only writer)
    frames/frame_*.png           rendered frames (when an offscreen GL context exists)

results.json records `twin_digest` (`twin_digest`: twin.json less its timings, versions, exports and
build options, and the meshes' contents): results of another twin (rebuilt since with other objects or
geometry) are told apart by `results_twin` (the report then shows none, the pipeline removes them).

OUT holds one run: once its task is valid, a run first removes every file of these names left by an
earlier run (`remove_previous`; results.json first, trials/<i> beyond this run's N), then writes its
own, results.json last. A killed run therefore leaves no results.json and only files of its own.
"""

from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import asdict
from pathlib import Path

import numpy as np

from splattwin import io

log = logging.getLogger(__name__)

# The names a run writes (module docstring); `remove_previous` removes nothing else
TOP_FILES = ("results.json", "trajectory.json", "trajectory.csv", "trajectory.ros2.yaml", "trajectory.goal.ros2.yaml",
             "gripper.ros2.yaml", "base_transform.yaml", "rollout.npz", "playback.npz")
_OWN = {"segments": re.compile(r"^step\d+_[A-Za-z0-9_]+\.json$"),
        "moveit": re.compile(r"^(collision_objects\.yaml|scene\.scene)$"),
        "frames": re.compile(r"^(frame_\d+_[A-Za-z0-9_]+|overview)\.png$")}
_TRIAL = re.compile(r"^(?P<i>\d+)(\.rollout\.npz|\.json)$")


def remove_previous(out: str | Path, keep_trials: int = 0) -> list[Path]:
    """Remove an earlier run's outputs from OUT: the files named in the module docstring, and of
    trials/ those of trials beyond `keep_trials` (the first keep_trials stay: the run resumes or
    rewrites them). Removes only plain files and links of our names (a link itself, never what it
    points to), never descends into a linked folder. results.json goes first: from then on OUT
    claims no finished run until this run writes its own. Returns what was removed."""
    out = Path(out)
    removed: list[Path] = []

    def unlink(p: Path) -> None:
        try:
            if p.is_symlink() or p.is_file():
                p.unlink()
                removed.append(p)
        except FileNotFoundError:
            pass

    for name in TOP_FILES:
        unlink(out / name)
    for sub, pattern in {**_OWN, "trials": _TRIAL}.items():
        d = out / sub
        if d.is_symlink() or not d.is_dir():
            continue
        with os.scandir(d) as it:
            for e in it:
                m = pattern.match(e.name)
                if m is None or e.is_dir(follow_symlinks=False):
                    continue
                if sub == "trials" and int(m.group("i")) <= keep_trials:
                    continue
                unlink(d / e.name)
    if removed:
        log.info("removed %d file(s) of an earlier run from %s", len(removed), out)
    return removed


# twin.json entries that do not change what the robot plans in: run times, package versions, the export
# files written, the build's recorded options (`config.build`: the twin's content is the rest)
_UNPLANNED = ("timings", "versions", "exports")


def twin_digest(twin_dir: str | Path) -> str | None:
    """A digest of the twin as the robot plans in it: twin.json (less `_UNPLANNED` and config.build, so a
    deterministic rebuild of the same twin keeps its digest) and the contents of the meshes it names.
    None when twin.json is unreadable."""
    import hashlib
    import json

    from splattwin.errors import InputError
    from splattwin.robot.trials import twin_meshes_digest

    try:
        doc = io.read_json(Path(twin_dir) / "twin.json")
    except InputError:
        return None
    if not isinstance(doc, dict):
        return None
    doc = {k: v for k, v in doc.items() if k not in _UNPLANNED}
    if isinstance(doc.get("config"), dict):
        doc["config"] = {k: v for k, v in doc["config"].items() if k != "build"}
    h = hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode())
    h.update(str(twin_meshes_digest(twin_dir)).encode())
    return h.hexdigest()


def results_twin(results, twin_dir: str | Path) -> str | None:
    """None when robot results (results.json, loaded) were made on the twin as it is now; else why they do
    not belong to it (a sentence): made on another twin (rebuilt since), or recording no twin at all
    (an earlier splattwin's results: they cannot be vouched for)."""
    if not isinstance(results, dict):
        return "robot/results.json is unreadable"
    made_on = results.get("twin_digest")
    if not isinstance(made_on, str):
        return ("robot/results.json records no twin digest (written by an earlier splattwin): it cannot be "
                "checked against this twin")
    if made_on != twin_digest(twin_dir):
        return ("robot/results.json was made on an earlier state of this twin (its objects or meshes have "
                "changed since): rerun `splattwin plan` (or build with --task)")
    return None


def stale_results(twin_dir: str | Path) -> str | None:
    """`results_twin` of TWIN/robot/results.json as it is on disk (a missing or unreadable file counts as
    unreadable): None when it belongs to the twin as it is now, else why not."""
    from splattwin.errors import InputError

    rj = Path(twin_dir) / "robot" / "results.json"
    try:
        results = io.read_json(rj) if rj.is_file() else None
    except InputError:
        results = None
    return results_twin(results, twin_dir)


def write_outputs(out: str | Path, spec, result, trials: dict | None, render_note: str = "",
                  frames: list[Path] | None = None, wall_s: float | None = None,
                  options: dict | None = None, names=None) -> dict[str, Path]:
    """OUT/results.json (with `options`: the robot options of this run, as `splattwin.options.to_dict`
    writes them; a twin's config.build.robot is what the build asked for when its twin stage ran, so the
    results say what made them), segments, trajectories, base transform, base-frame MoveIt scene, the
    rollout. names: the `export.ExportNames` of the trajectory files (None: the default naming)."""
    from splattwin.robot.export import write_base_frame_moveit, write_base_transform

    out = Path(out)
    robot = spec.robot_model()
    if names is None:
        from splattwin.robot.export import export_names

        names = export_names(None, robot.arm_joints, robot.root_body, spec.robot_mjcf is None)
    T_twin_base = spec.base.matrix()
    paths, notes = write_trajectories(out, result.trajectories, trajectory_meta(spec, robot, names), names)
    paths["base_transform"] = write_base_transform(out / "base_transform.yaml", T_twin_base, names.base_frame)
    paths.update(write_base_frame_moveit(out, spec.twin_dir, T_twin_base, names.base_frame))
    if render_note:
        notes.append(render_note)
    rollout_paths, tracking = write_rollout(out, spec, result)
    paths.update(rollout_paths)
    doc = {
        "twin": str(spec.twin_dir), "task": spec.task_path or "default (paper three-step rearrangement)",
        "base_pose": asdict(spec.base), "base_frame": names.base_frame,
        "joint_names": {"exported": list(names.joint_names), "simulated": list(robot.arm_joints)},
        "robot_mjcf": spec.robot_mjcf or "MuJoCo Menagerie franka_emika_panda",
        "planner": spec.planner, "seed": spec.seed,
        "nominal": result.to_dict(), "tracking": tracking,
        "trials": trials,
        "frames": [str(Path(f).relative_to(out)) for f in (frames or [])],
        "notes": notes, "wall_s": wall_s,
        "twin_digest": twin_digest(spec.twin_dir),   # the twin these results belong to (`results_twin`)
        **({"options": options} if options is not None else {}),
    }
    paths["results"] = io.write_json(out / "results.json", doc)
    return paths


def trajectory_meta(spec, robot, names) -> dict:
    """What a robot engineer needs beside the samples: robot, joint map (exported -> simulated), base pose
    (T_twin_base), start configuration, sample and simulation rates (the units are added by Trajectory)."""
    from splattwin.robot.export import base_pose_doc

    return {"robot": spec.robot_mjcf or "MuJoCo Menagerie franka_emika_panda (Franka Emika Panda + Hand)",
            "joint_naming": names.naming, "joint_map": names.joint_map(list(robot.arm_joints)),
            "base_frame": names.base_frame, "base_pose": base_pose_doc(spec.base.matrix(), names.base_frame),
            "timeline": ("as executed in the validation run: every motion, the hold after it and the gripper "
                         "holds; the gripper commands are issued at their t")}


def write_trajectories(out: Path, trajectories, meta: dict, names) -> tuple[dict[str, Path], list[str]]:
    """OUT/segments/<label>.json and the whole timeline as trajectory.{json,csv,ros2.yaml,goal.ros2.yaml}
    and gripper.ros2.yaml, with the exported joint names, accelerations consistent with the sampled
    velocities, and `meta` (+ the start state) in the JSON. Returns (paths, notes)."""
    from splattwin.robot.trajectory import concatenate

    paths: dict[str, Path] = {}
    notes: list[str] = []
    segs = []
    for label, tr in trajectories:
        tr = tr.renamed(names.joint_names).with_velocity_accelerations()
        tr.meta = dict(meta)
        paths[f"segment:{label}"] = tr.save_json(out / "segments" / f"{label}.json")
        segs.append(tr)
    if not segs:
        return paths, notes
    try:
        full = concatenate(segs).with_velocity_accelerations()
    except ValueError as e:  # a failed step can leave a gap: keep the segments only
        notes.append(f"no single trajectory file: {e}")
        return paths, notes
    grip0 = full.gripper[0].command if full.gripper and full.gripper[0].t <= 1e-9 else None
    rate = 1.0 / float(np.median(np.diff(full.t))) if len(full) > 1 else None
    full.meta = {**meta, "sample_rate_hz": None if rate is None else round(rate, 3), "start": {
        "q": full.q[0].tolist(), "gripper": grip0,
        "note": "bring the arm to q (the first sample, at rest) before sending the trajectory: it starts "
                "there and does not move the arm to it"}}
    paths["trajectory_json"] = full.save_json(out / "trajectory.json")
    paths["trajectory_csv"] = full.save_csv(out / "trajectory.csv")
    paths["trajectory_ros2"] = full.save_ros2_yaml(out / "trajectory.ros2.yaml")
    paths["trajectory_ros2_goal"] = full.save_ros2_goal_yaml(out / "trajectory.goal.ros2.yaml")
    paths["gripper_ros2"] = full.save_ros2_gripper_yaml(out / "gripper.ros2.yaml")
    return paths, notes


def write_rollout(out: str | Path, spec, result) -> tuple[dict[str, Path], dict | None]:
    """OUT/rollout.npz and OUT/playback.npz (the viewer's track) from the result's rollout, if it has one,
    and its `tracking_error` (None without a rollout).

    The track is posed on a world with the robot's visual meshes (built here: the executing world may
    have been built without them); the rollout's full qpos replays every body exactly."""
    from splattwin.robot.track import write_playback
    from splattwin.robot.world import build_world

    rollout = getattr(result, "rollout", None)
    if rollout is None or not len(rollout):
        return {}, None
    out = Path(out)
    paths = {"rollout": rollout.save(out / "rollout.npz")}
    world = build_world(spec.twin_dir, robot=spec.robot_model(), base=spec.base, visual=True)
    paths["playback"] = write_playback(out / "playback.npz", world, rollout)
    return paths, tracking_error(world, rollout)


def tracking_error(world, rollout, every: int = 5) -> dict:
    """How far physics was from the commanded (exported) trajectory over the run, every `every`-th control
    step: the arm joints (rad, max) and the TCP position (m, max / median / 95th percentile), measured
    against the TCP at the commanded joints with everything else as simulated."""
    import mujoco

    d = mujoco.MjData(world.model)
    tcp = world.tcp_site
    err = []
    for i in range(0, len(rollout), every):
        d.qpos[:] = rollout.qpos[i]
        mujoco.mj_kinematics(world.model, d)
        p_measured = d.site_xpos[tcp].copy()
        world.joints.set_arm(d.qpos, rollout.action_q_arm[i])
        mujoco.mj_kinematics(world.model, d)
        err.append(float(np.linalg.norm(d.site_xpos[tcp] - p_measured)))
    e = np.array(err)
    return {"joint_max_rad": round(float(np.abs(rollout.q_arm - rollout.action_q_arm).max()), 5),
            "tcp_max_m": round(float(e.max()), 5), "tcp_median_m": round(float(np.median(e)), 5),
            "tcp_p95_m": round(float(np.percentile(e, 95)), 5),
            "definition": "measured vs commanded arm over the validated run (rollout.npz: q_arm vs "
                          "action_q_arm, the exported trajectory), TCP by forward kinematics"}


def print_summary(result, trials: dict | None, paths: dict[str, Path]) -> None:
    from splattwin.console import console
    from rich.table import Table

    con = console()
    t = Table(title="task validation in MuJoCo")
    for c in ("step", "pick", "goal", "grasped", "lift cm", "placed", "at rest", "collisions", "plan ms", "result"):
        t.add_column(c)
    for s in result.steps:
        t.add_row(str(s.index), s.pick, s.goal, _yn(s.grasped), f"{s.lifted_m * 100:.1f}", _yn(s.placed), _yn(s.at_rest),
                  str(s.robot_collisions + s.object_collisions), " ".join(f"{p:.0f}" for p in s.plan_ms),
                  "[green]ok[/]" if s.success else "[red]FAILED[/]")
    con.print(t)
    for s in result.steps:
        if not s.success:
            con.print(f"step {s.index} failed: {s.failure}")
    con.print(f"overall: {'[green]success[/]' if result.success else '[red]failure[/]'}; "
              f"{result.sim_time:.1f} s simulated in {result.wall_s:.1f} s")
    if trials:
        lo, hi = trials["ci95"]
        con.print(f"trials: {trials['successes']}/{trials['trials']} at sigma {trials['sigma'] * 1000:.1f} mm per axis, "
                  f"yaw {math.degrees(trials['sigma_yaw']):.1f} deg (95 % CI {lo:.2f}-{hi:.2f}), "
                  f"collisions {trials['collisions']}"
                  + (f", {trials['resumed']} reused from an earlier run" if trials.get("resumed") else ""))
    con.print(f"results: {paths['results']}")


def _yn(b: bool) -> str:
    return "yes" if b else "no"
