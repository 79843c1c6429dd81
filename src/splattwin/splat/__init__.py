"""splat stage: 3D Gaussian Splatting reconstruction (model, trainer, PLY I/O, evaluation).

`Gaussians` (numpy, activated values) is the hand-over object to the later stages; the rasterizer is
`splattwin.splat.rasterization.rasterization`; the options are `splattwin.splat.config.TrainConfig`.
Imports are lazy (`splattwin.splat.config` is read by `splattwin --help`).
"""

from __future__ import annotations

__all__ = ["Gaussians"]


def __getattr__(name: str):
    if name == "Gaussians":
        from splattwin.splat.gaussians import Gaussians

        return Gaussians
    raise AttributeError(f"module 'splattwin.splat' has no attribute {name!r}")
