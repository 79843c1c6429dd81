"""Benchmark: transient masks (`TrainConfig.robust_quantile`, `splattwin.splat.robust`) against distractors.

    python bench/transients.py [--iters 3000] [--seeds 0,1] [--per-view 3] [--quantiles 0,0.8]

The embedded scene (15 training views at 320x240, 5 held-out views; bench/train.py's cache) with
"passers-by" painted into every training photo: --per-view opaque upright ellipses of random colour, size
(12-30 % of the image height) and place, a new draw per photo, so no two photos agree on them (what people,
cars and banners do to a photo collection). The held-out photos stay clean, so their PSNR measures what the
distractors leave in the model (ghosts, floaters) and what masking costs the static scene. Arms: the
clean capture (no distractors, masks off: the ceiling), and the painted capture at each --quantiles value
(0: off, the plain loss). Same steps, seed and initialisation (the scene's SfM-like points) in every arm;
figures are medians over --seeds (training seed and the distractors' draw). The masks are off by default
(`TrainConfig.robust_quantile`): on the real photo collection (british_museum, 8 views) they did not help;
its figures are in the README.

Last line: one JSON object: per arm psnr / ssim (medians) and masked share of the painted pixels / of the
rest (last pass), transients_psnr_clean, transients_psnr_off, transients_psnr_on (the arm of quantile
0.8, the value the option's help suggests), transients_gain_db (on - off) and transients_gap_db (clean - on).
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ON_QUANTILE = 0.8  # the arm reported as "on"


def paint_distractors(src: Path, dst: Path, per_view: int, seed: int) -> tuple[Path, dict[str, np.ndarray]]:
    """A copy of dataset `src` in `dst` with `per_view` random opaque ellipses painted into each training
    image; returns the copy and each training image's painted mask (by file name)."""
    from PIL import Image

    from splattwin.capture import load_dataset

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    rng = np.random.default_rng(1000 + seed)
    masks = {}
    for f in load_dataset(dst).train():
        img = np.asarray(Image.open(f.image_path).convert("RGB")).copy()
        h, w = img.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w]
        painted = np.zeros((h, w), bool)
        for _ in range(per_view):
            ry = rng.uniform(0.06, 0.15) * h          # half-height: the figure is 12-30 % of the image
            rx = ry * rng.uniform(0.3, 0.6)           # upright, like a person
            cy, cx = rng.uniform(0.2 * h, h - ry), rng.uniform(0, w)
            e = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0
            img[e] = rng.integers(0, 256, 3)
            painted |= e
        Image.fromarray(img).save(f.image_path)
        masks[f.image_path.name] = painted
    return dst, masks


def run_arm(ds_path: Path, out: Path, iters: int, seed: int, quantile: float,
            painted: dict[str, np.ndarray] | None) -> dict:
    import torch

    from splattwin.capture import load_dataset
    from splattwin.splat import trainer as trainer_mod
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import TrainConfig, Trainer

    ds = load_dataset(ds_path)
    cfg = TrainConfig(iters=iters, checkpoint_every=0, progress=False, seed=seed, robust_quantile=quantile)
    t = Trainer(ds, out, cfg)
    shares = {"painted": [], "rest": []}
    names = {id(v.image): f.image_path.name for v, f in zip(t.views, t.frames)}
    orig = trainer_mod.masked_target
    last_pass = max(1, len(t.views))

    def recording(img, gt, *a):   # what the trainer masks, pixel for pixel (last pass only)
        target, mask = orig(img, gt, *a)
        if painted is not None and t.step >= iters - last_pass:
            p = torch.from_numpy(painted[names[id(gt)]])
            shares["painted"].append(float(mask[p].float().mean()) if p.any() else 0.0)
            shares["rest"].append(float(mask[~p].float().mean()))
        return target, mask

    trainer_mod.masked_target = recording
    try:
        t0 = time.perf_counter()
        res = t.run()
        wall = time.perf_counter() - t0
    finally:
        trainer_mod.masked_target = orig
    ev = evaluate(res.gaussians, ds, out / "eval", progress=False, rasterize_mode=cfg.rasterize_mode,
                  eps2d=cfg.filter_eps2d())
    mean = lambda xs: round(float(np.mean(xs)), 4) if xs else None  # noqa: E731
    return {"psnr": ev.mean_psnr, "ssim": ev.mean_ssim, "wall_s": wall, "masked_painted": mean(shares["painted"]),
            "masked_rest": mean(shares["rest"])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--iters", type=int, default=3000)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--per-view", type=int, default=3)
    ap.add_argument("--quantiles", default="0,0.8")
    ap.add_argument("--scene-cache", type=Path, default=Path(tempfile.gettempdir()) / "splattwin_bench")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "bench"))
    from train import ensure_scene

    scene = ensure_scene(args.scene_cache, views=15, heldout=5, width=320, height=240, seed=0)
    seeds = [int(s) for s in args.seeds.split(",")]
    quantiles = [float(q) for q in args.quantiles.split(",")]
    work = Path(tempfile.mkdtemp(prefix="bench_transients_"))
    arms: dict[str, list[dict]] = {}
    try:
        for seed in seeds:
            arms.setdefault("clean", []).append(run_arm(scene, work / f"clean_{seed}", args.iters, seed, 0.0, None))
            ds, painted = paint_distractors(scene, work / f"painted_{seed}", args.per_view, seed)
            for q in quantiles:
                arms.setdefault(f"q{q:g}", []).append(run_arm(ds, work / f"q{q:g}_{seed}", args.iters, seed, q,
                                                              painted if q > 0 else None))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    med = lambda xs: None if any(x is None for x in xs) else round(statistics.median(xs), 4)  # noqa: E731
    summary = {arm: {k: med([r[k] for r in runs]) for k in runs[0]} for arm, runs in arms.items()}
    print(f"{'arm':<10} {'held-out PSNR':>14} {'SSIM':>7} {'masked painted':>15} {'masked rest':>12} {'wall s':>7}")
    for arm, s in summary.items():
        per_seed = " / ".join(f"{r['psnr']:.2f}" for r in arms[arm])
        print(f"{arm:<10} {s['psnr']:>14.2f} {s['ssim']:>7.4f} {str(s['masked_painted']):>15} "
              f"{str(s['masked_rest']):>12} {s['wall_s']:>7.0f}   seeds: {per_seed}")
    on = summary.get(f"q{ON_QUANTILE:g}")
    off = summary.get("q0")
    out = {"arms": summary, "seeds": seeds, "iters": args.iters, "per_view": args.per_view,
           "transients_psnr_clean": summary["clean"]["psnr"], "transients_psnr_off": off and off["psnr"],
           "transients_psnr_on": on and on["psnr"],
           "transients_gain_db": round(on["psnr"] - off["psnr"], 3) if on and off else None,
           "transients_gap_db": round(summary["clean"]["psnr"] - on["psnr"], 3) if on else None}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
