"""The MuJoCo world: the twin (table, background, free objects) plus the robot at a base pose.

Frames: the twin frame is MuJoCo's world frame (z up, table top at z = table_height, metres). The robot's
root body is placed at `BasePose` (x, y, z in metres, yaw in radians about +z). Default: beside the table
at (-0.50, 0, 0) facing +x (docs/CONTRACTS.md). Nothing here needs an OpenGL context.

`World` owns named frames and joint addressing, as mink's `Configuration` does for IK: callers ask for
the arm's joints, the gripper opening, an object's pose or a body's pose by name and never do qpos /
qvel address arithmetic themselves. `JointMap` is that addressing for one model; it also reads recorded
state arrays (qpos [..., nq]), so a rollout and the live simulation are read the same way.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.robot.assets import RobotModel
from splattwin.transforms import make_pose, pos_quat_wxyz_from_pose, pose_from_pos_quat_wxyz, pose_xyz_yaw
from splattwin.twin.manifest import Manifest
from splattwin.twin.mjcf import add_twin, check_scaled

log = logging.getLogger(__name__)

MAX_BASE_OFFSET = 1e4      # m: a robot base beyond this from the twin's origin is not a pose of this twin
MAX_BASE_YAW = 1e3         # rad (angles wrap; this only keeps them finite and meaningful)
MAX_RESULTS_BYTES = 256 << 20

# The start check (`World.settle_check`): physics is stepped this long (s) with the arm held before the robot
# acts, on a copy of the state that is then discarded; an object that moves more than SETTLE_MOVE_M or turns
# more than SETTLE_TURN_DEG from its twin pose in that time is not at rest where the twin puts it (floating
# above its support, sunk into it, tipping), so the run does not validate the twin (no real-arm files)
SETTLE_TIME_S = 0.5
SETTLE_MOVE_M = 0.01
SETTLE_TURN_DEG = 5.0


@dataclass(frozen=True)
class BasePose:
    """Robot base in the twin frame: position (m) and yaw (rad) about +z."""

    x: float = -0.50
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0

    def __post_init__(self) -> None:
        try:
            yaw = float(self.yaw)
        except (TypeError, ValueError):
            raise InputError(f"BasePose yaw must be a number (radians), got {self.yaw!r}") from None
        if math.isfinite(yaw) and abs(yaw) > 2 * math.pi:
            import warnings

            warnings.warn(f"BasePose yaw {yaw:g} is more than a full turn: yaw is in radians (degrees? use "
                          f"math.radians({yaw:g}) = {math.radians(yaw):.4g})", UserWarning, stacklevel=3)

    @classmethod
    def parse(cls, text: str) -> "BasePose":
        """'x,y,z,yaw' (m, m, m, rad) as given on the command line."""
        try:
            vals = [float(v) for v in text.split(",")]
        except ValueError:
            vals = []
        if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
            raise InputError(f"--base-pose must be 'x,y,z,yaw' (metres, radians), got {text!r}")
        return cls(*vals)

    def matrix(self) -> np.ndarray:
        """T_world_base [4,4]."""
        return pose_xyz_yaw(self.x, self.y, self.z, self.yaw)

    @classmethod
    def default_for(cls, frame) -> tuple["BasePose", str]:
        """The base pose to use when none is given, for a twin whose poses stage made `frame` (TwinFrame),
        and why. A twin posed by the robot itself (`--robot-poses`: frame source robot / sfm+robot) is in
        the robot base frame (moved by the frame's T_twin_input, if at all): the arm stands at that frame's
        origin, where it stood when it took the photos. Any other twin: beside the table (the class default:
        0.5 m behind the table centre of a table frame)."""
        source = getattr(frame, "source", None)
        if source in ("robot", "sfm+robot"):
            # robot: T_twin_input maps the robot base frame into the twin frame (identity as the poses stage
            # writes it); sfm+robot: the input is the SfM model, aligned INTO the robot base frame
            T = np.eye(4)
            if source == "robot" and frame.T_twin_input is not None:
                T = np.asarray(frame.T_twin_input, dtype=float)
            R = T[:3, :3]
            if (T.shape == (4, 4) and np.all(np.isfinite(T)) and np.all(np.abs(T[:3, 3]) <= MAX_BASE_OFFSET)
                    and R[2, 2] > math.cos(math.radians(1.0))):
                yaw = math.atan2(R[1, 0], R[0, 0])
                return cls(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), yaw), \
                    "the robot base: the twin is in the frame of the robot that posed the cameras"
            return cls(), ("beside the table: the twin is in the robot's frame, but tilted from it, so the base "
                           "pose is not known; give --base-pose")
        return cls(), "beside the table (the default)"

    @classmethod
    def for_twin(cls, twin_dir: str | Path, text: str | None) -> "BasePose":
        """`--base-pose` TEXT when given, else the default for the twin in `twin_dir` (`default_for`, logged)."""
        if text:
            return cls.parse(text)
        base, why = cls.default_for(Manifest.load(twin_dir).frame)
        log.info("robot base at x %.3f, y %.3f, z %.3f m, yaw %.1f deg: %s (--base-pose moves it)", base.x, base.y,
                 base.z, math.degrees(base.yaw), why)
        return base

    @classmethod
    def recorded(cls, results_json: str | Path) -> "BasePose":
        """The base pose `splattwin plan` recorded in robot/results.json; the default when the file or its
        `base_pose` is absent. A base_pose that is not four finite, bounded numbers is an InputError naming
        the file (a "nan" there made render fail with 'negative dimensions')."""
        from splattwin.limits import number, read_json

        path = Path(results_json)
        if not path.is_file():
            return cls()
        d = read_json(path, max_bytes=MAX_RESULTS_BYTES)
        b = d.get("base_pose") if isinstance(d, dict) else None
        if b is None:
            return cls()
        if not isinstance(b, dict) or not {"x", "y", "z", "yaw"} <= set(b):
            raise InputError("base_pose must be a mapping with x, y, z (m) and yaw (rad)", path)
        return cls(*(number(b[k], path, f"base_pose.{k}", -lim, lim)
                     for k, lim in (("x", MAX_BASE_OFFSET), ("y", MAX_BASE_OFFSET), ("z", MAX_BASE_OFFSET),
                                    ("yaw", MAX_BASE_YAW))))


@dataclass(frozen=True)
class JointMap:
    """Where the robot's joints and the objects' free joints live in one model's qpos / qvel.

    Every accessor takes the state array it reads or writes, the live `MjData.qpos` [nq] or a recorded
    [..., nq] array, so that recorded and simulated states are addressed by the same code. Arm joints
    are in `RobotModel.arm_joints` order; finger joints are the gripper's slide joints (their sum is the
    distance between the fingers, m); an object's free joint holds position (m) and quaternion (wxyz).
    """

    nq: int
    arm_qpos: np.ndarray                  # [n_arm] qpos addresses
    arm_dof: np.ndarray                   # [n_arm] qvel / qfrc addresses
    finger_qpos: np.ndarray               # [k] qpos addresses of the fingers' slide joints
    object_qpos: dict[str, int] = field(default_factory=dict)   # name -> first of 7 free-joint qpos
    object_dof: dict[str, int] = field(default_factory=dict)    # name -> first of 6 free-joint dofs

    @classmethod
    def from_model(cls, model, robot: RobotModel, objects: list[str] = ()) -> "JointMap":
        """Addresses in `model` of the robot's joints and of the free joints `<object>/free`."""
        import mujoco

        arm = [model.joint(n) for n in robot.arm_joints]
        slide = int(mujoco.mjtJoint.mjJNT_SLIDE)
        fingers = [model.joint(n) for n in robot.gripper_joints if int(model.joint(n).type[0]) == slide]
        free = {o: model.joint(f"{o}/free") for o in objects}
        return cls(nq=int(model.nq), arm_qpos=np.array([int(j.qposadr[0]) for j in arm]),
                   arm_dof=np.array([int(j.dofadr[0]) for j in arm]),
                   finger_qpos=np.array([int(j.qposadr[0]) for j in fingers], dtype=int),
                   object_qpos={o: int(j.qposadr[0]) for o, j in free.items()},
                   object_dof={o: int(j.dofadr[0]) for o, j in free.items()})

    # -- arm and gripper -------------------------------------------------------------------------------
    def arm(self, qpos: np.ndarray) -> np.ndarray:
        """Arm joints [..., n_arm] (rad) of qpos [..., nq] (a copy)."""
        return np.asarray(qpos)[..., self.arm_qpos].copy()

    def set_arm(self, qpos: np.ndarray, q_arm: np.ndarray) -> None:
        """Write arm joints q_arm [..., n_arm] (rad) into qpos [..., nq] in place."""
        qpos[..., self.arm_qpos] = q_arm

    def full(self, q_arm: np.ndarray, base_qpos: np.ndarray) -> np.ndarray:
        """A copy of base_qpos [nq] with the arm at q_arm [n_arm]."""
        q = np.array(base_qpos, dtype=float)
        self.set_arm(q, q_arm)
        return q

    def gripper_width(self, qpos: np.ndarray) -> np.ndarray:
        """Distance between the fingers [...] (m): the sum of the finger slide joints."""
        return np.asarray(qpos)[..., self.finger_qpos].sum(axis=-1)

    def set_gripper_width(self, qpos: np.ndarray, width: float) -> None:
        """Open the fingers symmetrically to `width` m (in place)."""
        if len(self.finger_qpos):
            qpos[..., self.finger_qpos] = width / len(self.finger_qpos)

    # -- objects --------------------------------------------------------------------------------------
    def _object(self, name: str) -> int:
        try:
            return self.object_qpos[name]
        except KeyError:
            raise KeyError(f"no free object named {name!r} (objects: {', '.join(self.object_qpos)})") from None

    def object_pose(self, qpos: np.ndarray, name: str) -> np.ndarray:
        """T_world_obj [..., 4, 4] of a free object in qpos [..., nq]."""
        a = self._object(name)
        q = np.asarray(qpos)
        return pose_from_pos_quat_wxyz(q[..., a:a + 3], q[..., a + 3:a + 7])

    def set_object_pose(self, qpos: np.ndarray, name: str, T_world_obj: np.ndarray) -> None:
        """Write T_world_obj [4,4] into the object's free joint in qpos (in place)."""
        a = self._object(name)
        p, q = pos_quat_wxyz_from_pose(T_world_obj)
        qpos[..., a:a + 3] = p
        qpos[..., a + 3:a + 7] = q

    def object_velocity(self, qvel: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(linear [...,3] m/s in the world frame, angular [...,3] rad/s in the body frame) of a free object."""
        self._object(name)
        a = self.object_dof[name]
        v = np.asarray(qvel)
        return v[..., a:a + 3].copy(), v[..., a + 3:a + 6].copy()


@dataclass(frozen=True)
class Contacts:
    """The contacts of one simulation instant, per contact k: bodies (ids) body1/body2 [K], signed
    distance dist [K] (m, < 0 penetrating), normal [K,3] (world, from body1 towards body2), pos [K,3] (m)."""

    body1: np.ndarray
    body2: np.ndarray
    dist: np.ndarray
    normal: np.ndarray
    pos: np.ndarray

    def __len__(self) -> int:
        return len(self.dist)

    def involving(self, body: int) -> np.ndarray:
        """[K] bool: contacts with `body` on either side."""
        return (self.body1 == body) | (self.body2 == body)

    def partners(self, body: int) -> set[int]:
        """Bodies touching (or within the contact margin of) `body`."""
        sel = self.involving(body)
        return {int(b2) if b1 == body else int(b1) for b1, b2 in zip(self.body1[sel], self.body2[sel])}


@dataclass
class World:
    """Compiled world (model + data) and named access to its state.

    objects: the free objects' names. joints: qpos/qvel addressing (`JointMap`). robot_bodies: body ids
    of the robot. Bodies, sites and objects are addressed by name; body ids appear only where contacts
    are scanned every physics step.
    """

    model: object
    data: object
    robot: RobotModel
    manifest: Manifest
    twin_dir: Path
    base: BasePose
    objects: list[str]
    joints: JointMap
    arm_act: np.ndarray
    grip_act: int
    tcp_site: int
    robot_bodies: set[int] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.is_robot = np.zeros(self.model.nbody, bool)
        self.is_robot[list(self.robot_bodies)] = True
        self.servo_lead = servo_lead(self.model, self.arm_act)

    # -- names ------------------------------------------------------------------------------------------
    def body_id(self, name: str) -> int:
        """Body id of a named body ('world' is 0)."""
        return 0 if name == "world" else int(self.model.body(name).id)

    def body_name(self, b: int) -> str:
        import mujoco

        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, int(b)) or "world"

    def object_body(self, name: str) -> int:
        if name not in self.joints.object_qpos:
            raise KeyError(f"no free object named {name!r}")
        return self.body_id(name)

    @property
    def tcp_body(self) -> int:
        """Body id of the body holding the TCP site (the Panda's hand)."""
        return int(self.model.site_bodyid[self.tcp_site])

    @property
    def finger_bodies(self) -> set[int]:
        """Body ids of the hand's bodies below the TCP body (the fingers)."""
        return {self.body_id(n) for n in self.robot.hand_bodies} - {self.tcp_body}

    # -- state: arm and gripper ---------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """s of simulated time."""
        return float(self.data.time)

    def qpos(self) -> np.ndarray:
        """The whole simulation configuration [nq] (a copy; for recording and exact replay)."""
        return self.data.qpos.copy()

    def arm_q(self) -> np.ndarray:
        """Measured arm joints [n_arm] (rad)."""
        return self.joints.arm(self.data.qpos)

    def gripper_width(self) -> float:
        """Measured distance between the fingers (m)."""
        return float(self.joints.gripper_width(self.data.qpos))

    def gripper_width_of_ctrl(self, ctrl: float | np.ndarray) -> float | np.ndarray:
        """Commanded finger distance (m) of a gripper actuator command: `gripper_closed` -> 0, `gripper_open`
        -> max_opening, linear in between (the Panda's tendon servo)."""
        r = self.robot
        return (np.asarray(ctrl, float) - r.gripper_closed) / (r.gripper_open - r.gripper_closed) * r.max_opening

    def set_arm(self, q: np.ndarray, gripper_open: bool = True) -> None:
        """Teleport the arm (and servo targets) to q, gripper open or closed; recompute kinematics."""
        import mujoco

        d = self.data
        self.joints.set_arm(d.qpos, q)
        d.qvel[self.joints.arm_dof] = 0.0
        d.ctrl[self.arm_act] = q
        self.joints.set_gripper_width(d.qpos, self.robot.max_opening if gripper_open else 0.0)
        d.ctrl[self.grip_act] = self.robot.gripper_open if gripper_open else self.robot.gripper_closed
        mujoco.mj_forward(self.model, d)

    # -- stepping the servos -----------------------------------------------------------------------------
    def command_gripper(self, ctrl: float) -> None:
        """Gripper actuator command (robot units: gripper_closed .. gripper_open)."""
        self.data.ctrl[self.grip_act] = ctrl

    def gripper_command(self) -> float:
        return float(self.data.ctrl[self.grip_act])

    def step(self, q_target: np.ndarray, qd_target: np.ndarray | None = None) -> None:
        """One physics step with the arm's position servos at q_target [n_arm] (rad) and gravity/Coriolis
        compensation applied as joint forces (as the Franka controller does). qd_target [n_arm] (rad/s):
        the reference velocity, fed forward (`servo_lead`) so the servos track a moving target without lag."""
        import mujoco

        d = self.data
        dof = self.joints.arm_dof
        # a position servo pushes kp (ctrl - q) - kd qd; ctrl = q_ref + kd/kp qd_ref makes that
        # kp (q_ref - q) + kd (qd_ref - qd): it no longer lags a moving target by kd/kp (0.1 s on the Panda)
        d.ctrl[self.arm_act] = q_target if qd_target is None else q_target + self.servo_lead * qd_target
        d.qfrc_applied[:] = 0.0
        d.qfrc_applied[dof] = d.qfrc_bias[dof]
        mujoco.mj_step(self.model, d)

    def contacts(self) -> Contacts:
        """The current contacts (after mj_step / mj_forward) by body."""
        d, m = self.data, self.model
        n = d.ncon
        geoms = d.contact.geom[:n]
        return Contacts(body1=m.geom_bodyid[geoms[:, 0]], body2=m.geom_bodyid[geoms[:, 1]],
                        dist=d.contact.dist[:n].copy(), normal=d.contact.frame[:n, :3].copy(),
                        pos=d.contact.pos[:n].copy())

    def contact_bodies(self) -> tuple[np.ndarray, np.ndarray]:
        """(body pairs [K,2], signed distances [K] m) of the current contacts: the cheap form for per-step scans."""
        d = self.data
        n = d.ncon
        return self.model.geom_bodyid[d.contact.geom[:n]], d.contact.dist[:n]

    # -- state: objects and frames ----------------------------------------------------------------------
    def object_pose(self, name: str) -> np.ndarray:
        """T_world_obj [4,4] of a free object now."""
        return self.joints.object_pose(self.data.qpos, name)

    def set_object_pose(self, name: str, T: np.ndarray) -> None:
        """Teleport a free object to T_world_obj [4,4], at rest (kinematics follow at the next step/forward)."""
        self.joints.set_object_pose(self.data.qpos, name, T)
        self.data.qvel[self.joints.object_dof[name]:self.joints.object_dof[name] + 6] = 0.0

    def settle_check(self, duration: float = SETTLE_TIME_S) -> dict:
        """How far physics moves each free object from its pose now (the twin's) in `duration` s with the
        arm held still, before the robot acts. Runs on the current state and restores it exactly afterwards
        (the executed run is unchanged). Returns {time_s, threshold_m, threshold_deg, objects: {name:
        {moved_m, turned_deg}}, moved: [names beyond a threshold], frame_source: the twin frame's source, for
        the message} (`SETTLE_MOVE_M`, `SETTLE_TURN_DEG`)."""
        import mujoco

        m, d = self.model, self.data
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        saved = np.empty(mujoco.mj_stateSize(m, spec))
        mujoco.mj_getState(m, d, saved, spec)
        before = {o: self.object_pose(o) for o in self.objects}
        q = self.arm_q()
        try:
            for _ in range(int(math.ceil(duration / float(m.opt.timestep)))):
                self.step(q)
            after = {o: self.object_pose(o) for o in self.objects}
        finally:
            mujoco.mj_setState(m, d, saved, spec)
            mujoco.mj_forward(m, d)
        objects = {}
        for o in self.objects:
            T0, T1 = before[o], after[o]
            cos = (np.trace(T0[:3, :3].T @ T1[:3, :3]) - 1.0) / 2.0
            objects[o] = {"moved_m": round(float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])), 4),
                          "turned_deg": round(math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0)))), 2),
                          "dz_m": round(float(T1[2, 3] - T0[2, 3]), 4)}
        moved = [o for o, v in objects.items() if v["moved_m"] > SETTLE_MOVE_M or v["turned_deg"] > SETTLE_TURN_DEG]
        return {"time_s": duration, "threshold_m": SETTLE_MOVE_M, "threshold_deg": SETTLE_TURN_DEG,
                "objects": objects, "moved": moved, "frame_source": self.manifest.frame.source}

    def forward(self) -> None:
        """Recompute kinematics, contacts and forces of the current state (mj_forward)."""
        import mujoco

        mujoco.mj_forward(self.model, self.data)

    def object_speed(self, name: str) -> float:
        """Linear speed (m/s) of a free object's body origin now."""
        lin, _ = self.joints.object_velocity(self.data.qvel, name)
        return float(np.linalg.norm(lin))

    def body_pose(self, name: str) -> np.ndarray:
        """T_world_body [4,4] of a named body now (after kinematics)."""
        b = self.body_id(name)
        return make_pose(self.data.xmat[b].reshape(3, 3), self.data.xpos[b])

    def site_pose(self, name: str) -> np.ndarray:
        """T_world_site [4,4] of a named site now."""
        s = int(self.model.site(name).id)
        return make_pose(self.data.site_xmat[s].reshape(3, 3), self.data.site_xpos[s])

    def tcp_pose(self) -> np.ndarray:
        """T_world_tcp [4,4] now (after mj_forward / mj_step)."""
        return make_pose(self.data.site_xmat[self.tcp_site].reshape(3, 3), self.data.site_xpos[self.tcp_site])

    def tcp_poses(self, qpos: np.ndarray) -> np.ndarray:
        """T_world_tcp [T,4,4] for recorded configurations qpos [T,nq] (forward kinematics on a scratch
        copy of the state; the simulation is not touched)."""
        import mujoco

        d = mujoco.MjData(self.model)
        out = np.zeros((len(qpos), 4, 4))
        for k, q in enumerate(np.atleast_2d(qpos)):
            d.qpos[:] = q
            mujoco.mj_kinematics(self.model, d)
            out[k] = make_pose(d.site_xmat[self.tcp_site].reshape(3, 3), d.site_xpos[self.tcp_site])
        return out

    def planning_state(self, object_poses: dict[str, np.ndarray], q_arm: np.ndarray, gripper_width: float):
        """A detached `MjData` of this world with the objects at `object_poses` (T_world_obj, e.g. the
        robot's belief), the arm at q_arm and the fingers `gripper_width` m apart; the rest as now."""
        import mujoco

        d = mujoco.MjData(self.model)
        d.qpos[:] = self.data.qpos
        for o, T in object_poses.items():
            self.joints.set_object_pose(d.qpos, o, T)
        self.joints.set_arm(d.qpos, q_arm)
        self.joints.set_gripper_width(d.qpos, gripper_width)
        return d


def _check_name_clashes(spec, manifest: Manifest, where: Path) -> None:
    """InputError when a twin object is named like one of the robot model's bodies (the Panda's `hand`,
    `link0`..`link7`, `left_finger`, `right_finger`, or a user MJCF's): the objects become bodies of the same
    MuJoCo model, by name, so such a twin failed to compile with 'repeated name' (exit 1, as a bug)."""
    robot_names = {b.name for b in spec.bodies if b.name}
    clash = sorted(o.name for o in manifest.objects if o.name in robot_names)
    if clash:
        raise InputError(f"object name(s) {clash} are also body names of the robot model "
                         f"({', '.join(sorted(robot_names))}): the robot and the objects share one simulation, "
                         f"where names must be unique; rename the object(s) (the masks' or the prompt's names) "
                         f"and build the twin again", where)


def build_world(twin_dir: str | Path, manifest: Manifest | None = None, robot: RobotModel | None = None,
                base: BasePose | None = None, poses: dict[str, np.ndarray] | None = None,
                visual: bool = True) -> World:
    """Compile twin + robot. poses: optional T_world_obj overrides (perturbed trials). visual=False:
    without the robot's visual meshes (same physics, fast compile; nothing to render). base: the robot base in
    the twin frame; None: where `splattwin plan` puts it without --base-pose (`BasePose.default_for`)."""
    import mujoco

    from splattwin.transforms import quat_wxyz_from_matrix

    twin_dir = Path(twin_dir)
    manifest = manifest or Manifest.load(twin_dir)
    check_scaled(manifest, twin_dir / "twin.json")
    robot = robot or RobotModel.panda()
    base = base or BasePose.default_for(manifest.frame)[0]
    spec = robot.spec(visual=visual)
    root = spec.body(robot.root_body)
    T = base.matrix()
    root.pos = T[:3, 3].tolist()
    root.quat = quat_wxyz_from_matrix(T[:3, :3]).tolist()
    spec.modelname = "splattwin_world"
    _stiffen_gripper(spec, robot)
    _check_name_clashes(spec, manifest, twin_dir / "twin.json")
    objects = add_twin(spec, manifest, twin_dir, poses=poses)
    region = _outline_region(manifest.config.get("target_frame"), twin_dir / "twin.json") if visual else None
    if region is not None:
        _add_region_outline(spec, *region, manifest.background.table_height)
    try:
        model = spec.compile()
    except ValueError as e:
        raise InputError(f"world does not compile: {e}", twin_dir / "twin.json") from e
    data = mujoco.MjData(model)
    root_id = model.body(robot.root_body).id
    robot_bodies = {b for b in range(model.nbody) if _under(model, b, root_id)}
    w = World(model=model, data=data, robot=robot, manifest=manifest, twin_dir=twin_dir, base=base,
              objects=objects, joints=JointMap.from_model(model, robot, objects),
              arm_act=np.array([model.actuator(n).id for n in robot.arm_actuators]),
              grip_act=model.actuator(robot.gripper_actuator).id,
              tcp_site=model.site(robot.tcp_site).id, robot_bodies=robot_bodies)
    w.set_arm(robot.home, gripper_open=True)
    return w


def servo_lead(model, actuators: np.ndarray) -> np.ndarray:
    """kd / kp (s) of each arm position actuator (ctrl gain kp, affine bias -kp q - kd qd); 0 for an
    actuator of another kind (no feed-forward for it)."""
    import mujoco

    out = np.zeros(len(actuators))
    for i, a in enumerate(actuators):
        kp, kd = float(model.actuator_gainprm[a, 0]), -float(model.actuator_biasprm[a, 2])
        if model.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE and kp > 0 and kd > 0:
            out[i] = kd / kp
    return out


GRIP_STIFFNESS = 1000.0   # N/m of the gripper's position servo (Menagerie: 100)


def hand_points_tcp(world: World) -> np.ndarray:
    """Points [K,3] (m, TCP frame) of the hand's and fingers' collision geometry at the current gripper
    opening: mesh vertices and box/other-primitive bounding-box corners. Max of [:, 2] is how far the
    fingers reach beyond the TCP along the approach (the fingertips, 8.9 mm on the Menagerie Panda)."""
    import mujoco

    m, d = world.model, world.data
    mujoco.mj_kinematics(m, d)
    T = world.tcp_pose()
    hand = {world.body_id(b) for b in world.robot.hand_bodies}
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pts = []
    for g in range(m.ngeom):
        if int(m.geom_bodyid[g]) not in hand or not (m.geom_contype[g] or m.geom_conaffinity[g]):
            continue
        if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_MESH):
            mid = int(m.geom_dataid[g])
            a = int(m.mesh_vertadr[mid])
            v = np.asarray(m.mesh_vert[a:a + int(m.mesh_vertnum[mid])], float)
        else:  # primitives: corners of their local bounding box (geom_aabb: centre, half-sizes)
            aabb = np.asarray(m.geom_aabb[g], float)
            v = aabb[:3] + corners * aabb[3:]
        p_world = d.geom_xpos[g] + v @ d.geom_xmat[g].reshape(3, 3).T
        pts.append((p_world - T[:3, 3]) @ T[:3, :3])
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def simulation_deviations(robot: RobotModel) -> dict:
    """How the simulated robot differs from its MJCF as written (Menagerie's Panda unless --robot-mjcf), for
    results.json: anyone re-simulating the exported files in the stock model gets other physics (a softer,
    ~10x weaker grasp). Values in SI units; the gripper servo on the Panda's finger tendon (mean opening)."""
    import mujoco

    from splattwin.robot.assets import TCP_SITE

    spec = robot.spec(visual=False)
    act = spec.actuator(robot.gripper_actuator)
    out: dict = {}
    if act is not None:
        stock = {"gain": float(act.gainprm[0]), "stiffness": -float(act.biasprm[1]),
                 "damping": -float(act.biasprm[2])}
        _stiffen_gripper(spec, robot)
        now = {"gain": float(act.gainprm[0]), "stiffness": -float(act.biasprm[1]), "damping": -float(act.biasprm[2])}
        if now != stock:
            out["gripper_servo"] = {
                "actuator": robot.gripper_actuator, "stiffness_N_per_m": now["stiffness"],
                "damping_Ns_per_m": now["damping"], "ctrl_gain": now["gain"],
                "model_stiffness_N_per_m": stock["stiffness"], "model_damping_Ns_per_m": stock["damping"],
                "model_ctrl_gain": stock["gain"],
                "why": (f"stiffened {now['stiffness'] / stock['stiffness']:g}x (GRIP_STIFFNESS) so that a closed hand "
                        "squeezes 12-40 N like a Franka Hand (the model's servo: ~1 N on a thin handle); it also closes far faster "
                        "than a real hand at the exported speed (robot/program.json waits for the gripper)")}
    out["gravity_compensation"] = ("the arm's gravity and Coriolis forces are cancelled by applied joint forces "
                                   "(qfrc_applied = qfrc_bias on the arm joints), as the Franka controller does")
    out["servo_feed_forward"] = ("the arm's position servos get ctrl = q + (kd/kp) qd of the trajectory (the "
                                 "reference velocity fed forward); without it they lag by kd/kp (0.1 s on the Menagerie Panda)")
    out["tcp_site"] = (f"site {TCP_SITE!r} on the hand between the fingertips, added when the model has none; "
                       "keyframes removed")
    return out


def _stiffen_gripper(spec, robot: RobotModel) -> None:
    """Raise the gripper servo's stiffness so that closing on an object squeezes it with a realistic force.

    The Menagerie Panda's finger servo is 100 N/m on the tendon (mean finger opening): closed on a 2.5 cm
    handle it pushes with ~1.3 N, less than a 200 g object weighs, while the real Franka hand grasps with
    20-70 N. At 1000 N/m it squeezes 12-40 N for 2.5-8 cm objects (force range +-100 N kept). Only
    affine-bias position servos are changed; the open/closed ctrl values stay the same.
    """
    import mujoco

    act = spec.actuator(robot.gripper_actuator)
    if act is None or act.biastype != mujoco.mjtBias.mjBIAS_AFFINE or act.biasprm[1] >= 0:
        return
    scale = GRIP_STIFFNESS / -act.biasprm[1]
    if scale <= 1.0:
        return
    g = list(act.gainprm)
    b = list(act.biasprm)
    g[0] *= scale
    b[1] *= scale
    b[2] *= scale
    act.gainprm = g
    act.biasprm = b


def _outline_region(region, where: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(centre [2+], size [2]) of twin.json's config.target_frame for the goal outline; None when absent,
    and None with a warning naming twin.json when malformed: the outline is only drawn, and a task that
    places into the region checks it itself (a size "big" crashed plans that never used it)."""
    from splattwin.limits import numbers

    if region is None:
        return None
    try:
        if not isinstance(region, dict) or "center" not in region or "size" not in region:
            raise InputError("config.target_frame must be {center: [x, y(, z)], size: s or [sx, sy]}", where)
        c, s = region["center"], region["size"]
        c = numbers(c, len(c) if isinstance(c, list) and len(c) in (2, 3) else 3, where,
                    "config.target_frame center", -MAX_BASE_OFFSET, MAX_BASE_OFFSET)
        s = numbers(s if isinstance(s, list) else [s], len(s) if isinstance(s, list) and len(s) in (1, 2) else 1,
                    where, "config.target_frame size", 0.0, MAX_BASE_OFFSET)
        if np.any(s <= 0):
            raise InputError("config.target_frame size must be > 0", where)
    except InputError as e:   # a library warning: through the logger, which a caller can filter or capture
        log.warning("%s; the goal region's outline is not drawn", e)
        return None
    return c, np.broadcast_to(s, (2,))


def _add_region_outline(spec, c: np.ndarray, s: np.ndarray, z: float) -> None:
    """Draw a goal region (centre, size xy) as a thin green outline on the table (visual only, no contacts)."""
    import mujoco

    w = 0.006
    for k, (dx, dy, hx, hy) in enumerate([(0, s[1] / 2, s[0] / 2, w), (0, -s[1] / 2, s[0] / 2, w),
                                          (s[0] / 2, 0, w, s[1] / 2), (-s[0] / 2, 0, w, s[1] / 2)]):
        spec.worldbody.add_geom(name=f"goal_outline_{k}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, 0.0005],
                                pos=[c[0] + dx, c[1] + dy, z + 0.0005], rgba=[0.1, 0.8, 0.2, 1], contype=0,
                                conaffinity=0, group=1)


def _under(model, b: int, ancestor: int) -> bool:
    while b > 0:
        if b == ancestor:
            return True
        b = int(model.body_parentid[b])
    return False
