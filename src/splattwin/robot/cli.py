"""Sub-commands of the robot stage: `splattwin plan TWIN --task task.yaml [...]`."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from splattwin.options import add_options
from splattwin.robot.options import RobotOptions

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Add this stage's sub-commands to the `splattwin` parser."""
    p = sub.add_parser(
        "plan",
        help="plan a pick-and-place task on a twin and validate it in MuJoCo physics (Franka Panda)",
        description="Plan the task against the twin (grasps, IK, OMPL paths, TOPP-RA timing), execute it in "
                    "MuJoCo with the real gripper, report per-step success and collisions, export the joint "
                    "trajectory (JSON, CSV, ROS 2 JointTrajectory YAML) and frames. Exit code 0 when the task "
                    "succeeded, 1 when it failed, 2 on bad input.",
    )
    p.add_argument("twin", type=Path, help="twin folder (with twin.json)")
    add_options(p, RobotOptions)
    p.add_argument("--out", type=Path, default=None, help="output folder (default: TWIN/robot)")
    p.set_defaults(func=run_plan)


def run_plan(args: argparse.Namespace) -> int:
    from splattwin.errors import InputError
    from splattwin.lock import output_lock
    from splattwin.options import from_args
    from splattwin.paths import is_inside
    from splattwin.robot.outputs import print_summary
    from splattwin.robot.stage import RobotInputs, run

    opts = from_args(RobotOptions, args)
    opts.validate()
    out = args.out or args.twin / "robot"
    if not args.twin.is_dir():
        raise InputError("twin folder does not exist", args.twin)
    # one writer per folder: the twin's lock when writing into it (splattwin.lock)
    with output_lock(args.twin if is_inside(out, args.twin) else out):
        res = run(RobotInputs(args.twin, out), opts)
    d = res.details
    print_summary(d["run"], d["trials"], d["paths"])
    ok = res.success and (d["trials"] is None or d["trials"]["successes"] == d["trials"]["trials"])
    return 0 if ok else 1
