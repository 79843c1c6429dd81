"""Per-camera SE(3) pose corrections learnt jointly with the Gaussians (as InstantSplat / gsplat pose_opt).

Each training camera c has a twist xi_c = (rho, phi) in R^6 (translation part rho in metres, rotation
part phi an axis-angle in radians, both in the camera frame), initialised at zero. The corrected
world-to-camera matrix is
    T_cam_world_corrected = exp(xi_c^) @ T_cam_world
passed to the rasterizer as its viewmat, which back-propagates to it. exp is torch.linalg.matrix_exp of
the 4x4 twist matrix: exact, differentiable, and cheap for one camera per step.
"""

from __future__ import annotations

import numpy as np
import torch


def hat(xi: torch.Tensor) -> torch.Tensor:
    """[..., 6] twists (rho, phi) -> [..., 4, 4] se(3) matrices."""
    rho, phi = xi[..., :3], xi[..., 3:]
    z = torch.zeros_like(phi[..., 0])
    wx, wy, wz = phi.unbind(-1)
    W = torch.stack([z, -wz, wy, wz, z, -wx, -wy, wx, z], dim=-1).reshape(xi.shape[:-1] + (3, 3))
    top = torch.cat([W, rho[..., None]], dim=-1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    return torch.cat([top, bottom], dim=-2)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """[..., 6] twists -> [..., 4, 4] rigid transforms."""
    return torch.linalg.matrix_exp(hat(xi))


class PoseCorrection:
    """Learnable corrections for C cameras with their own Adam optimizer (small learning rate)."""

    def __init__(self, n_cameras: int, lr: float = 1e-3, device: str | torch.device = "cpu"):
        self.xi = torch.nn.Parameter(torch.zeros(n_cameras, 6, device=device))
        self.optimizer = torch.optim.Adam([self.xi], lr=lr)

    def apply(self, viewmats: torch.Tensor, idx: torch.Tensor | list[int]) -> torch.Tensor:
        """Corrected world->camera matrices for cameras `idx`: exp(xi[idx]) @ viewmats [C,4,4]."""
        return se3_exp(self.xi[idx]) @ viewmats

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def corrected(self, T_cam_world: np.ndarray) -> np.ndarray:
        """Corrected world->camera matrices [C,4,4] (numpy float64) for all cameras."""
        with torch.no_grad():
            E = se3_exp(self.xi.detach().cpu().to(torch.float64)).numpy()
        return E @ np.asarray(T_cam_world, dtype=np.float64)

    def state_dict(self) -> dict:
        return {"xi": self.xi.detach().clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, sd: dict) -> None:
        with torch.no_grad():
            self.xi.copy_(sd["xi"].to(self.xi.device))
        self.optimizer.load_state_dict(sd["optimizer"])
