"""CUDA backend: gsplat's `rasterization()` (gsplat >= 1.4, tested API of 1.5) behind our contract.

Chosen by `rasterization(backend="auto")` when `torch.cuda.is_available()` and gsplat imports, or by
`backend="cuda"`. Inputs are moved to the CUDA device; outputs stay there (the caller's tensors decide).
Differences to the CPU/reference backends are gsplat's own small ones: alpha clamp 0.999 instead of 0.99,
and a Gaussian reaches every pixel of its tiles where its alpha is >= 1/255 (gsplat's opacity-aware
extent) instead of stopping at its 3-sigma box. With opacities <= 0.35 the two agree exactly (the
alpha >= 1/255 ellipse then lies inside the 3-sigma box). On the trained embedded scene (32k Gaussians,
320x240, emulated kernels) colours differ by 2e-4 on average and 2e-3 at the 99th percentile.

The meta dict is normalised to our contract: unpacked [C,N,...] tensors (packed=False), `radii` [C,N]
int32 (gsplat 1.5 returns per-axis radii [C,N,2]; we report the larger), `visibility` = both per-axis
radii > 0, and `means2d` with its gradient retained for densification.

Camera-pose gradients are exact: gsplat's own viewmat gradient is an approximation (its projection backward
leaves out the rotation's term through the 3D covariance; gsplat issue #737, PR #127). On an H200 it was
0.6 % off our float64 reference (1.2 % with a trained scene's opacities) while every other gradient agreed
to 1e-6 (`bench/cuda.py`). So when the view matrix needs a gradient (`--refine-poses`), the Gaussians are
brought into the camera frame by torch (means R x + t, covariances R Sigma R^T, SH colours from world-frame
directions) and gsplat renders them through an identity view matrix: autograd then differentiates the pose
exactly, as our CPU backend does (`_camera_frame_call`). That is done for one camera per call, as training
renders (several cameras in one call keep gsplat's approximation: a batched call would have to hand back
per-camera screen positions whose gradient densification reads). Without a pose gradient gsplat gets the
world-frame Gaussians as before.

Without a GPU this module is tested through gsplat's real Python front end (`gsplat.rasterization`) with
its CUDA primitives replaced by CPU emulations of the same kernels (tests/splat/conftest.py,
`gsplat_on_cpu`): argument conventions, SH, render modes, backgrounds, gradients and the trainer's
"cuda" path are checked against our reference; the CUDA kernels themselves are gsplat's and tested there.
"""

from __future__ import annotations

from typing import Any

import torch


def rasterization_cuda(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=None,
                       backgrounds=None, render_mode="RGB", near_plane=0.01, far_plane=1e10, eps2d=0.3,
                       rasterize_mode="classic") -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Same signature and outputs as `splattwin.splat.rasterize.rasterization` (backend "cuda")."""
    from splattwin.splat.rasterize import backend_device, resolve_backend

    resolve_backend("cuda")  # raises an InputError saying why when the backend cannot run here
    import gsplat

    # Tensors already on a CUDA device stay there (multi-GPU callers pick theirs); others go to the default.
    cuda = backend_device("cuda")
    dev = means.device if means.device.type == cuda.type else cuda
    mv = lambda t: None if t is None else t.to(dev)  # noqa: E731
    kw = dict(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, packed=False, tile_size=16,
              backgrounds=mv(backgrounds), render_mode=render_mode, rasterize_mode=rasterize_mode)
    if viewmats.requires_grad and torch.is_grad_enabled() and viewmats.shape[0] == 1:
        render, alphas, meta = _camera_frame_call(mv(means), mv(quats), mv(scales), mv(opacities), mv(colors),
                                                  mv(viewmats), mv(Ks), int(width), int(height), sh_degree, kw)
    else:
        render, alphas, meta = gsplat.rasterization(
            mv(means), mv(quats), mv(scales), mv(opacities), mv(colors), mv(viewmats), mv(Ks), int(width),
            int(height), sh_degree=sh_degree, **kw)
    radii = meta["radii"]
    if radii.ndim == 3:  # gsplat >= 1.5: per-axis [C,N,2]; a Gaussian is drawn only if both are > 0
        visible = (radii > 0).all(dim=-1)
        radii = torch.where(visible, radii.amax(dim=-1), torch.zeros_like(radii[..., 0]))
    else:
        visible = radii > 0
    radii = radii.to(torch.int32)
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    out = dict(meta)
    out.update({"means2d": means2d, "radii": radii, "depths": meta["depths"], "conics": meta.get("conics"),
                "visibility": visible, "width": int(width), "height": int(height), "backend": "cuda",
                "n_cameras": viewmats.shape[0]})
    return render, alphas, out


def _camera_frame_call(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, kw):
    """gsplat's rasterization of one camera (viewmats [1,4,4], world -> camera) with the Gaussians moved into
    its frame by torch, so that the pose gradient is autograd's exact one (see the module doc): means
    R x + t [N,3] m, covariances R Sigma R^T [N,3,3] m^2 (`reference.quat_scale_to_covar`), and colours
    [1,N,3] from the SH coefficients [N,K,3] along world-frame directions camera centre -> mean (gsplat's
    convention, +0.5 and clamped at 0), then an identity view matrix. Same outputs as the direct call."""
    import gsplat.rendering as gr

    from splattwin.splat.reference import quat_scale_to_covar

    R, t = viewmats[0, :3, :3], viewmats[0, :3, 3]
    means_cam = means @ R.T + t
    covars_cam = R @ quat_scale_to_covar(quats, scales) @ R.T
    if sh_degree is not None:
        campos = -R.T @ t   # camera centre in the world frame, m
        colors = torch.clamp_min(gr.spherical_harmonics(sh_degree, means - campos, colors) + 0.5, 0.0)
    eye = torch.eye(4, dtype=viewmats.dtype, device=viewmats.device)[None]
    colors = colors if colors.dim() == 3 else colors[None]   # [1,N,D]; per-camera colours are [1,N,D] already
    return gr.rasterization(means_cam, quats, scales, opacities, colors, eye, Ks, width, height,
                            sh_degree=None, covars=covars_cam, **kw)
