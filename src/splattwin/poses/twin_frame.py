"""The twin's coordinate frame (`TwinFrame`): where it comes from, whether it is metric, how sure the scale
is. The poses stage defines it (OUT/frame.json); the twin records it in twin.json (`Manifest.frame`).

Not to be confused with `splattwin.capture.Frame`, an image of the capture with its camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from splattwin.errors import InputError

FRAME_FILE = "frame.json"
UNSCALED_UNITS = "unscaled"  # TwinFrame.units of a frame without metric scale

# Where a twin frame can come from (poses stage): see `TwinFrame.source`.
FRAME_SOURCES = ("ground_truth", "known_poses", "robot", "sfm+robot", "marker", "table_plane+known_length",
                 "table_plane+depth", "unscaled")


@dataclass
class TwinFrame:
    """Definition of the twin frame (metres, z up when it comes from the table or the robot base).

    source: one of FRAME_SOURCES. scaled: False when the metric scale is unknown (robot planning refuses).
    units: "m", or "unscaled" when the frame is not metric (lengths are in arbitrary SfM units).
    scale_uncertainty_rel: 1-sigma relative scale uncertainty (0.01 = 1 %).
    nominal_metre: unscaled frames only: the frame units that stand for one metre when the stages derive
    their length thresholds (cleaning, meshing, fusion: every option with unit "m" is multiplied by it,
    see `length_scale`); estimated from the capture by `splattwin.poses.table.nominal_metre` (the
    cameras' median distance to the scene over a typical tabletop viewing distance). None for a metric
    frame, whose thresholds are used as given.
    T_twin_input: how the input's coordinates map into the twin frame (e.g. a z-down robot world rotated
    180 degrees about x). up_check: the evidence for up (cameras, table plane): for known poses, which
    way their world's up was; for a table frame (SfM, unscaled), which plane is the table.
    """

    source: str = "unscaled"
    scaled: bool = False
    units: str = "m"
    up: str = "+z"
    scale_uncertainty_rel: float | None = None
    description: str = ""
    # [4,4] similarity from the input's world (known or robot poses; the SfM model for SfM) to this frame
    T_twin_input: list | None = None
    # known poses: where up was found and the rotation applied (splattwin.poses.up.UpCheck.to_dict)
    up_check: dict | None = None
    nominal_metre: float | None = None

    def __post_init__(self) -> None:
        if not self.scaled:
            self.units = UNSCALED_UNITS  # never "m" for a frame without metric scale (older files said so)

    def check(self, where) -> None:
        """InputError naming `where` for fields of the wrong type (a received frame.json or twin.json:
        "scaled": "false" is a non-empty string, so truthy, and would mark an unscaled twin metric)."""
        for k in ("source", "units", "up", "description"):
            if not isinstance(getattr(self, k), str):
                raise InputError(f"malformed frame: {k} must be text, got {type(getattr(self, k)).__name__}", where)
        if self.source not in FRAME_SOURCES:   # the text travels into the exports' comments and names
            raise InputError(f"malformed frame: source {self.source[:60]!r} is none of {', '.join(FRAME_SOURCES)}",
                             where)
        if not isinstance(self.scaled, bool):
            raise InputError(f"malformed frame: scaled must be true or false, got {type(self.scaled).__name__} "
                             f"{str(self.scaled)[:40]!r}", where)

    def save(self, path: str | Path) -> Path:
        """Write this frame as `path` (a frame.json, or a folder to hold one), as the poses stage does;
        `load_frame` reads it back. Returns the file's path."""
        import dataclasses

        from splattwin import io

        path = Path(path)
        if path.is_dir():
            path = path / FRAME_FILE
        self.check(path)
        return io.write_json(path, dataclasses.asdict(self))

    @classmethod
    def load(cls, path: str | Path) -> TwinFrame:
        """`load_frame(path)`: a frame.json, or the folder holding one."""
        return load_frame(path)

    def summary(self) -> str:
        """One-line description for headers and logs, each fact said once: "unscaled (SfM units; up +z)",
        "marker (metric, metres; up +z)"; another source without metric scale: "known_poses (not metric; up +z)"."""
        if not self.scaled:
            units = "SfM units" if self.source == "unscaled" else "not metric"
        else:
            units = "metric, metres"
        return f"{self.source} ({units}; up {self.up})"

    def length_scale(self, fallback: float | None = None) -> float:
        """Factor applied to every metric length option: 1 for a metric frame; for an unscaled one its
        `nominal_metre`, else `fallback` (estimated by the caller from its data), else 1."""
        if self.scaled:
            return 1.0
        for v in (self.nominal_metre, fallback):
            if v is not None and math.isfinite(v) and v > 0:
                return float(v)
        return 1.0


def frame_beside(path: str | Path) -> TwinFrame | None:
    """The frame.json next to a posed dataset (`path`: its transforms.json or its folder), as the poses
    stage writes it; None when there is none."""
    p = Path(path)
    cand = (p.parent if p.is_file() else p) / FRAME_FILE
    return load_frame(cand) if cand.is_file() else None


def load_frame(path: str | Path) -> TwinFrame:
    """Frame definition from a frame.json (or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / FRAME_FILE
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    from splattwin.paths import own_file

    own_file(path.parent, path, FRAME_FILE)   # the poses folder's own record, not a link out of it
    d = read_json(path, "no frame definition here (expected frame.json)", MAX_RECORD_BYTES)
    if not isinstance(d, dict):
        raise InputError("malformed frame definition: expected a JSON object", path)
    try:
        frame = TwinFrame(**d)
    except TypeError as e:
        raise InputError(f"malformed frame definition: {e}", path) from None
    frame.check(path)
    return frame
