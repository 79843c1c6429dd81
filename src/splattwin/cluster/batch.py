"""Many captures, one twin each: `build` per capture on an executor, one summary of every capture.

    OUT/<name>/            the twin folder of each capture (name: the capture's folder or file name)
    OUT/batch.json         per capture: status, failed stage and error, figures, timings
    OUT/summary.csv        one row per capture
    OUT/summary.html       the same table with each capture's held-out render and a link to its report
    OUT/logs/<name>.log    everything the capture's build printed

Each capture is two tasks: its reconstruction (pipeline stages up to `splats`; one GPU when the cluster
has GPUs, so training lands on GPU nodes) and then the rest of its build (semantics, geometry, export,
robot, report; CPUs only). Both call `splattwin.pipeline.build.build` on the capture's twin folder, whose
stage hashing skips what is finished: a retried task (its worker was killed) or a re-run of the whole
batch continues where it stopped. A capture that fails (bad input, a stage error, a worker that died on
every retry) is reported with the stage and the error; the other captures go on.
"""

from __future__ import annotations

import contextlib
import csv
import io as _io
import logging
import os
import re
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from splattwin import io
from splattwin.errors import InputError
from splattwin.executor import Executor, ExecutorOptions, Job, Outcome, Resources, limit_threads

log = logging.getLogger(__name__)

RECON_UNTIL = "splats"     # the GPU part of a build: capture, poses, training


@dataclass
class Capture:
    name: str        # twin folder name under OUT
    input: str       # the capture (any layout `splattwin build` reads)


def capture_names(inputs: list[str | Path]) -> list[Capture]:
    """One unique, filesystem-safe folder name per capture (its folder or file name; -2, -3 on clashes)."""
    seen: set[str] = set()
    out = []
    for p in inputs:
        p = Path(p)
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", (p.stem if p.is_file() else p.name) or "capture").strip("._") or "capture"
        name, k = base, 2
        # never one of the batch's own entries: a capture folder named "logs" built its twin into OUT/logs/,
        # among the other captures' build logs
        while name.lower() in seen or name.lower() in ("batch.json", "summary.csv", "summary.html", "logs"):
            name, k = f"{base}-{k}", k + 1
        seen.add(name.lower())
        out.append(Capture(name, str(p.absolute())))
    return out


def _check_apart(caps: list[Capture], out: Path) -> None:
    """InputError when a capture's twin folder OUT/<name> would be the capture itself, or either would hold the
    other: `batch scans/*/ --out scans/` built every twin into its own capture folder, among the photos (and a
    rebuild then reads that capture with the twin's files in it)."""
    from splattwin.paths import is_inside

    for c in caps:
        twin, src = out / c.name, Path(c.input)
        if is_inside(twin, src) or is_inside(src, twin):
            raise InputError(f"the twin of capture {c.name!r} would be built into {twin}, "
                             f"{'the capture itself' if twin.resolve() == src.resolve() else 'nested with it'}: "
                             "give an --out folder apart from the captures", src)


class StageFailed(Exception):
    """A capture's build failed: which stage, and why (picklable: plain text)."""

    def __init__(self, message: str):
        super().__init__(message)


def _failed_stage(exc: BaseException) -> str | None:
    """The pipeline stage whose function raised `exc` (from the traceback), or None."""
    from splattwin.pipeline.build import stages

    # a stage's own function, or the one that lists its input files (hashed before the stage runs)
    fns = {f.__name__: s.name for s in stages() for f in (s.run, s.inputs) if f is not None}
    fns["preflight"] = "preflight"   # the checks that run before any stage (pipeline.build.preflight)
    stage = None
    for fr in traceback.extract_tb(exc.__traceback__):
        if fr.name in fns:
            stage = fns[fr.name]
    return stage


@contextlib.contextmanager
def _output_to(path: Path):
    """Send this process's stdout and stderr (Python and C level: numba, OpenGL) to `path` (appended) while
    a build runs, so the builds' stage lines and warnings go to one log per capture, not the terminal."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "ab") as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


@contextlib.contextmanager
def _stage_lines_to_stderr():
    """The build's stage lines ("▶ splat"), which `build(progress=False)` logs rather than prints, written to
    stderr (the capture's log) while a build task runs, as the command prints them."""
    lg = logging.getLogger("splattwin.pipeline.build.stages")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    saved = lg.level, lg.propagate
    lg.addHandler(handler)
    # once, as printed before: not again through a root handler a forked worker inherited from the command
    lg.setLevel(logging.INFO)
    lg.propagate = False
    try:
        yield
    finally:
        lg.removeHandler(handler)
        lg.setLevel(saved[0])
        lg.propagate = saved[1]


def in_ray_worker() -> bool:
    """True inside a Ray worker process."""
    if "ray" not in sys.modules:
        return False
    try:
        import ray

        return ray.is_initialized() and ray.get_runtime_context().worker.mode == ray.WORKER_MODE
    except Exception:  # noqa: BLE001 - any doubt: not a Ray worker
        return False


def build_task(twin: str, options, until: str | None, threads: int, log_path: str | None = None) -> dict:
    """One part of one capture's build (a task): `pipeline.build.build(twin, options)` with `options` a
    `BuildOptions`. Returns the stage results; raises StageFailed naming the stage and the error.
    log_path: the build's output goes there."""
    from splattwin.pipeline.build import build

    limit_threads(threads)
    if in_ray_worker():
        # the build's own process pools (the robot stage's trials) must not fork a Ray worker: its gRPC
        # threads do not survive fork(); fresh interpreters instead
        import multiprocessing

        multiprocessing.set_start_method("spawn", force=True)
    t0 = time.perf_counter()
    with _output_to(Path(log_path)) if log_path else contextlib.nullcontext(), _stage_lines_to_stderr():
        try:
            print(f"== {time.strftime('%Y-%m-%d %H:%M:%S')} build until {until or 'the end'} (pid {os.getpid()})",
                  flush=True)
            ctx = build(twin, options, until=until, progress=False)
        except Exception as e:
            traceback.print_exc()
            stage = _failed_stage(e)
            kind = "bad input" if isinstance(e, InputError) else type(e).__name__
            raise StageFailed(f"{stage or 'setup'}: {kind}: {e}") from None
    return {"stages": list(ctx.results), "timings": dict(ctx.timings), "wall_s": time.perf_counter() - t0,
            "pid": os.getpid()}


def figures(twin: Path) -> dict[str, Any]:
    """Headline figures of a built twin folder, read from its files (what the report shows)."""
    def js(rel: str):
        try:
            return io.read_json(twin / rel) if (twin / rel).is_file() else None
        except (OSError, ValueError, InputError):   # unreadable: the figure is left out
            return None

    f: dict[str, Any] = {}
    poses = js("poses/poses_report.json") or {}
    stats = poses.get("stats", poses)
    if isinstance(stats, dict) and stats.get("registered") is not None:
        f["views"] = f"{stats.get('registered')}/{stats.get('total')}"
    ev = js("splat/eval/metrics.json")
    if ev:
        f.update(psnr=ev.get("mean_psnr"), ssim=ev.get("mean_ssim"), eval_split=ev.get("split"))
    state = js("pipeline.json") or {}
    sp = (state.get("splats") or {}).get("outputs") or {}
    if sp.get("gaussians") is not None:
        f["gaussians"] = sp["gaussians"]
    if f.get("views") is None and (state.get("poses") or {}).get("outputs", {}).get("registered") is not None:
        po = state["poses"]["outputs"]
        f["views"] = f"{po['registered']}/{po['total']}"
    fu = js("semantics/fusion.json")
    if fu:
        f.update(miou_heldout=fu.get("miou_heldout"), consistency=fu.get("consistency"))
    man = js("twin.json")
    if man:
        objs = man.get("objects", [])
        f["objects_usable"] = f"{sum(1 for o in objs if o.get('usable', True))}/{len(objs)}"
    geo = js("geometry_metrics.json")
    if geo:
        f["f1_min"] = min(v["f1"] for v in geo.values())
    rob = js("robot/results.json")
    if rob:
        f["task_error"] = rob.get("error")
        f["task"] = "error" if "error" in rob else ("success" if rob.get("nominal", {}).get("success") else "failure")
        if rob.get("trials"):
            f["trials"] = f"{rob['trials']['successes']}/{rob['trials']['trials']}"
    if state:
        f["build_s"] = sum(float(v.get("seconds", 0.0)) for v in state.values() if isinstance(v, dict))
    if (twin / "report" / "index.html").is_file():
        f["report"] = "report/index.html"
    return f


def run_batch(inputs: list[str | Path], out: str | Path, options, executor: Executor, cpus: float = 2.0,
              gpus: float | None = None, progress: bool = True, until: str | None = None) -> dict:
    """Build every capture into OUT/<name>/ on `executor`; write the summaries; the summary dict.

    options: a `BuildOptions` for every capture (its `input` is set per capture; the robot stage's trials
    run on a local pool of the task's CPUs: the task is the unit a cluster schedules). cpus: CPUs each
    build task reserves (and the threads it uses); gpus: GPUs of the reconstruction task (default: 1 when
    the cluster has GPUs). until: stop every build after this stage."""
    from splattwin.options import merge
    from splattwin.pipeline.build import STAGES

    out = Path(out).absolute()     # workers may run in another directory (or on another node)
    if not inputs:
        raise InputError("no captures given")
    if until is not None and until not in STAGES:
        raise InputError(f"--until: unknown stage {until!r} (stages: {', '.join(STAGES)})")
    recon_only = until is not None and STAGES.index(until) <= STAGES.index(RECON_UNTIL)
    recon_until = until if recon_only else RECON_UNTIL
    caps = capture_names(inputs)
    _check_apart(caps, out)
    out.mkdir(parents=True, exist_ok=True)
    if gpus is None:
        gpus = 1.0 if getattr(executor, "gpus", lambda: 0.0)() > 0 else 0.0
    threads = max(1, int(cpus)) if executor.kind == "ray" else max(1, (os.cpu_count() or 1) // executor.workers)
    base = merge(options, {"robot": {"cluster": ExecutorOptions(executor="local", workers=threads)}})
    state: dict[str, dict] = {c.name: {"name": c.name, "input": c.input, "twin": str(out / c.name), "status": "pending",
                                       "log": str(out / "logs" / f"{c.name}.log")} for c in caps}
    t0 = time.perf_counter()

    def opts(c: Capture):
        return merge(base, {"input": c.input, "scene": None})

    def save() -> None:
        write_summary(out, {"captures": list(state.values()), "executor": executor.describe(),
                            "wall_s": time.perf_counter() - t0})

    def on_done(job: Job, o: Outcome):
        name, part = job.key
        st = state[name]
        if not o.ok:
            err = o.error or "unknown error"
            if err.startswith("StageFailed: "):          # the build raised: "stage: kind: message"
                stage, _, err = err[len("StageFailed: "):].partition(": ")
            else:                                        # its worker died on every retry
                stage = "reconstruction" if part == "recon" else "build"
            st.update(status="failed", failed_stage=stage, error=err, attempts=o.attempts)
            st.update(figures(out / name))
            save()
            return []
        st.setdefault("timings", {}).update(o.value["timings"])
        st.setdefault("pids", []).append(o.value["pid"])
        if part == "recon" and not recon_only:
            st["status"] = "reconstructed"
            save()
            return [Job((name, "finish"), build_task, (str(out / name), opts(caps_by[name]), until, threads,
                                                       state[name]["log"]),
                        Resources(cpus), name=f"batch-finish-{name}")]
        st.update(status="ok", error=None, failed_stage=None)
        st.update(figures(out / name))
        if st.get("task_error"):   # built, but the robot task could not run on it (`build` exits 2)
            st.update(status="failed", failed_stage="robot", error=st["task_error"])
        save()
        return []

    caps_by = {c.name: c for c in caps}
    jobs = [Job((c.name, "recon"), build_task, (str(out / c.name), opts(c), recon_until, threads, state[c.name]["log"]),
                Resources(cpus, gpus), name=f"batch-recon-{c.name}") for c in caps]
    save()
    executor.run(jobs, on_done=on_done, progress=progress, description="captures (recon + build)",
                 total=(1 if recon_only else 2) * len(caps))
    summary = {"captures": list(state.values()), "executor": executor.describe(), "wall_s": time.perf_counter() - t0,
               "ok": sum(1 for s in state.values() if s["status"] == "ok"), "failed": sum(1 for s in state.values() if s["status"] != "ok")}
    summary["outputs"] = {k: str(v) for k, v in write_summary(out, summary).items()}
    return summary


def lost_outputs(twin: Path) -> list[str]:
    """The outputs a twin folder's pipeline.json promises that are missing or unreadable (empty: complete).

    Every "@path" output of every recorded stage must exist; JSON, NumPy and PLY files must also load."""
    import numpy as np

    from splattwin.limits import MAX_RECORD_BYTES

    twin = Path(twin)
    try:
        state = io.read_json(twin / "pipeline.json", max_bytes=MAX_RECORD_BYTES)
        if not isinstance(state, dict) or not all(isinstance(r, dict) for r in state.values()):
            raise ValueError("not a mapping of stage records")
    except (OSError, ValueError, InputError) as e:
        return [f"pipeline.json: {e}"]
    lost = []
    for stage, rec in state.items():
        for name, v in (rec.get("outputs") or {}).items():
            if not (isinstance(v, str) and v.startswith("@")):
                continue
            path = twin / v[1:]
            try:
                if not path.is_file():
                    raise FileNotFoundError("missing")
                if path.suffix == ".json":
                    io.read_json(path, max_bytes=MAX_RECORD_BYTES)
                elif path.suffix == ".npy":
                    np.load(path, allow_pickle=False)
                elif path.suffix == ".ply":
                    from splattwin.splat.gaussians import Gaussians

                    Gaussians.load_ply(path)
            except Exception as e:  # noqa: BLE001 - any failure to read it counts as lost
                lost.append(f"{stage}.{name} {v[1:]}: {type(e).__name__}: {e}")
    return lost


# -- outputs --------------------------------------------------------------------------------------------
COLUMNS = ("name", "status", "failed_stage", "error", "views", "psnr", "ssim", "eval_split", "gaussians", "miou_heldout",
           "objects_usable", "f1_min", "task", "trials", "build_s", "input", "twin")


def write_summary(out: Path, summary: dict) -> dict[str, Path]:
    """OUT/batch.json, OUT/summary.csv and OUT/summary.html (atomically)."""
    buf = _io.StringIO()
    w = csv.writer(buf)
    w.writerow(COLUMNS)
    for c in summary["captures"]:
        w.writerow(["" if c.get(k) is None else (f"{c[k]:.4f}" if isinstance(c.get(k), float) else c.get(k)) for k in COLUMNS])
    return {"json": io.write_json(out / "batch.json", summary), "csv": io.write_text(out / "summary.csv", buf.getvalue()),
            "html": io.write_text(out / "summary.html", summary_html(out, summary))}


def summary_html(out: Path, summary: dict) -> str:
    import html

    import numpy as np

    from splattwin.report.html import Report

    caps = summary["captures"]
    n_ok = sum(1 for c in caps if c["status"] == "ok")
    rep = Report("splattwin batch", f"{len(caps)} captures: {n_ok} built, {len(caps) - n_ok} failed or pending · "
                                   f"{summary.get('executor', '')} · {summary.get('wall_s', 0):.0f} s")
    sec = rep.section("Captures")
    cols = [c for c in COLUMNS if c not in ("input", "twin", "error")]
    sec.table(cols, [[c.get(k) if c.get(k) is not None else "" for k in cols] for c in caps])
    for c in caps:
        s = rep.section(f"{c['name']} — {c['status']}")
        s.text(f"capture: {c['input']}")
        if c.get("error"):
            s.pre(f"failed in {c.get('failed_stage') or '?'}: {c['error']}\n(log: {c.get('log')})")
        twin = out / c["name"]
        # a finished build's picture only: a capture still building is writing its eval/ (hidden temp files)
        built = c["status"] == "ok" or c.get("failed_stage") == "robot"
        ev_dir = twin / "splat" / "eval"
        ev = sorted(p for p in ev_dir.glob("*.png") if not p.name.startswith(".")) if built and ev_dir.is_dir() else []
        if ev:
            from PIL import Image, UnidentifiedImageError

            try:
                with Image.open(ev[0]) as im:
                    im = im.convert("RGB")
                    im.thumbnail((480, 240))
                    s.image(np.asarray(im), caption=f"held-out view {ev[0].stem}: ground truth | render | error",
                            photo=True)
            except (OSError, UnidentifiedImageError):   # replaced or removed meanwhile: the summary goes on
                s.text(f"(held-out picture {ev[0].name} could not be read)")
        if c.get("report"):
            href = html.escape(f"{c['name']}/{c['report']}", quote=True)
            s.parts.append(f'<p><a href="{href}">report of {html.escape(c["name"])}</a></p>')
    return rep.to_html()


def print_summary(summary: dict) -> None:
    from splattwin.console import console
    from rich.table import Table

    cols = ("name", "status", "views", "psnr", "ssim", "miou_heldout", "objects_usable", "f1_min", "task", "build_s")
    t = Table(title=f"batch: {summary['ok']} built, {summary['failed']} failed ({summary['executor']}, {summary['wall_s']:.0f} s)")
    for c in cols:
        t.add_column(c, overflow="fold")
    for c in summary["captures"]:
        t.add_row(*["" if c.get(k) is None else (f"{c[k]:.4g}" if isinstance(c[k], float) else str(c[k])) for k in cols])
    con = console()
    con.print(t)
    for c in summary["captures"]:
        if c.get("error"):
            e = c["error"] if len(c["error"]) < 240 else c["error"][:237] + "..."
            con.print(f"[red]{c['name']}[/] failed in {c.get('failed_stage')}: {e}  (log: {c.get('log')})")
    con.print("  ".join(f"{k}: {v}" for k, v in summary.get("outputs", {}).items()))
