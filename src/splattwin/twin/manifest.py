"""The twin manifest (`twin.json`): one plain data object that loads and saves itself.

All paths inside are relative to the twin folder. Frame: the twin frame named in `frame` (metres,
z up, table surface at z = 0 when the frame comes from the table). Object meshes and convex parts are
stored in the object's own frame; `T_world_obj` places them in the twin frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from splattwin import io
from splattwin.errors import InputError

SCHEMA_VERSION = 1
MANIFEST_NAME = "twin.json"

# Where a twin frame can come from (poses stage): see `Frame.source`.
FRAME_SOURCES = ("ground_truth", "known_poses", "robot", "sfm+robot", "marker", "table_plane+known_length", "unscaled")


@dataclass
class Frame:
    """Definition of the twin frame.

    source: one of FRAME_SOURCES. scaled: False when the metric scale is unknown (robot stages refuse).
    scale_uncertainty_rel: 1-sigma relative scale uncertainty (0.01 = 1 %).
    """

    source: str = "unscaled"
    scaled: bool = False
    units: str = "m"
    up: str = "+z"
    scale_uncertainty_rel: float | None = None
    description: str = ""


@dataclass
class ObjectEntry:
    """One manipulable object of the twin.

    T_world_obj: [4,4] object frame in the twin frame (object frame = centre of its gravity-aligned
    oriented bounding box, z up). bbox_extent: box side lengths in the object frame (m).
    Paths are relative to the twin folder; None when not produced. usable=False marks an object whose
    geometry failed (problem says why): exporters skip it and robot stages refuse to plan with it.
    """

    name: str
    label: int
    prompt: str = ""
    T_world_obj: list = field(default_factory=lambda: np.eye(4).tolist())
    bbox_extent: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    mass: float | None = None
    volume: float | None = None
    splat_ply: str | None = None
    visual_mesh: str | None = None
    collision_mesh: str | None = None
    convex_parts: list = field(default_factory=list)
    usable: bool = True
    problem: str | None = None

    @property
    def pose(self) -> np.ndarray:
        return np.asarray(self.T_world_obj, dtype=np.float64)


@dataclass
class Background:
    """Static environment: the table (plane z = table_height in the twin frame) and other obstacles.

    Meshes are in the twin frame. table_extent: [xmin, xmax, ymin, ymax] of the table top (m).
    """

    table_height: float = 0.0
    table_extent: list = field(default_factory=lambda: [-0.5, 0.5, -0.4, 0.4])
    table_thickness: float = 0.03
    splat_ply: str | None = None
    collision_mesh: str | None = None
    convex_parts: list = field(default_factory=list)


@dataclass
class Manifest:
    frame: Frame = field(default_factory=Frame)
    objects: list[ObjectEntry] = field(default_factory=list)
    background: Background = field(default_factory=Background)
    cameras: str | None = None          # path of a cameras file (nerfstudio transforms.json)
    splats: str | None = None           # full-scene 3DGS PLY
    labels: str | None = None           # per-Gaussian label array (.npy, 0 = background)
    exports: dict[str, Any] = field(default_factory=dict)   # e.g. {"mjcf": "export/scene.xml"}
    config: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION

    def object(self, name: str) -> ObjectEntry:
        for o in self.objects:
            if o.name == name:
                return o
        raise InputError(f"no object named {name!r} in the twin (have: {', '.join(o.name for o in self.objects)})")

    # -- load / save ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return asdict(self)

    def save(self, twin_dir: str | Path) -> Path:
        return io.write_json(Path(twin_dir) / MANIFEST_NAME, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict, where: str | Path = MANIFEST_NAME) -> "Manifest":
        try:
            if d.get("schema_version") != SCHEMA_VERSION:
                raise InputError(f"unsupported schema_version {d.get('schema_version')!r} (expected {SCHEMA_VERSION})", where)
            return cls(
                frame=Frame(**d.get("frame", {})),
                objects=[ObjectEntry(**o) for o in d.get("objects", [])],
                background=Background(**d.get("background", {})),
                **{k: d[k] for k in ("cameras", "splats", "labels", "exports", "config", "versions", "timings", "schema_version") if k in d},
            )
        except TypeError as e:  # unknown / missing keys
            raise InputError(f"malformed manifest: {e}", where) from e

    @classmethod
    def load(cls, twin_dir: str | Path) -> "Manifest":
        path = Path(twin_dir) / MANIFEST_NAME
        return cls.from_dict(io.read_json(path, missing="no twin manifest here (expected twin.json)"), where=path)
