"""Benchmark: per-view exposure / white-balance changes in a robot capture: detected, and does the
per-image appearance correction help?

    python bench/exposure.py [--size 320x240] [--views 24] [--iters 500] [--modes off,gain] [--no-build]
                             [--build clean,perturbed] [--gain 0.7,1.3] [--wb 0.9,1.1] [--seed 0] [--keep DIR]

Captures: the embedded scene as a robot-style BOP capture (`splattwin.scene.robot_capture`, known poses,
D435-like depth) "clean", and the same capture "perturbed": each view's RGB (8-bit values, clipped)
scaled by a per-view gain drawn uniformly from --gain and a per-channel white balance from --wb (seed
--seed + 1; the draws are in the JSON). Held-out views: every 8th (the default hold-out).

Rows per capture: the poses stage's exposure check (`splattwin.poses.exposure`, poses_report.json
"exposure"): spread (largest channel-gain distance from 1, %), images flagged, and on the perturbed capture
the error of the recovered gains against the applied ones (both relative to their median image). Unless
--no-build, `build --until splats` per capture and --modes appearance mode ("auto": what the build decides
from the exposure check; the JSON records the mode trained and the decision, from train.json), with three
held-out figures:
`psnr` (the eval headline: the render without colour correction against the photo, as perturbed),
`psnr_right_corrected` (the appearance protocol: affine colour fitted on the left half of each held-out
view, PSNR on the right half; fair whichever the held-out view's exposure) and `psnr_clean_gt` (the render
against the unperturbed photo of the same view: how close the splats' canonical colour is to the scene's).

Last line: one JSON object: per capture the spread and flagged count, the gain error, and per (capture,
mode) the three PSNRs, the mode trained and the learnt corrections' common gain / bias (train.json
"gauge": how far the canonical colour's level drifted from the corrections' start).

Measured (Nov 2026, 2 shared cores, 500 steps, seed 0): clean 0.0 %, perturbed 56.3 % (gains recovered within
0.8 %); held-out PSNR / right-half corrected / against the clean photos: clean off 27.55 / 27.64 / 27.55, gain
27.24 / 27.86 / 27.24, affine 27.00 / 28.10 / 27.00; perturbed off 21.75 / 24.90 / 25.26, gain 21.86 / 25.84 /
26.01, affine 21.98 / 25.72 / 26.12. --gain 0.9,1.1 --wb 0.97,1.03: 14.1 %, off 25.93 / 26.75 / 26.59, gain
26.31 / 27.53 / 27.71. Seed 1 (--modes off,auto): clean 0.0 % (auto trained off: 26.41 / 26.35 / 26.41 both),
perturbed 51.0 % (gains within 1.0 %), off 19.80 / 27.11 / 25.78, auto (gain) 19.83 / 26.19 / 25.06: the
correction helped on seed 0 and hurt on seed 1, so it is suggested, not turned on by default.
Corrections started at the measured gains (`splat.appearance.initial_gains`; the JSON's "init"), auto (gain):
perturbed seed 0 23.21 / 26.62 / 26.29, seed 1 20.28 / 27.64 / 25.25; --gain 0.9,1.1 --wb 0.97,1.03 (14.1 % /
12.8 %) seed 0 26.07 / 27.78 / 27.48, seed 1 off 24.73 / 26.38 / 26.05, auto 25.33 / 26.81 / 26.06; clean seed 1
auto trains off (identical), a forced gain 25.65 / 26.01 / 25.65. Still not the default: seed 1 against the
clean photos -0.53 / +0.01 dB. The "gauge" of those auto runs: every bias drifted up (mean +0.007..+0.012, the
common gain +0.5-0.8 %), the canonical colour 3-5 % below its start (per-channel gain of the held-out renders
against the clean photos: 1.00-1.06 seed 0, 0.91-0.95 seed 1); seed 1's training photos themselves average
0.95-0.97 of the clean exposure. Anchoring the starts at their geometric mean and holding the common gain and bias while
training (tried, not kept; `splat.appearance` module comment): perturbed seed 0 21.96 / 26.62 / 27.28, seed 1
20.16 / 27.67 / 25.79; 0.9..1.1 seed 0 26.16 / 27.37 / 27.48, seed 1 24.69 / 26.00 / 25.87 (off identical).
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def perturb_capture(src: Path, dst: Path, gain: tuple[float, float], wb: tuple[float, float], seed: int) -> dict:
    """Copy the BOP capture `src` to `dst` and scale each rgb/*.png by a per-view gain x white balance.
    Returns {image stem: [r, g, b] applied gain}."""
    from splattwin.capture import load_image
    from splattwin.io import write_image

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    rng = np.random.default_rng(seed)
    applied = {}
    for p in sorted((dst / "rgb").glob("*.png")):
        g = rng.uniform(*gain) * rng.uniform(*wb, size=3)
        img = load_image(p)
        write_image(p, np.round(np.clip(img * g, 0.0, 1.0) * 255).astype(np.uint8))
        applied[p.stem] = [float(v) for v in g]
    return applied


def gain_error(rec: dict, applied: dict[str, list[float]]) -> float | None:
    """Largest |recovered / applied - 1| (%) over images and channels, both relative to their median image."""
    names = [n for n in rec.get("images", {}) if rec["images"][n]["rgb_gain"] is not None]
    stem = {n: Path(n).stem for n in names}
    names = [n for n in names if stem[n] in applied]
    if not names:
        return None
    got = np.log([rec["images"][n]["rgb_gain"] for n in names])
    want = np.log([applied[stem[n]] for n in names])
    want -= np.median(want, axis=0)
    got -= np.median(got, axis=0)
    return float(100 * np.expm1(np.abs(got - want).max()))


def clean_gt_psnr(twin: Path, clean: Path) -> float:
    """Held-out PSNR of the trained splats against the unperturbed photos of the same views."""
    import dataclasses

    from splattwin.capture import load_dataset
    from splattwin.splat.eval import evaluate

    ds = load_dataset(twin / "poses" / "transforms.json")
    frames = [dataclasses.replace(f, image_path=clean / "rgb" / Path(f.image_path).name) for f in ds.frames]
    ds = dataclasses.replace(ds, frames=frames)
    return float(evaluate(twin / "splat", ds, out_dir=None, progress=False).mean_psnr)


def run(work: Path, size: tuple[int, int], views: int, iters: int, modes: list[str], build: list[str],
        gain: tuple[float, float], wb: tuple[float, float], seed: int) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    w, h = size
    clean = write_robot_capture(work / "clean", SceneOptions(seed=seed, width=w, height=h, supersample=3),
                                RobotCaptureOptions(views=views, width=w, height=h, format="bop"), progress=False)
    applied = perturb_capture(clean, work / "perturbed", gain, wb, seed + 1)
    out: dict = {"applied_gains": applied, "captures": {}}
    for name in ("clean", "perturbed"):
        cap = work / name
        t0 = time.perf_counter()
        res = estimate_poses(load_dataset(cap), PoseOptions(method="known", progress=False))
        rec = res.stats["exposure"]
        row = {"poses_s": time.perf_counter() - t0, "check_s": rec.get("seconds"), "spread_pct": rec.get("spread_pct"),
               "flagged": len(rec.get("images_off") or []), "error": rec.get("error"),
               "gain_error_pct": gain_error(rec, applied if name == "perturbed" else
                                            {Path(n).stem: [1.0, 1.0, 1.0] for n in rec.get("images", {})})}
        if name in build:
            from splattwin.cli import main as cli

            for mode in modes:
                twin = work / f"twin_{name}_{mode}"
                t0 = time.perf_counter()
                code = cli(["build", str(cap), "--out", str(twin), "--poses", "known", "--iters", str(iters),
                            "--until", "splats", "--no-progress", "--splat.appearance", mode])
                m = json.loads((twin / "splat" / "eval" / "metrics.json").read_text()) if code == 0 else {}
                row[mode] = {"exit": code, "build_s": time.perf_counter() - t0, "psnr": m.get("mean_psnr"),
                             "psnr_right_plain": m.get("mean_psnr_right_plain"),
                             "psnr_right_corrected": m.get("mean_psnr_right_corrected"),
                             "psnr_clean_gt": clean_gt_psnr(twin, clean) if code == 0 else None,
                             "heldout": m.get("n_views")}
                if code == 0:   # what `auto` (or an explicit mode) trained, and why (splat.appearance.decide)
                    app = json.loads((twin / "splat" / "train.json").read_text()).get("appearance") or {}
                    row[mode].update(trained=app.get("mode"), decision=app.get("decision"), init=app.get("init"),
                                    gauge=app.get("gauge"))
        out["captures"][name] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--modes", default="off,gain", help="appearance modes trained per capture (comma list)")
    ap.add_argument("--no-build", action="store_true", help="the exposure check only (no training)")
    ap.add_argument("--build", default="clean,perturbed", help="captures trained (comma list)")
    ap.add_argument("--gain", default="0.7,1.3", help="range of the per-view gain")
    ap.add_argument("--wb", default="0.9,1.1", help="range of the per-view, per-channel white balance")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temp folder)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    rng = lambda s: tuple(float(v) for v in s.split(","))  # noqa: E731
    modes = [m for m in args.modes.split(",") if m]
    with tempfile.TemporaryDirectory(prefix="bench_exposure_") as tmp:
        work = args.keep or Path(tmp)
        build = [] if args.no_build else [c for c in args.build.split(",") if c]
        res = run(work, (w, h), args.views, args.iters, modes, build, rng(args.gain), rng(args.wb), args.seed)
    print(f"robot-style capture, {args.views} views at {w}x{h}; perturbed: gain {args.gain}, white balance "
          f"{args.wb} (machine shared)")
    print(f"{'capture':10} {'spread %':>9} {'flagged':>8} {'gain err %':>10} {'check s':>8}")
    for name, r in res["captures"].items():
        ge = r["gain_error_pct"]
        print(f"{name:10} {r['spread_pct'] if r['spread_pct'] is not None else float('nan'):9.2f} {r['flagged']:8d} "
              f"{ge if ge is not None else float('nan'):10.2f} {r['check_s'] or float('nan'):8.2f}")
    if not args.no_build:
        print(f"\n{'capture':10} {'appearance':10} {'trained':8} {'PSNR':>7} {'PSNR R corr':>11} {'PSNR clean GT':>13} "
              f"{'s':>6}")
        for name, r in res["captures"].items():
            for mode in modes:
                if mode not in r:
                    continue
                m = r[mode]
                f = lambda v: float("nan") if v is None else v  # noqa: E731
                print(f"{name:10} {mode:10} {str(m.get('trained')):8} {f(m['psnr']):7.2f} {f(m['psnr_right_corrected']):11.2f} "
                      f"{f(m['psnr_clean_gt']):13.2f} {m['build_s']:6.0f}")
    summary = {"captures": res["captures"], "iters": args.iters, "views": args.views, "size": [w, h]}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
