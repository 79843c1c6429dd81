"""Sub-commands of the scene stage: `splattwin scene generate OUT_DIR [...]`."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

ROBOT_CAPTURE = "robot-capture."  # flag prefix of the robot-style capture's options


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    from splattwin.options import add_options, add_progress_flag
    from splattwin.scene.options import RobotCaptureOptions, SceneOptions  # light: dataclasses only

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
    add_options(g, SceneOptions)
    g.add_argument("--clean-masks", action="store_true",
                   help="simulate a perfect segmenter (noisy masks equal the GT masks; overrides --noise.*)")
    # --robot-capture bop|tum (= --robot-capture.format) writes a robot-style capture instead (issue #16)
    add_options(g, RobotCaptureOptions, ROBOT_CAPTURE,
                title="robot-style capture (written instead of the scene; views and size from --views, --width, "
                      "--height)")
    add_progress_flag(g)
    g.set_defaults(func=_generate)


def _generate(args: argparse.Namespace) -> int:
    from splattwin.scene.generator import generate
    from splattwin.options import from_args, given
    from splattwin.scene.options import MaskNoise, RobotCaptureOptions, SceneOptions

    opts = from_args(SceneOptions, args)
    if args.clean_masks:
        opts = replace(opts, noise=MaskNoise.clean())
    t0 = time.perf_counter()
    from splattwin.lock import output_lock

    cap_given = given(args, RobotCaptureOptions, ROBOT_CAPTURE)
    if cap_given:
        from splattwin.errors import InputError
        from splattwin.scene.robot_capture import write_robot_capture

        if "format" not in cap_given:
            raise InputError(f"--{ROBOT_CAPTURE}* options need --robot-capture bop|tum (the capture's layout)")
        cap = from_args(RobotCaptureOptions, args, ROBOT_CAPTURE, views=opts.views, width=opts.width,
                        height=opts.height)
        with output_lock(args.out_dir):
            out = write_robot_capture(args.out_dir, opts, cap, progress=args.progress)
        print(f"robot-style capture ({cap.format}, world {cap.world}) written to {out.resolve()} "
              f"({cap.views} views, {cap.width}x{cap.height}, seed {opts.seed}, {time.perf_counter() - t0:.1f} s)")
        return 0
    with output_lock(args.out_dir):
        out = generate(args.out_dir, opts, progress=args.progress)
    print(f"scene written to {out.resolve()} ({opts.views} training + {opts.heldout} held-out views, "
          f"{opts.width}x{opts.height}, seed {opts.seed}, {time.perf_counter() - t0:.1f} s)")
    print(f"  cameras: {out.resolve() / 'transforms.json'}  ground truth: {out.resolve() / 'scene.json'}")
    return 0
