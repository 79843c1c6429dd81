"""Sub-commands of the poses stage: `splattwin poses INPUT OUT [...]`."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path

from splattwin.options import add_command, add_options, dest
from splattwin.poses.options import PoseOptions

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "poses", _run)
    p.add_argument("input", type=Path, help="dataset: image folder, video, transforms.json, COLMAP model, cameras.json, BOP scene, "
                                            "TUM pose list + intrinsics")
    p.add_argument("out", type=Path, help="output folder")
    add_options(p, PoseOptions)
    # shorter, older spellings of --method / --no-shared-intrinsics
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sfm", dest=dest("method"), action="store_const", const="sfm", default=argparse.SUPPRESS,
                     help="= --method sfm: structure from motion even if the dataset has poses")
    src.add_argument("--known", dest=dest("method"), action="store_const", const="known", default=argparse.SUPPRESS,
                     help="= --method known: use the dataset's poses as they are (assumed metric)")
    p.add_argument("--per-image-intrinsics", dest=dest("shared_intrinsics"), action="store_false",
                   default=argparse.SUPPRESS, help="= --no-shared-intrinsics")


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
    """Camera poses (SfM / known / robot) and a metric table frame -> posed nerfstudio dataset.

    Estimates camera poses for a capture and defines the twin frame. Writes OUT/transforms.json
    (nerfstudio, + points3D.ply), OUT/frame.json (frame source, scaled, scale uncertainty),
    OUT/poses_report.json and OUT/cameras.png. The frame comes from, in order: SfM aligned to robot poses,
    an ArUco marker, the table plane + a known length, robot/known poses; otherwise the table plane,
    marked 'unscaled' (robot stages refuse unscaled twins)."""
    from splattwin.capture import load_dataset
    from splattwin.options import from_args
    from splattwin.poses.estimate import estimate_poses

    opts = from_args(PoseOptions, args)
    if opts.work_dir is None:
        opts = replace(opts, work_dir=args.out / "sfm")
    opts.check()   # --max-frames, --min-change, SfM's limits, --min-registered, --marker-size
    from splattwin.lock import output_lock

    with output_lock(args.out):
        # a video's frames and upright copies of rotated photos go inside OUT, as in `build`
        ds = load_dataset(args.input, max_frames=opts.max_frames, min_change=opts.min_change,
                          frames_dir=args.out / "capture" / "frames", progress=opts.progress)
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
    print(f"frame: {fr.summary()}, scale uncertainty {unc}")
    print(f"  {fr.description}")
    print(f"wrote {path}")
    return 0
