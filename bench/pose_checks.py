"""Benchmark: the intrinsics and latency checks of `splattwin.poses.hand_eye_check` on the embedded scene
written as a robot-style TUM capture (`splattwin.scene.robot_capture`, 320x240, f = 307.5 px).

    python bench/pose_checks.py [--views 16] [--seeds 3] [--keep DIR]

Rows (known poses, `estimate_poses` with --poses.method known, the checks on):
- focal: camera.yaml's fx, fy scaled by 1.00, 1.01, 1.02, 1.05 (and 0.98); exact poses;
- principal point: camera.yaml's cx or cy moved by 2, 5, 10 px, both by (-7, +6) px, and cx by 5 px with fx, fy
  x1.02; exact poses (the estimated offset should be minus the one applied);
- pose noise: every pose 3 mm / 0.3 deg rms off (random per view); a poor hand-eye: every pose times one
  fixed 1 cm / 2 deg error (what T_base_ee @ a wrong T_ee_cam gives), both with the true intrinsics, over
  --seeds seeds: the false-alarm rate of the intrinsics check;
- latency: a moving arm (`moving_arm_tum`, one view per second: 40 ms ~ 3 mm / 0.3 deg, or per 0.5 s), images
  stamped 0, 20, 40, 60 ms late; the estimated offset should be minus that.
Per row: the intrinsics check's focal scale (the true one is 1 / the scale applied), its sigma and verdict;
the principal-point offset (px, full size), its sigma and verdict, and the error without and with it;
the latency check's offset, sigma and verdict; the pose consistency (px). Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def _row(folder: Path) -> dict:
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    t0 = time.perf_counter()
    res = estimate_poses(load_dataset(folder), PoseOptions(method="known", progress=False, depth_points=False,
                                                          triangulate=False, up="keep"))
    ic, lc, pc = (res.stats.get(k) or {} for k in ("intrinsics_check", "latency_check", "pose_consistency"))
    return {"focal_scale": ic.get("focal_scale"), "focal_sigma": ic.get("focal_scale_sigma"),
            "focal_verdict": ic.get("verdict"), "offset_ms": lc.get("time_offset_ms"),
            "offset_sigma_ms": lc.get("time_offset_sigma_ms"), "latency_verdict": lc.get("verdict"),
            "consistency_px": pc.get("sampson_median_px"), "floor_px": pc.get("sampson_floor_px"),
            "focal_err_given": ic.get("error_px_given"), "focal_err_best": ic.get("error_px_best"),
            "focal_median_best": ic.get("sampson_median_px_best"),
            "pp_offset_px": ic.get("principal_point_offset_px"), "pp_sigma_px": ic.get("principal_point_sigma_px"),
            "pp_verdict": ic.get("principal_point_verdict"), "pp_err_given": ic.get("principal_point_error_px_given"),
            "pp_err_best": ic.get("principal_point_error_px_best"), "pp_turn_err": ic.get("principal_point_turn_error_px"),
            "focal_joint": ic.get("focal_scale_joint"), "focal_joint_sigma": ic.get("focal_scale_joint_sigma"),
            "s": round(time.perf_counter() - t0, 2)}


def _edit_poses(folder: Path, fn) -> None:
    from splattwin.capture import tum

    poses = tum.read_pose_list(folder / "groundtruth.txt")
    tum.write_pose_list(folder / "groundtruth.txt", [(k, fn(i, T)) for i, (k, T) in enumerate(poses)])


def _scale_focal(folder: Path, s: float) -> None:
    import yaml

    p = folder / "camera.yaml"
    d = yaml.safe_load(p.read_text())
    d["fx"], d["fy"] = d["fx"] * s, d["fy"] * s
    p.write_text(yaml.safe_dump(d))


def _shift_principal_point(folder: Path, dx: float, dy: float) -> None:
    import yaml

    p = folder / "camera.yaml"
    d = yaml.safe_load(p.read_text())
    d["cx"], d["cy"] = d["cx"] + dx, d["cy"] + dy
    p.write_text(yaml.safe_dump(d))


def _rot(rng, deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    ax = rng.normal(size=3)
    return Rotation.from_rotvec(ax / np.linalg.norm(ax) * np.radians(deg)).as_matrix()


def main() -> None:
    from splattwin.scene.options import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, moving_arm_tum, write_robot_capture

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None)
    ap.add_argument("--cases", default="", help="run only the cases whose name contains this")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_pose_checks_") as tmp:
        work = args.keep or Path(tmp)
        base = write_robot_capture(work / "base", SceneOptions(width=320, height=240, supersample=1),
                                   RobotCaptureOptions(views=args.views, width=320, height=240, format="tum"),
                                   progress=False)
        rows = []

        def run(name: str, edit) -> None:
            if args.cases not in name:
                return
            d = work / name
            shutil.rmtree(d, ignore_errors=True)
            shutil.copytree(base, d)
            edit(d)
            r = {"case": name, **_row(d)}
            rows.append(r)
            print(json.dumps(r), flush=True)

        for s in (1.0, 1.01, 1.02, 1.05, 0.98):
            run(f"focal_x{s:g}", lambda d, s=s: _scale_focal(d, s))
        for d in (2, 5, 10):
            run(f"pp_x{d:+d}", lambda f, d=d: _shift_principal_point(f, d, 0.0))
            run(f"pp_y{d:+d}", lambda f, d=d: _shift_principal_point(f, 0.0, d))
        run("pp_x-7_y+6", lambda f: _shift_principal_point(f, -7.0, 6.0))
        run("pp_x+5_focal_x1.02", lambda f: (_shift_principal_point(f, 5.0, 0.0), _scale_focal(f, 1.02)))
        for seed in range(args.seeds):
            rng = np.random.default_rng([seed, 7])

            def noise(i, T, rng=rng):
                T = T.copy()
                from scipy.spatial.transform import Rotation

                T[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.3) / np.sqrt(3), 3)).as_matrix() @ T[:3, :3]
                T[:3, 3] += rng.normal(0, 3e-3 / np.sqrt(3), 3)
                return T
            run(f"pose_noise_3mm_0.3deg_seed{seed}", lambda d: _edit_poses(d, noise))
            X = np.eye(4)
            X[:3, :3] = _rot(rng, 2.0)
            v = rng.normal(size=3)
            X[:3, 3] = v / np.linalg.norm(v) * 0.01
            run(f"hand_eye_1cm_2deg_seed{seed}", lambda d, X=X: _edit_poses(d, lambda i, T: T @ X))
        for period in (1.0, 0.5):
            for ms in (0, 20, 40, 60):
                run(f"latency_{ms}ms_period{period:g}s", lambda d, p=period, ms=ms: moving_arm_tum(d, p, 100.0, ms / 1000.0))
        fa = [r for r in rows if r["case"].startswith(("pose_noise", "hand_eye"))]
        # every run but the principal-point ones has the true principal point
        pp_ok = [r for r in rows if not r["case"].startswith("pp_")]
        out = {"focal_false_alarms": sum(r["focal_verdict"] == "warn" for r in fa), "focal_no_fault_runs": len(fa),
               "pp_false_alarms": sum(r["pp_verdict"] == "warn" for r in pp_ok), "pp_no_fault_runs": len(pp_ok),
               "rows": rows}
        print(json.dumps({k: v for k, v in out.items() if k != "rows"}))


if __name__ == "__main__":
    main()
