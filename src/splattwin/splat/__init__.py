"""splat stage: 3D Gaussian Splatting reconstruction (model, trainer, PLY I/O, evaluation).

`Gaussians` (numpy, activated values) is the hand-over object to the later stages; the rasterizer is
`splattwin.splat.rasterization.rasterization`.
"""

from splattwin.splat.gaussians import Gaussians

__all__ = ["Gaussians"]
