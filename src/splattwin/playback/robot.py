"""The robot in the picture: the Panda as Gaussians sampled from its own visual meshes.

Decision (bench/photoreal.py, 320x240, the demo twin, 24 frames of the task, both paths interleaved on
the same frames, medians; the 2 cores were shared with other work, so absolute numbers moved 1.5x
between runs while the ranking did not):

    robot as Gaussians (chosen)     76 ms  = posing 21 + rasterizer 54 + compositing 1.5  (47k robot Gaussians)
    MuJoCo meshes + compositing    117 ms  = MuJoCo RGB+depth 79 (2x supersampled for the edges) + splats 32 + 1.5
    (under heavier load: 131 vs 201 ms)

MuJoCo's offscreen renderer runs on this machine's software Mesa (EGL/llvmpipe): the Panda's 136k visual
triangles cost ~60-120 ms per RGB frame even with shadows, reflections and the skybox off (~550 ms with
MuJoCo's default shadows), plus a depth pass, plus supersampling for antialiased edges, before the splats
are drawn. The Gaussians go through the splats' own rasterizer pass, so the depth order against the
splats, the antialiased silhouette (each Gaussian is a smooth footprint) and partial occlusion by
translucent splats come out of the same alpha compositing, with no GL context at all (the report and the
viewer run on machines without EGL). The cost: a softer look than shaded triangles up close. The mesh
path stays available (`MeshRobotLayer` + `composite_layers`) for machines with a hardware GL driver.

Shading: the meshes' material colours (MuJoCo `mat_rgba`), Lambertian under the twin's light (estimated from
its shadows, `playback.relight`; without one, a fixed light from above) with an ambient term, recomputed per
frame from each Gaussian's world normal. The arm's shadow on the scene: `playback.relight.ShadowMap`.
Frames: Gaussians are stored in their body's frame; MuJoCo forward kinematics places them per frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.transforms import (matrix_from_quat_wxyz, mujoco_quat_wxyz_from_matrix, quat_mul_wxyz,
                                  quat_wxyz_from_matrix)

LIGHT_DIR_WORLD = np.array([-0.35, 0.45, 1.0]) / np.linalg.norm([-0.35, 0.45, 1.0])  # towards the light
AMBIENT = 0.42           # ambient share of the fixed light (the rest is diffuse)
SPACING_ARM = 0.005      # m between samples on the links
SPACING_HAND = 0.003     # m on the hand body
SPACING_FINGERS = 0.0015  # m on the fingers (10-15 cm from the wrist camera)
SIGMA_FACTOR = 0.75      # tangential standard deviation / spacing
THICKNESS = 0.15         # normal standard deviation / tangential
OPACITY = 0.97


def _frames_from_normals(n: np.ndarray) -> np.ndarray:
    """[N,3,3] rotations whose third column is the unit normal."""
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def shade(albedo: np.ndarray, n_world: np.ndarray, light=None) -> np.ndarray:
    """[N,3] colour: albedo [N,3] at unit normals [N,3] (world) under `light` (a `playback.relight.Light`:
    the twin's, estimated from its shadows) or, without one, the fixed light from above."""
    if light is None:
        direction, ambient = LIGHT_DIR_WORLD, AMBIENT
    else:
        direction, ambient = np.asarray(light.direction, float), float(light.ambient)
    ndl = np.clip(n_world @ direction, 0.0, None)
    return np.clip(albedo * (ambient + (1.0 - ambient) * ndl)[:, None], 0.0, 1.0)


@dataclass
class RobotPose:
    """The robot's configuration for one frame: arm joints [n_arm] rad, gripper finger distance m."""

    q_arm: np.ndarray
    gripper_width: float


class RobotSplats:
    """Gaussians on the visual meshes of a robot MJCF, posed by MuJoCo forward kinematics.

    Attributes (N Gaussians, body frame): body [N] body id, p [N,3] m, n [N,3] unit normals, q [N,4] wxyz
    orientation of each flat Gaussian in its body, scales [N,3] m, albedo [N,3] in [0,1].
    """

    def __init__(self, xml_path: str | Path, T_world_base: np.ndarray | None = None, root_body: str = "link0",
                 arm_joints: list[str] | None = None, gripper_joints: list[str] | None = None,
                 spacing: float = SPACING_ARM, spacing_hand: float = SPACING_HAND,
                 spacing_fingers: float = SPACING_FINGERS, hand_bodies: tuple[str, ...] = ("hand",),
                 finger_bodies: tuple[str, ...] = ("left_finger", "right_finger"), seed: int = 0):
        import mujoco

        from splattwin.robot.assets import ensure_tcp_site

        spec = mujoco.MjSpec.from_file(str(xml_path))
        ensure_tcp_site(spec)
        for k in list(spec.keys):
            spec.delete(k)
        T = np.eye(4) if T_world_base is None else np.asarray(T_world_base, float)
        root = spec.body(root_body)
        if root is None:
            from splattwin.errors import InputError

            raise InputError(f"robot MJCF has no body {root_body!r}", xml_path)
        root.pos = T[:3, 3].tolist()
        root.quat = mujoco_quat_wxyz_from_matrix(T[:3, :3]).tolist()
        self.model = m = spec.compile()
        self.data = mujoco.MjData(m)
        self.T_world_base = T
        self.arm_joints = list(arm_joints or [])
        self.gripper_joints = list(gripper_joints or [])
        self._arm_adr = np.array([m.jnt_qposadr[m.joint(j).id] for j in self.arm_joints], int)
        self._grip_adr = np.array([m.jnt_qposadr[m.joint(j).id] for j in self.gripper_joints], int)
        ids = lambda names: {m.body(b).id for b in names if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) >= 0}  # noqa: E731
        hand_ids, finger_ids = ids(hand_bodies), ids(finger_bodies)
        rng = np.random.default_rng(seed)
        body, P, Nn, A, S = [], [], [], [], []
        for g in range(m.ngeom):
            visual = m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0
            if int(m.geom_type[g]) != int(mujoco.mjtGeom.mjGEOM_MESH) or not visual or m.geom_rgba[g, 3] == 0:
                continue
            mid = int(m.geom_dataid[g])
            va, vn = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
            fa, fn = int(m.mesh_faceadr[mid]), int(m.mesh_facenum[mid])
            V = np.asarray(m.mesh_vert[va:va + vn], float)
            F = np.asarray(m.mesh_face[fa:fa + fn], int)
            b = int(m.geom_bodyid[g])
            sp = spacing_fingers if b in finger_ids else spacing_hand if b in hand_ids else spacing
            tri = V[F]
            cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            area = 0.5 * np.linalg.norm(cr, axis=1)
            k = int(np.ceil(area.sum() / (sp * sp)))
            if k == 0:
                continue
            f = rng.choice(len(F), size=k, p=area / area.sum())
            r1, r2 = rng.random(k), rng.random(k)
            s1 = np.sqrt(r1)
            pts = (1 - s1)[:, None] * tri[f, 0] + (s1 * (1 - r2))[:, None] * tri[f, 1] + (s1 * r2)[:, None] * tri[f, 2]
            nrm = cr[f] / np.maximum(np.linalg.norm(cr[f], axis=1, keepdims=True), 1e-12)
            # geom frame -> body frame (MuJoCo stores the mesh in its re-centred geom frame)
            Rg = matrix_from_quat_wxyz(m.geom_quat[g])
            P.append(pts @ Rg.T + m.geom_pos[g])
            Nn.append(nrm @ Rg.T)
            matid = int(m.geom_matid[g])
            rgba = m.mat_rgba[matid] if matid >= 0 else m.geom_rgba[g]
            A.append(np.broadcast_to(np.asarray(rgba[:3], float), (k, 3)))
            S.append(np.full(k, sp))
            body.append(np.full(k, b))
        self.body = np.concatenate(body)
        self.p = np.concatenate(P)
        self.n = np.concatenate(Nn)
        self.albedo = np.concatenate(A)
        sp = np.concatenate(S)
        self.q = quat_wxyz_from_matrix(_frames_from_normals(self.n), canonical=False)
        sig = SIGMA_FACTOR * sp
        self.scales = np.stack([sig, sig, THICKNESS * sig], axis=1)
        self.opacities = np.full(len(self.p), OPACITY)

    @classmethod
    def panda(cls, T_world_base: np.ndarray | None = None, **kw) -> "RobotSplats":
        """The Menagerie Panda with hand (`splattwin.robot.assets`), base at T_world_base."""
        from splattwin.robot.assets import RobotModel

        rm = RobotModel.panda()
        return cls(rm.xml_path, T_world_base, root_body=rm.root_body, arm_joints=rm.arm_joints,
                   gripper_joints=rm.gripper_joints, **kw)

    def __len__(self) -> int:
        return int(len(self.p))

    def set_pose(self, pose: RobotPose) -> None:
        """Forward kinematics for one configuration (fingers at half the gripper width each)."""
        import mujoco

        d = self.data
        d.qpos[self._arm_adr] = np.asarray(pose.q_arm, float)[: len(self._arm_adr)]
        d.qpos[self._grip_adr] = float(pose.gripper_width) / 2
        mujoco.mj_kinematics(self.model, d)

    def body_pose(self, name: str) -> np.ndarray:
        """T_world_body [4,4] of a body at the last `set_pose`."""
        b = self.model.body(name).id
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[b].reshape(3, 3)
        T[:3, 3] = self.data.xpos[b]
        return T

    def posed(self, pose: RobotPose, light=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-frame means [N,3], quats [N,4] wxyz and shaded RGB [N,3] at `pose` (under `light`, see `shade`)."""
        self.set_pose(pose)
        d = self.data
        R = d.xmat.reshape(-1, 3, 3)[self.body]
        means = np.einsum("nij,nj->ni", R, self.p) + d.xpos[self.body]
        quats = quat_mul_wxyz(d.xquat[self.body], self.q)
        n_world = np.einsum("nij,nj->ni", R, self.n)
        return means, quats, shade(self.albedo, n_world, light)


class MeshRobotLayer:
    """The alternative: the robot's meshes through MuJoCo's offscreen renderer (RGB + depth), to be
    depth-composited over the splats with `composite_layers`. Needs an EGL/OSMesa context.

    Only the robot is in the model; shadows, reflections and the skybox are off (their cost on software
    GL is the larger part of a frame). Square pixels: the vertical field of view comes from fy, the
    principal point is honoured through the GL frustum.
    """

    def __init__(self, robot: RobotSplats, width: int, height: int, supersample: int = 2):
        import mujoco

        self.robot = robot
        self.s = int(supersample)
        self.width, self.height = width, height
        self.renderer = mujoco.Renderer(robot.model, height * self.s, width * self.s)
        self._mj = mujoco

    def render(self, camera, pose: RobotPose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rgb [H,W,3] float32, depth [H,W] (camera z, m; inf where no robot) and coverage [H,W] in [0,1]
        (fraction of the supersamples on the robot: the antialiased edge)."""
        mj = self._mj
        self.robot.set_pose(pose)
        r = self.renderer
        near, far = 0.01, 10.0
        self.robot.model.vis.map.znear = near / self.robot.model.stat.extent
        self.robot.model.vis.map.zfar = far / self.robot.model.stat.extent
        cam = mj.MjvCamera()
        r.update_scene(self.robot.data, camera=cam)
        for f in (mj.mjtRndFlag.mjRND_SHADOW, mj.mjtRndFlag.mjRND_REFLECTION, mj.mjtRndFlag.mjRND_SKYBOX):
            r.scene.flags[f] = False
        self._set_gl_camera(r.scene, camera, near, far)
        rgb = r.render().astype(np.float32) / 255.0
        r.enable_depth_rendering()
        depth = r.render().astype(np.float32)   # linear distance along the view axis (m)
        r.disable_depth_rendering()
        hit = depth < far * 0.999
        s, H, W = self.s, self.height, self.width
        cov = hit.reshape(H, s, W, s).mean(axis=(1, 3)).astype(np.float32)
        rgb_sum = (rgb * hit[..., None]).reshape(H, s, W, s, 3).sum(axis=(1, 3))
        n = hit.reshape(H, s, W, s).sum(axis=(1, 3))
        rgb_out = np.where(n[..., None] > 0, rgb_sum / np.maximum(n, 1)[..., None], 0).astype(np.float32)
        dmin = np.where(hit, depth, np.inf).reshape(H, s, W, s).min(axis=(1, 3))
        return rgb_out, dmin.astype(np.float32), cov

    def _set_gl_camera(self, scene, camera, near: float, far: float) -> None:
        T = camera.T_world_cam
        fy = camera.fy * self.s
        cx, cy = camera.cx * self.s, camera.cy * self.s
        W, H = self.width * self.s, self.height * self.s
        for c in scene.camera:
            c.pos[:] = T[:3, 3]
            c.forward[:] = T[:3, 2]
            c.up[:] = -T[:3, 1]
            c.frustum_near = near
            c.frustum_far = far
            c.frustum_top = near * cy / fy
            c.frustum_bottom = -near * (H - cy) / fy
            c.frustum_center = near * (W / 2 - cx) / fy

    def close(self) -> None:
        self.renderer.close()


def composite_layers(splat_rgb: np.ndarray, splat_depth: np.ndarray, splat_alpha: np.ndarray,
                     layer_rgb: np.ndarray, layer_depth: np.ndarray, layer_coverage: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Depth-composite an opaque layer (robot meshes) with the splats, per pixel.

    Where the layer is nearer than the splats' expected depth (or the splats are empty) it covers them by
    its coverage (antialiased edges), else the splats cover it by their alpha.
    Args: splat_rgb [H,W,3] premultiplied (rendered over black), splat_depth [H,W] expected depth (m),
        splat_alpha [H,W]; layer_rgb [H,W,3] (not premultiplied), layer_depth [H,W] (m, inf where empty),
        layer_coverage [H,W] in [0,1].
    Returns: premultiplied rgb [H,W,3] and alpha [H,W] (add background * (1 - alpha)).
    """
    sd = np.where(splat_alpha > 1e-4, splat_depth, np.inf)
    front = (layer_depth < sd)[..., None]
    c = layer_coverage[..., None]
    a = splat_alpha[..., None]
    rgb = np.where(front, layer_rgb * c + splat_rgb * (1 - c), splat_rgb + (1 - a) * c * layer_rgb)
    alpha = np.where(front, c + (1 - c) * a, a + (1 - a) * c)[..., 0]
    return rgb.astype(np.float32), alpha.astype(np.float32)
