"""The CPU kernels' first run after install: said once when numba compiles them, or done ahead (`warm`).

The rasterizer's kernels (`kernels.py`) and the SSIM loss's (`splat.losses`) are `cache=True` numba
functions: numba compiles one on its first call unless its on-disk cache holds an entry for the call's
argument types on this CPU, numba version and source file (index `<name>-<line>.pyXY.nbi` and data
`.nbc` files in the cache locator's folder: $NUMBA_CACHE_DIR, else `__pycache__` beside the source when
writable (an editable install), else the user-wide cache, `~/.cache/numba`, for a read-only site-packages).
On 2 cores that first compile takes ~40 s (a 20-step `train`: 41.7 s cold, 7.2 s warm), during which
nothing was printed and the progress bar stood at 0.

How the message knows: not by inspecting the cache files ahead (a kernel's signature is only known at its
call, and a cache written on another CPU or numba version has files that do not load), but from numba's
documented event API (`numba.core.event`): "numba:compile" is broadcast by the dispatcher only after its
cache lookup missed, just before compiling. So the message appears exactly when a compile happens, whatever
locator holds the cache, and never when every kernel loads from it.
"""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger(__name__)

# the modules whose numba functions a CPU training compiles in its first steps
WATCHED = ("splattwin.splat._cpu.kernels", "splattwin.splat.losses")
MESSAGE = ("compiling the CPU rasterizer and loss kernels (first run after install, ~40 s on 2 cores; "
           "cached afterwards)")

_state = {"registered": False, "said": False}
_guard = threading.Lock()


def _say_once(module: str) -> None:
    if module not in WATCHED:
        return
    with _guard:
        if _state["said"]:
            return
        _state["said"] = True
    log.info(MESSAGE)


def announce_first_compile() -> None:
    """Log MESSAGE once per process when numba starts compiling a function of WATCHED (its disk cache
    missed). Idempotent; called where those kernels are imported, before any of them runs."""
    with _guard:
        if _state["registered"]:
            return
        _state["registered"] = True
    from numba.core import event

    class _FirstCompile(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            try:  # never let a notice break a compile
                _say_once(getattr(ev.data["dispatcher"].py_func, "__module__", ""))
            except Exception:  # pragma: no cover - numba changed the event's data
                log.debug("numba compile event without a dispatcher", exc_info=True)

        def on_end(self, ev: event.Event) -> None:
            pass

    event.register("numba:compile", _FirstCompile())


def warm(progress: bool = True) -> float:
    """Compile (or load from numba's cache) every kernel a CPU training and evaluation calls, by running one
    tiny training step through the real code: rasterizer forward and backward (projection, SH, tiles) and
    the SSIM loss's, on 64 Gaussians seen by a 32x24 px camera. Returns the seconds it took (~40 s on 2
    cores when compiling, ~1 s from the cache)."""
    import torch

    from splattwin.progress import Progress
    from splattwin.runtime import start_numba_threads
    from splattwin.splat.losses import fused_ssim
    from splattwin.splat.rasterize import rasterization

    announce_first_compile()
    t0 = time.perf_counter()
    g = torch.Generator().manual_seed(0)
    n, w, h = 64, 32, 24
    # Gaussians ~2 m in front of a camera at the origin looking along +z (OpenCV), ~5 cm across
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([0.8, 0.6, 0.4]) + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.full((n, 3), 0.05)
    opacities = torch.full((n,), 0.7)
    sh = torch.rand(n, 4, 3, generator=g)   # SH degree 1
    for t in (means, quats, scales, opacities, sh):
        t.requires_grad_(True)
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[[30.0, 0.0, w / 2], [0.0, 30.0, h / 2], [0.0, 0.0, 1.0]]])
    target = torch.rand(h, w, 3, generator=g)
    with Progress(3, "CPU kernels", unit="pass", enabled=progress) as bar:
        start_numba_threads()
        img, _alpha, _ = rasterization(means, quats, scales, opacities, sh, viewmats, Ks, w, h, sh_degree=1,
                                       backend="cpu")
        bar.update(1)
        loss = 1.0 - fused_ssim(img[0], target) + (img[0] - target).abs().mean()
        bar.update(1)
        loss.backward()
        bar.update(1)
    return time.perf_counter() - t0
