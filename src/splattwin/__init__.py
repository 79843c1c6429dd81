"""splattwin: a few RGB photos of a tabletop -> a planning-ready 3D Gaussian Splatting digital twin.

Stages (one subpackage each): capture, poses, splat, semantics, geometry, twin, robot, report, viewer;
`scene` generates the embedded benchmark scene and `pipeline` ties the stages together.
Units are metres and radians; cameras follow the OpenCV convention (x right, y down, z forward).
"""

import os as _os

# Our CPU rasterizer runs numba threads between torch ops; torch's OpenMP workers must not spin-wait
# in between (measured: ~2x slower training steps on 2 cores). Must be set before torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# MuJoCo picks its GL backend when first imported: without a display, use EGL (headless Mesa works)
# so the robot stage can render frames whichever stage imported mujoco first.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "egl"

__version__ = "0.1.0"
