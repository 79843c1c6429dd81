"""Benchmark: SfM (pycolmap, CPU) time per stage and accuracy on the embedded scene, 15 and 30 views.

    python bench/poses.py [--repeats 3] [--cache DIR]

Rows: views x intrinsics (estimated vs known, the peer) for 15 views, estimated for 30 views. Each row
is the median over `--repeats` fresh runs (new database each time). Accuracy: max camera-centre error
after Sim(3) alignment to ground truth, relative to the table diagonal; focal error when estimated.
Last line: JSON with registered, total, center_err_rel, sfm_s (15 views, estimated intrinsics) and more.
Target: sfm_s <= 20 s for 15 views at 320x240 on 2 cores.
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import shutil
import statistics
import tempfile
from pathlib import Path

import numpy as np


def _scene(cache: Path, views: int) -> Path:
    from splattwin.scene import SceneOptions, generate

    out = cache / f"scene_{views}"
    if not (out / "transforms.json").is_file():
        if out.exists():
            shutil.rmtree(out)
        generate(out, SceneOptions(seed=0, width=320, height=240, views=views, heldout=0), progress=False)
    return out


def _run(scene: Path, known: bool) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses.align import umeyama
    from splattwin.poses.sfm import SfmOptions, run_sfm

    gt = load_dataset(scene)
    c0 = gt.frames[0].camera
    opts = SfmOptions(intrinsics=(c0.fx, c0.fy, c0.cx, c0.cy) if known else None)
    with tempfile.TemporaryDirectory(prefix="bench_poses_") as work:
        res = run_sfm([f.image_path for f in gt.frames], work, opts, progress=False)
    g = {f.image_path.name: f.camera for f in gt.frames}
    names = sorted(res.cameras)
    src = np.array([res.cameras[n].center for n in names])
    tgt = np.array([g[Path(n).name].center for n in names])
    ext = json.loads((scene / "scene.json").read_text())["table"]["extent"]
    diag = float(np.hypot(ext[1] - ext[0], ext[3] - ext[2]))
    fit = umeyama(src, tgt)
    f_err = float(np.mean([abs(res.cameras[n].fx - g[Path(n).name].fx) / g[Path(n).name].fx for n in names]))
    t = res.timings
    return {"registered": res.num_registered, "total": res.num_total, "reproj_px": res.mean_reproj_error,
            "center_err_rel": float(fit.residuals.max() / diag), "focal_err_rel": f_err,
            "extract_s": t["extract"], "match_s": t["match"], "map_s": t["map"],
            "sfm_s": t["extract"] + t["match"] + t["map"], "points": int(len(res.points_xyz))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "splattwin_bench_poses")
    args = ap.parse_args()
    from rich.console import Console
    from rich.table import Table

    import pycolmap

    pycolmap.logging.minloglevel = 2
    args.cache.mkdir(parents=True, exist_ok=True)
    configs = [(15, False), (15, True), (30, False)]
    rows = {}
    for views, known in configs:
        scene = _scene(args.cache, views)
        runs = [_run(scene, known) for _ in range(args.repeats)]
        rows[(views, known)] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    table = Table(title=f"SfM on the embedded scene, 320x240, median of {args.repeats} runs (2 threads)")
    for col in ("views", "intrinsics", "registered", "extract s", "match s", "map s", "SfM s", "reproj px",
                "centre err (rel)", "focal err", "points"):
        table.add_column(col, justify="right")
    for (views, known), r in rows.items():
        table.add_row(str(views), "known" if known else "estimated", f"{r['registered']:.0f}/{r['total']:.0f}",
                      f"{r['extract_s']:.2f}", f"{r['match_s']:.2f}", f"{r['map_s']:.2f}", f"{r['sfm_s']:.2f}",
                      f"{r['reproj_px']:.3f}", f"{r['center_err_rel'] * 100:.3f} %",
                      "-" if known else f"{r['focal_err_rel'] * 100:.3f} %", f"{r['points']:.0f}")
    Console(width=160).print(table)
    main_row, known_row, big = rows[(15, False)], rows[(15, True)], rows[(30, False)]
    out = {"registered": int(main_row["registered"]), "total": int(main_row["total"]),
           "center_err_rel": round(main_row["center_err_rel"], 6), "sfm_s": round(main_row["sfm_s"], 3),
           "extract_s": round(main_row["extract_s"], 3), "match_s": round(main_row["match_s"], 3),
           "map_s": round(main_row["map_s"], 3), "focal_err_rel": round(main_row["focal_err_rel"], 6),
           "reproj_px": round(main_row["reproj_px"], 4), "sfm_s_known_intrinsics": round(known_row["sfm_s"], 3),
           "registered_30": int(big["registered"]), "total_30": int(big["total"]), "sfm_s_30": round(big["sfm_s"], 3),
           "center_err_rel_30": round(big["center_err_rel"], 6), "target_sfm_s": 20.0,
           "meets_target": bool(main_row["sfm_s"] <= 20.0), "repeats": args.repeats}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
