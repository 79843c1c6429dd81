"""Photometric losses of 3DGS: L1, SSIM (11x11 Gaussian window, sigma 1.5) and their mix.

`ssim_map` is plain torch (separable Gaussian conv2d, autograd): the readable reference, any padding.
`fused_ssim` is the training loss: mean SSIM with "valid" windows and a hand-written gradient, computed by
numba kernels (two separable 1-D passes forward, their adjoints backward). It exists because torch's
depthwise conv2d on the CPU costs ~70 ms forward+backward at 320x240 -- as much as a whole rasterizer
step -- while these kernels take a few ms; no fused-SSIM package (fused-ssim, pytorch-msssim's CUDA
path) runs on the CPU. Tests compare it with `ssim_map` and finite differences.
Images are [..., H, W, 3] channels-last, as the rasterizer returns them.
"""

from __future__ import annotations

import math

import numpy as np

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def gaussian_window_1d(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """[size] normalised 1-D Gaussian."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)


def _blur(x: torch.Tensor, w: torch.Tensor, padding: str) -> torch.Tensor:
    """Separable Gaussian blur of x [B,C,H,W] (depthwise)."""
    c = x.shape[1]
    k = w.numel()
    pad = k // 2 if padding == "same" else 0
    wx = w.view(1, 1, 1, k).expand(c, 1, 1, k)
    wy = w.view(1, 1, k, 1).expand(c, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=c)
    return F.conv2d(x, wy, padding=(pad, 0), groups=c)


def ssim_map(img: torch.Tensor, ref: torch.Tensor, window: int = 11, sigma: float = 1.5,
             padding: str = "valid") -> torch.Tensor:
    """Per-pixel SSIM of images [..., H, W, C] (values in [0,1]) -> [B, C, H', W'].

    padding: "valid" (only full windows, like scikit-image/torchmetrics) or "same" (zero padded, like
    the original 3DGS code).
    """
    if img.shape != ref.shape:
        raise ValueError(f"image shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    h, w_, c = img.shape[-3:]
    x = img.reshape(-1, h, w_, c).permute(0, 3, 1, 2)
    y = ref.reshape(-1, h, w_, c).permute(0, 3, 1, 2)
    g = gaussian_window_1d(window, sigma, dtype=img.dtype).to(img.device)
    mu_x, mu_y = _blur(x, g, padding), _blur(y, g, padding)
    sxx = _blur(x * x, g, padding) - mu_x**2
    syy = _blur(y * y, g, padding) - mu_y**2
    sxy = _blur(x * y, g, padding) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


def ssim(img: torch.Tensor, ref: torch.Tensor, padding: str = "valid") -> torch.Tensor:
    """Mean SSIM (scalar tensor, differentiable)."""
    return ssim_map(img, ref, padding=padding).mean()


# -- fused SSIM (numba) --------------------------------------------------------------------------
_NUMBA = None


BAND = 48  # output rows per parallel work item of the fused SSIM kernels


def _kernels():
    """Compile (once, cached on disk) the numba SSIM kernels."""
    global _NUMBA
    if _NUMBA is not None:
        return _NUMBA
    import numba as nb
    import numpy as np

    from splattwin.runtime import start_numba_threads
    from splattwin.splat._cpu.first_run import announce_first_compile

    announce_first_compile()   # their first compile after install is said, not silent
    start_numba_threads()      # before the first kernel, keeping the caller's torch thread count (runtime.py)
    # Work in bands of output rows (in parallel over channel x band): each band keeps its last 11
    # horizontally blurred rows in a ring buffer (~150 KB at 640 px: L2-resident) instead of whole-image
    # temporaries (18 MB at 640x480, written and re-read 11 times: ~3x slower). Innermost loops run along
    # contiguous rows (LLVM vectorises them). The band layout is fixed by the image size, so the float
    # sums are the same for any thread count.
    @nb.njit(parallel=True, cache=True, fastmath=True)
    def fwd(x, y, g, c1, c2):  # x, y [C,H,W] float32 -> sum of the ssim map, d/dmx, d/dexx, d/dexy [C,Ho,Wo]
        C, H, W = x.shape
        k = g.shape[0]
        Ho, Wo = H - k + 1, W - k + 1
        nb_ = (Ho + BAND - 1) // BAND
        dmx = np.empty((C, Ho, Wo), np.float32)
        dexx = np.empty((C, Ho, Wo), np.float32)
        dexy = np.empty((C, Ho, Wo), np.float32)
        sums = np.zeros(C * nb_)
        for cb in nb.prange(C * nb_):
            c, b = cb // nb_, cb % nb_
            i0, i1 = b * BAND, min(Ho, (b + 1) * BAND)
            ring = np.zeros((k, 5, Wo), np.float32)  # horizontal blurs of x, y, xx, yy, xy of input rows
            m = np.empty((5, Wo), np.float32)
            p = np.empty((5, W), np.float32)  # x, y, xx, yy, xy of one input row
            acc = 0.0
            for r in range(i0, i1 + k - 1):  # input rows; output row r - k + 1 once k rows are in
                o = ring[r % k]
                xr, yr = x[c, r], y[c, r]
                for j in range(W):
                    xv, yv = xr[j], yr[j]
                    p[0, j] = xv
                    p[1, j] = yv
                    p[2, j] = xv * xv
                    p[3, j] = yv * yv
                    p[4, j] = xv * yv
                for q in range(5):
                    for j in range(Wo):
                        o[q, j] = 0.0
                    for t in range(k):
                        w = g[t]
                        for j in range(Wo):
                            o[q, j] += w * p[q, j + t]
                i = r - k + 1
                if i < i0:
                    continue
                for q in range(5):
                    for j in range(Wo):
                        m[q, j] = 0.0
                for t in range(k):
                    w = g[t]
                    src = ring[(i + t) % k]
                    for q in range(5):
                        for j in range(Wo):
                            m[q, j] += w * src[q, j]
                for j in range(Wo):
                    mx, my, exx, eyy, exy = m[0, j], m[1, j], m[2, j], m[3, j], m[4, j]
                    sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
                    A1, A2 = 2 * mx * my + c1, 2 * sxy + c2
                    B1, B2 = mx * mx + my * my + c1, sxx + syy + c2
                    sv = A1 * A2 / (B1 * B2)
                    acc += sv
                    dmx[c, i, j] = 2 * my * (A2 - A1) / (B1 * B2) - 2 * mx * sv * (1 / B1 - 1 / B2)
                    dexx[c, i, j] = -sv / B2
                    dexy[c, i, j] = 2 * A1 / (B1 * B2)
            sums[cb] = acc
        return sums.sum(), dmx, dexx, dexy

    @nb.njit(parallel=True, cache=True, fastmath=True)
    def bwd(x, y, g, dmx, dexx, dexy, scale):  # adjoint of the valid blurs -> dS_mean/dx [C,H,W]
        C, Ho, Wo = dmx.shape
        k = g.shape[0]
        H, W = Ho + k - 1, Wo + k - 1
        nb_ = (H + BAND - 1) // BAND
        out = np.empty((C, H, W), np.float32)
        for cb in nb.prange(C * nb_):
            c, b = cb // nb_, cb % nb_
            v = np.empty((3, Wo), np.float32)  # vertical adjoint of the three maps, one input row
            acc = np.empty((3, W), np.float32)
            for r in range(b * BAND, min(H, (b + 1) * BAND)):
                for q in range(3):
                    for j in range(Wo):
                        v[q, j] = 0.0
                for t in range(max(0, r - Ho + 1), min(k, r + 1)):
                    w = g[t]
                    a_, b_, d_ = dmx[c, r - t], dexx[c, r - t], dexy[c, r - t]
                    for j in range(Wo):
                        v[0, j] += w * a_[j]
                        v[1, j] += w * b_[j]
                        v[2, j] += w * d_[j]
                for q in range(3):
                    for j in range(W):
                        acc[q, j] = 0.0
                for t in range(k):
                    w = g[t]
                    for j in range(Wo):
                        acc[0, j + t] += w * v[0, j]
                        acc[1, j + t] += w * v[1, j]
                        acc[2, j + t] += w * v[2, j]
                xr, yr = x[c, r], y[c, r]
                for j in range(W):
                    out[c, r, j] = scale * (acc[0, j] + 2 * xr[j] * acc[1, j] + yr[j] * acc[2, j])
        return out

    _NUMBA = (fwd, bwd)
    return _NUMBA


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        fwd, _ = _kernels()
        x = img.detach().to(torch.float32).permute(2, 0, 1).contiguous().cpu().numpy()
        y = ref.detach().to(torch.float32).permute(2, 0, 1).contiguous().cpu().numpy()
        g = gaussian_window_1d(11, 1.5).numpy()
        total, dmx, dexx, dexy = fwd(x, y, g, SSIM_C1, SSIM_C2)
        ctx.save_for_backward(*(torch.from_numpy(a) for a in (x, y, dmx, dexx, dexy)))
        ctx.meta = (img.dtype, img.device, dmx.size)
        return torch.tensor(total / dmx.size, dtype=img.dtype, device=img.device)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        _, bwd = _kernels()
        x, y, dmx, dexx, dexy = (t.numpy() for t in ctx.saved_tensors)
        dtype, device, n = ctx.meta
        g = gaussian_window_1d(11, 1.5).numpy()
        d = bwd(x, y, g, dmx, dexx, dexy, np.float32(float(grad_out) / n))
        return torch.from_numpy(d).permute(1, 2, 0).to(dtype=dtype, device=device), None


def fused_ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of one image [H,W,3] vs [H,W,3] ("valid" 11x11 Gaussian windows), gradient for `img`
    only. Equal to `ssim(img, ref)` up to float32 rounding; fast on the CPU (numba)."""
    if img.dim() == 4 and img.shape[0] == 1:
        img, ref = img[0], ref[0]
    if img.dim() != 3 or img.shape != ref.shape:
        raise ValueError(f"fused_ssim needs two [H,W,C] images, got {tuple(img.shape)} and {tuple(ref.shape)}")
    if min(img.shape[0], img.shape[1]) < 11:
        raise ValueError(f"SSIM needs images of at least 11x11 pixels, got {tuple(img.shape)}")
    return _FusedSSIM.apply(img, ref)


def l1(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return (img - ref).abs().mean()


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, ssim_lambda: float = 0.2,
                     fused: bool = True) -> torch.Tensor:
    """(1 - lambda) * L1 + lambda * (1 - SSIM), the 3DGS training loss (lambda = 0.2).
    fused: use `fused_ssim` (CPU tensors [H,W,3]) instead of the torch conv2d SSIM."""
    loss = l1(img, ref)
    if ssim_lambda > 0:
        use_fused = fused and img.device.type == "cpu" and img.dim() == 3
        s = fused_ssim(img, ref) if use_fused else ssim(img, ref)
        loss = (1.0 - ssim_lambda) * loss + ssim_lambda * (1.0 - s)
    return loss


def psnr_from_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)
