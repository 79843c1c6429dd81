"""Sub-commands of the robot stage: `splattwin plan TWIN --task task.yaml [...]`."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from splattwin.options import add_command, add_options
from splattwin.robot.options import RobotOptions

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "plan", run_plan)
    p.add_argument("twin", type=Path, help="twin folder (with twin.json)")
    add_options(p, RobotOptions)
    p.add_argument("--out", type=Path, default=None, help="output folder (default: TWIN/robot)")


def run_plan(args: argparse.Namespace) -> int:
    """Plan a pick-and-place task on a twin and validate it in MuJoCo physics (Franka Panda).

    Plans the task against the twin (grasps, IK, OMPL paths, TOPP-RA timing), executes it in MuJoCo with
    the real gripper, reports per-step success and collisions, exports the joint trajectory (JSON, CSV,
    ROS 2 JointTrajectory YAML) and frames. Exit code 0 when the task succeeded, 1 when it failed, 2 on
    bad input."""
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
