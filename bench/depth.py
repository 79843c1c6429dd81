"""Benchmark: depth supervision on D435-like depth (issue #16, "depth supervision when depth is given").

    python bench/depth.py [--size 320x240] [--views 16] [--iters 1500] [--heldout-every 4]
                          [--weights 0.05,0.2,1.0] [--modes relative,inverse] [--seeds 0] [--perfect]

The embedded scene written as a robot-style BOP capture (`splattwin.scene.robot_capture`: D435-like
intrinsics, z-down world, 16-bit depth in mm) whose depth maps carry the D435-like error model
(`splattwin.scene.options.DepthNoise`: axial noise ~1 % at 1 m growing with z^2, edge fattening, holes in
occlusion shadows, at depth edges and in blobs). Every --heldout-every-th view is held out (as `build
--heldout-every`). Each arm trains the same number of steps from the same initialisation (back-projected
noisy depth: `init auto` on a capture with depth and no SfM points) and differs only in
`TrainConfig.depth_lambda` / `depth_mode`; lambda 0 is the peer without depth loss. With --perfect, the
best arms are repeated on the same capture written with perfect (ray-cast) depth, to show what the noise
costs.

Per arm: held-out PSNR / SSIM, and the geometry of the held-out views against the PERFECT ray-cast depth
(`render_depth`, alpha >= 0.5): median and mean |ED - D_true| (mm), the fraction of pixels within 5 mm,
and coverage (pixels with true depth that render alpha >= 0.5); and whether the Gaussians sit on the
objects (`surface_fidelity`: precision / recall / F1 at 5 mm of the opaque Gaussian centres against the
objects' meshes, what the geometry stage builds its meshes from). Figures are medians over --seeds (scene
layout and training seed). Training is deterministic; wall times come from a shared machine and are
informative only.

Last line: one JSON object: per arm its figures, and for the best weight of each mode
depth_loss_psnr_gain_db_<mode> (vs lambda 0), depth_loss_depth_err_median_mm_<mode> (and _off for lambda 0),
depth_loss_best_<mode> (its lambda); depth_loss_psnr_gain_db / depth_loss_depth_err_median_mm are those
of the overall best arm by depth error.
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def write_capture(out: Path, size: tuple[int, int], views: int, seed: int, perfect: bool) -> Path:
    from splattwin.scene.options import DepthNoise, SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    w, h = size
    cap = RobotCaptureOptions(views=views, width=w, height=h, format="bop")
    if perfect:
        cap = replace(cap, depth_noise=DepthNoise.perfect())
    if (out / "scene.json").is_file():
        return out
    return write_robot_capture(out, SceneOptions(seed=seed, width=w, height=h, supersample=3), cap, progress=False)


def true_depths(size: tuple[int, int], views: int, seed: int) -> list[np.ndarray]:
    """The ray-cast (perfect) z-depth of every view of the capture (inf = no surface)."""
    from splattwin.scene.generator import build_scene, look_target
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, sweep_cameras

    w, h = size
    opts = SceneOptions(seed=seed, width=w, height=h, supersample=1)
    objects, _, _, renderer = build_scene(opts)
    cams = sweep_cameras(RobotCaptureOptions(views=views, width=w, height=h), look_target(objects), seed)
    return [renderer.render(c, 1)["depth"] for c in cams]


def sensor_stats(capture: Path, truth: list[np.ndarray]) -> dict:
    """How far the capture's depth maps are from the truth (what the depth loss is fed)."""
    from splattwin.capture import load_dataset, load_depth

    ds = load_dataset(capture)
    errs, holes = [], []
    for f, t in zip(ds.frames, truth):
        d = load_depth(f.depth_path, ds.depth_scale)
        has = np.isfinite(t)
        ok = has & (d > 0)
        errs.append(np.abs(d[ok] - t[ok]))
        holes.append(float((has & (d <= 0)).sum() / has.sum()))
    e = np.concatenate(errs)
    return {"sensor_err_median_mm": float(np.median(e) * 1e3), "sensor_err_mean_mm": float(e.mean() * 1e3),
            "sensor_holes_frac": float(np.mean(holes))}


def surface_fidelity(gaussians, capture: Path, threshold: float = 0.005, min_opacity: float = 0.5) -> dict:
    """Do the Gaussians sit on the objects? Centres of the Gaussians with opacity >= min_opacity against
    points sampled every 2 mm on the scene's object meshes (scene.json's objects, meshes/ in the z-up world,
    moved into the capture's world): precision = fraction of the centres near an object (within 5 cm of
    one: the others belong to the table or background) that lie within `threshold`; recall = fraction of
    the visible object surface (the faces pressed on the table dropped) with a centre within `threshold`;
    F1 their harmonic mean (`splattwin.geometry.metrics`)."""
    import trimesh
    from scipy.spatial import cKDTree

    from splattwin.geometry.metrics import sample_surface

    scene = json.loads((capture / "scene.json").read_text())
    T = np.asarray(scene["robot_capture"]["R_capture_world"])
    gt = []
    for o in scene["objects"]:
        m = trimesh.load(capture / "meshes" / f"{o['name']}.ply", force="mesh")
        gt.append(sample_surface(m, 0.002, drop_supported=0.0))
    pts = np.concatenate(gt) @ T[:3, :3].T + T[:3, 3]
    op = np.asarray(gaussians.opacities).reshape(-1)
    c = np.asarray(gaussians.means)[op >= min_opacity]
    d_c = cKDTree(pts).query(c)[0]
    near = d_c <= 0.05
    prec = float((d_c[near] <= threshold).mean()) if near.any() else 0.0
    rec = float((cKDTree(c).query(pts)[0] <= threshold).mean()) if len(c) else 0.0
    return {"obj_precision": prec, "obj_recall": rec, "obj_f1": 2 * prec * rec / max(prec + rec, 1e-12)}


def train_arm(capture: Path, out: Path, iters: int, heldout_every: int, lam: float, mode: str, seed: int,
              truth: list[np.ndarray]) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses.holdout import apply_holdout
    from splattwin.poses.options import HoldoutOptions
    from splattwin.splat.config import TrainConfig
    from splattwin.splat.eval import evaluate
    from splattwin.splat.rendering import render_depth
    from splattwin.splat.trainer import Trainer

    ds = load_dataset(capture)
    apply_holdout(ds, HoldoutOptions(heldout_every=heldout_every))
    cfg = TrainConfig(iters=iters, depth_lambda=lam, depth_mode=mode, seed=seed, checkpoint_every=0, progress=False)
    t0, c0 = time.perf_counter(), time.process_time()
    res = Trainer(ds, out, cfg).run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ev = evaluate(res.gaussians, ds, None, resolution=cfg.resolution, progress=False)
    assert ev.split == "heldout"
    errs, cover = [], []
    idx = {f.name: i for i, f in enumerate(ds.frames)}
    for f in ds.heldout():
        t = truth[idx[f.name]]
        ed = render_depth(res.gaussians, f.camera, min_alpha=0.5)
        has = np.isfinite(t)
        ok = has & np.isfinite(ed)
        errs.append(np.abs(ed[ok] - t[ok]))
        cover.append(float(ok.sum() / max(1, has.sum())))
    e = np.concatenate(errs)
    fid = surface_fidelity(res.gaussians, capture)
    return {**fid, "psnr": ev.mean_psnr, "ssim": ev.mean_ssim, "depth_err_median_mm": float(np.median(e) * 1e3),
            "depth_err_mean_mm": float(e.mean() * 1e3), "within_5mm": float((e <= 0.005).mean()),
            "coverage": float(np.mean(cover)), "gaussians": len(res.gaussians), "init": res.init_method,
            "wall_s": wall, "cpu_s": cpu}


KEYS = ("psnr", "ssim", "depth_err_median_mm", "depth_err_mean_mm", "within_5mm", "coverage", "obj_precision",
        "obj_recall", "obj_f1")


def arm_name(depth: str, mode: str, lam: float) -> str:
    return "off" if lam == 0 else f"{depth}:{mode}:{lam:g}"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--heldout-every", type=int, default=4)
    ap.add_argument("--weights", default="0.05,0.2,1.0", help="depth_lambda values besides 0 (comma-separated)")
    ap.add_argument("--modes", default="relative,inverse")
    ap.add_argument("--seeds", default="0", help="scene + training seeds (comma-separated); figures are medians")
    ap.add_argument("--perfect", action="store_true", help="also train the best arm of each mode on perfect depth")
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (captures are reused)")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    weights = [float(x) for x in args.weights.split(",") if x]
    modes = [m for m in args.modes.split(",") if m]
    seeds = [int(s) for s in args.seeds.split(",") if s]
    arms = [("d435", "relative", 0.0)] + [("d435", m, lam) for m in modes for lam in weights]

    rows: dict[str, list[dict]] = {}
    sensor: dict[str, list[dict]] = {"d435": [], "perfect": []}
    with tempfile.TemporaryDirectory(prefix="bench_depth_") as tmp:
        work = args.keep or Path(tmp)
        for seed in seeds:
            truth = true_depths((w, h), args.views, seed)
            caps = {"d435": write_capture(work / f"s{seed}_d435", (w, h), args.views, seed, perfect=False)}
            sensor["d435"].append(sensor_stats(caps["d435"], truth))
            for depth, mode, lam in arms:
                name = arm_name(depth, mode, lam)
                r = train_arm(caps[depth], work / f"s{seed}_{name.replace(':', '_')}", args.iters, args.heldout_every,
                              lam, mode, seed, truth)
                rows.setdefault(name, []).append(r)
                print(f"seed {seed} {name:22} psnr {r['psnr']:.2f} depth err {r['depth_err_median_mm']:.2f} mm "
                      f"({r['wall_s']:.0f} s)", flush=True)
        med = {n: {k: statistics.median(r[k] for r in rs) for k in KEYS} for n, rs in rows.items()}
        best = {}
        for m in modes:
            cand = [arm_name("d435", m, lam) for lam in weights]
            if cand:
                best[m] = min(cand, key=lambda n: med[n]["depth_err_median_mm"])
        if args.perfect:
            for seed in seeds:
                truth = true_depths((w, h), args.views, seed)
                cap = write_capture(work / f"s{seed}_perfect", (w, h), args.views, seed, perfect=True)
                sensor["perfect"].append(sensor_stats(cap, truth))
                for m, n in best.items():
                    lam = float(n.rsplit(":", 1)[1])
                    name = arm_name("perfect", m, lam)
                    r = train_arm(cap, work / f"s{seed}_{name.replace(':', '_')}", args.iters, args.heldout_every,
                                  lam, m, seed, truth)
                    rows.setdefault(name, []).append(r)
            med = {n: {k: statistics.median(r[k] for r in rs) for k in KEYS} for n, rs in rows.items()}

    s = {k: statistics.median(x[k] for x in sensor["d435"]) for k in sensor["d435"][0]}
    print(f"\ndepth supervision on D435-like depth: robot-style BOP capture, {args.views} views at {w}x{h}, every "
          f"{args.heldout_every}th view held out, {args.iters} steps, seeds {seeds} (medians; machine shared, times "
          f"informative only)")
    print(f"sensor vs truth: median |D - D_true| {s['sensor_err_median_mm']:.2f} mm, mean {s['sensor_err_mean_mm']:.2f}"
          f" mm, holes {100 * s['sensor_holes_frac']:.1f} % of the pixels with a surface")
    print(f"{'arm (depth:mode:lambda)':24} {'PSNR dB':>8} {'SSIM':>7} {'|ED-D| med mm':>14} {'mean mm':>8} "
          f"{'<=5mm':>6} {'cover':>6} {'obj P':>6} {'obj R':>6} {'obj F1':>6} {'wall s':>7}")
    for n, m in med.items():
        wall = statistics.median(r["wall_s"] for r in rows[n])
        print(f"{n:24} {m['psnr']:8.2f} {m['ssim']:7.4f} {m['depth_err_median_mm']:14.2f} {m['depth_err_mean_mm']:8.2f} "
              f"{m['within_5mm']:6.3f} {m['coverage']:6.3f} {m['obj_precision']:6.3f} {m['obj_recall']:6.3f} "
              f"{m['obj_f1']:6.3f} {wall:7.0f}")
    off = med["off"]
    out: dict = {"iters": args.iters, "views": args.views, "size": f"{w}x{h}", "heldout_every": args.heldout_every,
                 "seeds": seeds, **{k: round(v, 3) for k, v in s.items()},
                 "arms": {n: {k: round(v, 4) for k, v in m.items()} for n, m in med.items()},
                 "depth_loss_depth_err_median_mm_off": round(off["depth_err_median_mm"], 3),
                 "depth_loss_psnr_off": round(off["psnr"], 3), "depth_loss_obj_f1_off": round(off["obj_f1"], 4)}
    for m, n in best.items():
        out[f"depth_loss_best_{m}"] = float(n.rsplit(":", 1)[1])
        out[f"depth_loss_psnr_gain_db_{m}"] = round(med[n]["psnr"] - off["psnr"], 3)
        out[f"depth_loss_ssim_gain_{m}"] = round(med[n]["ssim"] - off["ssim"], 4)
        out[f"depth_loss_depth_err_median_mm_{m}"] = round(med[n]["depth_err_median_mm"], 3)
        out[f"depth_loss_obj_f1_{m}"] = round(med[n]["obj_f1"], 4)
    if best:
        n = min(best.values(), key=lambda k: med[k]["depth_err_median_mm"])
        out["depth_loss_best_arm"] = n
        out["depth_loss_psnr_gain_db"] = round(med[n]["psnr"] - off["psnr"], 3)
        out["depth_loss_depth_err_median_mm"] = round(med[n]["depth_err_median_mm"], 3)
        out["depth_loss_depth_err_gain_mm"] = round(off["depth_err_median_mm"] - med[n]["depth_err_median_mm"], 3)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
