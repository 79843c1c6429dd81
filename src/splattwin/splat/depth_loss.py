"""Depth supervision of the rendered expected depth by measured depth maps (RGB-D, e.g. a RealSense D435).

Measured depth has holes (no return: 0/NaN/inf in the file; `load_views` turns all of them into inf) and
is noisier far away, so every loss here

- uses only pixels with a finite, positive measured depth D (holes are masked, never pulled to 0 or inf),
- and only where the splat renders something (accumulated alpha > `min_alpha`): the expected depth
  ED = sum_i w_i z_i / sum_i w_i is ill-defined where sum_i w_i is ~0.

Modes (`TrainConfig.depth_mode`):
    "relative":  mean |ED - D| / D                 (scale-free; the original splattwin loss)
    "inverse":   mean |1/ED - 1/D|   (1/m)          inverse-depth (disparity) L1 as in DN-Splatter /
                 gsplat's depth loss: a sensor's depth noise grows ~z^2, its disparity noise is ~constant,
                 so near surfaces weigh more and far noisy readings less.

Shapes: depth, alpha, gt_depth are [H,W] float tensors (m); the result is a scalar tensor, 0 (with a graph)
when no pixel qualifies.
"""

from __future__ import annotations

import torch

DEPTH_MODES = ("relative", "inverse")


def valid_depth_mask(gt_depth: torch.Tensor, alpha: torch.Tensor | None = None, min_alpha: float = 0.5
                     ) -> torch.Tensor:
    """[H,W] bool: measured depth finite and > 0 and (if given) rendered alpha > min_alpha."""
    ok = torch.isfinite(gt_depth) & (gt_depth > 0)
    if alpha is not None:
        ok = ok & (alpha.detach() > min_alpha)
    return ok


def depth_loss(depth: torch.Tensor, alpha: torch.Tensor, gt_depth: torch.Tensor, mode: str = "relative",
               min_alpha: float = 0.5, eps: float = 1e-6) -> torch.Tensor:
    """Depth loss of a rendered expected depth [H,W] against a measured z-depth [H,W] (m, inf/0/NaN where
    unknown), over the valid pixels (see module doc). mode: "relative" or "inverse"."""
    if mode not in DEPTH_MODES:
        raise ValueError(f"depth mode must be one of {DEPTH_MODES}, got {mode!r}")
    ok = valid_depth_mask(gt_depth, alpha, min_alpha)
    if not bool(ok.any()):
        return depth.sum() * 0.0
    d = gt_depth[ok]
    ed = depth[ok]
    if mode == "relative":
        return ((ed - d).abs() / d).mean()
    return (1.0 / ed.clamp_min(eps) - 1.0 / d).abs().mean()
