"""Convenience renders of a `Gaussians` set from a `Camera`, as numpy images, for the later stages.

No gradients (torch.no_grad); float32 in [0,1] for colours, metres for depth. The camera is treated as an
ideal pinhole: distortion coefficients, if any, are ignored (render undistorted images, or undistort the
photos, before comparing). Frames: `camera.T_cam_world` is the view matrix (OpenCV convention).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from splattwin.splat.rasterization import rasterization

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians


def _tensors(g: "Gaussians", camera: "Camera"):
    f = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)  # noqa: E731
    return (f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(camera.T_cam_world)[None], f(camera.K)[None])


@torch.no_grad()
def render_rgbd(gaussians: "Gaussians", camera: "Camera", background: tuple[float, float, float] | None = None,
                backend: str = "auto", sh_degree: int | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour, expected depth and alpha in one pass.

    Returns:
        rgb [H,W,3] float32 (over `background`, black by default), depth [H,W] float32 expected depth
        (m, camera z; NaN-free, 0 where nothing was drawn), alpha [H,W] float32 accumulated opacity.
    """
    means, quats, scales, opac, vm, K = _tensors(gaussians, camera)
    if len(gaussians) == 0:
        h, w = camera.height, camera.width
        rgb = np.zeros((h, w, 3), np.float32)
        if background is not None:
            rgb[:] = np.asarray(background, np.float32)
        return rgb, np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    deg = gaussians.sh_degree if sh_degree is None else min(int(sh_degree), gaussians.sh_degree)
    sh = torch.as_tensor(gaussians.sh, dtype=torch.float32)
    bg = None if background is None else torch.tensor([background], dtype=torch.float32)
    img, alpha, _ = rasterization(means, quats, scales, opac, sh, vm, K, camera.width, camera.height,
                                  sh_degree=deg, backgrounds=bg, render_mode="RGB+ED", backend=backend)
    img = img[0].numpy()
    return img[..., :3].copy(), img[..., 3].copy(), alpha[0, ..., 0].numpy().copy()


def render_rgb(gaussians: "Gaussians", camera: "Camera", background: tuple[float, float, float] | None = None,
               backend: str = "auto") -> np.ndarray:
    """[H,W,3] float32 colour image (over `background`, black by default)."""
    return render_rgbd(gaussians, camera, background=background, backend=backend)[0]


def render_depth(gaussians: "Gaussians", camera: "Camera", min_alpha: float = 0.5, backend: str = "auto"
                 ) -> np.ndarray:
    """[H,W] float32 expected depth (camera z, metres) = sum w_i z_i / alpha; inf where alpha < `min_alpha`
    (too little surface there to trust a depth)."""
    _, depth, alpha = render_rgbd(gaussians, camera, backend=backend, sh_degree=0)
    return np.where(alpha >= min_alpha, depth, np.inf).astype(np.float32)


@torch.no_grad()
def render_features(gaussians: "Gaussians", camera: "Camera", features: np.ndarray, backend: str = "auto"
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Composite arbitrary per-Gaussian features (e.g. one-hot labels) into the image.

    Args:
        features: [N,D] float values per Gaussian.
    Returns:
        image [H,W,D] float32 (sum_i w_i f_i, no background), alpha [H,W] float32.
    """
    feats = np.asarray(features, dtype=np.float32)
    if feats.ndim != 2 or feats.shape[0] != len(gaussians):
        raise ValueError(f"features must be [N,D] with N={len(gaussians)}, got {feats.shape}")
    h, w = camera.height, camera.width
    if len(gaussians) == 0:
        return np.zeros((h, w, feats.shape[1]), np.float32), np.zeros((h, w), np.float32)
    means, quats, scales, opac, vm, K = _tensors(gaussians, camera)
    img, alpha, _ = rasterization(means, quats, scales, opac, torch.from_numpy(feats), vm, K, w, h,
                                  backend=backend)
    return img[0].numpy().copy(), alpha[0, ..., 0].numpy().copy()
