"""Stage 1: intrinsic attribute filtering of Gaussians (paper section 3.3.1).

Low-opacity primitives (haze, ghosts) and needle-like or oversized ones (sparse-view artefacts that
would become false obstacles) are dropped. Needles are judged by largest / middle scale, not largest /
smallest: well-fitted surface Gaussians are flat discs (tiny smallest scale) and must survive. A needle
must also be long (largest scale > `needle_length`): trained splats line edges and sparsely seen sides
with short elongated Gaussians (on the demo twin 20-38 % of each object's splats have largest / middle
5-10, 93-98 % of those within 5 mm of the true surface; on the bottle's unseen side they are all there
is), and a few-millimetre splat cannot make a false obstacle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from splattwin.geometry.options import GeometryOptions


@dataclass
class FilterStats:
    """How many Gaussians each criterion removed (a Gaussian can fail several)."""

    total: int
    low_opacity: int
    oversized: int
    needle: int
    flat: int
    kept: int


def attribute_mask(opacities: np.ndarray, scales: np.ndarray, opts: GeometryOptions) -> tuple[np.ndarray, FilterStats]:
    """Boolean keep-mask [N] from opacities [N] and scales [N,3] (metres, activated).

    `opts.max_scale` must be resolved (see `GeometryOptions.resolved`); None disables that test.
    """
    opacities = np.asarray(opacities, dtype=np.float64).reshape(-1)
    s = np.sort(np.asarray(scales, dtype=np.float64).reshape(-1, 3), axis=1)  # ascending
    smallest, middle, largest = s[:, 0], s[:, 1], s[:, 2]
    low = opacities < opts.min_opacity
    big = largest > opts.max_scale if opts.max_scale is not None else np.zeros_like(low)
    with np.errstate(divide="ignore", invalid="ignore"):
        needle = (largest > opts.max_aspect * np.maximum(middle, 1e-12)) & (largest > opts.needle_length)
        flat = (largest > opts.max_flatness * np.maximum(smallest, 1e-12)) if opts.max_flatness else np.zeros_like(low)
    keep = ~(low | big | needle | flat)
    stats = FilterStats(total=int(len(keep)), low_opacity=int(low.sum()), oversized=int(big.sum()),
                        needle=int(needle.sum()), flat=int(flat.sum()), kept=int(keep.sum()))
    return keep, stats
