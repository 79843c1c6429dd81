"""Artifacts of a validation run, written atomically under OUT (default TWIN/robot):

    results.json                 task (its path and `task_sha256`), the success criteria (`criteria`),
                                 base pose and frame, exported joint names, per-step results and the
                                 task's step list (`nominal.task_steps`, with each region's numbers: the
                                 steps after a failed one were not attempted), the servos' tracking error
                                 (`tracking_error`), trials summary (sigma per axis, its definition,
                                 sigma_yaw), notes
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
    program.json, program/NN_*.goal.ros2.yaml
                                 the same cut at the gripper commands into arm phases and blocking
                                 gripper actions: what a real arm runs (`program.py`)
    (these real-robot files — REAL_ROBOT_FILES — are written only for a successful nominal run whose
    trajectory fits the named robot's limits, `--joint-names fr3`; results.json `real_robot` says whether
    they were and why not)
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

results.json records `twin_digest` (`twin_digest`: twin.json less its timings, versions, exports (list and files) and
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
from splattwin.hashing import TWIN_RUN_RECORD

log = logging.getLogger(__name__)

# The names a run writes (module docstring); `remove_previous` removes nothing else
REAL_ROBOT_FILES = ("trajectory.json", "trajectory.csv", "trajectory.ros2.yaml", "trajectory.goal.ros2.yaml",
                    "gripper.ros2.yaml", "program.json")   # and program/
TOP_FILES = ("results.json", *REAL_ROBOT_FILES, "base_transform.yaml", "rollout.npz", "playback.npz")
_OWN = {"segments": re.compile(r"^step\d+_[A-Za-z0-9_]+\.json$"),
        "program": re.compile(r"^\d{2,}_(arm|gripper_grasp|gripper_move)\.goal\.ros2\.yaml$"),
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


# twin.json entries that do not change what the robot plans in: its run record (run times, package
# versions, the export files written: `splattwin.hashing.TWIN_RUN_RECORD`, which the pipeline's twin stage
# also leaves out), and the build's recorded options (`config.build`: the twin's content is the rest)
_UNPLANNED = TWIN_RUN_RECORD


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
    """`results_twin` of TWIN/robot/results.json as it is on disk (an unreadable file counts as unreadable, a
    missing one says so): None when it belongs to the twin as it is now, else why not."""
    from splattwin.paths import own_file

    rj = own_file(twin_dir, Path(twin_dir) / "robot" / "results.json", "robot/results.json")
    if not rj.is_file():   # written last: the run that wrote the other files did not finish
        return ("robot/results.json is missing: the `splattwin plan` run that wrote robot/ did not finish "
                "(stopped or killed); run it again")
    return results_twin(io.read_record(rj), twin_dir)


def write_outputs(out: str | Path, spec, result, trials: dict | None, render_note: str = "",
                  frames: list[Path] | None = None, wall_s: float | None = None,
                  options: dict | None = None, names=None) -> tuple[dict[str, Path], dict]:
    """OUT/results.json (with `options`: the robot options of this run, as `splattwin.options.to_dict`
    writes them; a twin's config.build.robot is what the build asked for when its twin stage ran, so the
    results say what made them), segments, trajectories and program (for a successful run only:
    `write_trajectories`), base transform, base-frame MoveIt scene, the rollout. names: the
    `export.ExportNames` of the trajectory files (None: the default naming). Returns (paths, real_robot:
    whether the real-robot files were written and why not, as results.json records it)."""
    from splattwin.robot.export import write_base_frame_moveit, write_base_transform
    from splattwin.robot.world import simulation_deviations

    out = Path(out)
    robot = spec.robot_model()
    if names is None:
        from splattwin.robot.export import export_names

        names = export_names(None, robot.arm_joints, robot.root_body, spec.robot_mjcf is None)
    T_twin_base = spec.base.matrix()
    from splattwin.robot.execute import unsettled

    settle = getattr(result, "settle", None)
    # an object physics moved before the robot acted (floating, sunk in): the run was made on another scene
    # than the twin's and validates nothing, successful or not (`execute.unsettled`)
    not_at_rest = unsettled(settle)
    failed = not_at_rest if not_at_rest else None if result.success else _failure(result)
    paths, notes, real_robot = write_trajectories(out, result.trajectories, trajectory_meta(spec, robot, names),
                                                  names, failed=failed)
    if not_at_rest:
        real_robot["not_at_rest"] = {o: settle["objects"][o] for o in settle["moved"]}
    paths["base_transform"] = write_base_transform(out / "base_transform.yaml", T_twin_base, names.base_frame)
    paths.update(write_base_frame_moveit(out, spec.twin_dir, T_twin_base, names.base_frame))
    if render_note:
        notes.append(render_note)
    rollout_paths, tracking = write_rollout(out, spec, result)
    paths.update(rollout_paths)
    doc = {
        # absolute: a path as typed (`tasks/mine.yaml`) says nothing once read from elsewhere
        "twin": str(spec.twin_dir), "task": (str(Path(spec.task_path).resolve()) if spec.task_path
                                             else "default (paper three-step rearrangement)"),
        "base_pose": asdict(spec.base), "base_frame": names.base_frame,
        "joint_names": {"exported": list(names.joint_names), "simulated": list(robot.arm_joints)},
        "robot_mjcf": spec.robot_mjcf or "MuJoCo Menagerie franka_emika_panda",
        "robot": {"model": spec.robot_mjcf or "MuJoCo Menagerie franka_emika_panda (Franka Emika Panda + Hand)",
                  "simulation_deviations": simulation_deviations(robot)},
        "real_robot": real_robot,
        # False when the run does not validate the twin: the task failed, or the scene moved before the
        # robot acted (`settle`: how far physics moved each object from its twin pose in the start check)
        "validated": bool(result.success) and not not_at_rest, "settle": settle,
        # the task's file by content: the path alone names whatever the file holds after an edit
        "task_sha256": _task_digest(spec.task_path),
        "criteria": _criteria(),   # the thresholds each step was judged by (judge.criteria)
        "planner": spec.planner, "seed": spec.seed,
        "nominal": result.to_dict(), "tracking": tracking,
        "trials": trials,
        "frames": [str(Path(f).relative_to(out)) for f in (frames or [])],
        "notes": notes, "wall_s": wall_s,
        "twin_digest": twin_digest(spec.twin_dir),   # the twin these results belong to (`results_twin`)
        **({"options": options} if options is not None else {}),
    }
    paths["results"] = io.write_json(out / "results.json", doc)
    return paths, real_robot


def _task_digest(task_path: str | None) -> str | None:
    """sha256 of the task file's bytes (the default task's when None)."""
    from splattwin.robot.task import default_task_path
    from splattwin.robot.trials import file_digest

    return file_digest(task_path or default_task_path())


def _criteria() -> dict:
    from splattwin.robot.candidates import LIFT
    from splattwin.robot.execute import SETTLE_TIME
    from splattwin.robot.judge import criteria

    return criteria(LIFT, SETTLE_TIME)


def trajectory_meta(spec, robot, names) -> dict:
    """What a robot engineer needs beside the samples: robot, joint map (exported -> simulated), base pose
    (T_twin_base), start configuration, sample and simulation rates (the units are added by Trajectory)."""
    from splattwin.robot.export import base_pose_doc

    return {"robot": spec.robot_mjcf or "MuJoCo Menagerie franka_emika_panda (Franka Emika Panda + Hand)",
            "joint_naming": names.naming, "joint_map": names.joint_map(list(robot.arm_joints)),
            "base_frame": names.base_frame, "base_pose": base_pose_doc(spec.base.matrix(), names.base_frame),
            "timeline": ("as executed in the validation run: every motion, the hold after it and the gripper "
                         "holds; the gripper commands are issued at their t. The gripper holds are the simulated "
                         "hand's, shorter than a real Franka Hand needs: a real arm runs program.json (blocking "
                         "gripper actions between arm phases)")}


def _failure(result) -> str:
    """Why a nominal run failed, in a sentence (its first failed step, or the steps it did not reach)."""
    bad = next((st for st in result.steps if not st.success), None)
    if bad is not None:
        return f"the task failed in the validation run at step {bad.index} ({bad.pick}): {bad.failure}"
    return "the task failed in the validation run (not every step ran)"


def write_trajectories(out: Path, trajectories, meta: dict, names,
                       failed: str | None = None) -> tuple[dict[str, Path], list[str], dict]:
    """OUT/segments/<label>.json, and for the real robot the whole timeline as
    trajectory.{json,csv,ros2.yaml,goal.ros2.yaml} and gripper.ros2.yaml and the program (program.json,
    program/: `program.py`), with the exported joint names, accelerations consistent with the sampled
    velocities, and `meta` (+ the start state) in the JSON.

    The real-robot files are written only when the run succeeded (`failed` None; else it says why it
    failed) and, for a naming with its own robot limits (`export.NAMED_LIMITS`: fr3), the timeline stays
    inside them; otherwise only the segments (what was attempted, for inspection). Returns (paths, notes,
    real_robot: {written, reason, files, limit_violations?} as results.json records it)."""
    from splattwin.robot.export import NAMED_LIMITS, limit_violations
    from splattwin.robot.program import write_program
    from splattwin.robot.trajectory import concatenate

    paths: dict[str, Path] = {}
    notes: list[str] = []
    segs, labelled = [], []
    for label, tr in trajectories:
        tr = tr.renamed(names.joint_names).with_velocity_accelerations()
        tr.meta = dict(meta)
        paths[f"segment:{label}"] = tr.save_json(out / "segments" / f"{label}.json")
        segs.append(tr)
        labelled.append((label, tr))

    def refused(reason: str, **extra) -> tuple[dict[str, Path], list[str], dict]:
        notes.append(f"no trajectory for the real arm: {reason}")
        # the reason is said once, by the command's summary (plan's `print_summary`, build's headline)
        log.info("no files for the real arm (robot/trajectory.*, gripper.ros2.yaml, program.json); results.json "
                 "real_robot says why%s", "; the attempted motions are in robot/segments/" if segs else "")
        return paths, notes, {"written": False, "reason": reason, "files": [], **extra}

    if failed is not None:
        return refused(failed)
    if not segs:
        return refused("the run executed no motion")
    try:
        full = concatenate(segs).with_velocity_accelerations()
    except ValueError as e:  # a gap between segments (not expected of a successful run): keep the segments only
        return refused(f"the segments do not join into one trajectory: {e}")
    limits = NAMED_LIMITS.get(names.naming)
    if limits is not None:
        bad = limit_violations(full, limits, names.naming.upper())
        if bad:
            return refused(f"the trajectory leaves the {names.naming.upper()}'s joint limits "
                           f"(--joint-names {names.naming}; planned with the simulated Panda's): " + "; ".join(bad),
                           limit_violations=bad, limits_source=limits["source"])
    grip0 = full.gripper[0].command if full.gripper and full.gripper[0].t <= 1e-9 else None
    rate = 1.0 / float(np.median(np.diff(full.t))) if len(full) > 1 else None
    full.meta = {**meta, "sample_rate_hz": None if rate is None else round(rate, 3), "start": {
        "q": full.q[0].tolist(), "gripper": grip0,
        "note": "bring the arm to q (the first sample, at rest) before sending the trajectory: it starts "
                "there and does not move the arm to it"}}
    try:
        program = write_program(out, labelled, {k: v for k, v in meta.items() if k != "timeline"})
    except ValueError as e:
        return refused(f"the timeline does not cut into arm phases and gripper actions: {e}")
    paths.update(program)
    paths["trajectory_json"] = full.save_json(out / "trajectory.json")
    paths["trajectory_csv"] = full.save_csv(out / "trajectory.csv")
    paths["trajectory_ros2"] = full.save_ros2_yaml(out / "trajectory.ros2.yaml")
    paths["trajectory_ros2_goal"] = full.save_ros2_goal_yaml(out / "trajectory.goal.ros2.yaml")
    paths["gripper_ros2"] = full.save_ros2_gripper_yaml(out / "gripper.ros2.yaml")
    files = sorted(str(p.relative_to(out)) for k, p in paths.items() if not k.startswith("segment:"))
    extra = {"limits_checked": limits["source"]} if limits is not None else {}
    return paths, notes, {"written": True, "reason": None, "files": files, **extra}


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


def print_summary(result, trials: dict | None, paths: dict[str, Path], real_robot: dict | None = None) -> None:
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
    from splattwin.robot.execute import unsettled

    moved = unsettled(getattr(result, "settle", None)) is not None
    overall = ("[red]success in simulation, but NOT a validation of the twin[/] (objects moved before the robot "
               "acted)" if result.success and moved else "[green]success[/]" if result.success else "[red]failure[/]")
    con.print(f"overall: {overall}; {result.sim_time:.1f} s simulated in {result.wall_s:.1f} s")
    if trials:
        lo, hi = trials["ci95"]
        con.print(f"trials: {trials['successes']}/{trials['trials']} at sigma {trials['sigma'] * 1000:.1f} mm per axis, "
                  f"yaw {math.degrees(trials['sigma_yaw']):.1f} deg (95 % CI {lo:.2f}-{hi:.2f}), "
                  f"collisions {trials['collisions']}"
                  + (f", {trials['resumed']} reused from an earlier run" if trials.get("resumed") else ""))
        for line in trial_failures(trials):
            con.print(line, markup=False, highlight=False)
    if real_robot is not None and not real_robot.get("written"):
        from rich.markup import escape

        con.print(f"[red]no trajectory for the real arm[/]: {escape(str(real_robot.get('reason')))}", highlight=False)
    elif "program" in paths:
        con.print(f"real arm: {paths['program']} (arm phases and blocking gripper actions; README)", highlight=False)
    con.print(f"results: {paths['results']}")


def trial_failures(trials: dict, limit: int = 5) -> list[str]:
    """Lines naming the failed trials (at most `limit`, then how many more) and why each failed: its
    first failed step, or its worker's error; [] when every trial succeeded."""
    bad = [(i, r) for i, r in enumerate(trials.get("results") or [], start=1)
           if isinstance(r, dict) and not r.get("success")]
    lines = []
    for i, r in bad[:limit]:
        step = next((st for st in r.get("steps") or [] if isinstance(st, dict) and not st.get("success")), None)
        why = (f"step {step.get('index')} ({step.get('pick')}): {step.get('failure')}" if step is not None
               else f"its start: {r.get('error')}" if r.get("error") else "a step it did not reach")
        kept = "" if r.get("error") else f", trials/{i}.json"   # a worker that died left no file
        lines.append(f"trial {i} (seed {r.get('seed')}{kept}) failed at {why}")
    if len(bad) > limit:
        lines.append(f"... and {len(bad) - limit} more failed trial(s) (results.json trials.results)")
    return lines


def _yn(b: bool) -> str:
    return "yes" if b else "no"
