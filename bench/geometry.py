"""Benchmark of the geometry stage on the embedded scene (paper Table 5 + conversion time).

Builds the small embedded scene, samples ~200k synthetic Gaussians with 3DGS artefacts on it
(`splattwin.scene.synthetic_gaussians`), lets the artefacts leak into the object labels as mask lifting
would (`leak_labels`), then prints
  1. the four-configuration ablation per object: Chamfer (mm), precision, recall, F1 @ 5 mm;
  2. the conversion time (median of --runs, after one warm-up run) with per-stage times, side by side with
     two peers: exact DBSCAN on all points (no voxel weighting) and voxel remeshing instead of alpha shapes.
Last line: one JSON object (f1_5mm_min, chamfer_raw, chamfer_full, convert_s, ...).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000, help="approximate number of Gaussians")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--scene", type=Path, default=None, help="existing scene folder (default: generate one)")
    args = ap.parse_args(argv)

    from rich.console import Console
    from rich.table import Table

    from splattwin.geometry.convert import CONFIGS, ablation, convert
    from splattwin.geometry.options import GeometryOptions
    from splattwin.geometry.synthetic import leak_labels, load_scene_gt
    from splattwin.scene import SceneOptions, generate, synthetic_gaussians

    con = Console(width=150)
    tmp = tempfile.TemporaryDirectory()
    scene = args.scene or generate(Path(tmp.name) / "scene", SceneOptions(seed=0, width=160, height=120, views=8, heldout=3),
                                   progress=False)
    # density: object surface Gaussians per m^2 (table gets half); ~32k Gaussians at 40000 on this scene
    g, labels_gt = synthetic_gaussians(scene, seed=0, density=40000.0 * args.gaussians / 32000.0)
    objects, meshes = load_scene_gt(scene)
    labels = leak_labels(g, labels_gt, {lab: meshes[n].bounds for n, lab, _ in objects})
    con.print(f"scene {scene}: {len(g)} Gaussians, {len(objects)} objects, "
              f"{int((labels != labels_gt).sum())} artefacts leaked into object labels")

    ab = ablation(g, labels, objects, meshes)
    t = Table(title="Geometric fidelity of the cleaned Gaussian centres vs GT (threshold 5 mm)")
    t.add_column("object")
    for c in CONFIGS:
        t.add_column(f"{c}\nCD mm / P / R / F1", justify="right")
    for n, _, _ in objects:
        t.add_row(n, *[f"{ab[c][n].chamfer * 1e3:.2f} / {ab[c][n].precision:.3f} / {ab[c][n].recall:.3f} / "
                       f"{ab[c][n].f1:.3f}" for c in CONFIGS])
    mean = {c: {k: float(np.mean([getattr(ab[c][n], k) for n, _, _ in objects])) for k in ("chamfer", "precision", "recall", "f1")}
            for c in CONFIGS}
    t.add_row("[b]mean", *[f"{mean[c]['chamfer'] * 1e3:.2f} / {mean[c]['precision']:.3f} / {mean[c]['recall']:.3f} / "
                           f"{mean[c]['f1']:.3f}" for c in CONFIGS])
    con.print(t)

    peers = {"ours (voxel-weighted DBSCAN, alpha shapes)": GeometryOptions(),
             "peer: exact DBSCAN on all points": GeometryOptions(dbscan_voxel=0.0),
             "peer: voxel remesh instead of alpha shapes": GeometryOptions(use_alpha=False)}
    results = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert(g, labels, objects, GeometryOptions(), progress=False)  # warm-up: imports, numba/JIT caches
        for name, opts in peers.items():
            runs = []
            for _ in range(args.runs if name.startswith("ours") else 1):
                t0 = time.perf_counter()
                conv = convert(g, labels, objects, opts, progress=False)
                runs.append((time.perf_counter() - t0, conv))
            runs.sort(key=lambda r: r[0])
            results[name] = runs[len(runs) // 2]
    stages = ("filter", "cluster", "mesh", "decompose", "background")
    t2 = Table(title=f"Conversion of {len(g)} Gaussians ({args.runs} runs for ours, median; 1 run per peer), seconds")
    t2.add_column("method")
    for s in (*stages, "total"):
        t2.add_column(s, justify="right")
    t2.add_column("usable / watertight")
    for name, (sec, conv) in results.items():
        ok = sum(o.usable for o in conv.objects)
        wt = sum(bool(o.usable and o.collision.is_watertight) for o in conv.objects)
        t2.add_row(name, *[f"{conv.timings.get(s, 0.0):.2f}" for s in stages], f"{sec:.2f}", f"{ok}/{wt} of {len(conv.objects)}")
    con.print(t2)
    ours_s, ours = results["ours (voxel-weighted DBSCAN, alpha shapes)"]
    parts = {o.name: len(o.parts) for o in ours.objects}
    con.print("convex parts: " + ", ".join(f"{k} {v}" for k, v in parts.items()))
    out = {
        "n_gaussians": len(g),
        "f1_5mm_min": min(ab["full"][n].f1 for n, _, _ in objects),
        "chamfer_raw": mean["raw"]["chamfer"], "chamfer_attribute": mean["attribute"]["chamfer"],
        "chamfer_cluster": mean["cluster"]["chamfer"], "chamfer_full": mean["full"]["chamfer"],
        "precision_full": mean["full"]["precision"], "recall_full": mean["full"]["recall"],
        "convert_s": round(ours_s, 3),
        **{f"{s}_s": round(ours.timings.get(s, 0.0), 3) for s in stages},
        "convert_s_exact_dbscan": round(results["peer: exact DBSCAN on all points"][0], 3),
        "convert_s_voxel_remesh": round(results["peer: voxel remesh instead of alpha shapes"][0], 3),
        "all_watertight": all(o.collision.is_watertight for o in ours.objects if o.usable),
        "hammer_parts": max((v for k, v in parts.items() if "hammer" in k), default=0),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
