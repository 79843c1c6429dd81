"""Validation runs of a task: one nominal run with outputs, and N perturbed trials in parallel processes.

A trial builds the physical world with every object's pose perturbed — sigma is the RMS planar
position error (x, y ~ N(0, sigma / sqrt 2) each) and a point 10 cm from the object centre moves by sigma
RMS through the yaw error (yaw ~ N(0, sigma / 0.1) rad) — while the robot still plans with the twin's
nominal poses: the trial measures how much reconstruction error the plan-then-execute loop tolerates.
The success rate comes with a Wilson score 95 % interval (good at small N and rates near 0 or 1).
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.robot.world import BasePose

YAW_LEVER = 0.10   # m: the yaw perturbation moves a point this far from the centre by sigma RMS


def wilson_interval(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval for k successes out of n (95 % for the default z)."""
    if n <= 0:
        return (0.0, 1.0)
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def perturb_poses(poses: dict[str, np.ndarray], sigma: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Object poses T_world_obj [4,4] with planar noise: RMS xy error sigma (per axis sigma/sqrt 2, m),
    yaw ~ N(0, sigma / YAW_LEVER) rad."""
    out = {}
    for name, T in poses.items():
        T = np.asarray(T, float).copy()
        dx, dy = rng.normal(0.0, sigma / math.sqrt(2.0), 2)
        a = rng.normal(0.0, sigma / YAW_LEVER)
        c, s = math.cos(a), math.sin(a)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        T[:3, :3] = Rz @ T[:3, :3]
        T[:2, 3] += [dx, dy]
        out[name] = T
    return out


@dataclass
class TrialSpec:
    twin_dir: str
    task_path: str | None
    base: BasePose = field(default_factory=BasePose)
    robot_mjcf: str | None = None
    sigma: float = 0.0
    seed: int = 0
    planner: str = "RRTConnect"


def run_once(spec: TrialSpec, frame_dir: str | Path | None = None, keep_trajectories: bool = False):
    """Build the world (perturbed when sigma > 0), validate the task, execute it. Returns RunResult
    (+ the recorder's note when frames were asked for)."""
    from splattwin.robot.assets import RobotModel
    from splattwin.robot.execute import Executor
    from splattwin.robot.task import load_task, validate_task
    from splattwin.robot.world import build_world
    from splattwin.twin.manifest import Manifest

    manifest = Manifest.load(spec.twin_dir)
    task = load_task(spec.task_path, manifest)
    validate_task(task, manifest, spec.twin_dir, spec.base.matrix())
    robot = RobotModel.from_mjcf(spec.robot_mjcf) if spec.robot_mjcf else RobotModel.panda()
    nominal = {o.name: o.pose for o in manifest.objects if o.usable}
    poses = perturb_poses(nominal, spec.sigma, np.random.default_rng(spec.seed)) if spec.sigma > 0 else None
    world = build_world(spec.twin_dir, manifest, robot, spec.base, poses=poses, visual=frame_dir is not None)
    rec = None
    if frame_dir is not None:
        from splattwin.robot.render import FrameRecorder

        rec = FrameRecorder(frame_dir, world.model)
    ex = Executor(world, belief=nominal, seed=spec.seed, planner=spec.planner, frame_cb=rec if rec and rec.available else None)
    try:
        result = ex.run(task)
        if rec is not None:
            rec.contact_sheet()
    finally:
        if rec is not None:
            rec.close()
    if not keep_trajectories:
        result.trajectories = []
    return result, (rec.note if rec is not None else ""), (rec.paths if rec is not None else [])


def _trial_worker(spec: TrialSpec) -> dict:
    t0 = time.perf_counter()
    try:
        r, _, _ = run_once(spec)
        d = r.to_dict()
    except Exception as e:  # a crashed trial is a failed trial, with the reason
        d = {"success": False, "collisions": 0, "plan_ms": [], "steps": [], "error": f"{type(e).__name__}: {e}"}
    d["seed"] = spec.seed
    d["trial_wall_s"] = time.perf_counter() - t0
    return d


def run_trials(base_spec: TrialSpec, n: int, sigma: float, workers: int | None = None, progress: bool = True) -> dict:
    """N perturbed trials (seeds base_spec.seed + 1 .. + n) in a process pool; summary dict."""
    from dataclasses import replace

    specs = [replace(base_spec, sigma=sigma, seed=base_spec.seed + 1 + i) for i in range(n)]
    workers = max(1, min(n, workers or (os.cpu_count() or 1)))
    t0 = time.perf_counter()
    results: list[dict] = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        it = pool.map(_trial_worker, specs)
        if progress:
            from rich.progress import track

            it = track(it, total=n, description=f"trials (sigma {sigma * 1000:.1f} mm)")
        for r in it:
            results.append(r)
    k = sum(1 for r in results if r["success"])
    lo, hi = wilson_interval(k, n)
    plan_ms = [p for r in results for p in r.get("plan_ms", [])]
    return {"trials": n, "successes": k, "success_rate": k / n if n else 0.0, "ci95": [lo, hi], "sigma": sigma,
            "collisions": int(sum(r.get("collisions", 0) for r in results)),
            "plan_ms_median": float(np.median(plan_ms)) if plan_ms else None,
            "trial_wall_s_median": float(np.median([r["trial_wall_s"] for r in results])) if results else None,
            "wall_s": time.perf_counter() - t0, "workers": workers, "results": results}
