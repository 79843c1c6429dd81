"""Benchmark of the geometry stage on the embedded scene (paper Table 5 + conversion time).

Two sources of labelled Gaussians:
  * synthetic (default): builds the small embedded scene, samples ~200k synthetic Gaussians with 3DGS
    artefacts on it (`splattwin.scene.synthetic_gaussians`) and lets the artefacts leak into the object
    labels as mask lifting would (`leak_labels`);
  * trained: `--twin-from RUN` (a `splattwin demo --out RUN` or `build --out RUN` folder:
    RUN/splat/point_cloud.ply, RUN/semantics/labels.npy + objects.json, the capture cameras in
    RUN/poses/transforms.json, GT in RUN/scene, or --scene), or `--splats PLY --labels NPY --scene DIR`
    [--objects JSON] [--cameras transforms.json]: the splats the trainer produced, with their real
    artefacts (centres inside the surface, unobserved sides, thick splats seen face-on, label bleed).
    With cameras, ours carves the meshes (`geometry.carving`, as the twin stage does) and the mesh
    table shows the same conversion without carving side by side. The capture's depth maps (RUN/poses/
    depth/, an RGB-D capture's) carve the meshes against the measured depth as well, as the twin stage
    does (`twin.build.capture_views`: a metric frame, frame.json beside the cameras file, and the 2D masks
    the build fused: semantics/masks2d of a prompt, --masks, else the scene's own); the mesh table then
    adds ours without the measured depth, and its title says whether that carving ran or why not.
Prints
  1. the four-configuration ablation per object on the cleaned Gaussian centres: Chamfer (mm),
     precision, recall, F1 @ 5 mm;
  2. the fidelity of the twin's meshes (visual mesh vs GT mesh, both sampled at 2 mm, as
     `splattwin demo` reports it), ours vs a baseline that meshes the splat centres without support fill;
  3. the conversion time (median of --runs, after one warm-up run) with per-stage times; in synthetic mode
     side by side with two peers: exact DBSCAN on all points and voxel remeshing instead of alpha shapes.
Last line: one JSON object (f1_5mm_min [centres], f1_5mm_mesh_min [meshes], chamfer_raw, chamfer_full,
convert_s, depth_carving [as twin.json config.depth_carving], ...).
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def _load_trained(args) -> tuple:
    """(Gaussians, labels [N], objects [(name, label, prompt)], GT meshes {name: Trimesh}, source text,
    the capture as the twin stage sees it (`twin.build.CaptureViews`) or None without a cameras file)."""
    from splattwin import io
    from splattwin.errors import InputError
    from splattwin.twin.groundtruth import load_scene_gt
    from splattwin.splat.gaussians import Gaussians

    run = args.twin_from
    if run is not None:
        ply, lab_path, obj_path = run / "splat/point_cloud.ply", run / "semantics/labels.npy", run / "semantics/objects.json"
        scene = args.scene or run / "scene"
        cameras_path = args.cameras or run / "poses/transforms.json"
    else:
        ply, lab_path, obj_path, scene = args.splats, args.labels, args.objects, args.scene
        cameras_path = args.cameras
        if lab_path is None or scene is None:
            raise InputError("--splats needs --labels and --scene", ply)
    for p in (ply, lab_path, scene / "scene.json"):
        if not Path(p).is_file():
            raise InputError("missing input of the trained-splat benchmark", p)
    g = Gaussians.load_ply(ply)
    labels = np.load(lab_path).astype(np.int64).reshape(-1)
    if len(labels) != len(g):
        raise InputError(f"{len(labels)} labels for {len(g)} Gaussians in {ply}", lab_path)
    scene_objects, meshes = load_scene_gt(scene)
    objects = [tuple(o) for o in io.read_json(obj_path)] if obj_path is not None and Path(obj_path).is_file() else scene_objects
    views = None
    if cameras_path is not None and Path(cameras_path).is_file():
        views = _capture_views(Path(cameras_path), run, scene)
    return g, labels, objects, meshes, f"trained:{ply}", views


def _capture_views(cameras_path: Path, run: Path | None, scene: Path):
    """The capture's cameras, 2D masks and measured depth as the twin stage gives them to `convert`
    (`twin.build.capture_views`): the frame of frame.json beside the cameras file (none: unscaled, so no
    measured depth), the refined poses of RUN/splat, and with --twin-from the masks the build fused."""
    from splattwin.poses.twin_frame import TwinFrame, frame_beside
    from splattwin.splat.refined_poses import path_in
    from splattwin.twin.build import capture_views

    frame = frame_beside(cameras_path) or TwinFrame()
    masks = _build_masks(run, cameras_path, scene) if run is not None else None
    return capture_views(cameras_path.parent, cameras_path, frame, masks=masks,
                         refined_poses=path_in(run / "splat") if run is not None else None)


def _build_masks(run: Path, cameras_path: Path, scene: Path):
    """The 2D masks the build of RUN fused, as its twin stage reads them (`pipeline.build._stage_masks`):
    a prompt's saved RUN/semantics/masks2d, the build's --masks (twin.json config.build), else the scene
    folder's own (an embedded scene's noisy masks of the training views, a robot-style capture's); None
    with a note when there are none (then no measured-depth carving: depth is trusted inside masks only)."""
    from splattwin import io
    from splattwin.capture import load_dataset
    from splattwin.errors import InputError
    from splattwin.semantics.masks import load_masks
    from splattwin.semantics.options import SemanticsOptions
    from splattwin.semantics.stage import load_stage_masks

    saved = run / "semantics" / "masks2d"
    if (saved / "masks.json").is_file():
        return load_masks(saved)
    twin_json = run / "twin.json"
    built = io.read_json(twin_json).get("config", {}).get("build", {}) if twin_json.is_file() else {}
    given = (built.get("semantics") or {}).get("masks")
    try:
        frames = load_dataset(cameras_path, validate=False, require_images=False).frames
        return load_stage_masks(SemanticsOptions(masks=Path(given) if given else None), frames, scene)[0]
    except InputError as e:
        print(f"no 2D masks for the measured-depth carving: {e}")
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000, help="approximate number of Gaussians (synthetic)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--scene", type=Path, default=None, help="existing scene folder (default: generate one, or RUN/scene)")
    ap.add_argument("--twin-from", type=Path, default=None, help="a `splattwin demo --out` folder: its trained splats")
    ap.add_argument("--splats", type=Path, default=None, help="trained splat PLY (with --labels and --scene)")
    ap.add_argument("--labels", type=Path, default=None, help="labels.npy, one int per Gaussian (0 = background)")
    ap.add_argument("--objects", type=Path, default=None, help="objects.json [[name, label, prompt], ...] (default: the scene's)")
    ap.add_argument("--cameras", type=Path, default=None,
                    help="transforms.json of the capture (twin frame), for the meshes' carving (default: RUN/poses/)")
    args = ap.parse_args(argv)

    from rich.console import Console
    from rich.table import Table

    from splattwin.geometry.convert import CONFIGS, ablation, conversion_fidelity, convert
    from splattwin.geometry.options import GeometryOptions
    from splattwin.scene import SceneOptions, generate, synthetic_gaussians
    from splattwin.scene.synthetic import leak_labels
    from splattwin.twin.build import depth_carving_record
    from splattwin.twin.groundtruth import load_scene_gt

    con = Console(width=150)
    tmp = tempfile.TemporaryDirectory()
    trained = args.twin_from is not None or args.splats is not None
    views = None
    if trained:
        g, labels, objects, meshes, source, views = _load_trained(args)
        con.print(f"{source}: {len(g)} Gaussians, {len(objects)} objects, "
                  f"{len(views.cameras) if views and views.cameras else 'no'} cameras")
    else:
        scene = args.scene or generate(Path(tmp.name) / "scene", SceneOptions(seed=0, width=160, height=120, views=8,
                                                                              heldout=3), progress=False)
        # density: object surface Gaussians per m^2 (table gets half); ~32k Gaussians at 40000 on this scene
        g, labels_gt = synthetic_gaussians(scene, seed=0, density=40000.0 * args.gaussians / 32000.0)
        objects, meshes = load_scene_gt(scene)
        labels = leak_labels(g, labels_gt, {lab: meshes[n].bounds for n, lab, _ in objects})
        source = "synthetic"
        con.print(f"scene {scene}: {len(g)} Gaussians, {len(objects)} objects, "
                  f"{int((labels != labels_gt).sum())} artefacts leaked into object labels")
    objects = [o for o in objects if o[0] in meshes]
    cameras = views.cameras if views is not None else None
    # what the twin stage passes besides the cameras: the objects' masks and the capture's measured depth
    seen = {} if views is None else {"masks": views.silhouettes, "measured": views.measured}

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

    ours_name = "ours (voxel-weighted DBSCAN, alpha shapes)"
    peers = {ours_name: GeometryOptions()}
    if not trained:
        peers["peer: exact DBSCAN on all points"] = GeometryOptions(dbscan_voxel=0.0)
        peers["peer: voxel remesh instead of alpha shapes"] = GeometryOptions(use_alpha=False)
    results = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        convert(g, labels, objects, GeometryOptions(), progress=False, cameras=cameras, **seen)  # warm-up: imports, JIT
        for name, opts in peers.items():
            runs = []
            for _ in range(args.runs if name == ours_name else 1):
                t0 = time.perf_counter()
                conv = convert(g, labels, objects, opts, progress=False, cameras=cameras, **seen)
                if views is not None and views.depth_skipped is not None:
                    conv.depth_skipped = views.depth_skipped   # why not, as build_twin records it
                runs.append((time.perf_counter() - t0, conv))
            runs.sort(key=lambda r: r[0])
            results[name] = runs[len(runs) // 2]
        # baseline meshing: the splat centres alone, no fill under the seen surface (the path before issue 6)
        base = convert(g, labels, objects, GeometryOptions(densify=False, fill_to_support=False), progress=False)
        uncarved = convert(g, labels, objects, GeometryOptions(carve=False), progress=False) if cameras else None
        no_depth = None   # ours with the cameras and masks but not the measured depth: what that carving adds
        if views is not None and views.measured is not None:
            no_depth = convert(g, labels, objects, GeometryOptions(), progress=False, cameras=cameras,
                               masks=views.silhouettes)
    ours_s, ours = results[ours_name]
    depth = depth_carving_record(ours) if views is not None else None
    fid = conversion_fidelity(ours, meshes)
    fid_base = conversion_fidelity(base, meshes)
    fid_unc = conversion_fidelity(uncarved, meshes) if uncarved is not None else None
    fid_nod = conversion_fidelity(no_depth, meshes) if no_depth is not None else None
    tm = Table(title="Twin meshes vs GT (visual mesh and GT both sampled at 2 mm; threshold 5 mm)"
               + ("" if depth is None else f"; measured-depth carving: {_carving_said(depth)}"))
    tm.add_column("object")
    cols = {"baseline: centres, no support fill": fid_base}
    if fid_unc is not None:
        cols["ours without carving"] = fid_unc
    if fid_nod is not None:
        cols["ours without measured depth"] = fid_nod
    cols["ours" + (f" (carved from {len(cameras)} cameras"
                   + (" and their measured depth" if depth and depth["used"] else "") + ")" if cameras else "")] = fid
    for c in cols:
        tm.add_column(f"{c}\nCD mm / P / R / F1", justify="right")
    for n, _, _ in objects:
        tm.add_row(n, *[f"{f[n].chamfer * 1e3:.2f} / {f[n].precision:.3f} / {f[n].recall:.3f} / {f[n].f1:.3f}"
                        for f in cols.values()])
    con.print(tm)
    stages = ("filter", "cluster", "mesh", "carve", "decompose", "background")
    t2 = Table(title=f"Conversion of {len(g)} Gaussians ({args.runs} runs for ours, median; 1 run per peer), seconds")
    t2.add_column("method")
    for s_ in (*stages, "total"):
        t2.add_column("carve\n(in mesh)" if s_ == "carve" else s_, justify="right")
    t2.add_column("usable / watertight")
    for name, (sec, conv) in results.items():
        ok = sum(o.usable for o in conv.objects)
        wt = sum(bool(o.usable and o.collision.is_watertight) for o in conv.objects)
        t2.add_row(name, *[f"{conv.timings.get(s_, 0.0):.2f}" for s_ in stages], f"{sec:.2f}", f"{ok}/{wt} of {len(conv.objects)}")
    con.print(t2)
    parts = {o.name: len(o.parts) for o in ours.objects}
    con.print("convex parts: " + ", ".join(f"{k} {v}" for k, v in parts.items()))
    out = {
        "source": source,
        "n_gaussians": len(g),
        "f1_5mm_min": min(ab["full"][n].f1 for n, _, _ in objects),
        "chamfer_raw": mean["raw"]["chamfer"], "chamfer_attribute": mean["attribute"]["chamfer"],
        "chamfer_cluster": mean["cluster"]["chamfer"], "chamfer_full": mean["full"]["chamfer"],
        "precision_full": mean["full"]["precision"], "recall_full": mean["full"]["recall"],
        "f1_5mm_mesh_min": min(f.f1 for f in fid.values()),
        "f1_5mm_mesh": {n: round(f.f1, 4) for n, f in fid.items()},
        "chamfer_mesh": float(np.mean([f.chamfer for f in fid.values()])),
        "f1_5mm_mesh_min_baseline": min(f.f1 for f in fid_base.values()),
        **({"f1_5mm_mesh_min_uncarved": min(f.f1 for f in fid_unc.values()),
            "f1_5mm_mesh_uncarved": {n: round(f.f1, 4) for n, f in fid_unc.items()}} if fid_unc is not None else {}),
        "carve_cameras": len(cameras) if cameras else 0,
        **({"depth_carving": depth} if depth is not None else {}),
        **({"f1_5mm_mesh_no_measured_depth": {n: round(f.f1, 4) for n, f in fid_nod.items()}} if fid_nod else {}),
        "convert_s": round(ours_s, 3),
        **{f"{s_}_s": round(ours.timings.get(s_, 0.0), 3) for s_ in stages},
        "all_watertight": all(o.collision.is_watertight for o in ours.objects if o.usable),
        "all_usable": all(o.usable for o in ours.objects),
        "hammer_parts": max((v for k, v in parts.items() if "hammer" in k), default=0),
    }
    if not trained:
        out["convert_s_exact_dbscan"] = round(results["peer: exact DBSCAN on all points"][0], 3)
        out["convert_s_voxel_remesh"] = round(results["peer: voxel remesh instead of alpha shapes"][0], 3)
    print(json.dumps(out))
    return 0


def _carving_said(record: dict) -> str:
    """The mesh table's word on the measured-depth carving (twin.json config.depth_carving): ran, with how many
    of the carved objects' points it dropped, or skipped and why."""
    if not record["used"]:
        return f"skipped ({record['skipped']})"
    objs = record.get("objects", {})
    return (f"ran ({sum(o['dropped'] for o in objs.values())} of {sum(o['points'] for o in objs.values())} points "
            f"dropped over {len(objs)} objects)")


if __name__ == "__main__":
    sys.exit(main())
