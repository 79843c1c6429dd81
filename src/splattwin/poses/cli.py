"""Sub-commands of the poses stage: `splattwin poses INPUT OUT [...]`."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from splattwin.errors import InputError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    p = sub.add_parser(
        "poses",
        help="camera poses (SfM / known / robot) and a metric table frame -> posed nerfstudio dataset",
        description="Estimate camera poses for a capture and define the twin frame. Writes OUT/transforms.json "
                    "(nerfstudio, + points3D.ply), OUT/frame.json (frame source, scaled, scale uncertainty), "
                    "OUT/poses_report.json and OUT/cameras.png. The frame comes from, in order: SfM aligned to "
                    "robot poses, an ArUco marker, the table plane + a known length, robot/known poses; "
                    "otherwise the table plane, marked 'unscaled' (robot stages refuse unscaled twins).",
    )
    p.add_argument("input", type=Path, help="dataset: image folder, video, transforms.json, COLMAP model, cameras.json, BOP scene, "
                                            "TUM pose list + intrinsics")
    p.add_argument("out", type=Path, help="output folder")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sfm", action="store_true", help="structure from motion even if the dataset has poses")
    src.add_argument("--known", action="store_true", help="use the dataset's poses as they are (assumed metric)")
    p.add_argument("--robot-poses", type=Path, metavar="FILE",
                   help="JSON/YAML list of end-effector poses T_base_ee per image (4x4, or position + quat_xyzw/quat_wxyz); "
                        "alone: exact cameras in the robot base frame; with --sfm: SfM aligned to them (Umeyama)")
    p.add_argument("--hand-eye", type=Path, metavar="FILE", help="hand-eye calibration T_ee_cam (JSON/YAML)")
    p.add_argument("--marker-size", type=float, metavar="M", help="ArUco marker side in metres: marker frame + scale")
    p.add_argument("--marker-dict", default="DICT_4X4_50", help="ArUco dictionary (default DICT_4X4_50)")
    p.add_argument("--marker-id", type=int, default=0, help="ArUco marker id (default 0)")
    p.add_argument("--known-length", metavar="SPEC",
                   help="metric scale for the table frame: camera_height=M (mean camera height above the table), "
                        "camera_height@IMAGE=M, or baseline@IMG_A,IMG_B=M (distance between two camera centres)")
    p.add_argument("--intrinsics", metavar="fx,fy,cx,cy",
                   help="known pinhole intrinsics in pixels (kept fixed), or 'dataset' to use the dataset's")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   choices=["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"],
                   help="camera model when SfM estimates the intrinsics (default SIMPLE_RADIAL)")
    p.add_argument("--per-image-intrinsics", action="store_true", help="one camera per image (default: shared)")
    p.add_argument("--matcher", default="auto", choices=["auto", "exhaustive", "sequential", "retrieval"],
                   help="feature matching (auto: exhaustive for <= 50 images; beyond, sequential + loop closure "
                        "for video frames, vocabulary-tree retrieval for unordered photos)")
    p.add_argument("--max-image-size", type=int, default=1600, metavar="PX",
                   help="SfM extracts features from images resized to this longest side (default 1600; 0: full size)")
    p.add_argument("--max-features", type=int, default=4096, metavar="N",
                   help="SIFT features per image (default 4096)")
    p.add_argument("--no-retry", action="store_true",
                   help="no automatic SfM retries when images fail to register")
    p.add_argument("--threads", type=int, default=0, metavar="N", help="CPU threads for SfM (default 0: all cores)")
    p.add_argument("--no-triangulate", action="store_true",
                   help="known/robot poses without a point cloud: do not triangulate points from the images")
    p.add_argument("--min-registered", type=int, metavar="N",
                   help="fail unless SfM registers at least N images (default: all but 3, at least 3)")
    p.add_argument("--work-dir", type=Path, help="SfM scratch folder, re-used to resume (default OUT/sfm)")
    p.add_argument("--max-frames", type=int, help="use at most N frames (evenly spaced; videos: best N)")
    p.add_argument("--no-depth-points", action="store_true", help="do not back-project depth images")
    p.add_argument("--up", default="auto", choices=("auto", "keep", "+z", "-z", "+y", "-y", "+x", "-x"),
                   help="known poses: the world axis that points up (--up=+z, --up=-z, +y, -y, +x, -x); auto (default) finds it from the "
                        "cameras and the table plane and rotates z-down/y-up worlds to z up (recorded in frame.json), "
                        "stopping when unclear; keep = use the poses as they are")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_run)


def parse_intrinsics(text: str | None) -> str | tuple[float, float, float, float] | None:
    if text is None:
        return None
    if text.strip() == "dataset":
        return "dataset"
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError as e:
        raise InputError(f"--intrinsics {text!r}: expected fx,fy,cx,cy in pixels or 'dataset'") from e
    if len(vals) != 4 or vals[0] <= 0 or vals[1] <= 0:
        raise InputError(f"--intrinsics {text!r}: expected four numbers fx,fy,cx,cy with positive focal lengths")
    return vals  # type: ignore[return-value]


def print_sfm_summary(stats: dict) -> None:
    """Attempts (retries) and timings of an SfM or triangulation run, as plain lines."""
    attempts = stats.get("attempts") or []
    if len(attempts) > 1:
        print("  SfM attempts: " + "; ".join(f"{a['name']} {a['registered']}/{stats.get('total')}" for a in attempts))
    t = stats.get("timings") or {}
    if t:
        parts = [f"{k} {v:.1f} s" for k, v in t.items() if k not in ("cpu", "retries")]
        print(f"  SfM time: {', '.join(parts)} (peak memory {stats.get('peak_rss_gib', 0):.2f} GiB, "
              f"matcher {stats.get('matcher', '?')})")
    tri = stats.get("triangulation")
    if tri:
        print(f"  points from known poses: {tri.get('points', 0)}" + (f" ({tri['error']})" if "error" in tri else ""))


def _run(args: argparse.Namespace) -> int:
    from splattwin.capture import load_dataset
    from splattwin.poses.estimate import PoseOptions, estimate_poses
    from splattwin.poses.table import KnownLength

    if args.min_registered is not None and args.min_registered < 2:
        raise InputError(f"--min-registered must be >= 2, got {args.min_registered}")
    method = "sfm" if args.sfm else "known" if args.known else "auto"
    opts = PoseOptions(
        method=method, robot_poses=args.robot_poses, hand_eye=args.hand_eye, marker_size=args.marker_size,
        marker_dict=args.marker_dict, marker_id=args.marker_id,
        known_length=KnownLength.parse(args.known_length) if args.known_length else None,
        intrinsics=parse_intrinsics(args.intrinsics), camera_model=args.camera_model,
        shared_intrinsics=not args.per_image_intrinsics, matcher=args.matcher, min_registered=args.min_registered,
        max_image_size=args.max_image_size, max_num_features=args.max_features, retry=not args.no_retry,
        num_threads=args.threads, work_dir=args.work_dir or (args.out / "sfm"), depth_points=not args.no_depth_points,
        triangulate=not args.no_triangulate, seed=args.seed, up=args.up,
    )
    if opts.marker_size is not None and opts.marker_size <= 0:
        raise InputError(f"--marker-size must be positive (metres), got {opts.marker_size}")
    from splattwin.lock import output_lock

    ds = load_dataset(args.input, max_frames=args.max_frames)
    with output_lock(args.out):
        res = estimate_poses(ds, opts)
        path = res.save(args.out)
    st = res.stats
    fr = res.frame
    unc = "n/a" if fr.scale_uncertainty_rel is None else f"{fr.scale_uncertainty_rel * 100:.2f} %"
    print(f"poses: {st.get('registered')}/{st.get('total')} images posed ({st.get('method')})"
          + (f", mean reprojection error {st['mean_reproj_error']:.3f} px" if "mean_reproj_error" in st else ""))
    print_sfm_summary(st)
    if res.unregistered:
        failures = st.get("failures") or {}
        print(f"  not registered ({len(res.unregistered)}):")
        for u in res.unregistered:
            name = Path(u).name
            why = next((v for k, v in failures.items() if Path(k).name == name), "no pose")
            print(f"    {name}: {why}")
    print(f"frame: {fr.source} ({'metric' if fr.scaled else 'UNSCALED'}), scale uncertainty {unc}")
    print(f"  {fr.description}")
    print(f"wrote {path}")
    return 0
