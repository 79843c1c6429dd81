"""CUDA backend: gsplat's `rasterization()` (gsplat >= 1.4, tested API of 1.5) behind our contract.

Chosen by `rasterization(backend="auto")` when `torch.cuda.is_available()` and gsplat imports, or by
`backend="cuda"`. Inputs are moved to the CUDA device; outputs stay there (the caller's tensors decide).
Differences to the CPU/reference backends are gsplat's own small ones (alpha clamp 0.999 instead of 0.99,
tile-granular instead of pixel-granular 3-sigma culling); images agree to a few 1e-3.

The meta dict is normalised to our contract: unpacked [C,N,...] tensors (packed=False), `radii` [C,N]
int32 (gsplat 1.5 returns per-axis radii [C,N,2]; we report the larger), `visibility` = radii > 0, and
`means2d` with its gradient retained for densification.
"""

from __future__ import annotations

from typing import Any

import torch

from splattwin.errors import InputError


def rasterization_cuda(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=None,
                       backgrounds=None, render_mode="RGB", near_plane=0.01, far_plane=1e10, eps2d=0.3,
                       rasterize_mode="classic") -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Same signature and outputs as `splattwin.splat.rasterization.rasterization` (backend "cuda")."""
    try:
        import gsplat
    except Exception as e:  # pragma: no cover - needs a GPU machine
        raise InputError(f"rasterizer backend 'cuda' needs gsplat (pip install gsplat): {e}") from e
    if not torch.cuda.is_available():
        raise InputError("rasterizer backend 'cuda' requested but no CUDA device is available")
    dev = means.device if means.device.type == "cuda" else torch.device("cuda")  # pragma: no cover
    mv = lambda t: None if t is None else t.to(dev)  # noqa: E731  # pragma: no cover
    render, alphas, meta = gsplat.rasterization(  # pragma: no cover
        mv(means), mv(quats), mv(scales), mv(opacities), mv(colors), mv(viewmats), mv(Ks), int(width), int(height),
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        tile_size=16, backgrounds=mv(backgrounds), render_mode=render_mode, rasterize_mode=rasterize_mode)
    radii = meta["radii"]  # pragma: no cover
    if radii.ndim == 3:  # pragma: no cover - gsplat >= 1.5: per-axis [C,N,2]
        radii = radii.amax(dim=-1)
    radii = radii.to(torch.int32)  # pragma: no cover
    means2d = meta["means2d"]  # pragma: no cover
    if means2d.requires_grad:  # pragma: no cover
        means2d.retain_grad()
    out = dict(meta)  # pragma: no cover
    out.update({"means2d": means2d, "radii": radii, "depths": meta["depths"], "conics": meta.get("conics"),
                "visibility": radii > 0, "width": int(width), "height": int(height), "backend": "cuda",
                "n_cameras": viewmats.shape[0]})
    return render, alphas, out  # pragma: no cover
