"""Benchmark of the cluster executors: robot trials on a local Ray instance vs the local process pool, and
a two-capture batch on Ray with a worker killed mid-build.

1. Trials: N trials (default 200) of the paper's three-step task on the demo twin at sigma 5 mm per axis,
   the same seeds on both executors, run alternately (local, ray, ray, local, ... : ABBA order, so a drift
   of the shared machine's speed hits both alike), each run in a fresh Python process; medians over the
   repeats. wall(ray) counts the whole
   command as a user runs it: `ray.init(num_cpus=W)` (start-up of the local Ray instance and its workers),
   the trials, `ray.shutdown()`; wall(local) the process pool's start, the trials and its shutdown.
   ray_overhead = median wall(ray) / median wall(local) - 1; ray_overhead_warm leaves Ray's start-up and
   shutdown out (a cluster that is already running). cpu_s: CPU seconds of every process of the run (the
   driver, pool workers / Ray's raylet, GCS and workers), which sharing the machine does not inflate;
   ray_cpu_overhead = median cpu_s(ray) / median cpu_s(local) - 1 is the overhead a busy machine cannot hide.
   The outcomes of every trial must be equal on both executors (timings aside).
2. Batch: two small embedded captures built on Ray (`run_batch`, 1 CPU per build); the reconstruction
   worker of the first capture is killed (SIGKILL) once its build has recorded a stage; Ray retries it.
   batch_lost_outputs = promised outputs (pipeline.json "@" files of every stage) missing or unreadable,
   plus captures not built.

The demo twin is built once (`splattwin demo --out DIR`, ~4-8 min) into --demo (default a scratch folder
outside the repository) and reused. Prints tables; the LAST line is one JSON object with trials,
trials_per_min_local, trials_per_min_ray, ray_overhead, ray_overhead_warm, ray_cpu_overhead, wall_local_s,
wall_ray_s, cpu_s_local, cpu_s_ray, outcomes_equal, batch_lost_outputs, batch_killed, batch_retried, batch_ok.

    python bench/scale.py [--demo DIR] [--trials 200] [--repeats 2] [--workers 2] [--skip-batch]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path



def tree_cpu_s() -> float:
    """CPU seconds (user + system) of this process and every live descendant, plus reaped children."""
    import psutil

    me = psutil.Process()
    total = sum(me.cpu_times()[:4])   # user, system, children_user, children_system
    for p in me.children(recursive=True):
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def ensure_demo(path: Path) -> Path:
    if (path / "twin.json").is_file():
        return path
    print(f"building the demo twin into {path} (once; reused by later runs)", file=sys.stderr)
    subprocess.run([sys.executable, "-m", "splattwin.cli", "demo", "--out", str(path)], check=True)
    return path


def run_trials_once(kind: str, twin: Path, n: int, sigma: float, workers: int) -> dict:
    """One run in a fresh Python process (as a user runs the command; no state carried between runs)."""
    r = subprocess.run([sys.executable, __file__, "--one", kind, "--demo", str(twin), "--trials", str(n),
                        "--sigma", str(sigma), "--workers", str(workers)], check=True, stdout=subprocess.PIPE, text=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _one(kind: str, twin: Path, n: int, sigma: float, workers: int) -> dict:
    from splattwin.executor import LocalExecutor, RayExecutor
    from splattwin.robot.trials import TrialSpec, run_trials

    cpu0 = tree_cpu_s()
    out = Path(tempfile.mkdtemp(prefix=f"scale_{kind}_"))
    t0 = time.perf_counter()
    ex = LocalExecutor(workers) if kind == "local" else RayExecutor(num_cpus=workers)
    t1 = time.perf_counter()
    s = run_trials(TrialSpec(str(twin), None), n, sigma, out_dir=out, executor=ex, progress=False)
    t2 = time.perf_counter()
    cpu = tree_cpu_s() - cpu0      # before the workers exit (their CPU time is lost with them)
    ex.close()
    t3 = time.perf_counter()
    return {"kind": kind, "wall_s": t3 - t0, "warm_s": t2 - t1, "cpu_s": cpu, "successes": s["successes"],
            "results": s["results"]}


def worker_pids(prefix: str) -> list[int]:
    import psutil

    pids = []
    for p in psutil.Process().children(recursive=True):
        try:
            if p.name().startswith(f"ray::{prefix}"):
                pids.append(p.pid)
        except psutil.Error:
            pass
    return pids


def batch_with_kill(tmp: Path) -> dict:
    import ray

    from splattwin.cluster.batch import lost_outputs, run_batch
    from splattwin.executor import RayExecutor
    from splattwin.pipeline.build import BuildOptions
    from splattwin.scene import SceneOptions, generate

    caps = [generate(tmp / f"capture{s}", SceneOptions(seed=s, width=160, height=120, views=8, heldout=3),
                     progress=False) for s in (0, 1)]
    out = tmp / "batch"
    killed: list[int] = []

    def killer() -> None:
        t0 = time.time()
        while time.time() - t0 < 900 and not killed:
            pids = worker_pids("batch-recon-capture0") if (out / "capture0" / "pipeline.json").is_file() else []
            if pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
            time.sleep(0.2)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    opts = BuildOptions.from_dict({"poses": {"method": "known"},
                                   "splat": {"iters": 300, "max_gaussians": 15000, "checkpoint_every": 50}})
    t0 = time.perf_counter()
    with RayExecutor(num_cpus=2, max_retries=3) as ex:
        s = run_batch(caps, out, opts, ex, cpus=1, progress=False)
    wall = time.perf_counter() - t0
    th.join(timeout=1)
    assert not ray.is_initialized()
    lost = {c["name"]: lost_outputs(out / c["name"]) for c in s["captures"]}
    not_built = [c["name"] for c in s["captures"] if c["status"] != "ok"]
    return {"killed_pid": killed[0] if killed else None, "ok": s["ok"], "wall_s": wall, "lost": lost,
            "not_built": not_built, "lost_outputs": sum(len(v) for v in lost.values()) + len(not_built),
            "retried": bool(killed) and killed[0] not in s["captures"][0].get("pids", [])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demo", type=Path, default=Path(tempfile.gettempdir()) / "splattwin_bench_demo",
                    help="demo twin folder (built once when missing)")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--sigma", type=float, default=0.005)
    ap.add_argument("--repeats", type=int, default=2, help="runs per executor (ABBA order)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--skip-batch", action="store_true")
    ap.add_argument("--one", choices=("local", "ray"), default=None, help=argparse.SUPPRESS)  # one run (internal)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(_one(args.one, args.demo, args.trials, args.sigma, args.workers)))
        return 0

    from rich.console import Console
    from rich.table import Table

    con = Console(stderr=True)
    twin = ensure_demo(args.demo)
    order = [("local", "ray") if i % 2 == 0 else ("ray", "local") for i in range(args.repeats)]
    runs: list[dict] = []
    for pair in order:
        for kind in pair:
            r = run_trials_once(kind, twin, args.trials, args.sigma, args.workers)
            con.print(f"{kind}: {r['wall_s']:.1f} s wall ({r['warm_s']:.1f} s without start/stop), "
                      f"{r['cpu_s']:.0f} CPU s, {r['successes']}/{args.trials}")
            runs.append(r)
    from splattwin.robot.trials import trial_outcome as outcome

    by = {k: [r for r in runs if r["kind"] == k] for k in ("local", "ray")}
    ref = outcome(by["local"][0]["results"])
    equal = all(outcome(r["results"]) == ref for r in runs)
    med = {k: {m: statistics.median(r[m] for r in v) for m in ("wall_s", "warm_s", "cpu_s")} for k, v in by.items()}
    tpm = {k: args.trials / (med[k]["wall_s"] / 60) for k in med}

    t = Table(title=f"{args.trials} trials of the three-step task (demo twin, sigma {args.sigma * 1000:.0f} mm), "
                    f"{args.workers} workers, median of {args.repeats} (ABBA); machine shared with other developers")
    for c in ("executor", "wall s (runs)", "wall s median", "warm s median", "CPU s median", "trials/min", "successes"):
        t.add_column(c)
    for k in ("local", "ray"):
        t.add_row(k, ", ".join(f"{r['wall_s']:.0f}" for r in by[k]), f"{med[k]['wall_s']:.1f}", f"{med[k]['warm_s']:.1f}",
                  f"{med[k]['cpu_s']:.0f}", f"{tpm[k]:.1f}", ", ".join(str(r["successes"]) for r in by[k]))
    Console().print(t)
    res = {"trials": args.trials, "workers": args.workers, "repeats": args.repeats,
           "trials_per_min_local": round(tpm["local"], 2), "trials_per_min_ray": round(tpm["ray"], 2),
           "ray_overhead": round(med["ray"]["wall_s"] / med["local"]["wall_s"] - 1, 4),
           "ray_overhead_warm": round(med["ray"]["warm_s"] / med["local"]["warm_s"] - 1, 4),
           "wall_local_s": round(med["local"]["wall_s"], 1), "wall_ray_s": round(med["ray"]["wall_s"], 1),
           "cpu_s_local": round(med["local"]["cpu_s"], 1), "cpu_s_ray": round(med["ray"]["cpu_s"], 1),
           "ray_cpu_overhead": round(med["ray"]["cpu_s"] / med["local"]["cpu_s"] - 1, 4),
           "outcomes_equal": equal, "successes": by["local"][0]["successes"]}
    if not args.skip_batch:
        b = batch_with_kill(Path(tempfile.mkdtemp(prefix="scale_batch_")))
        bt = Table(title="two-capture batch on Ray, reconstruction worker of capture0 killed (SIGKILL) mid-build")
        for c in ("killed pid", "retried", "captures built", "lost outputs", "wall s"):
            bt.add_column(c)
        bt.add_row(str(b["killed_pid"]), str(b["retried"]), f"{b['ok']}/2", str(b["lost_outputs"]), f"{b['wall_s']:.0f}")
        Console().print(bt)
        for name, lost in b["lost"].items():
            for line in lost:
                con.print(f"[red]{name}: {line}[/]")
        res.update(batch_lost_outputs=b["lost_outputs"], batch_killed=b["killed_pid"] is not None,
                   batch_retried=b["retried"], batch_ok=b["ok"], batch_wall_s=round(b["wall_s"], 1))
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
