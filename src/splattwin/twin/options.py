"""Options of the twin stage's exports (`splattwin export`, `splattwin geometry`, `build --export.*`).
The geometry options are `splattwin.geometry.options.GeometryOptions`. Light: read by `splattwin --help`."""

from __future__ import annotations

from dataclasses import dataclass

from splattwin.errors import InputError
from splattwin.options import option

FORMATS = ("mjcf", "urdf", "moveit", "gltf")
METRIC_FORMATS = ("mjcf",)   # physics needs metres: refused for an unscaled twin


@dataclass
class ExportOptions:
    formats: str | None = option(None, "exports to write, comma-separated from mjcf,urdf,moveit,gltf ('' for none; "
                                 "none: all, less mjcf for an unscaled twin)")

    def resolve(self, scaled: bool, where: str = "--formats") -> tuple[str, ...]:
        """The formats to write for a twin whose frame is (not) metric. InputError for unknown names."""
        if self.formats is None:
            return tuple(f for f in FORMATS if scaled or f not in METRIC_FORMATS)
        fmts = tuple(f.strip().lower() for f in self.formats.split(",") if f.strip())
        bad = [f for f in fmts if f not in FORMATS]
        if bad:
            raise InputError(f"unknown export format(s) {', '.join(bad)}; choose from {', '.join(FORMATS)}", where)
        return fmts

