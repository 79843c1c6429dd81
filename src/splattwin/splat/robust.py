"""Transient masks for the photometric loss: what one photo shows and no other does (people, cars,
banners of a photo collection) is left out of that photo's loss.

A least-squares fit paints such distractors into the scene, as ghosts seen from every other view.
RobustNeRF (Sabour et al., "RobustNeRF: Ignoring Distractors with Robust Losses", CVPR 2023) trims the
loss instead: pixels with the largest residuals are left out, but only where they form blobs -- the
scene's own hard pixels (edges, fine texture) are scattered, a distractor covers a connected region.
The rule here follows that idea on the current render's residual (all tensors detached):

1. candidates: per-pixel residual (mean |render - photo| over the channels) above its `quantile` in
   this image and above `contrast` times its median (without the second test a photo with nothing in it
   but the scene still loses its worst-fitted regions: 4-7 % of each clean view of a synthetic scene at
   contrast 0, 0.7 % at 4, while 92 % of a painted-in square stays masked either way);
2. a pixel is an outlier when at least half of its 3x3 neighbourhood are candidates (isolated edge
   pixels drop out, a blob's holes fill in);
3. ... and at least `blob_frac` of its `patch` x `patch` neighbourhood are outliers (only blobs of
   about a patch or larger stay masked).

`masked_target` puts the (detached) render in place of the photo at the outliers, so L1 and SSIM see no
error there and send no gradient from them; the trainer uses it after a warm-up (`TrainConfig.
robust_start`), when the static scene is fitted and the distractors stand out. Written here because it is
a handful of operations on the residual image and no maintained package offers it for a torch trainer
(RobustNeRF's own code is a JAX research release).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

CONTRAST = 4.0  # candidates' least residual, in medians of their photo's residual


def _box_mean(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean of x [H,W] (float) over each pixel's k x k window, rows and columns i - k//2 .. i + (k-1)//2
    (centred for odd k, as avg_pool2d with padding k//2), shrunk to the pixels inside the image at the
    border. A summed-area table: O(HW) whatever k (a 16x16 pooling adds 256 values per pixel)."""
    h, w = x.shape
    S = F.pad(x.double().cumsum(0).cumsum(1), (1, 0, 1, 0))   # S[i, j] = sum of x[:i, :j]
    lo, hi = k // 2, k - k // 2                                # window [i - lo, i + hi)
    y0 = (torch.arange(h, device=x.device) - lo).clamp(0, h)
    y1 = (torch.arange(h, device=x.device) + hi).clamp(0, h)
    x0 = (torch.arange(w, device=x.device) - lo).clamp(0, w)
    x1 = (torch.arange(w, device=x.device) + hi).clamp(0, w)
    total = S[y1][:, x1] - S[y0][:, x1] - S[y1][:, x0] + S[y0][:, x0]
    count = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    return (total / count).to(x.dtype)


def outlier_mask(residual: torch.Tensor, quantile: float = 0.8, patch: int = 16, blob_frac: float = 0.5,
                 contrast: float = CONTRAST) -> torch.Tensor:
    """Bool [H,W]: the pixels left out of the loss (see the module docstring). residual [H,W] >= 0 (any
    unit: only ranks and ratios matter). quantile in (0, 1): the share of pixels that are never candidates."""
    if residual.dim() != 2:
        raise ValueError(f"outlier_mask needs a residual image [H,W], got {tuple(residual.shape)}")
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {quantile}")
    r = residual.detach().float()
    flat = r.reshape(-1)
    n = flat.numel()
    med = flat.kthvalue(max(1, (n + 1) // 2)).values            # selection, not a sort: ~4x faster here
    top = flat.kthvalue(min(n, max(1, math.ceil(quantile * n)))).values
    thr = torch.maximum(top, contrast * med)
    cand = (r > thr).float()
    out = (_box_mean(cand, 3) >= 0.5).float()
    blob = _box_mean(out, patch) >= blob_frac
    return (out > 0) & blob


def masked_target(img: torch.Tensor, gt: torch.Tensor, quantile: float = 0.8, patch: int = 16,
                  blob_frac: float = 0.5, contrast: float = CONTRAST) -> tuple[torch.Tensor, torch.Tensor]:
    """(target [H,W,3], outliers [H,W] bool): the photo gt with the render img [H,W,3] (detached) in
    place of its outlier pixels, for the usual photometric loss."""
    residual = (img.detach() - gt).abs().mean(-1)
    out = outlier_mask(residual, quantile, patch, blob_frac, contrast)
    return torch.where(out[..., None], img.detach(), gt), out


def transient_sheet(photos: list[np.ndarray], masks: list[np.ndarray], names: list[str], path, cols: int = 4,
                    thumb_width: int = 256) -> Path:
    """One PNG of every photo [H,W,3] float in [0, 1] with its masked pixels (bool [H,W]) tinted red and its
    name and masked share written under it: what training left out of each photo."""
    from PIL import Image, ImageDraw

    from splattwin.io import write_image

    thumbs = []
    for img, m, name in zip(photos, masks, names):
        tinted = np.clip(img, 0, 1).copy()
        tinted[m] = 0.45 * tinted[m] + 0.55 * np.array([1.0, 0.0, 0.0])
        h = max(1, round(thumb_width * img.shape[0] / img.shape[1]))
        im = Image.fromarray((tinted * 255 + 0.5).astype(np.uint8)).resize((thumb_width, h), Image.BILINEAR)
        cell = Image.new("RGB", (thumb_width, h + 14), (255, 255, 255))
        cell.paste(im, (0, 0))
        ImageDraw.Draw(cell).text((2, h + 1), f"{name[:28]}  {100 * float(m.mean()):.1f} % masked", fill=(0, 0, 0))
        thumbs.append(cell)
    cols = max(1, min(cols, len(thumbs)))
    rows = (len(thumbs) + cols - 1) // cols
    cell_h = max(t.height for t in thumbs) if thumbs else 1
    sheet = Image.new("RGB", (cols * thumb_width, rows * cell_h), (255, 255, 255))
    for i, t in enumerate(thumbs):
        r, c = divmod(i, cols)
        sheet.paste(t, (c * thumb_width, r * cell_h))
    return write_image(Path(path), np.asarray(sheet))
