"""Benchmark: visibility-aware semantic fusion vs the naive baseline on the embedded scene.

Data: the default embedded scene (320x240, 15 training + 5 held-out views, seed 0) with its simulated
noisy open-vocabulary masks; Gaussians from `splattwin.scene.synthetic_gaussians` (GT surfaces with
haze / floater / needle artefacts) at ~200k, or a trained PLY via --splats. Fusion uses the training
views only; held-out views are only rendered and scored.

Reported (paper definitions, `splattwin.semantics.metrics`): 2D mIoU of rendered label maps vs GT label
images (train / held-out), for the fusion, the naive baseline and an "oracle" (the GT labels of the same
Gaussians rendered the same way: the ceiling any labelling can reach with this model and renderer);
3D projection consistency; ghost index; the kappa sweep; fusion time (median of --repeats runs) for
4 objects x 15 views x ~200k Gaussians, with the point z-buffer depth and with the rasterizer's depth.

Usage: python bench/semantics.py [--scene DIR] [--splats PLY] [--n 200000] [--repeats 3] [--out DIR]
The last line printed is one JSON object.
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=None, help="generated scene (default: generate into a temp dir)")
    ap.add_argument("--splats", type=Path, default=None, help="trained 3DGS PLY of the scene (default: synthetic)")
    ap.add_argument("--n", type=int, default=200_000, help="synthetic Gaussians (about)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write label-map pictures here")
    ap.add_argument("--no-splat-depth", action="store_true", help="skip the (slow) rasterizer-depth fusion run")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")

    from splattwin.capture import load_dataset
    from splattwin.semantics.fusion import FusionOptions, View, fuse, naive_fusion, splat_normals
    from splattwin.semantics.masks import MaskSet, read_mask_image, scene_masks
    from splattwin.semantics.metrics import ghost_index, miou, projection_consistency
    from splattwin.semantics.label_render import PointDepth, SplatDepth, colorize, render_label_maps

    tmp = tempfile.TemporaryDirectory()
    scene = args.scene
    if scene is None:
        from splattwin.scene import SceneOptions, generate

        t = time.perf_counter()
        scene = generate(Path(tmp.name) / "scene", SceneOptions(seed=0), progress=False)
        print(f"generated the embedded scene in {time.perf_counter() - t:.1f} s")
    ds = load_dataset(scene)
    ms = scene_masks(scene, "noisy")
    if args.splats is not None:
        from splattwin.splat.gaussians import Gaussians

        g, gt, source = Gaussians.load_ply(args.splats), None, f"trained PLY {args.splats.name}"
    else:
        from splattwin.scene.synthetic import scene_gaussians

        g, gt = scene_gaussians(scene, n=args.n)
        source = "synthetic_gaussians (GT surfaces + haze/floaters/needles)"
    N = len(g.means)
    tr = [View(f.name, f.camera) for f in ds.train()]
    ho, trf = ds.heldout(), ds.train()
    labs = sorted(ms.objects)
    normals = splat_normals(g.quats, g.scales)
    print(f"data: {source}, {N} Gaussians, {len(tr)} training + {len(ho)} held-out views "
          f"{tr[0].camera.width}x{tr[0].camera.height}, objects: {', '.join(ms.objects[k] for k in labs)}")

    # -- timing: 4 objects x 15 views ----------------------------------------------------------
    four = MaskSet(objects={k: ms.objects[k] for k in labs[:4]}, sizes=dict(ms.sizes),
                   masks={v: {k: m for k, m in d.items() if k in labs[:4]} for v, d in ms.masks.items()},
                   scores={v: {k: s for k, s in d.items() if k in labs[:4]} for v, d in ms.scores.items()})
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        fuse(g.means, tr, four, normals=normals)
        times.append(time.perf_counter() - t)
    fusion_s = statistics.median(times)
    t = time.perf_counter()
    naive_fusion(g.means, tr, four)
    naive_s = time.perf_counter() - t
    splat_s = None
    res_splat = None
    if not args.no_splat_depth:
        try:
            t = time.perf_counter()
            res_splat = fuse(g.means, tr, four, depth_renderer=SplatDepth(g), normals=normals)
            splat_s = time.perf_counter() - t
        except Exception as e:  # noqa: BLE001 - report, do not fail the bench
            print(f"rasterizer depth unavailable: {e}")

    # -- quality: all objects -------------------------------------------------------------------
    res = fuse(g.means, tr, ms, normals=normals)
    naive = naive_fusion(g.means, tr, ms)
    gts = {"train": [read_mask_image(f.label_path) for f in trf], "heldout": [read_mask_image(f.label_path) for f in ho]}
    frames = {"train": trf, "heldout": ho}

    # Label maps of trained splats are rendered with the rasterizer (their centres are too sparse for a
    # point z-buffer); synthetic Gaussians are dense surface samples, so the point render is the default.
    main_renderer = "splat" if args.splats is not None else "points"

    def score(labels, renderer=None):
        renderer = renderer or main_renderer
        return {s: miou(render_label_maps(g, labels, [f.camera for f in frames[s]], max(labs), renderer=renderer),
                        gts[s], labs) for s in frames}

    print(f"label maps for the headline mIoU: {main_renderer} renderer")
    q = {"fusion": score(res.labels), "naive": score(naive)}
    if gt is not None:
        q["oracle (GT labels)"] = score(gt)
    try:
        other = "points" if main_renderer == "splat" else "splat"
        q[f"fusion, {other} label maps"] = score(res.labels, other)
        q[f"naive, {other} label maps"] = score(naive, other)
    except Exception as e:  # noqa: BLE001
        print(f"rasterizer label maps unavailable: {e}")
    cons = projection_consistency(g.means, res.labels, tr, ms)
    cons_naive = projection_consistency(g.means, naive, tr, ms)
    cons_oracle = projection_consistency(g.means, gt, tr, ms) if gt is not None else None
    depths = PointDepth(g.means)(None, [v.camera for v in tr])
    cons_vis = projection_consistency(g.means, res.labels, tr, ms, depths=depths)
    cons_vis_naive = projection_consistency(g.means, naive, tr, ms, depths=depths)
    ghost = ghost_index(res)

    print()
    print(f"{'labels':28s} {'mIoU train':>10s} {'mIoU held-out':>14s}")
    for name, d in q.items():
        print(f"{name:28s} {d['train']:10.3f} {d['heldout']:14.3f}")
    print()
    print(f"3D projection consistency (paper: all in-image views): fusion {cons:.2f} %, naive {cons_naive:.2f} %"
          + (f", GT labels {cons_oracle:.2f} % (occlusions and mask misses cap it)" if cons_oracle is not None else ""))
    print(f"3D projection consistency (visible views only):        fusion {cons_vis:.2f} %, naive {cons_vis_naive:.2f} %")
    print(f"ghost index (kappa 1.5): {ghost:.2f} %")
    if gt is not None:
        print(f"{'object':16s} {'precision':>9s} {'recall':>7s} {'naive prec':>10s} {'naive rec':>9s}")
        for k in labs:
            pr = lambda lab: ((gt[lab == k] == k).mean(), (lab[gt == k] == k).mean())  # noqa: E731
            a, b = pr(res.labels), pr(naive)
            print(f"{ms.objects[k]:16s} {a[0]:9.3f} {a[1]:7.3f} {b[0]:10.3f} {b[1]:9.3f}")

    print()
    print(f"{'kappa':>6s} {'tau':>7s} {'labelled':>9s} {'consistency %':>14s} {'ghost index %':>14s} {'mIoU held-out':>14s}")
    sweep = {}
    for kappa in (2.0, 1.8, 1.5, 1.2, 1.0):
        r = fuse(g.means, tr, ms, FusionOptions(kappa=kappa), normals=normals)
        c, gi = projection_consistency(g.means, r.labels, tr, ms), ghost_index(r)
        m = score(r.labels)["heldout"]
        sweep[str(kappa)] = {"consistency": c, "ghost_index": gi, "miou_heldout": m}
        print(f"{kappa:6.1f} {'N/' + str(kappa):>7s} {int((r.labels > 0).sum()):9d} {c:14.2f} {gi:14.2f} {m:14.3f}")

    print()
    print(f"fusion time, 4 objects x {len(tr)} views x {N} Gaussians (median of {args.repeats}): "
          f"{fusion_s:.2f} s with point z-buffer depth; naive {naive_s:.2f} s"
          + (f"; {splat_s:.2f} s with rasterizer depth (1 run)" if splat_s is not None else ""))
    if res_splat is not None:
        print(f"  rasterizer-depth fusion labels agree with point-depth labels on "
              f"{(res_splat.labels == fuse(g.means, tr, four, normals=normals).labels).mean() * 100:.1f} % of Gaussians")

    if args.out is not None:
        from splattwin import io
        from splattwin.capture import load_image

        maps = render_label_maps(g, res.labels, [f.camera for f in ho], max(labs))
        nmaps = render_label_maps(g, naive, [f.camera for f in ho], max(labs))
        for f, m, nm, G in zip(ho, maps, nmaps, gts["heldout"]):
            img = load_image(f.image_path)
            row = np.concatenate([colorize(nm, {}, img, legend=False), colorize(m, {}, img, legend=False),
                                  colorize(G.astype(np.int32), ms.objects, img)], axis=1)
            io.write_image(args.out / f"{f.name}_naive_fusion_gt.png", row)
        print(f"pictures (naive | fusion | GT) in {args.out}")

    out = {"data": source, "n_gaussians": N, "views": len(tr),
           "miou_heldout": q["fusion"]["heldout"], "miou_train": q["fusion"]["train"],
           "miou_naive": q["naive"]["heldout"], "miou_naive_train": q["naive"]["train"],
           "miou_oracle": q.get("oracle (GT labels)", {}).get("heldout"),
           "label_maps": main_renderer,
           "miou_heldout_splat_maps": (q["fusion"] if main_renderer == "splat"
                                       else q.get("fusion, splat label maps", {})).get("heldout"),
           "consistency": cons, "consistency_naive": cons_naive, "consistency_oracle": cons_oracle,
           "consistency_visible": cons_vis,
           "consistency_visible_naive": cons_vis_naive, "ghost_index": ghost,
           "kappa_sweep": sweep, "fusion_s": fusion_s, "fusion_s_splat_depth": splat_s, "naive_s": naive_s}
    print(json.dumps(out))
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
