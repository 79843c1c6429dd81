"""splattwin: a few RGB photos of a tabletop -> a planning-ready 3D Gaussian Splatting digital twin.

Stages (one subpackage each): capture, poses, splat, semantics, geometry, twin, robot, report, viewer;
`scene` generates the embedded benchmark scene and `pipeline` ties the stages together.
Units are metres and radians; cameras follow the OpenCV convention (x right, y down, z forward).

Importing splattwin (or any subpackage) changes no environment variable and no thread setting; call
`splattwin.runtime.configure()` once at the start of a program, before torch, numba or mujoco load
(the `splattwin` command does): OpenMP passive waiting, headless MuJoCo rendering, numba threads.
A built twin from Python (its objects, splats rendered and scored, fusion with your masks, one object's
geometry, a pick-and-place in MuJoCo): README.md, "Using splattwin as a library".
"""

__version__ = "0.1.0"

# The stage packages as attributes, imported on first use (PEP 562): `import splattwin; splattwin.splat.Gaussians`
# works as in numpy/scipy, and `import splattwin` itself still imports nothing (the packages are lazy too).
_PACKAGES = ("capture", "poses", "splat", "semantics", "geometry", "twin", "robot", "playback", "report", "viewer",
             "scene", "pipeline", "cluster")


def __getattr__(name: str):
    if name in _PACKAGES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PACKAGES))
