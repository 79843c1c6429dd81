"""What goes to the real robot besides the joint trajectory: joint naming, base transform, base-frame scene.

Frames: the twin frame (`twin`: the frame of twin.json and TWIN/export/, which those files call `world`;
z up, metres) and the robot base frame (the arm's root body, `panda_link0` on a Panda). The base pose
T_twin_base is `BasePose` (robot/world.py). A stock MoveIt / franka_ros setup plans in the base frame
(its virtual joint puts `world` at `panda_link0`), so the files here are in the base frame or say how
to get there:

* `ExportNames` / `export_names`: the joint names written to the trajectory files (the simulation keeps
  the MJCF's names): `panda` (panda_joint1..7: franka_ros, panda_moveit_config; base frame panda_link0),
  `fr3` (fr3_joint1..7: franka_ros2; fr3_link0), `model` (the MJCF's own, e.g. Menagerie's joint1..7;
  base frame its root body) or a comma-separated list, one name per arm joint (base frame the root body);
  `--base-frame` names the base frame for any of them (e.g. `base_link` or `robot1/panda_link0`).
* `write_base_transform`: robot/base_transform.yaml, a geometry_msgs/TransformStamped twin -> base
  (translation m, rotation quaternion xyzw) with the `ros2 run tf2_ros static_transform_publisher`
  arguments as a comment.
* `write_base_frame_moveit`: robot/moveit/collision_objects.yaml (moveit_msgs/CollisionObject list)
  and robot/moveit/scene.scene (MoveIt text scene), the twin's collision world with every pose in the
  base frame (frame_id the base frame), made with twin/moveit.py's writers.
"""

from __future__ import annotations

import math
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError

TWIN_FRAME = "twin"
JOINT_NAMINGS = {"panda": ("panda_joint", "panda_link0"), "fr3": ("fr3_joint", "fr3_link0")}
MODEL_NAMING = "model"
_ROS_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")   # a ROS 2 name token (joint names, frames)
# a TF frame id for the base: tokens as above joined by single '/' (a namespace: robot1/panda_link0); no
# leading '/' (tf2 refuses frame ids that start with one), no empty or trailing segment
_FRAME_ID = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}(/[A-Za-z_][A-Za-z0-9_]{0,63}){0,7}")
BASE_TRANSFORM = "base_transform.yaml"
MOVEIT_DIR = "moveit"
MOVEIT_FILES = ("collision_objects.yaml", "scene.scene")


# Franka Research 3 joint limits (rad, rad/s): Franka's "Robot and interface specifications", Limits for Franka
# Research 3 (https://frankaemika.github.io/docs/control_parameters.html#limits-for-franka-research-3), the same
# values as libfranka's FR3 limits. The plan is made with the Panda's (Menagerie's) limits, which differ
# (q1 +-2.8973, q6 -0.0175..3.7525, ...): a Panda plan exported with FR3 names is checked against these.
# libfranka lowers the FR3's velocity limits near the position limits (computeUpperLimitsJointVelocity); these
# are the maxima.
FR3_LIMITS = {"q_min": (-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159),
              "q_max": (2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159),
              "qd_max": (2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26),
              "source": "Franka documentation, Limits for Franka Research 3 (control_parameters.html)"}
NAMED_LIMITS = {"fr3": FR3_LIMITS}   # a naming whose robot has other limits than the simulated Panda


def limit_violations(tr, limits: dict, robot: str = "FR3") -> list[str]:
    """Where trajectory `tr` (exported joint names) leaves `limits` (q_min, q_max, qd_max per joint): the
    first violation of each joint and kind, as sentences (empty when it stays inside)."""
    out = []
    q_min, q_max, qd_max = (np.asarray(limits[k], float) for k in ("q_min", "q_max", "qd_max"))
    for j, name in enumerate(tr.joint_names):
        q, qd = tr.q[:, j], tr.qd[:, j]
        checks = (("position", q, q_min[j] - q, f"below the {robot}'s {q_min[j]:g} rad"),
                  ("position", q, q - q_max[j], f"above the {robot}'s {q_max[j]:g} rad"),
                  ("velocity", qd, np.abs(qd) - qd_max[j], f"beyond the {robot}'s {qd_max[j]:g} rad/s"))
        for kind, v, excess, what in checks:   # excess > 0: outside the limit by that much
            bad = excess > 1e-9
            if bad.any():
                k, worst = int(np.argmax(bad)), int(np.argmax(excess))
                out.append(f"{name} at t = {tr.t[k]:.3f} s: {kind} {v[k]:.4f} {what} "
                           f"({int(bad.sum())} samples, worst {v[worst]:.4f} at t = {tr.t[worst]:.3f} s)")
    return out


@dataclass(frozen=True)
class ExportNames:
    """Names in the exported files: `joint_names` [n] (exported order = the simulated arm joints' order),
    `base_frame` (the arm's root link), `naming` (the option value they came from)."""

    joint_names: tuple[str, ...]
    base_frame: str
    naming: str

    def joint_map(self, sim_names: list[str]) -> dict[str, str]:
        """exported name -> simulated (MJCF) name, per arm joint."""
        return dict(zip(self.joint_names, sim_names))


def check_naming(naming: str | None) -> None:
    """InputError unless `naming` is None, a known naming or a comma-separated list of ROS names."""
    if naming is None or naming in JOINT_NAMINGS or naming == MODEL_NAMING:
        return
    names = [n.strip() for n in naming.split(",")]
    bad = [n for n in names if not _ROS_NAME.match(n)]
    if bad or len(set(names)) != len(names):
        raise InputError(f"--joint-names must be one of {', '.join([*JOINT_NAMINGS, MODEL_NAMING])} or distinct "
                         f"comma-separated joint names (letters, digits, _), got {naming!r}")


def check_base_frame(base_frame: str | None) -> None:
    """InputError unless `base_frame` is None or a well-formed TF frame id (see `_FRAME_ID`)."""
    if base_frame is None:
        return
    if not isinstance(base_frame, str) or not _FRAME_ID.fullmatch(base_frame):
        lead = " (tf2 refuses a leading '/')" if isinstance(base_frame, str) and base_frame.startswith("/") else ""
        raise InputError(f"--base-frame must be a TF frame id: letters, digits and '_' (not starting with a "
                         f"digit), optionally namespaced with single '/' (robot1/base_link){lead}, got "
                         f"{str(base_frame)[:80]!r}")
    if base_frame == TWIN_FRAME:
        raise InputError(f"--base-frame {TWIN_FRAME!r} is the twin frame's name (base_transform.yaml: {TWIN_FRAME} -> "
                         f"base); name the robot base otherwise")


def is_frame_id(name) -> bool:
    """Whether `name` is a TF frame id the exported files may carry as the base frame (`_FRAME_ID`, not the
    twin frame's name): it goes into YAML values, a MoveIt scene header and a shell command line."""
    return isinstance(name, str) and bool(_FRAME_ID.fullmatch(name)) and name != TWIN_FRAME


def check_frame_id(base_frame) -> str:
    """`base_frame` if it is a valid exported base frame (`is_frame_id`), else InputError: the guard of every
    writer of the base frame, whatever named it (--base-frame, a joint naming, the MJCF's root body)."""
    if not is_frame_id(base_frame):
        raise InputError(f"the robot base frame {str(base_frame)[:80]!r} is not a TF frame id (letters, digits "
                         f"and '_', optionally namespaced with single '/', not {TWIN_FRAME!r}); name it with "
                         f"--base-frame")
    return base_frame


def export_names(naming: str | None, arm_joints: list[str], root_body: str, default_model: bool,
                 base_frame: str | None = None) -> ExportNames:
    """The names to export for an arm with simulated joints `arm_joints` and root body `root_body`.
    naming None: `panda` for the default (Menagerie Panda) model, `model` for a user MJCF (its own names
    unless mapped). InputError when the naming does not fit the arm (e.g. 7 Panda names for a 6-joint arm).
    base_frame: the base frame's name in the exported files; None: the naming's (`panda_link0`, `fr3_link0`)
    or, for `model` and a list of names, the MJCF's root body."""
    check_naming(naming)
    check_base_frame(base_frame)
    naming = naming or ("panda" if default_model else MODEL_NAMING)
    if base_frame is None and naming not in JOINT_NAMINGS and not is_frame_id(root_body):
        # the MJCF's root body names the base: a name from a file, written into YAML, the MoveIt scene and
        # base_transform.yaml's shell command line, so it must be a frame id like --base-frame's
        raise InputError(f"the robot MJCF's root body {str(root_body)[:80]!r} cannot name the robot base frame "
                         f"in the exported files (a TF frame id: letters, digits and '_', optionally namespaced "
                         f"with single '/', not {TWIN_FRAME!r}); give --base-frame")
    n = len(arm_joints)
    if naming == MODEL_NAMING:
        bad = [j for j in arm_joints if not (isinstance(j, str) and _ROS_NAME.match(j))]
        if bad:
            # names from a file, written into the trajectory YAML/CSV/JSON and the FollowJointTrajectory
            # goals: ROS name tokens only, as a --joint-names list must be
            raise InputError(f"the robot MJCF's joint name {str(bad[0])[:80]!r} cannot name a joint in the exported "
                             f"files (a ROS name: letters, digits and '_', not starting with a digit); give "
                             f"--joint-names with {n} names")
        return ExportNames(tuple(arm_joints), base_frame or root_body, naming)
    if naming in JOINT_NAMINGS:
        prefix, base = JOINT_NAMINGS[naming]
        if n != 7:
            raise InputError(f"--joint-names {naming} names 7 joints; this arm has {n}: give {n} names")
        return ExportNames(tuple(f"{prefix}{i}" for i in range(1, 8)), base_frame or base, naming)
    names = tuple(s.strip() for s in naming.split(","))
    if len(names) != n:
        raise InputError(f"--joint-names gives {len(names)} names; the arm has {n} joints ({', '.join(arm_joints)})")
    return ExportNames(names, base_frame or root_body, naming)


def quat_xyzw_of(T: np.ndarray) -> list[float]:
    """Quaternion (x, y, z, w) of a pose's rotation, w >= 0 (the ROS order)."""
    from splattwin.transforms import quat_wxyz_from_matrix, quat_xyzw_from_wxyz

    return [float(v) for v in quat_xyzw_from_wxyz(quat_wxyz_from_matrix(np.asarray(T)[:3, :3]))]


def base_pose_doc(T_twin_base: np.ndarray, base_frame: str) -> dict:
    """The base pose as recorded in the trajectory files: parent/child frames, translation (m),
    quaternion xyzw and yaw (rad) about +z."""
    T = np.asarray(T_twin_base, dtype=float)
    return {"parent_frame": TWIN_FRAME, "child_frame": base_frame,
            "translation": [float(v) for v in T[:3, 3]], "quaternion_xyzw": quat_xyzw_of(T),
            "yaw": math.atan2(float(T[1, 0]), float(T[0, 0]))}


def static_transform_args(T_twin_base: np.ndarray, base_frame: str) -> str:
    """`ros2 run tf2_ros static_transform_publisher` arguments (Humble and later) for twin -> base."""
    T = np.asarray(T_twin_base, dtype=float)
    q = quat_xyzw_of(T)
    # a valid frame id needs no quoting (shlex.quote leaves it as is); the quote is a second guard for the
    # command line the user pastes
    return (f"--x {T[0, 3]:.9g} --y {T[1, 3]:.9g} --z {T[2, 3]:.9g} --qx {q[0]:.9g} --qy {q[1]:.9g} "
            f"--qz {q[2]:.9g} --qw {q[3]:.9g} --frame-id {TWIN_FRAME} "
            f"--child-frame-id {shlex.quote(check_frame_id(base_frame))}")


def write_base_transform(path: str | Path, T_twin_base: np.ndarray, base_frame: str) -> Path:
    """robot/base_transform.yaml: geometry_msgs/TransformStamped twin -> base (m, quaternion xyzw), with
    the static_transform_publisher command as a comment."""
    import yaml

    check_frame_id(base_frame)
    T = np.asarray(T_twin_base, dtype=float)
    q = quat_xyzw_of(T)
    doc = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": TWIN_FRAME}, "child_frame_id": base_frame,
           "transform": {"translation": dict(zip("xyz", (float(v) for v in T[:3, 3]))),
                         "rotation": dict(zip("xyzw", q))}}
    head = (f"# the robot base ({base_frame}) in the twin frame ('{TWIN_FRAME}': twin.json and TWIN/export/, "
            "which call it 'world'); metres, quaternion xyzw\n"
            f"# ros2 run tf2_ros static_transform_publisher {static_transform_args(T, base_frame)}\n")
    return io.write_text(path, head + yaml.safe_dump(doc, sort_keys=False))


def write_base_frame_moveit(out_dir: str | Path, twin_dir: str | Path, T_twin_base: np.ndarray,
                            base_frame: str) -> dict[str, Path]:
    """OUT/moveit/collision_objects.yaml and scene.scene: the twin's collision world (table, background
    obstacles, usable objects' collision meshes; `twin.moveit.scene_objects`) with every object pose in
    the base frame, T_base_obj = T_twin_base^-1 T_twin_obj (frame_id `base_frame`)."""
    import yaml

    from splattwin.transforms import invert_pose
    from splattwin.twin.manifest import Manifest
    from splattwin.twin.moveit import collision_object_msgs, scene_objects, scene_text

    check_frame_id(base_frame)
    twin_dir, out = Path(twin_dir), Path(out_dir) / MOVEIT_DIR
    T_base_twin = invert_pose(np.asarray(T_twin_base, dtype=float))
    objs = scene_objects(twin_dir, Manifest.load(twin_dir))
    for o in objs:   # the field is named for the twin export's frame; here it holds T_base_obj
        o.T_world_obj = T_base_twin @ o.T_world_obj
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # libyaml: mesh-sized lists
    head = (f"# moveit_msgs/msg/CollisionObject list; poses in the robot base frame {base_frame} "
            f"(robot/{BASE_TRANSFORM} places it in the twin frame); metres, quaternions xyzw\n")
    yml = io.write_text(out / MOVEIT_FILES[0], head + yaml.dump(collision_object_msgs(objs, base_frame), Dumper=dumper,
                                                                default_flow_style=None, sort_keys=False,
                                                                width=1 << 20))
    scene = io.write_text(out / MOVEIT_FILES[1], scene_text(objs, f"splattwin_{base_frame}"))
    return {"moveit_collision_objects": yml, "moveit_scene": scene}
