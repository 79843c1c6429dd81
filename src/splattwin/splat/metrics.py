"""Image-quality metrics for evaluation: PSNR and SSIM, computed in float64 on [0,1] images.

SSIM uses the standard 11x11 Gaussian window (sigma 1.5, K1 0.01, K2 0.03) over full windows only
("valid", as scikit-image with `gaussian_weights=True` and torchmetrics), averaged over channels.
`masked_psnr` / `masked_ssim`: the same over the pixels a mask keeps (nerfstudio loss masks, `eval`).
"""

from __future__ import annotations

import numpy as np
import torch

from splattwin.splat.losses import psnr_from_mse, ssim_map


def _as64(a: np.ndarray | torch.Tensor) -> torch.Tensor:
    # torch.as_tensor copies what from_numpy would share: an array of a PIL image is read-only, which torch warns of
    t = a.detach() if isinstance(a, torch.Tensor) else torch.as_tensor(np.array(a, copy=True))
    return t.to(torch.float64).cpu()


def _integer(a) -> bool:
    dt = a.dtype if isinstance(a, torch.Tensor) else np.asarray(a).dtype
    return not (dt.is_floating_point if isinstance(dt, torch.dtype) else np.issubdtype(dt, np.inexact))


def _pair(img, ref, what: str, integers: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as float64 tensors. ValueError for an integer image (0-255, e.g. np.asarray(PIL image)) beside a
    float one: the [0,1] render against 0-255 read -41 dB; `integers` False refuses integer images at all (SSIM's
    constants are for [0,1])."""
    ints = [_integer(a) for a in (img, ref)]
    if (any(ints) and not all(ints)) or (any(ints) and not integers):
        which = " and ".join(n for n, i in zip(("img", "ref"), ints) if i)
        raise ValueError(f"{what} compares float images in [0, 1]; {which} holds integers (0-255?): divide by 255 "
                         f"(splattwin.capture.load_image reads a photo as float in [0, 1])")
    return _as64(img), _as64(ref)


def psnr(img: np.ndarray | torch.Tensor, ref: np.ndarray | torch.Tensor, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of HxWxC images (inf when identical): float images in [0, 1] (max_val 1),
    or two integer images with their max_val (255 for 8-bit); an integer image beside a float one is a
    ValueError (a 0-255 photo against a [0,1] render)."""
    x, y = _pair(img, ref, "psnr", integers=True)
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    mse = float(((x - y) ** 2).mean()) / max_val**2
    return psnr_from_mse(mse)


def masked_psnr(img: np.ndarray | torch.Tensor, ref: np.ndarray | torch.Tensor, mask: np.ndarray) -> float:
    """PSNR in dB (data range 1) over the pixels of HxWxC images where the HxW bool `mask` is set: NaN when
    the mask is empty, inf when those pixels are identical."""
    m = torch.from_numpy(np.asarray(mask, bool))
    if not bool(m.any()):
        return float("nan")
    x, y = _pair(img, ref, "masked_psnr", integers=False)
    return psnr_from_mse(float(((x[m] - y[m]) ** 2).mean()))


def ssim(img: np.ndarray | torch.Tensor, ref: np.ndarray | torch.Tensor) -> float:
    """Mean structural similarity of HxWxC float images in [0,1] (1 when identical); integer images (0-255) are a
    ValueError (SSIM's constants assume the [0,1] range)."""
    x, y = _pair(img, ref, "ssim", integers=False)
    if min(x.shape[-3], x.shape[-2]) < 11:
        raise ValueError(f"SSIM needs images of at least 11x11 pixels, got {tuple(x.shape)}")
    return float(ssim_map(x, y, padding="valid").mean())


def masked_ssim(img: np.ndarray | torch.Tensor, ref: np.ndarray | torch.Tensor, mask: np.ndarray) -> float:
    """Mean SSIM of HxWxC images over the pixels where the HxW bool `mask` is set (a loss mask's kept
    pixels). The ignored pixels are set to 0 in both images (as splatfacto masks its loss), so their colours
    never enter; the SSIM map (full 11x11 windows, as `ssim`) is averaged over the windows whose centre pixel
    is kept. A window reaching into the ignored region sees the same zeros in both images there: they
    neither reward nor penalise the render. Equal to `ssim` for a mask that keeps every pixel; NaN when no
    window centre is kept."""
    x, y = _pair(img, ref, "masked_ssim", integers=False)
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    h, w = x.shape[-3], x.shape[-2]
    if min(h, w) < 11:
        raise ValueError(f"SSIM needs images of at least 11x11 pixels, got {tuple(x.shape)}")
    m = torch.from_numpy(np.asarray(mask, bool))
    if tuple(m.shape) != (h, w):
        raise ValueError(f"mask is {tuple(m.shape)}, the images {h}x{w}")
    centre = m[5:h - 5, 5:w - 5]
    if not bool(centre.any()):
        return float("nan")
    mf = m[..., None].to(x.dtype)
    smap = ssim_map(x * mf, y * mf, padding="valid")[0]   # [C, H-10, W-10]
    return float(smap[:, centre].mean())


def error_heatmap(img: np.ndarray, ref: np.ndarray, vmax: float = 0.25) -> np.ndarray:
    """HxWx3 uint8 colour map (black -> red -> yellow -> white) of the per-pixel mean absolute error."""
    err = np.clip(np.abs(np.asarray(img, np.float64) - np.asarray(ref, np.float64)).mean(axis=-1) / vmax, 0, 1)
    rgb = np.stack([np.clip(3 * err, 0, 1), np.clip(3 * err - 1, 0, 1), np.clip(3 * err - 2, 0, 1)], axis=-1)
    return (rgb * 255 + 0.5).astype(np.uint8)
