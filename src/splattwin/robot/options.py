"""Options of the robot stage (`splattwin plan`, `build --robot.*`): one plain dataclass, the single source
of their defaults and help (see `splattwin.options`). Light: no MuJoCo here (`splattwin --help`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from splattwin.errors import InputError
from splattwin.executor import ExecutorOptions
from splattwin.options import option

IN_HAND = ("sensed", "planned")
#: Planner names `robot.planning.plan_path` accepts (OMPL geometric planners; BITstar/AORRTC when the build has
#: them). Declared here, as the option's choices, so a typo is refused before a run removes the previous one.
PLANNERS = ("RRTConnect", "RRT", "RRTstar", "InformedRRTstar", "PRM", "PRMstar", "BITstar", "AORRTC",
            "KPIECE1", "BKPIECE1", "LBKPIECE1")
# --trials at most: 5x the largest run we document (2000 on a Ray cluster); each trial's result is kept
# in memory and in results.json, so an unbounded count only grows memory until the machine gives out
MAX_TRIALS = 10_000


@dataclass
class RobotOptions:
    """How the task is validated in physics. `task` None: `splattwin plan` runs the paper's three-step
    task, `splattwin build` skips the robot stage; "default" names the paper's task explicitly."""

    task: str | None = option(None, "task YAML ('default': the paper's three steps: blue box onto the cardboard "
                              "box, yellow cube onto the blue box, toy hammer into the target frame)", path=True,
                              build_alias="task")
    trials: int = option(0, f"extra trials with perturbed object poses (at most {MAX_TRIALS})",
                         build_alias="trials")
    sigma: float = option(0.005, "object pose error of the trials: per-axis standard deviation of the x and y "
                          "position error (the robot plans with the twin's poses)", unit="m", build_alias="sigma")
    sigma_yaw: float | None = option(None, "standard deviation of the objects' yaw error in the trials (none: "
                                     "sigma / 0.1 m: 0.05 rad = 2.9 deg at sigma 5 mm)", unit="rad")
    base_pose: str | None = option(None, "robot base in the twin frame: x,y,z,yaw (m, rad); write "
                                   "--base-pose=-0.5,0,0,0 when x is negative (none: for a twin posed with "
                                   "--robot-poses, which is in that robot's base frame, its origin; else "
                                   "-0.5,0,0,0, beside the table)")
    robot_mjcf: Path | None = option(None, "your own arm+gripper MJCF with a TCP site (z = approach, y = finger "
                                     "closing axis), one position actuator per arm joint and one gripper actuator "
                                     "(none: Menagerie Franka Panda); a keyframe named 'home' gives the neutral "
                                     "arm pose", path=True)
    tcp_site: str = option("tcp", "name of the TCP site in robot_mjcf")
    joint_names: str | None = option(None, "joint names in the exported trajectory files (the simulation keeps "
                                     "the MJCF's): 'panda' (panda_joint1..7, franka_ros / panda_moveit_config; "
                                     "base frame panda_link0), 'fr3' (fr3_joint1..7, franka_ros2; fr3_link0), "
                                     "'model' (the MJCF's own names; base frame its root body) or one name per "
                                     "arm joint, comma-separated (none: 'panda' for the default Panda, 'model' "
                                     "for robot_mjcf)")
    base_frame: str | None = option(None, "name of the robot base frame in the exported files (base_transform.yaml's "
                                    "child frame, the base-frame MoveIt scene's frame_id, results.json): a TF frame "
                                    "id such as 'base_link' or 'robot1/panda_link0' (none: panda_link0 for 'panda' "
                                    "joint names, fr3_link0 for 'fr3', else the MJCF's root body)")
    in_hand: str = option("sensed", "where the transfer assumes the held object sits: 'sensed' (read in the "
                          "simulation, as an in-hand estimate such as a wrist camera gives) or 'planned' (as grasped "
                          "on the twin pose; no in-hand sensing on the real cell)", choices=IN_HAND)
    planner: str = option("RRTConnect", "OMPL planner", choices=PLANNERS)
    seed: int = option(0, "seed of the planner and of the trials' perturbations")
    render: bool = option(True, "render PNG frames of the execution", build_alias="frames")
    record: Path | None = option(None, "record every run (the nominal one as episode 0, trial i as episode i) as a "
                                 "LeRobot-layout episode (v2.1: parquet of joint positions, gripper width and "
                                 "commanded actions + one MP4 per camera: wrist and scene) into this folder, "
                                 "rendered photoreal from the twin's splats (replaces a dataset already there)",
                                 hashed=False)
    record_fps: float = option(10.0, "frame rate of the recorded episodes", unit="Hz", hashed=False)
    record_camera: str = option("capture:0", "scene camera of the recorded episodes: a capture image name, "
                                "'capture:<index>' or a camera YAML (as `splattwin render --camera`); the wrist "
                                "camera (eye-in-hand, D435-like) is always recorded", hashed=False)
    record_width: int = option(320, "image width of the recorded episodes (the wrist camera is 4:3 at this width, "
                               "the scene camera keeps its aspect)", unit="px", hashed=False)
    cluster: ExecutorOptions = option(factory=ExecutorOptions, help="where the trials run: a local process pool "
                                      "or a Ray cluster (splattwin.executor)", hashed=False)
    resume: bool = option(True, "reuse finished trials in OUT/trials/ with the same twin, task, robot, seed and "
                          "sigmas, so a killed run continues", hashed=False)

    def validate(self) -> None:
        if not 0 <= self.trials <= MAX_TRIALS:
            raise InputError(f"--trials must be in [0, {MAX_TRIALS}], got {self.trials}")
        if not 0 <= self.sigma <= 0.05:
            raise InputError(f"--sigma must be in [0, 0.05] metres, got {self.sigma}")
        if self.sigma_yaw is not None and not 0 <= self.sigma_yaw <= 0.5:
            raise InputError(f"--sigma-yaw must be in [0, 0.5] radians, got {self.sigma_yaw}")
        from splattwin.robot.export import check_base_frame, check_naming

        check_naming(self.joint_names)
        check_base_frame(self.base_frame)
        if self.robot_mjcf is not None and not Path(self.robot_mjcf).is_file():
            raise InputError("robot MJCF not found", self.robot_mjcf)
        if not 0 < self.record_fps <= 120:
            raise InputError(f"--record-fps must be in (0, 120] Hz, got {self.record_fps}")
        if not 16 <= self.record_width <= 4096:
            raise InputError(f"--record-width must be in [16, 4096] pixels, got {self.record_width}")
        kind, address = self.cluster.resolve()   # a bad executor choice fails before the nominal run
        if self.trials > 0 and kind == "ray":
            # and so do a missing Ray and a cluster nobody answers at: the nominal run removes the previous
            # run's files, and the trials' executor starts only after it
            from splattwin.executor import check_reachable, import_ray

            import_ray()
            if address:
                check_reachable(address)
