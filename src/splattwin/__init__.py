"""splattwin: a few RGB photos of a tabletop -> a planning-ready 3D Gaussian Splatting digital twin.

Stages (one subpackage each): capture, poses, splat, semantics, geometry, twin, robot, report, viewer;
`scene` generates the embedded benchmark scene and `pipeline` ties the stages together.
Units are metres and radians; cameras follow the OpenCV convention (x right, y down, z forward).

Importing splattwin (or any subpackage) changes no environment variable and no thread setting; call
`splattwin.runtime.configure()` once at the start of a program, before torch, numba or mujoco load
(the `splattwin` command does): OpenMP passive waiting, headless MuJoCo rendering, numba threads.
"""

__version__ = "0.1.0"
