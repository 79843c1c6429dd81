"""Sub-commands of the robot stage: `splattwin plan TWIN --task task.yaml [...]`."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

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
    p.add_argument("--task", type=Path, default=None,
                   help="task YAML (default: the paper's three steps: blue box onto the cardboard box, yellow "
                        "cube onto the blue box, toy hammer into the target frame)")
    p.add_argument("--trials", type=int, default=0, help="extra trials with perturbed object poses (default 0)")
    p.add_argument("--sigma", type=float, default=0.005,
                   help="object pose error of the trials: per-axis standard deviation of the x and y position "
                        "error, metres (default 0.005); the robot plans with the twin's poses")
    p.add_argument("--sigma-yaw", type=float, default=None,
                   help="standard deviation of the objects' yaw error in the trials, radians "
                        "(default sigma / 0.1 m: 0.05 rad = 2.9 deg at sigma 5 mm)")
    p.add_argument("--no-resume", action="store_true",
                   help="re-run every trial (default: reuse finished trials in OUT/trials/ with the same "
                        "twin, task, robot, seed and sigmas, so a killed run continues)")
    p.add_argument("--base-pose", default="-0.5,0,0,0",
                   help="robot base in the twin frame: x,y,z,yaw (m, rad); write --base-pose=-0.5,0,0,0 "
                        "when x is negative")
    p.add_argument("--robot-mjcf", type=Path, default=None,
                   help="your own arm+gripper MJCF with a TCP site (z = approach, y = finger closing axis), one "
                        "position actuator per arm joint and one gripper actuator (default: Menagerie Franka "
                        "Panda); a keyframe named 'home' gives the neutral arm pose")
    p.add_argument("--tcp-site", default="tcp", help="name of the TCP site in --robot-mjcf (default tcp)")
    p.add_argument("--in-hand", choices=("sensed", "planned"), default="sensed",
                   help="where the transfer assumes the held object sits: 'sensed' (default; read in the "
                        "simulation, as an in-hand estimate such as a wrist camera gives) or 'planned' (as "
                        "grasped on the twin pose; no in-hand sensing on the real cell)")
    p.add_argument("--planner", default="RRTConnect", help="OMPL planner (default RRTConnect)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None,
                   help="processes for the trials (default: CPU count); with --executor ray and no address: CPUs "
                        "of the local Ray")
    p.add_argument("--no-render", action="store_true", help="do not render PNG frames")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: TWIN/robot)")
    from splattwin.cluster.cli import add_executor_args

    add_executor_args(p)
    p.set_defaults(func=run_plan)


def run_plan(args: argparse.Namespace) -> int:
    from splattwin.robot.render import prefer_egl

    prefer_egl()  # before mujoco is imported
    from splattwin.errors import InputError
    from splattwin.robot.outputs import print_summary, write_outputs
    from splattwin.robot.trials import TrialSpec, run_once, run_trials
    from splattwin.robot.world import BasePose

    if args.trials < 0:
        raise InputError(f"--trials must be >= 0, got {args.trials}")
    if not 0 <= args.sigma <= 0.05:
        raise InputError(f"--sigma must be in [0, 0.05] metres, got {args.sigma}")
    if args.sigma_yaw is not None and not 0 <= args.sigma_yaw <= 0.5:
        raise InputError(f"--sigma-yaw must be in [0, 0.5] radians, got {args.sigma_yaw}")
    if args.robot_mjcf is not None and not args.robot_mjcf.is_file():
        raise InputError("robot MJCF not found", args.robot_mjcf)
    out = args.out or args.twin / "robot"
    spec = TrialSpec(twin_dir=str(args.twin), task_path=str(args.task) if args.task else None,
                     base=BasePose.parse(args.base_pose), robot_mjcf=str(args.robot_mjcf) if args.robot_mjcf else None,
                     seed=args.seed, planner=args.planner, tcp_site=args.tcp_site, in_hand=args.in_hand)
    t0 = time.perf_counter()
    result, note, frames = run_once(spec, frame_dir=None if args.no_render else out / "frames", keep_trajectories=True)
    trials = None
    if args.trials > 0:
        from splattwin.cluster.cli import executor_from_args

        with executor_from_args(args, args.workers) as ex:
            trials = run_trials(spec, args.trials, args.sigma, workers=args.workers, out_dir=out,
                                resume=not args.no_resume, sigma_yaw=args.sigma_yaw, executor=ex)
    paths = write_outputs(out, spec, result, trials, render_note=note if not args.no_render else "rendering disabled (--no-render)",
                          frames=frames, wall_s=time.perf_counter() - t0)
    print_summary(result, trials, paths)
    ok = result.success and (trials is None or trials["successes"] == trials["trials"])
    return 0 if ok else 1
