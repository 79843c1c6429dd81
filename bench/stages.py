"""Benchmark: where a real-photo build spends its time, the rasterizer apart.

    python bench/stages.py                          # both sections, cake, 300 steps, half resolution
    python bench/stages.py --sections profile --iters 1000 --keep /tmp/cake_twin

Sections (each returns table rows and JSON keys):
- profile: one `splattwin build` of the real cake (SfM, colour-threshold masks from bench/real.py's
  `cake_masks`, so fusion, geometry, exports and the report run too) under cProfile in a child process
  (numba kernels compiled and cached by a warm-up first). Rows: each stage's seconds (pipeline.json), and
  the whole process's time split by where the CPU was (cProfile's own time per function, so the parts sum
  to the total): the rasterizer's numba kernels, the fused SSIM kernels, waiting on the COLMAP worker
  process (SfM runs there), imports, image encoding/decoding, torch operators, numba compilation, the rest
  (Python). Then the training steps alone: kernels vs everything else per step. cProfile slows
  Python-heavy code (imports, the loop's glue) more than the kernels: the non-kernel shares are upper bounds.
- steps: the training steps alone, without a profiler: --steps steps of `Trainer.train_step` on the cake
  twin's poses (half resolution, the build's options), every numba kernel call (rasterizer, SSIM) timed by
  a wrapper (a perf_counter pair, ~1 us); ms per step in the kernels and in the rest (torch operators,
  autograd, Adam, densification, Python), Adam's six optimizers and the densification hooks timed alike,
  medians over three blocks of steps (the run's schedule: --steps steps in all).
Keys: profile_* (seconds and shares), steps_*.
The machine may be shared: the load average is printed at the start and end. Last line: one JSON object.
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()  # before torch/numba load (the steps section trains here), as the CLI

import argparse  # noqa: E402
import json
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]   # bench/ is on sys.path as the script's folder (real.py)


_TEMP: list[Path] = []   # temporary folders of this run, removed when it ends


def _tempdir(prefix: str) -> Path:
    d = Path(tempfile.mkdtemp(prefix=prefix))
    _TEMP.append(d)
    return d


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=str(ROOT / "src"))


def _build(out: Path, masks: Path, iters: int, prof: Path | None) -> float:
    from real import DATA

    cmd = [sys.executable] + (["-m", "cProfile", "-o", str(prof)] if prof else []) + [
        "-m", "splattwin.cli", "build", str(DATA / "cake" / "images"), "--masks", str(masks), "--out", str(out),
        "--iters", str(iters), "--resolution", "2", "--no-progress", "--seed", "0"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=_env(), capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"cake build failed (exit {r.returncode}): {r.stderr.strip()[-400:]}")
    return time.perf_counter() - t0


def _name(k) -> str:
    return f"{k[0]}:{k[1]}({k[2]})"


def categories(stats: pstats.Stats) -> dict[str, float]:
    """Own time (s) of a profile's functions by category; the categories sum to the total."""
    out: dict[str, float] = {}
    for k, v in stats.stats.items():
        f, fn, own = k[0], k[2], v[2]
        if "splat/_cpu/kernels.py" in f:
            cat = "rasterizer kernels (numba)"
        elif f.endswith("splat/losses.py") and fn in ("fwd", "bwd"):
            cat = "SSIM kernels (numba)"
        elif "acquire' of '_thread.lock" in fn or "method 'acquire'" in fn:
            cat = "waiting on the COLMAP worker (SfM)"
        elif "/numba/" in f or "/llvmlite/" in f:
            cat = "numba compilation / dispatch"
        elif ("importlib" in f or "<frozen" in f or fn == "<module>" or "marshal.loads" in fn
              or "_imp." in fn or fn == "<built-in method builtins.compile>"):
            cat = "imports"
        elif "ImagingEncoder" in fn or "ImagingDecoder" in fn or "zlib" in fn:
            cat = "image encoding / decoding (PIL)"
        elif "torch" in fn or "torch._C" in fn or "run_backward" in fn or "/torch/" in f:
            cat = "torch operators and autograd"
        else:
            cat = "rest (Python, NumPy, SciPy, Open3D, ...)"
        out[cat] = out.get(cat, 0.0) + own
    return out


LIBRARIES = ("torch", "torch/_dynamo", "numba", "scipy/stats", "sklearn", "trimesh", "open3d", "matplotlib",
             "mujoco", "pycolmap", "skimage", "cv2", "transformers")


def library_imports(stats: pstats.Stats) -> dict[str, float]:
    """Cumulative seconds of importing each heavy library (its package __init__'s module code, what it
    imports included; torch/_dynamo is imported by torch.optim on first use, apart from torch's own import)."""
    out = {}
    for k, v in stats.stats.items():
        if k[2] == "<module>" and "site-packages/" in k[0]:
            rel = k[0].split("site-packages/")[-1]
            for lib in LIBRARIES:
                if rel == f"{lib}/__init__.py":
                    out[lib.replace("/", ".")] = v[3]
    return out


def step_split(stats: pstats.Stats) -> dict | None:
    """Training steps: total, kernels (rasterizer + SSIM) and the rest, seconds; None without a training loop."""
    steps = [v for k, v in stats.stats.items() if k[0].endswith("splat/trainer.py") and k[2] == "train_step"]
    if not steps:
        return None
    n, total = steps[0][0], steps[0][3]
    # kernels called from train_step's subtree: each kernel's own time, scaled to the share of its calls made
    # by training (renders for evaluation, fusion and coverage call them too)
    kern = 0.0
    for k, v in stats.stats.items():
        if "splat/_cpu/kernels.py" in k[0] or (k[0].endswith("splat/losses.py") and k[2] in ("fwd", "bwd")):
            calls = v[1]
            kern += v[2] * min(1.0, n / calls) if calls else 0.0
    return {"steps": n, "total_s": total, "kernels_s": kern, "rest_s": total - kern}


def section_profile(args) -> tuple[list[tuple[str, str]], dict]:
    from real import cake_masks

    work = Path(args.keep) if args.keep else _tempdir("bench_stages_")
    work.mkdir(parents=True, exist_ok=True)
    masks = cake_masks(work / "masks")
    _build(work / "warmup", masks, 20, None)   # numba kernels compiled and cached on disk
    prof = work / "build.prof"
    twin = work / "twin"
    wall = _build(twin, masks, args.iters, prof)
    args.twin = twin
    pj = json.loads((twin / "pipeline.json").read_text())
    st = pstats.Stats(str(prof))
    cats = categories(st)
    total = sum(cats.values())
    rows = [(f"cake build, {args.iters} steps, half resolution, under cProfile", f"{wall:.1f} s wall")]
    keys: dict = {"profile_build_s": round(wall, 1)}
    for stage, rec in pj.items():
        if isinstance(rec, dict) and "seconds" in rec:
            rows.append((f"  stage {stage}", f"{rec['seconds']:.1f} s"))
            keys[f"profile_stage_{stage}_s"] = round(rec["seconds"], 2)
    rows.append(("  where the time went (own time)", f"{total:.1f} s in all"))
    for cat, s in sorted(cats.items(), key=lambda x: -x[1]):
        rows.append((f"    {cat}", f"{s:6.1f} s  {100 * s / total:4.1f} %"))
        keys[f"profile_share_{cat.split(' (')[0].replace(' ', '_').replace('/', '').replace('__', '_')}"] = \
            round(s / total, 4)
    libs = library_imports(st)
    rows.append(("  imports of heavy libraries, cumulative", ", ".join(f"{k} {v:.1f} s" for k, v in
                                                                    sorted(libs.items(), key=lambda x: -x[1]))))
    keys["profile_imports_s"] = {k: round(v, 2) for k, v in libs.items()}
    sp = step_split(st)
    if sp:
        per = lambda s: f"{1000 * s / sp['steps']:.1f} ms"  # noqa: E731
        rows.append((f"  training steps ({sp['steps']})", f"{per(sp['total_s'])}/step: kernels {per(sp['kernels_s'])} "
                     f"({100 * sp['kernels_s'] / sp['total_s']:.0f} %), the rest {per(sp['rest_s'])}"))
        keys.update(profile_step_ms=round(1000 * sp["total_s"] / sp["steps"], 2),
                    profile_step_kernel_share=round(sp["kernels_s"] / sp["total_s"], 4))
    top = sorted(((v[3], _name(k)) for k, v in st.stats.items() if "splattwin" in k[0]), reverse=True)
    rows.append(("  splattwin functions, cumulative (top 12)", ""))
    for s, nm in top[:12]:
        rows.append((f"    {nm.split('src/splattwin/')[-1]}", f"{s:6.1f} s"))
    return rows, keys


def section_steps(args) -> tuple[list[tuple[str, str]], dict]:
    import functools

    import numpy as np

    from real import cake_masks
    from splattwin.runtime import torch_threads
    from splattwin.splat import losses
    from splattwin.splat._cpu import kernels
    from splattwin.splat.config import TrainConfig
    from splattwin.splat.trainer import Trainer

    twin = args.twin
    if twin is None:
        work = _tempdir("bench_stages_")
        twin = work / "twin"
        _build(twin, cake_masks(work / "masks"), 20, None)
    spent = {"kernels": 0.0, "adam": 0.0, "densify": 0.0}

    def timed(f, part="kernels"):
        @functools.wraps(f)
        def g(*a, **k):
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                spent[part] += time.perf_counter() - t0
        return g

    names = ["project_fwd", "project_bwd", "sh_fwd", "sh_bwd", "make_records", "bin_tiles", "raster_fwd",
             "raster_bwd", "reduce_isect_grads"]
    saved = {n: getattr(kernels, n) for n in names}
    losses._kernels()
    saved_ssim = losses._NUMBA
    try:
        for n in names:
            setattr(kernels, n, timed(saved[n]))
        losses._NUMBA = tuple(timed(f) for f in saved_ssim)
        cfg = TrainConfig(iters=max(args.steps, 30), resolution=2, checkpoint_every=0, progress=False)
        tr = Trainer(twin / "poses" / "transforms.json", _tempdir("bench_steps_"), cfg)
        tr._fresh_state()
        tr.model.step = timed(tr.model.step, "adam")   # the six Adam optimizers (instance attributes)
        for hook in ("step_pre_backward", "step_post_backward"):
            setattr(tr.strategy, hook, timed(getattr(tr.strategy, hook), "densify"))
        blocks = []
        n_block = max(args.steps // 3, 1)
        with torch_threads(1):   # as the training loop runs on the CPU backend
            for _ in range(3):
                spent.update(kernels=0.0, adam=0.0, densify=0.0)
                t0 = time.perf_counter()
                for _ in range(n_block):
                    tr.train_step()
                blocks.append((time.perf_counter() - t0, spent["kernels"], spent["adam"], spent["densify"]))
    finally:
        for n in names:
            setattr(kernels, n, saved[n])
        losses._NUMBA = saved_ssim
    tot, ker, adam, dens = (float(np.median([b[k] for b in blocks])) / n_block for k in range(4))
    rows = [(f"training steps, no profiler ({3 * n_block} steps, {len(tr.model)} Gaussians at the end)",
             f"{1000 * tot:.1f} ms/step: kernels {1000 * ker:.1f} ms ({100 * ker / tot:.0f} %), the rest "
             f"{1000 * (tot - ker):.1f} ms, of it Adam {1000 * adam:.1f} ms and densification {1000 * dens:.1f} ms "
             f"(medians of 3 blocks)")]
    return rows, {"steps_ms": round(1000 * tot, 2), "steps_kernel_ms": round(1000 * ker, 2),
                  "steps_rest_ms": round(1000 * (tot - ker), 2), "steps_adam_ms": round(1000 * adam, 2),
                  "steps_densify_ms": round(1000 * dens, 2)}


SECTIONS = {"profile": section_profile, "steps": section_steps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sections", default="profile,steps", help=f"comma list of {', '.join(SECTIONS)}")
    ap.add_argument("--iters", type=int, default=300, help="profile: training steps of the cake build")
    ap.add_argument("--steps", type=int, default=150, help="steps: training steps timed (three blocks)")
    ap.add_argument("--keep", help="profile: build into this folder (kept) instead of a temporary one")
    ap.add_argument("--twin", type=Path, help="steps without profile: a built cake twin to use")
    args = ap.parse_args(argv)
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    if any(s not in SECTIONS for s in sections):
        ap.error(f"--sections: choose from {', '.join(SECTIONS)}")
    from real import DATA, print_table

    if not (DATA / "cake" / "images").is_dir():
        sys.exit(f"the real cake photos are not at {DATA / 'cake' / 'images'} (set SPLATTWIN_REAL_DATA)")
    load0 = os.getloadavg()[0]
    all_rows: list[tuple[str, str]] = []
    keys: dict = {}
    try:
        for s in sections:
            rows, k = SECTIONS[s](args)
            all_rows += rows
            keys.update(k)
    finally:
        for d in _TEMP:
            shutil.rmtree(d, ignore_errors=True)
    load1 = os.getloadavg()[0]
    keys.update(load_start=round(load0, 2), load_end=round(load1, 2))
    print_table(f"bench/stages.py: {os.cpu_count()} cores, load average {load0:.1f} at start, {load1:.1f} at end",
                all_rows, keys)
    return 0


if __name__ == "__main__":
    sys.exit(main())
