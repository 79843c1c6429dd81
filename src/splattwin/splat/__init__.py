"""splat stage: 3D Gaussian Splatting reconstruction (model, trainer, PLY I/O, evaluation).

Public API (each name from the module in brackets):
- `Gaussians` (`gaussians`): numpy, activated values; the hand-over object to the later stages.
- `rasterization`, `RENDER_MODES`, `RASTERIZE_MODES`, `BACKENDS` (`rasterize`): the gsplat-like
  differentiable rasterizer (backends "cpu", "cuda", "reference").
- `render`, `render_rgb`, `render_rgbd`, `render_depth`, `render_features` (`rendering`): numpy renders of
  `Gaussians` from a `Camera`.
- `train`, `Trainer`, `TrainResult` (`trainer`); options `TrainConfig`, `LearningRates` (`config`);
  densification `Strategy`, `DefaultStrategy` (`strategy`); the raw parameters `GaussianModel` (`model`).
- `evaluate`, `EvalResult` (`eval`): held-out PSNR / SSIM; `psnr`, `ssim` (`metrics`).

Imports are lazy (`splattwin.splat.config` is read by `splattwin --help` without torch).

The modules are named apart from the functions they define (`rasterize` holds `rasterization`, `rendering`
holds `render`), so that importing a module never rebinds the package's function of the same name.
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

_EXPORTS = {"Gaussians": "gaussians",
            "rasterization": "rasterize", "RENDER_MODES": "rasterize",
            "RASTERIZE_MODES": "rasterize", "BACKENDS": "rasterize",
            "render": "rendering", "render_rgb": "rendering", "render_rgbd": "rendering", "render_depth": "rendering",
            "render_features": "rendering",
            "train": "trainer", "Trainer": "trainer", "TrainResult": "trainer",
            "TrainConfig": "config", "LearningRates": "config",
            "Strategy": "strategy", "DefaultStrategy": "strategy", "GaussianModel": "model",
            "evaluate": "eval", "EvalResult": "eval", "psnr": "metrics", "ssim": "metrics"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
