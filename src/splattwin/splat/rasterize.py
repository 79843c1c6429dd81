"""`rasterization()`: the one entry point for rendering 3D Gaussians (gsplat-like API), several backends.

Backends:
    "cpu"        our numba kernels (tile-based, hand-written backward) - `splattwin.splat._cpu`.
    "cuda"       gsplat's `rasterization()` (needs a CUDA device and an importable gsplat).
    "reference"  plain PyTorch + autograd, dense (small sizes only) - `splattwin.splat.reference`.
    "auto"       "cuda" when CUDA and gsplat are available and the inputs are on a CUDA device, else "cpu".

The "cpu" and "reference" backends share this module's pipeline: (1) colours (SH evaluated per camera
from the view direction camera-centre -> mean when `sh_degree` is given), (2) EWA projection, (3) tile
compositing, with the depth appended as an extra colour channel for the depth render modes (as gsplat).
All semantics (culling, 3-sigma extents, alpha thresholds, early stop) are documented in
`splattwin.splat.reference`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import torch

from splattwin.errors import InputError
from splattwin.splat import reference as _ref
from splattwin.splat.config import DEFAULT_EPS2D  # noqa: F401  (re-exported: the rasterizer's defaults)

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")
# DEFAULT_EPS2D: the low-pass added to every 2D covariance (px^2) when the caller gives none, per mode.
# classic: 3DGS's dilation 0.3, which only keeps sub-pixel Gaussians visible. antialiased: Mip-Splatting's
# 2D filter 0.1, chosen there to approximate one pixel's box filter (variance 1/12 px^2), i.e. what a
# sensor pixel integrates; with 0.3 every Gaussian is blurred ~1.8x wider than a pixel, so fine print
# cannot be fitted (demo scene, 5x5-sampled pixels: held-out 34.10 -> 36.31 dB).
BACKENDS = ("auto", "cpu", "cuda", "reference")
# Where the "cuda" backend's tensors live. One name for the whole package, so the test-suite can run the
# gsplat path with gsplat's CUDA primitives emulated on the CPU (tests/splat/conftest.py).
CUDA_DEVICE = "cuda"


def cuda_unavailable_reason() -> str | None:
    """Why the "cuda" backend cannot run here, or None when it can (a CUDA device, an importable gsplat,
    and gsplat's CUDA kernels loaded: gsplat compiles them on first use, which needs the CUDA toolkit)."""
    if not torch.cuda.is_available():
        return "no CUDA device is available (torch.cuda.is_available() is False)"
    return _gsplat_unavailable_reason()


@functools.lru_cache(maxsize=1)
def _gsplat_unavailable_reason() -> str | None:
    # Cached: a failed import is not cached by Python, and each retry would re-run gsplat's JIT build.
    try:
        import gsplat  # noqa: F401
    except Exception as e:
        return f"gsplat is not installed or fails to import ({type(e).__name__}: {e}); pip install gsplat"
    try:
        from gsplat.cuda._backend import _C
    except Exception as e:  # a failed JIT build raises here
        return f"gsplat's CUDA kernels fail to build or load ({type(e).__name__}: {e})"
    if _C is None:
        return ("gsplat's CUDA kernels are not built and no CUDA toolkit was found to compile them "
                "(install the CUDA toolkit, or a gsplat wheel built for your torch and CUDA)")
    return None


def cuda_available() -> bool:
    """True when the "cuda" backend can run (see `cuda_unavailable_reason`)."""
    return cuda_unavailable_reason() is None


def backend_device(name: str) -> torch.device:
    """The torch device a concrete backend's inputs live on: CUDA for "cuda", the CPU otherwise."""
    return torch.device(CUDA_DEVICE if name == "cuda" else "cpu")


def resolve_backend(backend: str, device: torch.device | None = None) -> str:
    """Map "auto" to a concrete backend; raise InputError for an unknown or unavailable one."""
    if backend not in BACKENDS:
        raise InputError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "auto":
        if cuda_available() and (device is None or device.type == backend_device("cuda").type):
            return "cuda"
        return "cpu"
    why = cuda_unavailable_reason() if backend == "cuda" else None
    if why:
        raise InputError(f"rasterizer backend 'cuda' requested but {why}; use backend 'cpu' (--device cpu)")
    return backend


def _check_types(width, height, backgrounds, **tensors) -> None:
    """TypeError naming the argument for a non-tensor input (a numpy array failed deep inside with
    "'numpy.ndarray' object has no attribute 'is_floating_point'") or a non-integer image size (64.7 px
    rendered 64 px)."""
    from splattwin.errors import require_type

    for name, t in [*tensors.items(), ("backgrounds", backgrounds)]:
        if not (name == "backgrounds" and t is None):
            require_type(t, torch.Tensor, name, "(torch.as_tensor converts a numpy array)")
    for name, v in (("width", width), ("height", height)):
        try:
            whole = not isinstance(v, bool) and int(v) == v
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not whole:
            raise TypeError(f"{name} must be a whole number of pixels, got {v!r}")


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                  backgrounds, render_mode, near_plane, far_plane) -> None:
    N = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N,3], got {tuple(means.shape)}")
    if tuple(quats.shape) != (N, 4):
        raise ValueError(f"quats must be [N,4] (wxyz) with N={N}, got {tuple(quats.shape)}")
    if tuple(scales.shape) != (N, 3):
        raise ValueError(f"scales must be [N,3] with N={N}, got {tuple(scales.shape)}")
    if tuple(opacities.shape) != (N,):
        raise ValueError(f"opacities must be [N] with N={N}, got {tuple(opacities.shape)}")
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C,4,4], got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if tuple(Ks.shape) != (C, 3, 3):
        raise ValueError(f"Ks must be [C,3,3] with C={C}, got {tuple(Ks.shape)}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    # z <= 0 is behind the camera: projected, it would be mirrored, and the CPU backend orders depths by
    # their float32 bit patterns, which holds for positive depths only
    if not (math.isfinite(near_plane) and near_plane > 0):
        raise ValueError(f"near_plane must be a finite distance > 0 m, got {near_plane}")
    if not far_plane > near_plane:
        raise ValueError(f"far_plane must be beyond near_plane ({near_plane} m), got {far_plane}")
    if sh_degree is not None:
        if colors.ndim != 3 or colors.shape[0] != N or colors.shape[2] != 3:
            raise ValueError(f"with sh_degree, colors must be SH coefficients [N,K,3], got {tuple(colors.shape)}")
        if not 0 <= sh_degree <= 3 or colors.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(f"sh_degree {sh_degree} needs 0..3 and K >= {(sh_degree + 1) ** 2}, "
                             f"got K={colors.shape[1]}")
    else:
        ok = (colors.ndim == 2 and colors.shape[0] == N) or (colors.ndim == 3 and colors.shape[:2] == (C, N))
        if not ok:
            raise ValueError(f"colors must be [N,D] or [C,N,D] (or SH [N,K,3] with sh_degree), "
                             f"got {tuple(colors.shape)}")


def antialias_compensation(conics: torch.Tensor, eps2d: float) -> torch.Tensor:
    """[...] opacity factor sqrt(det(S) / det(S + eps2d I)) of 2D covariances S, from the conics [..., 3]
    (a, b, c) = entries of (S + eps2d I)^-1. With q = a c - b^2 = 1 / det(S + eps I):
    det(S) / det(S + eps I) = 1 - eps (a + c) + eps^2 q. Culled Gaussians (conic 0) get 1."""
    a, b, c = conics[..., 0], conics[..., 1], conics[..., 2]
    ratio = 1.0 - eps2d * (a + c) + eps2d * eps2d * (a * c - b * b)
    return torch.sqrt(torch.clamp_min(ratio, 1e-12))  # clamped: no infinite gradient at det(S) = 0


def _backend_module(name: str) -> Any:
    if name == "reference":
        return _ref
    from splattwin.runtime import start_numba_threads
    from splattwin.splat import _cpu

    start_numba_threads()   # before the first kernel, keeping the caller's torch thread count (runtime.py)
    return _cpu


def view_colors(means: torch.Tensor, sh: torch.Tensor, viewmats: torch.Tensor, sh_degree: int,
                backend: str = "auto") -> torch.Tensor:
    """[C,N,3] colours of SH [N,K,3] seen from each camera, exactly as `rasterization` evaluates them
    (clamp_min(SH + 0.5, 0), view direction from the camera centre): for renders that append channels of
    their own to the colours (then passed with sh_degree None). means [N,3] m, viewmats [C,4,4]."""
    name = resolve_backend(backend, means.device)
    if name == "cuda":  # the CUDA backend evaluates SH in its kernels; the reference maths is the same
        name = "reference"
    return _backend_module(name).sh_colors(means, sh, viewmats, sh_degree)


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float | None = None,
    backend: str = "auto",
    rasterize_mode: str = "classic",
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render N Gaussians into C cameras (differentiable w.r.t. every tensor input but Ks).

    Precision and dtypes: every floating-point input (quats, scales, opacities, colors, viewmats, Ks,
    backgrounds) is cast to `means.dtype` first (differentiably: gradients come back in each input's own
    dtype), on every backend. The outputs have `means.dtype`, but only "reference" also *computes* in it:
    "cpu" (the default off CUDA) runs its kernels in float32 whatever the input dtype (float64 per-Gaussian
    scalars, float32 per pixel) and "cuda" is gsplat's float32. float64 inputs therefore give float32
    accuracy (~1e-6 relative) on those backends: use backend="reference" (float64 throughout, autograd)
    for `torch.autograd.gradcheck` or finite differences.

    Args:
        means: [N,3] world frame, m.  quats: [N,4] wxyz (normalised internally, the norm clamped at
            1e-12 on the "cpu" and "reference" backends, so a zero quaternion is the identity).
        scales: [N,3] m.
        opacities: [N] in [0,1].
        colors: [N,D] or [C,N,D] any number of channels D (sh_degree None), or SH [N,K,3] (sh_degree 0..3).
        viewmats: [C,4,4] world->camera (T_cam_world, OpenCV).  Ks: [C,3,3] pixel intrinsics.
        width, height: image size (pixels).
        backgrounds: [C,D] colour behind the Gaussians (colour channels only), or None (black).
        render_mode: "RGB" colours; "D" accumulated depth sum w_i z_i; "ED" expected depth D / alpha;
            "RGB+D" / "RGB+ED" colours with the depth as the last channel.
        near_plane, far_plane: cull Gaussians whose camera z is outside (near, far), m; 0 < near < far
            (far may be inf), else ValueError.
        eps2d: low-pass filter added to the 2D covariance diagonal (px^2); None: the mode's
            `DEFAULT_EPS2D` (0.3 classic, 0.1 antialiased).
        backend: "auto" | "cpu" | "cuda" | "reference".
        rasterize_mode: "classic" (3DGS: the eps2d low-pass widens a Gaussian at unchanged opacity, so
            Gaussians smaller than a pixel render too large and too bright) or "antialiased" (gsplat's mode,
            Mip-Splatting's 2D filter: opacity scaled by sqrt(det(cov2d) / det(cov2d + eps2d I)), which
            keeps each Gaussian's integrated footprint; see `antialias_compensation`).
    Returns:
        render_colors [C,H,W,ch], render_alphas [C,H,W,1], meta dict with
        means2d [C,N,2] (pixels; its .grad is filled by backward, for densification), radii [C,N] int32,
        depths [C,N] (camera z, m), conics [C,N,3], visibility [C,N] bool, width, height, backend.
    """
    _check_types(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats,
                 Ks=Ks, backgrounds=backgrounds, width=width, height=height)
    width, height = int(width), int(height)
    if not means.is_floating_point():
        raise ValueError(f"means must be a floating-point tensor, got {means.dtype}")
    dt = means.dtype  # one dtype for every backend (the reference's matmuls refuse mixed dtypes)
    quats, scales, opacities, colors, viewmats, Ks = (t.to(dt) for t in (quats, scales, opacities, colors,
                                                                         viewmats, Ks))
    if backgrounds is not None:
        backgrounds = backgrounds.to(dt)
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                  backgrounds, render_mode, float(near_plane), float(far_plane))
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    eps2d = DEFAULT_EPS2D[rasterize_mode] if eps2d is None else float(eps2d)
    name = resolve_backend(backend, means.device)
    if name == "cuda":
        from splattwin.splat.cuda_backend import rasterization_cuda
        return rasterization_cuda(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                  sh_degree=sh_degree, backgrounds=backgrounds, render_mode=render_mode,
                                  near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
                                  rasterize_mode=rasterize_mode)
    B = _backend_module(name)
    C = viewmats.shape[0]
    proj = B.project(means, quats, scales, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane,
                     far_plane=far_plane)
    means2d, conics, depths = proj["means2d"], proj["conics"], proj["depths"]

    chans: list[torch.Tensor] = []
    bgs: list[torch.Tensor] = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        if sh_degree is not None:
            cols = B.sh_colors(means, colors, viewmats, sh_degree)  # [C,N,3]
        else:
            cols = colors if colors.ndim == 3 else colors[None].expand(C, -1, -1)
        chans.append(cols)
        D = cols.shape[-1]
        if backgrounds is not None:
            if tuple(backgrounds.shape) != (C, D):
                raise ValueError(f"backgrounds must be [C,D]=({C},{D}), got {tuple(backgrounds.shape)}")
            bgs.append(backgrounds)
        else:
            bgs.append(torch.zeros(C, D, dtype=means.dtype, device=means.device))
    if render_mode != "RGB":
        chans.append(depths[..., None])
        bgs.append(torch.zeros(C, 1, dtype=means.dtype, device=means.device))
    feats = chans[0] if len(chans) == 1 else torch.cat(chans, dim=-1)
    bg = bgs[0] if len(bgs) == 1 else torch.cat(bgs, dim=-1)
    use_bg = backgrounds is not None and render_mode in ("RGB", "RGB+D", "RGB+ED")

    if means2d.requires_grad:
        means2d.retain_grad()
    if rasterize_mode == "antialiased":
        opacities = opacities[None, :] * antialias_compensation(conics, eps2d)  # [C,N]
    render, alphas = B.rasterize(means2d, conics, feats.contiguous(), opacities, depths, proj["extents"],
                                 width, height, backgrounds=bg if use_bg else None)
    if render_mode in ("ED", "RGB+ED"):
        ed = render[..., -1:] / torch.clamp_min(alphas, 1e-10)
        render = torch.cat([render[..., :-1], ed], dim=-1)
    radii = proj["radii"]
    meta = {"means2d": means2d, "radii": radii, "depths": depths, "conics": conics, "visibility": radii > 0,
            "width": width, "height": height, "backend": name, "n_cameras": C}
    return render, alphas, meta
