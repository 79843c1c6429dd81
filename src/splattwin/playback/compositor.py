"""Per-frame photoreal renders of the twin in motion: splats (background, fills, moved objects) and the
robot's Gaussians, composited in one rasterizer pass.

`PlaybackRenderer` keeps all Gaussians in preallocated float32 arrays laid out as
[background | per-object residue groups | fills | objects | robot]; a frame rewrites only the rows that
move (objects whose pose changed, the robot) and hands the rasterizer a contiguous prefix, so the static
background is never copied. The residue of an object that left its place (its cleaned-out Gaussians and
the background under its footprint) is not drawn (the rows of the background are masked by opacity 0);
its fill is. With a light (`DynamicScene.light`, estimated from the twin's shadows) the rows whose shadow
changes in a state -- the table where a moved object's shadow was or now falls, the moved objects, others
in their new shadows -- get their colours scaled (`playback.relight`); their trained colours come back when
the state changes.

Units: metres; images float32 [0,1]; depth = expected camera z (m), 0 where nothing was drawn.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from splattwin.capture.camera import Camera
from splattwin.playback.cameras import EyeInHand
from splattwin.playback.relight import scale_sh
from splattwin.playback.robot import RobotPose, RobotSplats
from splattwin.playback.scene import DynamicScene, pose_moved, rigid_transform
from splattwin.splat.config import filter_for
from splattwin.splat.gaussians import rgb_to_sh0


@dataclass
class FrameImage:
    """One rendered frame: rgb [H,W,3] float32 in [0,1] (over the background colour), depth [H,W] float32
    (expected camera z, m; 0 where empty), alpha [H,W] float32; timings ms by phase."""

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    timings: dict = field(default_factory=dict)

    def to_uint8(self) -> np.ndarray:
        return (np.clip(self.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


class PlaybackRenderer:
    """Renders a `DynamicScene` (and optionally the robot's Gaussians) for any camera and state.

    background: RGB behind everything (the splats' training background, black by default).
    """

    def __init__(self, scene: DynamicScene, robot: RobotSplats | None = None,
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0), backend: str = "auto",
                 relight: bool = True, robot_shadows: bool = True):
        from splattwin.errors import require_type

        require_type(scene, DynamicScene, "scene", "(DynamicScene.load(twin_dir))")
        self.scene, self.robot = scene, robot
        self.background = np.asarray(background, np.float32)
        self.backend = backend
        deg = scene.sh_degree
        self.K = (deg + 1) ** 2
        bd = scene.backdrop if scene.backdrop is not None else None
        self.n_backdrop = n_bd = len(bd) if bd is not None else 0
        bg = scene.background
        fills = [scene.fills[n].gaussians for n in scene.objects if n in scene.fills]
        n_bg = n_bd + len(bg)
        self._fill_slices: dict[str, slice] = {}
        n_fill = sum(len(f) for f in fills)
        n_obj = sum(len(g) for g in scene.objects.values())
        n_rob = len(robot) if robot is not None else 0
        N = n_bg + n_fill + n_obj + n_rob
        self.means = np.zeros((N, 3), np.float32)
        self.quats = np.zeros((N, 4), np.float32)
        self.quats[:, 0] = 1
        self.scales = np.zeros((N, 3), np.float32)
        self.opac = np.zeros(N, np.float32)
        self.sh = np.zeros((N, self.K, 3), np.float32)
        if n_bd:
            self._put(slice(0, n_bd), bd.means, bd.quats, bd.scales, bd.opacities, bd.sh)
        self._put(slice(n_bd, n_bg), bg.means, bg.quats, bg.scales, bg.opacities, bg.sh)
        self._bg_opac = self.opac[:n_bg].copy()
        self.n_bg = n_bg   # static rows: backdrop then background
        self._residue = {n: np.asarray(r, np.int64) + n_bd for n, r in scene.residue.items()}
        self._fills = {n: scene.fills[n].gaussians for n in scene.objects if n in scene.fills}
        self.n_obj, self.n_rob = n_obj, n_rob
        self._obj_cache: dict[str, tuple[np.ndarray, tuple]] = {}
        self._hidden: frozenset = frozenset()
        self._rob_start = -1
        self._backdrop_cache: tuple[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        if robot is not None:
            self._rob_scales = robot.scales.astype(np.float32)
            self._rob_opac = robot.opacities.astype(np.float32)
        # re-lighting (playback.relight): rows whose colour the current state scales, with their unscaled SH
        self.relighter = None
        if relight and scene.light is not None and scene.meshes:
            from splattwin.playback.relight import Relighter

            self.relighter = Relighter(scene.light, scene.meshes, scene.T_world_obj0, bg, scene.table_height,
                                       scene.objects, scene.unit)
        self._fill_lit0: dict[str, np.ndarray] = {}   # capture-time lit share of each fill's sources
        self._relit: list[tuple[np.ndarray, np.ndarray]] = []
        self._relit_key: bytes | None = None
        self.relit_rows = 0
        self.robot_shadows = robot_shadows

    def _put(self, sl: slice, means, quats, scales, opac, sh) -> None:
        self.means[sl] = means
        self.quats[sl] = quats
        self.scales[sl] = scales
        self.opac[sl] = opac
        k = min(self.K, sh.shape[1])
        self.sh[sl, :k] = sh[:, :k]
        if k < self.K:
            self.sh[sl, k:] = 0

    # ------------------------------------------------------------------------------------------------
    def layout(self, object_poses: dict[str, np.ndarray], robot_pose: RobotPose | None) -> int:
        """Write the state into the buffers; returns the number of Gaussians to draw."""
        sc = self.scene
        moved = frozenset(n for n in sc.objects if n in object_poses
                          and pose_moved(sc.T_world_obj0[n], np.asarray(object_poses[n])))
        relight_key = None
        robot_drawn = self.robot is not None and robot_pose is not None
        if self.relighter is not None:
            relight_key = b"".join([",".join(sorted(moved)).encode()] + [
                np.asarray(object_poses.get(n, sc.T_world_obj0[n]), np.float64).tobytes() for n in sc.objects] + (
                [np.asarray(robot_pose.q_arm, np.float64).tobytes(), np.float64(robot_pose.gripper_width).tobytes()]
                if robot_drawn and self.robot_shadows else [b"no robot"]))
            if relight_key != self._relit_key:
                for rows, base in self._relit:   # back to the trained colours before this state's are written
                    self.sh[rows] = base
                self._relit = []
        if moved != self._hidden:   # residue of moved objects hidden (opacity 0), others restored
            self.opac[:self.n_bg] = self._bg_opac
            for n in moved:
                self.opac[self._residue.get(n, np.zeros(0, np.int64))] = 0.0
            self._hidden = moved
            self._fill_slices = {}
        i = self.n_bg
        for n in sorted(moved):
            f = self._fills.get(n)
            if f is not None and len(f):
                sl = slice(i, i + len(f))
                if self._fill_slices.get(n) != sl:
                    self._put(sl, f.means, f.quats, f.scales, f.opacities, f.sh)
                    self._fill_slices[n] = sl
                i += len(f)
        obj_slices = {}
        for n, g in sc.objects.items():
            T = np.asarray(object_poses.get(n, sc.T_world_obj0[n]), float)
            sl = slice(i, i + len(g))
            key = (sl.start, T.tobytes())
            if self._obj_cache.get(n) != key:   # only moved rows are rewritten
                m, q, sh = rigid_transform(g, T)
                self._put(sl, m, q, g.scales, g.opacities, sc.object_sh(n, sh, T))
                self._obj_cache[n] = key
            obj_slices[n] = sl
            i += len(g)
        robot_means = None
        if robot_drawn:
            light = self.scene.light if self.relighter is not None else None
            m, q, rgb = self.robot.posed(robot_pose, light)
            sl = slice(i, i + len(m))
            self.means[sl] = m
            self.quats[sl] = q
            self.scales[sl] = self._rob_scales
            self.opac[sl] = self._rob_opac
            if self._rob_start != sl.start:   # higher SH bands of the robot are zero (Lambertian)
                self.sh[sl, 1:] = 0
                self._rob_start = sl.start
            self.sh[sl, 0] = rgb_to_sh0(rgb)
            robot_means = m
            i += len(m)
        if relight_key is not None and relight_key != self._relit_key:
            self._relight(sorted(moved), object_poses, obj_slices, robot_means if self.robot_shadows else None)
            self._relit_key = relight_key
        return i

    def _relight(self, moved: list[str], object_poses: dict[str, np.ndarray], obj_slices: dict[str, slice],
                 robot_means: np.ndarray | None = None) -> None:
        """Scale the colours of the rows this state shadows or lights differently from the capture
        (`playback.relight`): the moved objects' shadows (ray cast against their meshes, on the rows that
        can be in them) and the robot's (`ShadowMap` of its Gaussians, every row); the unscaled rows are
        kept in `_relit` for the next state."""
        from splattwin.playback.relight import ROBOT_SHADOW_CELL, ROBOT_SHADOW_EPS, ShadowMap

        rl, sc = self.relighter, self.scene
        poses = {n: np.asarray(object_poses.get(n, sc.T_world_obj0[n]), float) for n in sc.objects}
        sm = None
        if robot_means is not None and len(robot_means):
            sm = ShadowMap(robot_means, rl.L, ROBOT_SHADOW_CELL * sc.unit, ROBOT_SHADOW_EPS * sc.unit)
        total = 0

        def block(start: int, means: np.ndarray, lit0, ndl0, ndl, owner: str | None = None, every: bool = False):
            nonlocal total
            f = rl.block_factors(means, lit0, ndl0, ndl, poses, moved, owner,
                                 lambda c: self._spread(c + start), every, sm)
            rows = np.flatnonzero(np.abs(f - 1.0) > 1e-4)
            if len(rows):
                g = rows + start
                base = self.sh[g].copy()
                self._relit.append((g, base))
                self.sh[g] = scale_sh(base, f[rows])
                total += len(rows)

        if not (moved or sm is not None):
            self.relit_rows = 0
            return
        nb = self.n_backdrop
        block(nb, self.means[nb:self.n_bg].astype(np.float64), rl.static_lit0, rl.static_ndl, rl.static_ndl)
        for n, sl in self._fill_slices.items():   # fills: table copies, lit as their sources were, facing up
            up = np.full(sl.stop - sl.start, rl.L[2])
            block(sl.start, self.means[sl].astype(np.float64), self._fill_lit(n), up, up)
        for n, sl in obj_slices.items():
            if n in rl.index:
                ndl0, ndl = rl.object_ndl(n, poses[n])
                block(sl.start, self.means[sl].astype(np.float64), rl.obj_lit0[n], ndl0, ndl, n, every=n in moved)
        self.relit_rows = total

    def _fill_lit(self, name: str) -> np.ndarray:
        """Capture-time lit share of object `name`'s fill Gaussians: their sources' (the fill copies the
        table around the footprint, shadows included), 1 where the fill records no source."""
        if name not in self._fill_lit0:
            f = self.scene.fills[name]
            src = np.asarray(getattr(f, "source", np.zeros(0)), np.int64)
            if len(src) == len(f.gaussians) and len(src):
                self._fill_lit0[name] = self.relighter.static_lit0[src]   # static rows = the background
            else:
                self._fill_lit0[name] = np.ones(len(f.gaussians))
        return self._fill_lit0[name]

    def _spread(self, rows: np.ndarray) -> np.ndarray | None:
        """Footprint axes (world, current state) of buffer rows, for the soft shadow test."""
        return self.relighter.spread(self.quats[rows], self.scales[rows])

    def _raster(self, start: int, n: int, camera: Camera, filt: tuple[str, float | None]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Premultiplied rgb [H,W,3] (over black), expected depth [H,W] (0 where empty), alpha [H,W].
        filt: (rasterize_mode, eps2d px^2 or None for the mode's default)."""
        from splattwin.splat.rasterize import rasterization
        from splattwin.splat.rendering import resolve_backend_device

        name, dev = resolve_backend_device(self.backend)
        f = lambda a: torch.from_numpy(a[start:n]).to(dev)  # noqa: E731  (zero-copy rows on the CPU)
        vm = torch.as_tensor(camera.T_cam_world, dtype=torch.float32, device=dev)[None]
        Kt = torch.as_tensor(camera.K, dtype=torch.float32, device=dev)[None]
        means, quats, scales, opac, sh = self.means, self.quats, self.scales, self.opac, self.sh
        img, alpha, _ = rasterization(f(means), f(quats), f(scales), f(opac), f(sh), vm, Kt, camera.width,
                                      camera.height, sh_degree=self.scene.sh_degree, backgrounds=None,
                                      render_mode="RGB+ED", backend=name, rasterize_mode=filt[0], eps2d=filt[1])
        img = img[0].cpu().numpy()
        a = alpha[0, ..., 0].cpu().numpy()
        return img[..., :3], np.where(a > 1e-4, img[..., 3], 0.0).astype(np.float32), a

    def _backdrop_layer(self, camera: Camera, filt: tuple[str, float | None]):
        """The backdrop's render for this camera, cached while the camera stays put (static cameras pay
        it once per video)."""
        key = b"".join(np.ascontiguousarray(x, np.float64).tobytes() for x in
                       (camera.T_cam_world, camera.K, np.array([camera.width, camera.height]))) + repr(filt).encode()
        if self._backdrop_cache is not None and self._backdrop_cache[0] == key:
            return self._backdrop_cache[1]
        out = self._raster(0, self.n_backdrop, camera, filt)
        self._backdrop_cache = (key, out)
        return out

    @torch.no_grad()
    def render(self, camera: Camera, object_poses: dict[str, np.ndarray] | None = None,
               robot_pose: RobotPose | None = None, rasterize_mode: str | None = None,
               layered: bool | None = None) -> FrameImage:
        """One frame. object_poses: T_world_obj per object (missing: twin pose); robot_pose: None = no robot.
        rasterize_mode: None = the one the splats were trained with (`DynamicScene.rasterize_mode`, with
        its low-pass `DynamicScene.eps2d`); another mode renders with that mode's default low-pass.

        layered (default: when the robot is drawn): the backdrop (`DynamicScene.backdrop`) is rendered
        as a layer behind everything, so that no surroundings splat veils the robot; without the robot
        one depth-sorted pass of all splats, exactly as they were trained."""
        t0 = time.perf_counter()
        filt = filter_for((self.scene.rasterize_mode, self.scene.eps2d), rasterize_mode)
        n = self.layout(object_poses or {}, robot_pose)
        layered = (robot_pose is not None and self.robot is not None) if layered is None else layered
        layered = layered and self.n_backdrop > 0
        t1 = time.perf_counter()
        rgb, depth, a = self._raster(self.n_backdrop if layered else 0, n, camera, filt)
        t2 = time.perf_counter()
        bg = np.broadcast_to(self.background, rgb.shape)
        a_tot = a
        if layered:
            b_rgb, b_depth, b_a = self._backdrop_layer(camera, filt)
            bg = b_rgb + (1 - b_a)[..., None] * self.background
            depth = np.where(a > 1e-4, depth, b_depth)
            a_tot = a + (1 - a) * b_a
        out = rgb + (1 - a)[..., None] * bg
        t3 = time.perf_counter()
        return FrameImage(np.clip(out, 0, 1).astype(np.float32), depth.astype(np.float32), a_tot.astype(np.float32),
                          {"layout_ms": (t1 - t0) * 1e3, "raster_ms": (t2 - t1) * 1e3,
                           "backdrop_ms": (t3 - t2) * 1e3, "n_gaussians": n})

    def camera_for(self, camera: Camera | EyeInHand, robot_pose: RobotPose | None) -> Camera:
        """A world camera as is; an eye-in-hand camera placed on the robot's body at `robot_pose`."""
        if isinstance(camera, EyeInHand):
            if self.robot is None or robot_pose is None:
                raise ValueError("an eye-in-hand camera needs the robot and its pose")
            self.robot.set_pose(robot_pose)
            return camera.camera(self.robot.body_pose(camera.body))
        return camera

    def fill_mask(self, camera: Camera, object_poses: dict[str, np.ndarray]) -> np.ndarray:
        """[H,W] float32 in [0,1]: how much of each pixel shows hole-fill Gaussians in this state (for the
        report's mark of the filled regions), occlusion by everything else included."""
        from splattwin.splat.rendering import render

        sc = self.scene
        moved = set(sc.moved(object_poses))
        g = sc.gaussians(object_poses)
        keep = np.ones(len(sc.background), bool)
        for m in moved:
            keep[sc.residue.get(m, np.zeros(0, np.int64))] = False
        n_keep = int(keep.sum()) + (len(sc.backdrop) if sc.backdrop is not None else 0)
        feat = np.zeros((len(g), 1))
        n_fill = sum(len(sc.fills[m].gaussians) for m in moved if m in sc.fills)
        feat[n_keep:n_keep + n_fill] = 1.0
        img, _ = render(g, camera, colors=feat, backend=self.backend)
        return np.clip(img[..., 0], 0, 1)


def rollout_state(rollout, k: int) -> tuple[dict[str, np.ndarray], RobotPose]:
    """Object poses and robot pose of sample k of a `Rollout`."""
    poses = {n: T[k] for n, T in rollout.object_poses.items()}
    return poses, RobotPose(rollout.q_arm[k], float(rollout.gripper_width[k]))
