"""splat stage: 3D Gaussian Splatting reconstruction (model, trainer, PLY I/O, evaluation).

Public API (each name from the module in brackets):
- `Gaussians` (`gaussians`): numpy, activated values; the hand-over object to the later stages.
- `rasterization`, `RENDER_MODES`, `RASTERIZE_MODES`, `BACKENDS` (`rasterization`): the gsplat-like
  differentiable rasterizer (backends "cpu", "cuda", "reference").
- `render`, `render_rgb`, `render_rgbd`, `render_depth`, `render_features` (`render`): numpy renders of
  `Gaussians` from a `Camera`.
- `train`, `Trainer`, `TrainResult` (`trainer`); options `TrainConfig`, `LearningRates` (`config`);
  densification `Strategy`, `DefaultStrategy` (`strategy`); the raw parameters `GaussianModel` (`model`).
- `evaluate`, `EvalResult` (`eval`): held-out PSNR / SSIM; `psnr`, `ssim` (`metrics`).

Imports are lazy (`splattwin.splat.config` is read by `splattwin --help` without torch).

`rasterization` and `render` are both a function and the module that defines it: the package attribute
is the function (as `from splattwin.splat import rasterization` reads best); the modules are
`splattwin.splat.rasterization` for `from splattwin.splat.rasterization import ...` and
`importlib.import_module`.
"""

from __future__ import annotations

import importlib
import sys
import types

_EXPORTS = {"Gaussians": "gaussians",
            "rasterization": "rasterization", "RENDER_MODES": "rasterization",
            "RASTERIZE_MODES": "rasterization", "BACKENDS": "rasterization",
            "render": "render", "render_rgb": "render", "render_rgbd": "render", "render_depth": "render",
            "render_features": "render",
            "train": "trainer", "Trainer": "trainer", "TrainResult": "trainer",
            "TrainConfig": "config", "LearningRates": "config",
            "Strategy": "strategy", "DefaultStrategy": "strategy", "GaussianModel": "model",
            "evaluate": "eval", "EvalResult": "eval", "psnr": "metrics", "ssim": "metrics"}

__all__ = list(_EXPORTS)

# Exported names that are also submodules: importing the submodule binds it on this package (setattr),
# which would replace the function with its module; the package keeps the function instead.
_FUNCTION_OVER_MODULE = frozenset(n for n, m in _EXPORTS.items() if n == m)


class _Package(types.ModuleType):
    def __setattr__(self, name: str, value) -> None:
        if name in _FUNCTION_OVER_MODULE and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"splattwin.splat.{_EXPORTS[name]}"), name)
        globals()[name] = value  # cached: later lookups do not come here
        return value
    raise AttributeError(f"module 'splattwin.splat' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
