"""Options of the twin stage: its exports (`splattwin export`, `splattwin geometry`, `build --export.*`)
and, as the stage runs, the pair geometry + exports (`TwinOptions`). The geometry options are
`splattwin.geometry.options.GeometryOptions`. Light: read by `splattwin --help`."""

from __future__ import annotations

from dataclasses import dataclass, field

from splattwin.errors import InputError
from splattwin.geometry.options import GeometryOptions
from splattwin.options import option

FORMATS = ("mjcf", "urdf", "moveit", "gltf")


@dataclass
class ExportOptions:
    formats: str | None = option(None, "exports to write, comma-separated from mjcf,urdf,moveit,gltf ('' for none; "
                                 "none: all; an unscaled twin's are marked unscaled in each file)")

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
