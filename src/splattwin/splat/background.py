"""Background / far field for unbounded captures (a statue in a hall, a table in a room).

A 3DGS scene initialised from SfM points has Gaussians only where features were matched; what lies beyond
(ceiling, sky, a far wall with no texture) is rendered over the fixed background colour (black), so the
optimiser fakes it with floaters close to the cameras, which ruin new views. Two remedies, each optional:

1. `BackgroundModel` (TrainConfig.background_mode): what shows where the splats are transparent,
   composited as  C = C_splats + (1 - alpha) * B(ray):
     "fixed"  B = TrainConfig.background (the 3DGS default, nothing learnt)
     "color"  B = one learnt RGB colour
     "env"    B = a learnt low-resolution environment map (equirectangular, `env_size` = (H, W), RGB,
              bilinear), looked up by the world-frame direction of each pixel's ray: the far field as a
              function of direction only, so a new view sees the same sky/ceiling in the same direction.
2. `sphere_points` (TrainConfig.bg_sphere_points): extra initial Gaussians spread evenly (Fibonacci
   lattice) on a sphere around the scene beyond the initial points, each coloured by the mean of the
   training pixels it projects to (the views that see it), so the far field starts as geometry too.

Frames: directions in the world frame of the cameras (T_world_cam, OpenCV: x right, y down, z forward);
the environment map's longitude is atan2(y, x) and latitude asin(z) of the world direction.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

BACKGROUND_MODES = ("fixed", "color", "env")


def ray_directions(K: torch.Tensor, T_world_cam: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H,W,3] unit world-frame directions of the rays through the pixel centres (u+0.5, v+0.5).
    K [3,3] intrinsics (px), T_world_cam [4,4] camera-to-world."""
    dev, dt = K.device, K.dtype
    v, u = torch.meshgrid(torch.arange(height, device=dev, dtype=dt) + 0.5,
                          torch.arange(width, device=dev, dtype=dt) + 0.5, indexing="ij")
    d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    d = d_cam @ T_world_cam[:3, :3].T
    return d / d.norm(dim=-1, keepdim=True)


def equirect_lookup(env: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of an environment map env [3,He,We] (values as stored) at unit directions [...,3]
    -> [...,3]. Longitude atan2(y, x) in [-pi, pi] spans the width (wrapping), latitude asin(z) the height
    (+pi/2 at row 0)."""
    shape = dirs.shape[:-1]
    d = dirs.reshape(-1, 3)
    lon = torch.atan2(d[:, 1], d[:, 0]) / math.pi                   # [-1, 1]
    lat = -torch.asin(d[:, 2].clamp(-1.0, 1.0)) / (math.pi / 2)     # [-1, 1], up = -1 (row 0)
    # wrap in longitude: pad one column on each side so the seam interpolates across
    e = torch.cat([env[:, :, -1:], env, env[:, :, :1]], dim=2)
    we = env.shape[2]
    x = lon * we / (we + 2)  # align_corners=False coordinates of the padded map
    grid = torch.stack([x, lat], -1)[None, None]  # [1,1,P,2]
    out = F.grid_sample(e[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.reshape(*shape, 3)


class BackgroundModel:
    """A learnt background ("color" or "env", see module doc) with its own Adam optimizer."""

    def __init__(self, mode: str, init_rgb: Sequence[float] = (0.5, 0.5, 0.5), env_size: tuple[int, int] = (16, 32),
                 lr: float = 1e-2, device: str | torch.device = "cpu"):
        if mode not in ("color", "env"):
            raise ValueError(f"learnt background mode must be 'color' or 'env', got {mode!r}")
        self.mode = mode
        rgb = torch.as_tensor(np.clip(np.asarray(init_rgb, np.float64), 0.0, 1.0), dtype=torch.float32)
        shape = (3, 1, 1) if mode == "color" else (3, int(env_size[0]), int(env_size[1]))
        self.param = torch.nn.Parameter(rgb.reshape(3, 1, 1).expand(shape).clone().to(device))
        self.optimizer = torch.optim.Adam([self.param], lr=lr)

    def colors(self, dirs: torch.Tensor) -> torch.Tensor:
        """Background colour [...,3] for unit world directions [...,3] (values clamped to [0,1])."""
        if self.mode == "color":
            return self.param[:, 0, 0].clamp(0.0, 1.0).expand(dirs.shape)
        return equirect_lookup(self.param, dirs).clamp(0.0, 1.0)

    def composite(self, img: torch.Tensor, alpha: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                  rendered_bg: torch.Tensor | None = None) -> torch.Tensor:
        """img [H,W,3] rendered over the constant `rendered_bg` [3] (None: black), alpha [H,W,1] ->
        the image over this background: img + (1 - alpha) (B(ray) - rendered_bg)."""
        h, w = img.shape[:2]
        B = self.colors(ray_directions(K, T_world_cam, w, h))
        if rendered_bg is not None:
            B = B - rendered_bg.reshape(1, 1, 3)
        return img + (1.0 - alpha) * B

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return {"mode": self.mode, "param": self.param.detach().cpu().clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, sd: dict) -> None:
        if sd["mode"] != self.mode or tuple(sd["param"].shape) != tuple(self.param.shape):
            raise ValueError(f"background state is {sd['mode']!r} {tuple(sd['param'].shape)}, this run "
                             f"{self.mode!r} {tuple(self.param.shape)}")
        with torch.no_grad():
            self.param.copy_(sd["param"].to(self.param.device))
        self.optimizer.load_state_dict(sd["optimizer"])

    @classmethod
    def from_state(cls, sd: dict, device: str | torch.device = "cpu") -> BackgroundModel:
        """A model holding a saved state's parameters (for rendering; the optimizer state is fresh)."""
        p = sd["param"]
        m = cls(sd["mode"], env_size=tuple(p.shape[1:]), device=device)
        with torch.no_grad():
            m.param.copy_(p.to(device))
        return m


def sphere_points(cameras: Sequence, images: Sequence[np.ndarray], center: np.ndarray, radius: float, n: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """n points [n,3] evenly on the sphere (center, radius) and colours [n,3] in [0,1]: the mean of the
    pixels they project to in the cameras (`Camera`s, with images [H,W,3] of any size) that see them,
    the mean image colour where none does. Lens distortion is ignored."""
    from splattwin.splat.init import fibonacci_sphere

    xyz = np.asarray(center, np.float64) + radius * fibonacci_sphere(n)
    acc, cnt = np.zeros((n, 3)), np.zeros(n)
    for cam, img in zip(cameras, images):
        h, w = img.shape[:2]
        s = w / cam.width
        T = cam.T_cam_world
        p = xyz @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        front = z > 1e-6
        u = (cam.fx * p[:, 0] / np.where(front, z, 1.0) + cam.cx) * s
        v = (cam.fy * p[:, 1] / np.where(front, z, 1.0) + cam.cy) * s
        ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        acc[ok] += img[v[ok].astype(int), u[ok].astype(int), :3]
        cnt[ok] += 1
    mean = np.mean([im.reshape(-1, im.shape[-1])[:, :3].mean(0) for im in images], axis=0) if len(images) else 0.5
    rgb = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], mean)
    return xyz, np.clip(rgb, 0.0, 1.0)


def sphere_radius(points_xyz: np.ndarray | None, center: np.ndarray, scene_scale: float, factor: float) -> float:
    """Radius of the background sphere: `factor` x the scene scale, and beyond 98 % of the initial points
    (so the sphere lies behind the reconstructed geometry), m."""
    r = factor * scene_scale
    if points_xyz is not None and len(points_xyz):
        r = max(r, 1.1 * float(np.quantile(np.linalg.norm(np.asarray(points_xyz) - center, axis=1), 0.98)))
    return r
