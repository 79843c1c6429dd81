"""Per-object Gaussian splat PLYs (Unity Gaussian Splatting, SuperSplat), in the object frame.

Moving Gaussians into another frame rotates means, orientations *and* the view-dependent colour
(`splattwin.splat.transform`, re-exported here).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin.splat.gaussians import Gaussians
from splattwin.splat.transform import eval_sh, sh_basis, sh_rotation, transform_gaussians  # noqa: F401 (re-exported)


def write_object_splats(path: str | Path, g: Gaussians, T_world_obj: np.ndarray, comments=()) -> Path:
    """Write Gaussians (world frame) as a standard 3DGS PLY in the object frame, atomically.
    comments: PLY comment lines (units, frame; see `splat.ply.write_gaussians_ply`)."""
    from splattwin.splat.ply import write_gaussians_ply

    return write_gaussians_ply(path, transform_gaussians(g, np.linalg.inv(T_world_obj)), comments)
