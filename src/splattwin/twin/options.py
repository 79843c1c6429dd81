"""Options of the twin stage: its exports (`splattwin export`, `splattwin geometry`, `build --export.*`)
and, as the stage runs, the pair geometry + exports (`TwinOptions`). The geometry options are
`splattwin.geometry.options.GeometryOptions`. Light: read by `splattwin --help`."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from splattwin.errors import InputError
from splattwin.geometry.options import GeometryOptions
from splattwin.options import option

FORMATS = ("mjcf", "urdf", "moveit", "gltf")
_PACKAGE_RE = re.compile(r"package://[A-Za-z][A-Za-z0-9_]{0,99}")
# a TF frame id: segments of letters, digits and '_' (each starting with a letter) joined by single '/'
_FRAME_RE = re.compile(r"/?[A-Za-z][A-Za-z0-9_]{0,63}(/[A-Za-z][A-Za-z0-9_]{0,63}){0,3}")


@dataclass
class ExportOptions:
    """Options of the twin's exporters (`splattwin export`, `build --export.*`): which formats, how URDF
    files name their meshes, the frame of the MoveIt objects. Passed as `options=` to `export_twin` and each
    `export_<format>`."""
    formats: str | None = option(None, "exports to write, comma-separated from mjcf,urdf,moveit,gltf ('' for none; "
                                 "none: all; an unscaled twin's are marked unscaled in each file)")

    urdf_uri: str = option("relative", "URDF mesh filenames: 'relative' (to the URDF file: simulators, yourdfpy; the "
                           "twin folder can move), 'file' (absolute file:// URIs: ROS on this machine) or "
                           "'package://NAME' (a ROS package NAME whose root is the twin folder)")
    moveit_frame: str = option("twin", "frame_id of the MoveIt collision objects: the twin frame's name in TF (not "
                               "'world', which stock Panda MoveIt configs put at the robot base)")

    def __post_init__(self):
        self.check()

    def check(self, where: str = "--urdf-uri") -> None:
        """InputError for a malformed urdf_uri or moveit_frame."""
        u = self.urdf_uri
        if not isinstance(u, str) or not (u in ("relative", "file") or _PACKAGE_RE.fullmatch(u)):
            raise InputError(f"urdf_uri {u!r} must be 'relative', 'file' or 'package://NAME' (NAME: letters, digits, "
                             "'_'; the package's root is the twin folder)", where)
        if not isinstance(self.moveit_frame, str) or not _FRAME_RE.fullmatch(self.moveit_frame):
            raise InputError(f"moveit_frame {self.moveit_frame!r} must be a TF frame name (letters, digits, '_', '/', "
                             "starting with a letter or '/')", "--moveit-frame")

    def resolve(self, where: str = "--formats") -> tuple[str, ...]:
        """The formats to write. InputError for unknown names."""
        if self.formats is None:
            return FORMATS
        fmts = tuple(f.strip().lower() for f in self.formats.split(",") if f.strip())
        bad = [f for f in fmts if f not in FORMATS]
        if bad:
            raise InputError(f"unknown export format(s) {', '.join(bad)}; choose from {', '.join(FORMATS)}", where)
        return fmts


@dataclass
class TwinOptions:
    """The twin stage's options as it runs (`splattwin.twin.stage.run`): the geometry conversion and the
    exports. `build` nests the two separately (`--geometry.*`, `--export.*`)."""

    geometry: GeometryOptions = field(default_factory=GeometryOptions)
    export: ExportOptions = field(default_factory=ExportOptions)
