"""Validation runs of a task: one nominal run with outputs, and N perturbed trials in parallel processes.

A trial builds the physical world with every object's pose perturbed — sigma is the per-axis standard
deviation of the position error (dx, dy ~ N(0, sigma) independently, metres; z unchanged, the objects
stay on their support) and yaw ~ N(0, sigma_yaw) rad with sigma_yaw = sigma / 0.1 m by default (a point
10 cm from the object centre moves by sigma through the yaw error: 2.9 deg at sigma = 5 mm) — while the
robot still plans with the twin's nominal poses: the trial measures how much reconstruction error the
plan-then-execute loop tolerates.
The success rate comes with a Wilson score 95 % interval (good at small N and rates near 0 or 1).
With an output folder every finished trial is written atomically to OUT/trials/<i>.json with its key
(twin, task and robot files by content, base, planner, seed, sigmas); a re-run skips those (resume).
The trials run on an executor (`splattwin.executor`): a local process pool by default, or a Ray
cluster; a trial's outcome depends only on its spec (seeded), not on where it ran.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.robot.options import RobotOptions
from splattwin.robot.world import BasePose
from splattwin.transforms import rot_z

log = logging.getLogger(__name__)

YAW_LEVER = 0.10   # m: default sigma_yaw = sigma / YAW_LEVER (a point this far from the centre moves by sigma)
SIGMA_DEFINITION = ("sigma: per-axis standard deviation (m) of each object's x and y position error, drawn "
                    "independently; sigma_yaw: standard deviation (rad) of its yaw error; z unchanged")


def wilson_interval(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval for k successes out of n (95 % for the default z)."""
    if n <= 0:
        return (0.0, 1.0)
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def default_sigma_yaw(sigma: float) -> float:
    """rad: the yaw standard deviation used with a per-axis position sigma (m) unless given."""
    return sigma / YAW_LEVER


def perturb_poses(poses: dict[str, np.ndarray], sigma: float, rng: np.random.Generator,
                  sigma_yaw: float | None = None) -> dict[str, np.ndarray]:
    """Object poses T_world_obj [4,4] with planar noise: dx, dy ~ N(0, sigma) each (per-axis standard
    deviation, m), yaw ~ N(0, sigma_yaw) rad about world z (default sigma / YAW_LEVER)."""
    sigma_yaw = default_sigma_yaw(sigma) if sigma_yaw is None else sigma_yaw
    out = {}
    for name, T in poses.items():
        T = np.asarray(T, float).copy()
        dx, dy = rng.normal(0.0, sigma, 2)
        T[:3, :3] = rot_z(rng.normal(0.0, sigma_yaw)) @ T[:3, :3]
        T[:2, 3] += [dx, dy]
        out[name] = T
    return out


@dataclass
class TrialSpec:
    """One validation run: the twin and task, the robot and how it plans (defaults: `RobotOptions`'s),
    and the perturbation of this trial (sigma 0: the nominal run).

    twin_dir: the twin folder; task_path: a task YAML (`robot.task`), None: the default task. base: the robot
    base in the twin frame; None (the default) puts it where `splattwin plan` does without --base-pose
    (`BasePose.default_for` the twin's frame: at the robot's origin in a twin posed by the robot, else beside
    the table)."""

    twin_dir: str
    task_path: str | None
    base: BasePose | None = None
    robot_mjcf: str | None = None
    sigma: float = 0.0               # m, per-axis (x, y) standard deviation of the object position error
    seed: int = RobotOptions.seed
    sigma_yaw: float | None = None   # rad; None: sigma / YAW_LEVER
    tcp_site: str = RobotOptions.tcp_site      # TCP site of a user robot MJCF
    planner: str = RobotOptions.planner
    in_hand: str = RobotOptions.in_hand        # held object's pose for the transfer (execute.py)

    def __post_init__(self) -> None:
        if self.base is None:
            self.base = default_base(self.twin_dir)

    @classmethod
    def from_options(cls, twin_dir: str | Path, opts: RobotOptions) -> "TrialSpec":
        """The nominal run of `opts` on the twin in `twin_dir`."""
        return cls(twin_dir=str(twin_dir), task_path=None if opts.task in (None, "default") else str(opts.task),
                   base=BasePose.for_twin(twin_dir, opts.base_pose),
                   robot_mjcf=str(opts.robot_mjcf) if opts.robot_mjcf else None, seed=opts.seed,
                   tcp_site=opts.tcp_site, planner=opts.planner, in_hand=opts.in_hand)

    def robot_model(self):
        """The `RobotModel` this spec names: the user's MJCF with its TCP site, else the Menagerie Panda."""
        from splattwin.robot.assets import RobotModel

        return RobotModel.from_mjcf(self.robot_mjcf, tcp_site=self.tcp_site) if self.robot_mjcf else RobotModel.panda()


def default_base(twin_dir: str | Path) -> BasePose:
    """The base pose `splattwin plan` uses without --base-pose (`BasePose.default_for` the twin's frame); beside
    the table when the folder has no readable twin.json (whatever then reads the twin, as `run_once` first
    does, names the file and its problem: a spec alone, e.g. for a trial's key, is no reason to fail)."""
    from splattwin.errors import InputError
    from splattwin.twin.manifest import Manifest

    try:
        return BasePose.default_for(Manifest.load(twin_dir).frame)[0]
    except InputError:
        return BasePose()


def run_once(spec: TrialSpec, frame_dir: str | Path | None = None, keep_trajectories: bool = False,
             on_valid=None, warn: bool = True, task=None):
    """Build the world (perturbed when sigma > 0), validate the task, execute it. Returns (RunResult, the
    frame recorder's note, frame paths); keep_trajectories: the result keeps its trajectories and rollout.
    task: the task to run instead of `spec.task_path`'s: a `Task`, or plain data as `task.parse_task` reads it
    (`[{"pick": "blue_box", "place_in": {"center": [x, y], "size": 0.15}}]`, metres, twin frame).
    on_valid: called once the task is valid, before any frame is written (the stage clears the earlier
    run's outputs there, so a bad task leaves them as they were). warn: the task's warnings are logged
    (False in the trials: the nominal run said them once)."""
    from splattwin.errors import require_type
    from splattwin.robot.execute import Executor
    from splattwin.robot.task import Task, load_task, parse_task, validate_task
    from splattwin.robot.world import build_world
    from splattwin.twin.manifest import Manifest

    require_type(spec, TrialSpec, "spec", "(e.g. TrialSpec(twin_dir, task_path=None))")
    manifest = Manifest.load(spec.twin_dir)
    if task is None:
        task = load_task(spec.task_path, manifest)
    elif not isinstance(task, Task):
        task = parse_task(task, None, manifest)
    robot = spec.robot_model()
    validate_task(task, manifest, spec.twin_dir, spec.base.matrix(), robot=robot, warn=warn)
    if on_valid is not None:
        on_valid()
    nominal = {o.name: o.pose for o in manifest.objects if o.usable}
    poses = perturb_poses(nominal, spec.sigma, np.random.default_rng(spec.seed), spec.sigma_yaw) if spec.sigma > 0 else None
    world = build_world(spec.twin_dir, manifest, robot, spec.base, poses=poses, visual=frame_dir is not None)
    rec = None
    if frame_dir is not None:
        from splattwin.robot.render import FrameRecorder

        rec = FrameRecorder(frame_dir, world.model)
    ex = Executor(world, belief=nominal, seed=spec.seed, planner=spec.planner, in_hand=spec.in_hand,
                  frame_cb=rec if rec and rec.available else None)
    try:
        result = ex.run(task)
        if rec is not None:
            rec.contact_sheet()
    finally:
        if rec is not None:
            rec.close()
    if not keep_trajectories:
        result.trajectories = []
        result.rollout = None
    return result, (rec.note if rec is not None else ""), (rec.paths if rec is not None else [])


def file_digest(path: str | Path | None) -> str | None:
    """sha256 of a file's bytes (None for no file): a rebuilt twin or an edited task is another trial."""
    from splattwin.hashing import sha256_file

    return sha256_file(path) if path is not None and Path(path).is_file() else None


def twin_meshes_digest(twin_dir: str | Path) -> str | None:
    """One digest over the meshes the trial's physics reads (visual, collision and convex parts of the
    objects and the background, as twin.json names them): a twin whose meshes were rebuilt with the same
    twin.json is another trial. None when twin.json is unreadable (the trial then fails on it anyway)."""
    from splattwin.errors import InputError
    from splattwin.hashing import DigestCache
    from splattwin.twin.manifest import Manifest

    try:
        m = Manifest.load(twin_dir)  # paths checked: inside the twin folder
    except InputError:
        return None
    files = [Path(twin_dir) / p for what, p in m.paths() if "mesh" in what or "convex part" in what]
    return DigestCache().files(files)


def trial_key(spec: TrialSpec) -> dict:
    """What makes a trial's result reusable: the same twin (path, twin.json and mesh contents), task,
    robot, base, planner, seed and noise, and the same code (the robot and twin packages' source: an
    upgraded splattwin plans and executes anew)."""
    from dataclasses import asdict

    from splattwin.hashing import code_digest

    return {"twin": str(Path(spec.twin_dir).resolve()),
            "twin_json_sha256": file_digest(Path(spec.twin_dir) / "twin.json"),
            "twin_meshes_sha256": twin_meshes_digest(spec.twin_dir),
            "code": code_digest(("splattwin.robot", "splattwin.twin")),
            "task": str(Path(spec.task_path).resolve()) if spec.task_path else None,
            "task_sha256": file_digest(spec.task_path),
            "robot_mjcf": str(Path(spec.robot_mjcf).resolve()) if spec.robot_mjcf else None,
            "robot_mjcf_sha256": file_digest(spec.robot_mjcf),
            "tcp_site": spec.tcp_site if spec.robot_mjcf else None,
            "base": asdict(spec.base), "planner": spec.planner, "in_hand": spec.in_hand, "seed": spec.seed, "sigma": spec.sigma,
            "sigma_yaw": default_sigma_yaw(spec.sigma) if spec.sigma_yaw is None else spec.sigma_yaw}


def rollout_path(trial_json: str | Path) -> Path:
    """Where a trial's rollout is kept beside its result: trials/<i>.json -> trials/<i>.rollout.npz."""
    p = Path(trial_json)
    return p.with_name(p.stem + ".rollout.npz")


MAX_TRIAL_BYTES = 64 << 20     # a stored trial result (its steps and timings) is kilobytes
MAX_TRIAL_PLANS = 100_000      # planning times listed in one trial result


def load_finished(path: Path, spec: TrialSpec, rollouts: bool = False) -> dict | None:
    """The stored result of a finished trial with the same key, else None (missing, stale or unreadable).
    rollouts: a trial that ran without keeping its rollout (or lost it) counts as not finished.
    A result with the right key but wrongly typed fields ("success": "no") is not counted: it is re-run,
    with a warning naming the file."""
    import json

    from splattwin.errors import InputError
    from splattwin.limits import read_json

    if not Path(path).is_file():
        return None
    try:
        d = read_json(path, max_bytes=MAX_TRIAL_BYTES)
    except InputError:
        return None
    if not (isinstance(d, dict) and d.get("key") == json.loads(json.dumps(trial_key(spec)))):
        return None
    problem = _result_problem(d)
    if problem:   # a library warning: through the logger, which a caller can filter or capture
        log.warning("%s: stored trial result ignored (%s); running the trial again", path, problem)
        return None
    # the result must name its rollout: a rollout file beside a result that does not is another run's
    if rollouts and "error" not in d and (d.get("rollout") != rollout_path(path).name
                                          or not rollout_path(path).is_file()):
        return None
    return d


def _result_problem(d: dict) -> str | None:
    """Why a stored trial result cannot be summarised (types the summary relies on), else None."""
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0

    if not isinstance(d.get("success"), bool):
        return f"'success' must be true or false, got {type(d.get('success')).__name__}"
    c = d.get("collisions", 0)
    if not (isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 10**9):
        return "'collisions' must be a whole number"
    plans = d.get("plan_ms", [])
    if not (isinstance(plans, list) and len(plans) <= MAX_TRIAL_PLANS and all(number(p) for p in plans)):
        return "'plan_ms' must be a list of numbers"
    if "trial_wall_s" in d and not number(d["trial_wall_s"]):
        return "'trial_wall_s' must be a number"
    if not isinstance(d.get("steps", []), list) or not isinstance(d.get("error", ""), str):
        return "'steps' must be a list and 'error' text"
    return None


def run_trial_job(spec: TrialSpec, path: str | None, keep_rollout: bool = False) -> dict:
    """One perturbed trial (a task for any executor): its result dict; written atomically to `path` with
    its key as soon as it finishes, so a killed run keeps it. keep_rollout: its `Rollout` is written
    first, to `rollout_path(path)` (the result names it under "rollout")."""
    t0 = time.perf_counter()
    r = None
    try:
        r, _, _ = run_once(spec, keep_trajectories=keep_rollout and path is not None, warn=False)
        d = r.to_dict()
    except Exception as e:  # a crashed trial is a failed trial, with the reason
        d = {"success": False, "collisions": 0, "plan_ms": [], "steps": [], "error": f"{type(e).__name__}: {e}"}
    d["seed"] = spec.seed
    d["trial_wall_s"] = time.perf_counter() - t0
    if path is not None:
        from splattwin import io

        if r is not None and r.rollout is not None and len(r.rollout):
            # the rollout first (atomic), the result that marks the trial finished last
            d["rollout"] = r.rollout.save(rollout_path(path)).name
        else:  # an earlier run's rollout of this trial is not this result's: gone before the result lands
            rollout_path(path).unlink(missing_ok=True)
        d["key"] = trial_key(spec)
        io.write_json(path, d)
    return d


def trial_jobs(base_spec: TrialSpec, n: int, sigma: float, out_dir: str | Path | None = None,
               sigma_yaw: float | None = None) -> tuple[list[TrialSpec], list[Path | None]]:
    """The specs (seeds base_spec.seed + 1 .. + n) and result paths (out_dir/trials/<i>.json) of n trials."""
    from dataclasses import replace

    # absolute paths: a worker may run in another working directory (or on another node of a cluster)
    absolute = {k: str(Path(v).resolve()) for k in ("twin_dir", "task_path", "robot_mjcf")
                if (v := getattr(base_spec, k)) is not None}
    base_spec = replace(base_spec, **absolute)
    specs = [replace(base_spec, sigma=sigma, sigma_yaw=sigma_yaw, seed=base_spec.seed + 1 + i) for i in range(n)]
    paths = [Path(out_dir) / "trials" / f"{i + 1}.json" if out_dir is not None else None for i in range(n)]
    return specs, paths


TIMING_KEYS = ("plan_ms", "wall_s", "trial_wall_s")


def trial_outcome(d):
    """A trial result (dict/list tree) without its wall-clock timings: everything physics and planning
    decided, which equal seeds reproduce bit for bit on any executor."""
    if isinstance(d, dict):
        return {k: trial_outcome(v) for k, v in d.items() if k not in TIMING_KEYS}
    if isinstance(d, list):
        return [trial_outcome(v) for v in d]
    return d


def summarize_trials(done: list[dict], n: int, sigma: float, sigma_yaw: float | None = None) -> dict:
    """Success rate with its Wilson 95 % interval, collisions and timings of finished trial results."""
    k = sum(1 for r in done if r["success"])
    lo, hi = wilson_interval(k, n)
    plan_ms = [p for r in done for p in r.get("plan_ms", [])]
    walls = [r["trial_wall_s"] for r in done if "trial_wall_s" in r]   # (a stored result may lack it)
    return {"trials": n, "successes": k, "success_rate": k / n if n else 0.0, "ci95": [lo, hi], "sigma": sigma,
            "sigma_yaw": default_sigma_yaw(sigma) if sigma_yaw is None else sigma_yaw,
            "sigma_definition": SIGMA_DEFINITION,
            "collisions": int(sum(r.get("collisions", 0) for r in done)),
            "plan_ms_median": float(np.median(plan_ms)) if plan_ms else None,
            "trial_wall_s_median": float(np.median(walls)) if walls else None}


def run_trials(base_spec: TrialSpec, n: int, sigma: float, workers: int | None = None, progress: bool = True,
               out_dir: str | Path | None = None, resume: bool = True, sigma_yaw: float | None = None,
               executor=None, keep_rollouts: bool = False) -> dict:
    """N perturbed trials (seeds base_spec.seed + 1 .. + n) in parallel; summary dict.

    sigma: m, per-axis (x and y) standard deviation of each object's position error; sigma_yaw: rad
    (default sigma / YAW_LEVER). out_dir: each finished trial is written atomically to
    out_dir/trials/<i>.json (i = 1..n) with its key (`trial_key`); with resume, a re-run with the same
    key skips the trials already there (a killed run continues where it stopped).
    executor: a `splattwin.executor.Executor` (e.g. Ray); default a local pool of `workers`
    processes (default: CPU count). keep_rollouts (needs out_dir): each trial also writes its `Rollout`
    to out_dir/trials/<i>.rollout.npz (atomically, before its result), e.g. for `plan --record`.
    """
    from splattwin.executor import Job, LocalExecutor

    specs, paths = trial_jobs(base_spec, n, sigma, out_dir, sigma_yaw)
    keep_rollouts = keep_rollouts and out_dir is not None
    results: list[dict | None] = [load_finished(p, sp, rollouts=keep_rollouts) if (p is not None and resume) else None
                                  for sp, p in zip(specs, paths)]
    todo = [i for i, r in enumerate(results) if r is None]
    ex = executor or LocalExecutor(max(1, min(len(todo) or 1, workers or (os.cpu_count() or 1))))
    t0 = time.perf_counter()
    if todo:
        def done(job, out) -> None:
            # a trial whose worker died max_retries + 1 times is a failed trial (not stored: a re-run tries again)
            results[job.key] = out.value if out.ok else {"success": False, "collisions": 0, "plan_ms": [], "steps": [],
                                                         "seed": specs[job.key].seed, "trial_wall_s": 0.0,
                                                         "error": f"worker: {out.error}"}
        try:
            ex.run([Job(i, run_trial_job, (specs[i], str(paths[i]) if paths[i] else None, keep_rollouts), name=f"trial-{i + 1}")
                    for i in todo], on_done=done, progress=progress,
                   description=f"trials (sigma {sigma * 1000:.1f} mm per axis)")
        finally:
            if executor is None:
                ex.close()
    done_results: list[dict] = [r for r in results if r is not None]
    return {**summarize_trials(done_results, n, sigma, sigma_yaw), "wall_s": time.perf_counter() - t0,
            "workers": ex.workers, "executor": ex.kind, "resumed": n - len(todo), "results": done_results}
