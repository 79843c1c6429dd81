"""Benchmark: the embedded scene as a robot-style capture in a z-down world becomes a z-up twin
(issue #16, target `zdown_fixed`).

    python bench/robot_capture.py [--size 320x240] [--views 16] [--iters 300] [--no-build] [--keep DIR]

The capture: `splattwin.scene.robot_capture` (D435-like intrinsics, 16-bit depth in mm, per-instance
masks, known poses in the scene's world rotated 180 degrees about x), as a BOP scene and as a TUM pose
list. Rows: format x up handling, "auto" (the check of `splattwin.poses.up`) side by side with its peer
"keep" (the poses used as given: the behaviour before #16). Per row: the up axis found, the rotation
applied, the angle between the table normal and +z in the output frame (RANSAC plane through the
back-projected depth, oriented towards the cameras), the largest camera-centre error against the
scene's z-up ground truth, and the poses stage's wall time (one run each: the geometry numbers are
deterministic, the times come from a machine shared with other work).

Unless --no-build, the BOP capture then goes through the whole `build` (known poses, its BOP masks,
--iters iterations) and the table normal is measured again on the twin itself: a RANSAC plane through
the trained background Gaussians (label 0), and twin.json's frame must say up +z with the rotation
recorded in T_twin_input. The build's mesh F1@5 mm against the scene's ground truth is reported too
(`robot_capture_f1_5mm_min`; run with --iters 3000, the default training length, for the README figure).

`zdown_fixed` is true when the twin (or, with --no-build, the poses stage's frame) has its table
normal within 1 degree of +z. Last line: one JSON object with `zdown_fixed` and the measured angles.
`measure_zdown(work_dir, ...)` returns the same figures for bench/real.py.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

TARGET_DEG = 1.0


def _normal_deg(points: np.ndarray, camera_centres: np.ndarray) -> float:
    """Degrees between +z and the dominant plane's normal (oriented towards the cameras)."""
    from splattwin.poses.table import fit_table_plane

    plane = fit_table_plane(points, camera_centres)
    return math.degrees(math.acos(float(np.clip(plane.normal[2], -1.0, 1.0))))


def _poses_row(capture: Path, up: str) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.scene.generator import build_scene, look_target
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, sweep_cameras

    t0 = time.perf_counter()
    ds = load_dataset(capture)
    res = estimate_poses(ds, PoseOptions(method="known", up=up, progress=False))
    wall = time.perf_counter() - t0
    scene = json.loads((capture / "scene.json").read_text())
    opts = SceneOptions.from_dict(scene["options"])
    rc = scene["robot_capture"]
    cap = RobotCaptureOptions.from_dict(rc)
    objects = build_scene(opts)[0]
    truth = sweep_cameras(cap, look_target(objects), opts.seed)
    centre_err = max(float(np.linalg.norm(f.camera.center - c.center)) for f, c in zip(res.frames, truth))
    chk = res.frame.up_check or {}
    found = chk.get("input_up", "-")
    return {"up_found": "(kept)" if found.startswith("kept") else found, "applied": chk.get("applied", "none"),
            "table_normal_deg": _normal_deg(res.points_xyz, np.array([c.center for c in res.cameras])),
            "centre_err_m": centre_err, "poses_s": wall}


def _twin_normal_deg(twin: Path) -> tuple[float, dict]:
    from splattwin.capture import load_dataset
    from splattwin.splat.gaussians import Gaussians

    g = Gaussians.load_ply(twin / "splat" / "point_cloud.ply")
    labels = np.load(twin / "semantics" / "labels.npy")
    means = g.means.detach().cpu().numpy() if hasattr(g.means, "detach") else np.asarray(g.means)
    cams = np.array([f.camera.center for f in load_dataset(twin / "poses" / "transforms.json", validate=False).frames])
    frame = json.loads((twin / "twin.json").read_text())["frame"]
    return _normal_deg(means[labels == 0], cams), frame


def measure_zdown(work_dir: str | Path, size: tuple[int, int] = (320, 240), views: int = 16, iters: int = 300,
                  build: bool = True, seed: int = 0) -> dict:
    """Write the robot-style captures under `work_dir`, run the rows (see module docstring) and, with
    `build`, the whole build of the BOP capture. Returns {"rows": [...], "zdown_fixed": bool,
    "zdown_table_normal_deg": float (twin, or poses frame without build), ...}."""
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    work = Path(work_dir)
    w, h = size
    sopts = SceneOptions(seed=seed, width=w, height=h, supersample=3)
    rows = []
    caps = {}
    for fmt in ("bop", "tum"):
        t0 = time.perf_counter()
        caps[fmt] = write_robot_capture(work / f"capture_{fmt}", sopts,
                                        RobotCaptureOptions(views=views, width=w, height=h, format=fmt), progress=False)
        gen_s = time.perf_counter() - t0
        for up in ("auto", "keep"):
            rows.append({"format": fmt, "up": up, **_poses_row(caps[fmt], up), "generate_s": gen_s})
    auto = [r for r in rows if r["up"] == "auto"]
    out: dict = {"rows": rows,
                 "zdown_poses_table_normal_deg": max(r["table_normal_deg"] for r in auto),
                 "zdown_keep_table_normal_deg": min(r["table_normal_deg"] for r in rows if r["up"] == "keep"),
                 "zdown_centre_err_m": max(r["centre_err_m"] for r in auto)}
    fixed = out["zdown_poses_table_normal_deg"] <= TARGET_DEG and all(r["up_found"] == "-z" for r in auto)
    out["zdown_table_normal_deg"] = out["zdown_poses_table_normal_deg"]
    if build:
        from splattwin.cli import main as cli

        twin = work / "twin"
        t0 = time.perf_counter()
        code = cli(["build", str(caps["bop"]), "--out", str(twin), "--poses", "known", "--masks",
                    str(caps["bop"] / "mask_visib"), "--iters", str(iters), "--no-frames"])
        out["build_s"] = time.perf_counter() - t0
        out["build_exit"] = code
        if code == 0:
            gm = twin / "geometry_metrics.json"
            if gm.is_file():  # the build scores its meshes against the scene's ground truth
                f1 = {k: round(float(v["f1"]), 4) for k, v in json.loads(gm.read_text()).items()}
                out["robot_capture_f1_5mm"] = f1
                out["robot_capture_f1_5mm_min"] = min(f1.values()) if f1 else None
            deg, frame = _twin_normal_deg(twin)
            out["zdown_twin_table_normal_deg"] = deg
            out["zdown_table_normal_deg"] = deg
            R = np.asarray(frame.get("T_twin_input") or np.eye(4))[:3, :3]
            fixed = (fixed and deg <= TARGET_DEG and frame.get("up") == "+z"
                     and np.allclose(R, np.diag([1.0, -1.0, -1.0])))
        else:
            fixed = False
    out["zdown_fixed"] = bool(fixed)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="320x240", help="capture size WxH (D435 intrinsics scaled to it)")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--iters", type=int, default=300, help="training iterations of the build")
    ap.add_argument("--no-build", action="store_true", help="poses stage only (no training)")
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temp folder)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    with tempfile.TemporaryDirectory(prefix="bench_robot_capture_") as tmp:
        work = args.keep or Path(tmp)
        res = measure_zdown(work, (w, h), args.views, args.iters, build=not args.no_build)
    print(f"robot-style capture, {args.views} views at {w}x{h}, world z down (machine shared; one run per row)")
    print(f"{'format':6} {'up':5} {'up found':8} {'rotation applied':24} {'table normal vs +z':>19} "
          f"{'centre err vs truth':>19} {'poses s':>8}")
    for r in res["rows"]:
        print(f"{r['format']:6} {r['up']:5} {r['up_found']:8} {r['applied'][:24]:24} {r['table_normal_deg']:17.3f} deg"
              f" {r['centre_err_m'] * 1000:16.3f} mm {r['poses_s']:8.2f}")
    if "build_exit" in res:
        tw = res.get("zdown_twin_table_normal_deg")
        print(f"build (BOP, known poses, BOP masks, {args.iters} iters): exit {res['build_exit']}, "
              f"{res['build_s']:.0f} s, twin table normal vs +z: "
              + (f"{tw:.3f} deg" if tw is not None else "n/a"))
        if res.get("robot_capture_f1_5mm"):
            print("mesh F1@5mm vs ground truth: " + ", ".join(f"{k} {v:.3f}" for k, v in res["robot_capture_f1_5mm"].items()))
    print(f"target: table normal within {TARGET_DEG} deg of +z -> zdown_fixed = {res['zdown_fixed']}")
    summary = {k: v for k, v in res.items() if k != "rows"}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
