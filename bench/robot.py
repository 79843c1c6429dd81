"""Benchmark of the robot stage: the paper's three-step task validated in MuJoCo, N perturbed trials.

On the ground-truth twin of the embedded scene (seed 0) and, when `--recon-twin PATH` is given and exists
(e.g. demo_out after `splattwin demo --out demo_out`), on a reconstructed twin side by side. Each trial
perturbs every object's pose in the simulated world — x and y each ~ N(0, sigma) (sigma is the per-axis
standard deviation), yaw ~ N(0, sigma_yaw), default sigma_yaw = sigma / 0.1 m — while the robot plans
with the twin's poses. Prints a table; the LAST line is one JSON object with the keys successes, trials,
collisions, plan_ms_median, wall_s (GT twin), sigma, sigma_yaw, sigma_definition, plus per-twin details
(touch_corrections: trials in which a finger landed on an object and the grasp was corrected by touch).

wall_s: median wall time of one whole three-step validation (world build, grasp synthesis, planning,
timing, physics) inside a warm worker process. Targets: 20/20, 0 collisions, plan_ms_median <= 200,
wall_s <= 15 on 2 cores.

    python bench/robot.py [--scene DIR] [--recon-twin PATH] [--trials 20] [--sigma 0.005] [--sigma-yaw RAD]
                          [--workers 2]
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="embedded scene folder (default: generate seed 0)")
    ap.add_argument("--recon-twin", type=Path, default=None, help="a reconstructed twin of the same scene")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--sigma", type=float, default=0.005, help="per-axis (x, y) position error std, m")
    ap.add_argument("--sigma-yaw", type=float, default=None, help="yaw error std, rad (default sigma / 0.1 m)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--in-hand", choices=("sensed", "planned"), default="sensed",
                    help="held object's pose for the transfer: sensed in the hand, or as planned")
    args = ap.parse_args()

    from rich.console import Console
    from rich.table import Table

    from splattwin.robot.trials import TrialSpec, run_trials
    from splattwin.twin.groundtruth import twin_from_scene

    tmp = Path(tempfile.mkdtemp(prefix="bench_robot_"))
    scene = args.scene
    if scene is None:
        from splattwin.scene import SceneOptions, generate

        scene = generate(tmp / "scene", SceneOptions(seed=0, width=160, height=120, views=4, heldout=0), progress=False)
    twins = {"ground truth": twin_from_scene(scene, tmp / "gt_twin") and tmp / "gt_twin"}
    if args.recon_twin is not None and (args.recon_twin / "twin.json").is_file():
        twins["reconstructed"] = args.recon_twin
    rows = {}
    for name, twin in twins.items():
        t0 = time.perf_counter()
        s = run_trials(TrialSpec(str(twin), None, in_hand=args.in_hand), args.trials, args.sigma, workers=args.workers,
                       sigma_yaw=args.sigma_yaw)
        sigma_yaw, sigma_definition = s["sigma_yaw"], s["sigma_definition"]
        s["total_wall_s"] = time.perf_counter() - t0
        fails = [r.get("error") or next((st["failure"] for st in r["steps"] if not st["success"]), None)
                 for r in s["results"] if not r["success"]]
        rows[name] = {"successes": s["successes"], "trials": s["trials"], "collisions": s["collisions"],
                      "plan_ms_median": s["plan_ms_median"], "wall_s": s["trial_wall_s_median"],
                      "ci95": s["ci95"], "total_wall_s": s["total_wall_s"], "failures": fails[:5],
                      "touch_corrections": sum(1 for r in s["results"]
                                               if any(st["grasp"].get("touch_corrections") for st in r["steps"]))}
    t = Table(title=f"robot: three-step task, {args.trials} trials at sigma {args.sigma * 1000:.1f} mm per axis, "
                    f"yaw {math.degrees(sigma_yaw):.1f} deg, {args.workers} workers")
    for c in ("twin", "success", "95% CI", "collisions", "touch-corrected", "plan ms (median)",
              "validation s (median)", "total s"):
        t.add_column(c)
    for name, r in rows.items():
        t.add_row(name, f"{r['successes']}/{r['trials']}", f"{r['ci95'][0]:.2f}-{r['ci95'][1]:.2f}",
                  str(r["collisions"]), str(r["touch_corrections"]),
                  f"{r['plan_ms_median']:.0f}" if r["plan_ms_median"] else "-",
                  f"{r['wall_s']:.1f}", f"{r['total_wall_s']:.0f}")
    Console().print(t)
    for name, r in rows.items():
        for f in r["failures"]:
            print(f"  {name} failure: {f}")
    gt = rows["ground truth"]
    out = {k: gt[k] for k in ("successes", "trials", "collisions", "plan_ms_median", "wall_s")}
    out["sigma"] = args.sigma
    out["sigma_yaw"] = sigma_yaw
    out["sigma_definition"] = sigma_definition
    out["twins"] = {k: {kk: v for kk, v in r.items() if kk != "failures"} for k, r in rows.items()}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
