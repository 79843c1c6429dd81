"""Convenience renders of a `Gaussians` set from a `Camera`, as numpy images, for the later stages.

One function, `render()`, wraps `rasterization()` for every consumer (evaluation, semantic fusion,
geometry, report): it moves the arrays to the backend's device (CPU, or CUDA when gsplat is used),
renders without gradients and returns numpy. The thin helpers below (`render_rgb`, `render_rgbd`,
`render_depth`, `render_features`) pick its mode.

Float32 in [0,1] for colours, metres for depth. The camera is treated as an ideal pinhole: distortion
coefficients, if any, are ignored. Photos with lens distortion are compared with renders at their pinhole
camera after undistortion (`splattwin.capture.undistort`, done by `trainer.load_views` for training and
evaluation), or renders are resampled to the photo's grid (`undistort.distort_image`, the semantic fusion).
Frames: `camera.T_cam_world` is the view matrix (OpenCV convention); `T_cam_world=` overrides it (e.g. a
refined pose from training).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from splattwin.splat.rasterize import RENDER_MODES, backend_device, rasterization, resolve_backend

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.capture.camera import Camera
    from splattwin.splat.gaussians import Gaussians

RenderMode = str  # one of RENDER_MODES: "RGB" | "D" | "ED" | "RGB+D" | "RGB+ED"


def resolve_backend_device(backend: str = "auto") -> tuple[str, torch.device]:
    """The concrete rasterizer backend for `backend` and the torch device its inputs live on."""
    name = resolve_backend(backend)
    return name, backend_device(name)


def as_tensor(a: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """float32 contiguous tensor of an array, on `device` (the rasterizer's input convention)."""
    return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)


@torch.no_grad()
def render(gaussians: "Gaussians", camera: "Camera", *, mode: RenderMode = "RGB",
           colors: np.ndarray | None = None, background: tuple[float, ...] | None = None,
           backend: str = "auto", sh_degree: int | None = None, T_cam_world: np.ndarray | None = None,
           rasterize_mode: str = "classic", eps2d: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render one camera.

    Args:
        mode: "RGB" (colour channels), "ED" (expected depth only), "RGB+ED" (channels then depth), or
            "D" / "RGB+D" (the accumulated depth sum w_i z_i instead of the expected depth), as
            `rasterization`'s render_mode; anything else is a ValueError.
        colors: [N,D] float per-Gaussian features to composite instead of the SH colours (no view
            dependence, no clamping); None = the Gaussians' SH evaluated up to `sh_degree`.
        background: [D] values behind the Gaussians (channel modes only); None = zeros. For colour
            images (colors None) each value must be in [0, 1] (not 0-255): ValueError otherwise.
        sh_degree: cap on the SH degree used (None = the model's degree).
        T_cam_world: [4,4] view matrix overriding `camera.T_cam_world`.
        rasterize_mode, eps2d: the rasterizer's mode and low-pass (px^2; None: the mode's default), as the
            splats were trained (`splat.config.trained_filter`; a twin's: `Manifest.render_filter()`, a
            `splattwin train` folder's PLY: `splat.config.filter_beside(ply)`).
    Returns:
        image [H,W,C] float32 (C = D for "RGB", 1 for "D"/"ED", D+1 for "RGB+D"/"RGB+ED"), alpha [H,W]
        float32.
    """
    from splattwin.capture.camera import Camera
    from splattwin.errors import require_type
    from splattwin.splat.gaussians import Gaussians

    require_type(gaussians, Gaussians, "gaussians", "(splattwin.splat.Gaussians; from a file: Gaussians.load_ply)")
    require_type(camera, Camera, "camera", "(splattwin.capture.Camera)")
    h, w = camera.height, camera.width
    if mode not in RENDER_MODES:
        raise ValueError(f"render mode must be one of {', '.join(RENDER_MODES)}, got {mode!r}")
    if colors is not None and (np.ndim(colors) != 2 or len(colors) != len(gaussians)):
        raise ValueError(f"colors must be [N,D] with N={len(gaussians)}, got {np.shape(colors)}")
    d = 3 if colors is None else np.shape(colors)[-1]
    channels = mode.startswith("RGB")
    c = (d if channels else 0) + (0 if mode == "RGB" else 1)
    if background is not None:
        background = np.asarray(background, dtype=np.float64)
        if background.shape != (d,):
            raise ValueError(f"background must have {d} values (one per channel), got shape {background.shape}")
        if colors is None and not np.all((background >= 0) & (background <= 1)):
            raise ValueError(f"background colour must be in [0, 1] (float images, not 0-255), got "
                             f"{background.tolist()}")
        if not channels:
            background = None  # depth-only modes: nothing to draw it into
    if len(gaussians) == 0:
        img = np.zeros((h, w, c), np.float32)
        if background is not None:
            img[..., :d] = background.astype(np.float32)
        return img, np.zeros((h, w), np.float32)
    name, dev = resolve_backend_device(backend)
    t = lambda a: as_tensor(a, dev)  # noqa: E731
    if colors is None:
        deg = gaussians.sh_degree if sh_degree is None else min(int(sh_degree), gaussians.sh_degree)
        feats, deg_arg = t(gaussians.sh), deg
    else:
        feats, deg_arg = t(colors), None
    bg = None if background is None else t(background)[None]
    vm = camera.T_cam_world if T_cam_world is None else T_cam_world
    img, alpha, _ = rasterization(t(gaussians.means), t(gaussians.quats), t(gaussians.scales),
                                  t(gaussians.opacities), feats, t(vm)[None], t(camera.K)[None], w, h,
                                  sh_degree=deg_arg, backgrounds=bg, render_mode=mode, backend=name,
                                  rasterize_mode=rasterize_mode, eps2d=eps2d)
    return img[0].cpu().numpy().copy(), alpha[0, ..., 0].cpu().numpy().copy()


def render_rgbd(gaussians: "Gaussians", camera: "Camera", background: tuple[float, float, float] | None = None,
                backend: str = "auto", sh_degree: int | None = None, T_cam_world: np.ndarray | None = None,
                rasterize_mode: str = "classic", eps2d: float | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour, expected depth and alpha in one pass (rasterize_mode, eps2d: as `render`).

    Returns:
        rgb [H,W,3] float32 (over `background`, black by default), depth [H,W] float32 expected depth
        (m, camera z; NaN-free, 0 where nothing was drawn), alpha [H,W] float32 accumulated opacity.
    """
    img, alpha = render(gaussians, camera, mode="RGB+ED", background=background, backend=backend,
                        sh_degree=sh_degree, T_cam_world=T_cam_world, rasterize_mode=rasterize_mode, eps2d=eps2d)
    return img[..., :3].copy(), img[..., 3].copy(), alpha


def render_rgb(gaussians: "Gaussians", camera: "Camera", background: tuple[float, float, float] | None = None,
               backend: str = "auto", T_cam_world: np.ndarray | None = None, rasterize_mode: str = "classic",
               eps2d: float | None = None) -> np.ndarray:
    """[H,W,3] float32 colour image in [0,1] (over `background`, black by default)."""
    img, _ = render(gaussians, camera, mode="RGB", background=background, backend=backend,
                    T_cam_world=T_cam_world, rasterize_mode=rasterize_mode, eps2d=eps2d)
    return np.clip(img, 0.0, 1.0)


def render_depth(gaussians: "Gaussians", camera: "Camera", min_alpha: float = 0.5, backend: str = "auto",
                 T_cam_world: np.ndarray | None = None, rasterize_mode: str = "classic", eps2d: float | None = None
                 ) -> np.ndarray:
    """[H,W] float32 expected depth (camera z, metres) = sum w_i z_i / alpha; inf where alpha < `min_alpha`
    (too little surface there to trust a depth). rasterize_mode, eps2d, T_cam_world: as `render`."""
    img, alpha = render(gaussians, camera, mode="ED", colors=np.zeros((len(gaussians), 1), np.float32),
                        backend=backend, T_cam_world=T_cam_world, rasterize_mode=rasterize_mode, eps2d=eps2d)
    return np.where(alpha >= min_alpha, img[..., -1], np.inf).astype(np.float32)


def render_features(gaussians: "Gaussians", camera: "Camera", features: np.ndarray, backend: str = "auto",
                    T_cam_world: np.ndarray | None = None, rasterize_mode: str = "classic",
                    eps2d: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Composite arbitrary per-Gaussian features (e.g. one-hot labels) into the image.

    Args:
        features: [N,D] float values per Gaussian.
        T_cam_world, rasterize_mode, eps2d: as `render` (draw antialiased splats as they were trained).
    Returns:
        image [H,W,D] float32 (sum_i w_i f_i, no background), alpha [H,W] float32.
    """
    return render(gaussians, camera, mode="RGB", colors=np.asarray(features, dtype=np.float32), backend=backend,
                  T_cam_world=T_cam_world, rasterize_mode=rasterize_mode, eps2d=eps2d)
