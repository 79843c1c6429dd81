"""The MuJoCo world: the twin (table, background, free objects) plus the robot at a base pose.

Frames: the twin frame is MuJoCo's world frame (z up, table top at z = table_height, metres). The robot's
root body is placed at `BasePose` (x, y, z in metres, yaw in radians about +z). Default: beside the table
at (-0.50, 0, 0) facing +x (docs/CONTRACTS.md). Nothing here needs an OpenGL context.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.robot.assets import RobotModel
from splattwin.twin.manifest import Manifest
from splattwin.twin.mjcf import add_twin, check_scaled, mat_to_quat_wxyz


@dataclass(frozen=True)
class BasePose:
    """Robot base in the twin frame: position (m) and yaw (rad) about +z."""

    x: float = -0.50
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0

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
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = [self.x, self.y, self.z]
        return T


def pose_from_qpos(qpos7: np.ndarray) -> np.ndarray:
    """Free-joint qpos [7] (pos, quat wxyz) -> T_world_body [4,4]."""
    import mujoco

    T = np.eye(4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(qpos7[3:7], dtype=np.float64))
    T[:3, :3] = R.reshape(3, 3)
    T[:3, 3] = qpos7[:3]
    return T


def qpos_from_pose(T: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(T)[:3, 3], mat_to_quat_wxyz(np.asarray(T)[:3, :3])])


@dataclass
class World:
    """Compiled world and the indices the robot stage needs.

    arm_qpos_adr / arm_dof_adr: [n_arm] addresses of the arm joints. arm_act / grip_act: actuator ids.
    obj_qpos_adr: free-joint qpos address per object name. robot_bodies: body ids of the robot.
    """

    model: object
    data: object
    robot: RobotModel
    manifest: Manifest
    twin_dir: Path
    base: BasePose
    objects: list[str]
    arm_qpos_adr: np.ndarray
    arm_dof_adr: np.ndarray
    arm_act: np.ndarray
    grip_act: int
    tcp_site: int
    obj_qpos_adr: dict[str, int]
    obj_body: dict[str, int]
    robot_bodies: set[int] = field(default_factory=set)

    # -- state ------------------------------------------------------------------------------------
    def arm_q(self) -> np.ndarray:
        return self.data.qpos[self.arm_qpos_adr].copy()

    def set_arm(self, q: np.ndarray, gripper_open: bool = True) -> None:
        """Teleport the arm (and servo targets) to q, gripper open or closed; recompute kinematics."""
        import mujoco

        d = self.data
        d.qpos[self.arm_qpos_adr] = q
        d.qvel[self.arm_dof_adr] = 0.0
        d.ctrl[self.arm_act] = q
        half = self.robot.max_opening / 2 if gripper_open else 0.0
        for name in self.robot.gripper_joints:
            j = self.model.joint(name)
            d.qpos[j.qposadr[0]] = half
        d.ctrl[self.grip_act] = self.robot.gripper_open if gripper_open else self.robot.gripper_closed
        mujoco.mj_forward(self.model, d)

    def object_pose(self, name: str) -> np.ndarray:
        """T_world_obj [4,4] of a free object now."""
        a = self.obj_qpos_adr[name]
        return pose_from_qpos(self.data.qpos[a:a + 7])

    def set_object_pose(self, name: str, T: np.ndarray) -> None:
        a = self.obj_qpos_adr[name]
        self.data.qpos[a:a + 7] = qpos_from_pose(T)

    def tcp_pose(self) -> np.ndarray:
        """T_world_tcp [4,4] now (after mj_forward / mj_step)."""
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[self.tcp_site].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[self.tcp_site]
        return T

    def body_name(self, b: int) -> str:
        import mujoco

        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, int(b)) or "world"


def build_world(twin_dir: str | Path, manifest: Manifest | None = None, robot: RobotModel | None = None,
                base: BasePose | None = None, poses: dict[str, np.ndarray] | None = None,
                visual: bool = True) -> World:
    """Compile twin + robot. poses: optional T_world_obj overrides (perturbed trials). visual=False:
    without the robot's visual meshes (same physics, fast compile; nothing to render)."""
    import mujoco

    twin_dir = Path(twin_dir)
    manifest = manifest or Manifest.load(twin_dir)
    check_scaled(manifest, twin_dir / "twin.json")
    robot = robot or RobotModel.panda()
    base = base or BasePose()
    spec = robot.spec(visual=visual)
    root = spec.body(robot.root_body)
    T = base.matrix()
    root.pos = T[:3, 3].tolist()
    root.quat = mat_to_quat_wxyz(T[:3, :3]).tolist()
    spec.modelname = "splattwin_world"
    _stiffen_gripper(spec, robot)
    objects = add_twin(spec, manifest, twin_dir, poses=poses)
    if visual and isinstance(manifest.config.get("target_frame"), dict):
        _add_region_outline(spec, manifest.config["target_frame"], manifest.background.table_height)
    try:
        model = spec.compile()
    except ValueError as e:
        raise InputError(f"world does not compile: {e}", twin_dir / "twin.json") from e
    data = mujoco.MjData(model)
    jid = lambda n: model.joint(n).id  # noqa: E731
    arm_j = [jid(n) for n in robot.arm_joints]
    obj_qpos = {o: int(model.jnt_qposadr[model.joint(f"{o}/free").id]) for o in objects}
    obj_body = {o: model.body(o).id for o in objects}
    root_id = model.body(robot.root_body).id
    robot_bodies = {b for b in range(model.nbody) if _under(model, b, root_id)}
    w = World(model=model, data=data, robot=robot, manifest=manifest, twin_dir=twin_dir, base=base,
              objects=objects, arm_qpos_adr=np.array([model.jnt_qposadr[j] for j in arm_j]),
              arm_dof_adr=np.array([model.jnt_dofadr[j] for j in arm_j]),
              arm_act=np.array([model.actuator(n).id for n in robot.arm_actuators]),
              grip_act=model.actuator(robot.gripper_actuator).id,
              tcp_site=model.site(robot.tcp_site).id, obj_qpos_adr=obj_qpos, obj_body=obj_body,
              robot_bodies=robot_bodies)
    w.set_arm(robot.home, gripper_open=True)
    return w


GRIP_STIFFNESS = 1000.0   # N/m of the gripper's position servo (Menagerie: 100)


def hand_points_tcp(world: World) -> np.ndarray:
    """Points [K,3] (m, TCP frame) of the hand's and fingers' collision geometry at the current gripper
    opening: mesh vertices and box/other-primitive bounding-box corners. Max of [:, 2] is how far the
    fingers reach beyond the TCP along the approach (the fingertips, 8.9 mm on the Menagerie Panda)."""
    import mujoco

    m, d = world.model, world.data
    mujoco.mj_kinematics(m, d)
    T = world.tcp_pose()
    hand = {m.body(b).id for b in world.robot.hand_bodies}
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


def _add_region_outline(spec, region: dict, z: float) -> None:
    """Draw a goal region {center, size} as a thin green outline on the table (visual only, no contacts)."""
    import mujoco

    c = np.asarray(region["center"], float)
    s = np.broadcast_to(np.asarray(region["size"], float), (2,))
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
