"""Benchmark: generating the embedded tabletop scene (target: default scene < 30 s on 2 cores).

    python bench/scene.py [--repeats 3]

Rows (median of `--repeats` runs each, same machine, same run):
  generate default    `splattwin.scene.generator`, 320x240, 15 + 5 views, no marker (all files written)
  generate marker     the same with the ArUco marker
  render view ss=N    one view: RGB (N x N supersampled, the default N; shadows) + GT depth/labels, no writing
  render view ss=1    one view without supersampling
  cast 80x60 open3d   ray-mesh intersection of 4800 pixel rays with the scene (Open3D/Embree, ours)
  cast 80x60 trimesh  the same rays with trimesh's pure-numpy ray-triangle intersector (the peer)
Last line: JSON with default_scene_s, marker_scene_s, per_view_ms, cast_open3d_ms, cast_trimesh_ms, target_s.
"""

from __future__ import annotations

import splattwin.runtime

# OpenMP passive waiting, headless MuJoCo, numba threads: before torch, numba or mujoco load (as the CLI)
splattwin.runtime.configure()

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    import trimesh

    from splattwin.capture.camera import Camera
    from splattwin.scene import SceneOptions, generate
    from splattwin.scene.cameras import scan_cameras
    from splattwin.scene.generator import build_scene, look_target

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        generate(Path(tmp) / "warm", SceneOptions(width=32, height=24, views=1, heldout=0), progress=False)  # JIT
        t_def = _median_time(lambda: generate(Path(tmp) / "d", SceneOptions(), progress=False), args.repeats)
        t_mk = _median_time(lambda: generate(Path(tmp) / "m", SceneOptions(marker=True), progress=False),
                            args.repeats)
    rows += [("generate default", t_def, "s"), ("generate marker", t_mk, "s")]

    opts = SceneOptions()
    objects, _, _, renderer = build_scene(opts)
    cams = scan_cameras(opts.views, opts.heldout, opts.width, opts.height, opts.fov_x, look_target(objects), 0)
    cam = cams[3]
    t_ssn = _median_time(lambda: renderer.render(cam, opts.supersample), max(5, args.repeats))
    t_ss1 = _median_time(lambda: renderer.render(cam, 1), max(5, args.repeats))
    rows += [(f"render view ss={opts.supersample}", t_ssn * 1e3, "ms"), ("render view ss=1", t_ss1 * 1e3, "ms")]

    small = Camera(K=cam.scaled(0.25).K, width=80, height=60, T_world_cam=cam.T_world_cam)
    rays = renderer.camera_rays(small, 1).reshape(-1, 6).astype(np.float64)
    world = trimesh.util.concatenate([s.mesh_world for s in renderer.surfaces])
    rmi = trimesh.ray.ray_triangle.RayMeshIntersector(world)
    t_o3d = _median_time(lambda: renderer.cast(rays), max(5, args.repeats))
    t_tm = _median_time(lambda: rmi.intersects_first(rays[:, :3], rays[:, 3:]), args.repeats)
    # same answers? (fraction of rays whose first hit agrees: hit/miss, and depth within 0.1 mm)
    o3d_t = renderer.cast(rays)["t"]
    tri = rmi.intersects_first(rays[:, :3], rays[:, 3:])
    locs, idx, _ = rmi.intersects_location(rays[:, :3], rays[:, 3:], multiple_hits=True)
    tm_t = np.full(len(rays), np.inf)
    for loc, i in zip(locs, idx):
        tm_t[i] = min(tm_t[i], float(np.linalg.norm(loc - rays[i, :3]) / np.linalg.norm(rays[i, 3:])))
    both = np.isfinite(o3d_t) & np.isfinite(tm_t)
    close = np.zeros(len(rays), bool)
    close[both] = np.abs(o3d_t[both] - tm_t[both]) < 1e-4
    agree = float(np.mean((np.isinf(o3d_t) & np.isinf(tm_t)) | close))
    rows += [("cast 80x60 open3d", t_o3d * 1e3, "ms"), ("cast 80x60 trimesh", t_tm * 1e3, "ms")]

    print(f"{'row':<22}{'median':>12}")
    for name, v, unit in rows:
        print(f"{name:<22}{v:>10.2f} {unit}")
    print(f"open3d vs trimesh: {t_tm / t_o3d:.0f}x faster; same first hit on {100 * agree:.1f} % of rays "
          f"({len(tri)} rays)")
    print(f"target: default scene < 30 s -> {'OK' if t_def < 30 else 'MISSED'}")
    print(json.dumps({"default_scene_s": round(t_def, 2), "marker_scene_s": round(t_mk, 2),
                      "per_view_ms": round(t_ssn * 1e3, 1), "cast_open3d_ms": round(t_o3d * 1e3, 2),
                      "cast_trimesh_ms": round(t_tm * 1e3, 1), "ray_agreement": round(agree, 4),
                      "target_s": 30, "repeats": args.repeats}))


if __name__ == "__main__":
    main()
