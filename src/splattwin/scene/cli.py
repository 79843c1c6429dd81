"""Sub-commands of the scene stage: `splattwin scene generate OUT_DIR [...]`."""

from __future__ import annotations

import argparse
import math
import time


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    from splattwin.scene.options import SceneOptions  # light: dataclasses only
    p = sub.add_parser("scene", help="the embedded benchmark tabletop scene",
                       description="The embedded benchmark tabletop scene (synthetic, with ground truth).")
    ssub = p.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    g = ssub.add_parser(
        "generate", help="render the tabletop scene with ground truth and simulated segmenter masks",
        description="Render the seeded tabletop scene into OUT_DIR: images/, depth/ (metres), masks/gt/, "
                    "masks/noisy/, meshes/, transforms.json (nerfstudio), scene.json. "
                    "Same seed and options give byte-identical files.")
    g.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created)")
    g.add_argument("--seed", type=int, default=0, help="layout/texture/noise seed (default 0)")
    g.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    g.add_argument("--height", type=int, default=240, help="image height in pixels (default 240)")
    g.add_argument("--views", type=int, default=15, help="training views (default 15)")
    g.add_argument("--heldout", type=int, default=5, help="held-out views interleaved with them (default 5)")
    g.add_argument("--marker", action="store_true", help="print an ArUco marker (DICT_4X4_50 id 0) on the table")
    g.add_argument("--marker-size", type=float, default=0.08, help="marker side in metres (default 0.08)")
    g.add_argument("--fov", type=float, default=70.0, help="horizontal field of view in degrees (default 70)")
    g.add_argument("--supersample", type=int, default=SceneOptions.supersample,
                   help=f"rays per pixel side, box-filtered (anti-aliasing; 1-8, default {SceneOptions.supersample})")
    g.add_argument("--clean-masks", action="store_true",
                   help="simulate a perfect segmenter (noisy masks equal the GT masks)")
    # robot-style capture (issue #16); the options refactor may regenerate these from RobotCaptureOptions
    g.add_argument("--robot-capture", choices=("bop", "tum"), default=None,
                   help="write a robot-style RGB-D capture instead (D435-like camera, 16-bit depth in mm, "
                        "per-instance masks, known poses in a z-down world): a BOP scene or a TUM pose list")
    g.add_argument("--robot-world", choices=("z-down", "z-up"), default="z-down",
                   help="world of the robot capture's poses (default z-down: the scene rotated 180 deg about x)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.set_defaults(func=_generate)


def _generate(args: argparse.Namespace) -> int:
    from splattwin.scene.generate import generate
    from splattwin.scene.options import MaskNoise, SceneOptions

    opts = SceneOptions(seed=args.seed, width=args.width, height=args.height, views=args.views,
                        heldout=args.heldout, marker=args.marker, marker_size=args.marker_size,
                        fov_x=math.radians(args.fov), supersample=args.supersample,
                        noise=MaskNoise.clean() if args.clean_masks else MaskNoise())
    t0 = time.perf_counter()
    from splattwin.lock import output_lock

    if args.robot_capture:
        from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

        cap = RobotCaptureOptions(views=args.views, width=args.width, height=args.height, world=args.robot_world,
                                  format=args.robot_capture)
        with output_lock(args.out_dir):
            out = write_robot_capture(args.out_dir, opts, cap, progress=not args.no_progress)
        print(f"robot-style capture ({args.robot_capture}, world {args.robot_world}) written to {out.resolve()} "
              f"({args.views} views, {args.width}x{args.height}, seed {args.seed}, {time.perf_counter() - t0:.1f} s)")
        return 0
    with output_lock(args.out_dir):
        out = generate(args.out_dir, opts, progress=not args.no_progress)
    print(f"scene written to {out.resolve()} ({args.views} training + {args.heldout} held-out views, "
          f"{args.width}x{args.height}, seed {args.seed}, {time.perf_counter() - t0:.1f} s)")
    print(f"  cameras: {out.resolve() / 'transforms.json'}  ground truth: {out.resolve() / 'scene.json'}")
    return 0
