"""The twin manifest (`twin.json`): one plain data object that loads and saves itself.

All paths inside are relative to the twin folder, so the folder can be moved or copied whole. Frame:
the twin frame named in `frame` (metres, z up, table surface at z = 0 when the frame comes from the
table). Object meshes and convex parts are stored in the object's own frame; `T_world_obj` places them
in the twin frame.

A twin.json is often received from someone else, so `Manifest.load` checks it before anything uses it:
object names are valid, unique names (`splattwin.names`), labels are unique positive integers, poses
are finite 4x4 matrices, sizes and masses finite numbers, and every path is relative and stays inside
the twin folder once `..` and symbolic links are resolved (`splattwin.paths`). Anything else is an
InputError naming twin.json (exit 2).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.names import check_unique, object_name
from splattwin.paths import confined
from splattwin.poses.twin_frame import TwinFrame

SCHEMA_VERSION = 1
MANIFEST_NAME = "twin.json"

def unscaled_note(frame: TwinFrame) -> str | None:
    """The line every export of an unscaled twin carries (a comment or metadata), None for a metric twin."""
    if frame.scaled:
        return None
    nm = f"; about {frame.nominal_metre:.4g} units stand for 1 m (a guess)" if frame.nominal_metre else ""
    return (f"UNSCALED twin: lengths are in arbitrary SfM units, not metres (frame source {frame.source!r}{nm}); "
            "masses are nominal. Rebuild with --known-length, --marker-size or metric poses for a metric twin.")


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

    Meshes are in the twin frame. table_extent: [xmin, xmax, ymin, ymax] of the table top (m; frame
    units in an unscaled twin). table_default: why the table is assumed, in whole (no table in the splats)
    or in part (extended under the objects), None when the splats' table is used as found.
    """

    table_height: float = 0.0
    table_extent: list = field(default_factory=lambda: [-0.5, 0.5, -0.4, 0.4])
    table_thickness: float = 0.03
    splat_ply: str | None = None
    collision_mesh: str | None = None
    convex_parts: list = field(default_factory=list)
    table_default: str | None = None


@dataclass
class Manifest:
    frame: TwinFrame = field(default_factory=TwinFrame)
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

    def paths(self) -> list[tuple[str, Any]]:
        """(what, relative path) of every file the manifest refers to."""
        out: list[tuple[str, Any]] = []
        for k in ("cameras", "splats", "labels"):
            out.append((k, getattr(self, k)))
        for o in self.objects:
            for k in ("splat_ply", "visual_mesh", "collision_mesh"):
                out.append((f"object {o.name!r} {k}", getattr(o, k)))
            out += [(f"object {o.name!r} convex part", p) for p in o.convex_parts]
        b = self.background
        out += [("background splat_ply", b.splat_ply), ("background collision_mesh", b.collision_mesh)]
        out += [("background convex part", p) for p in b.convex_parts]
        out += [(f"export {k}", v) for k, v in self.exports.items() if isinstance(v, str)]
        return [(w, p) for w, p in out if p is not None]

    def validate(self, twin_dir: str | Path | None = None, where: str | Path = MANIFEST_NAME) -> None:
        """Check names, labels, numbers and paths (see module docstring); with `twin_dir` the paths are
        also resolved (symbolic links) and must stay inside it. InputError naming `where`."""
        if not isinstance(self.objects, list) or not all(isinstance(o, ObjectEntry) for o in self.objects):
            raise InputError("malformed manifest: objects must be a list of objects", where)
        if self.frame.T_twin_input is not None:
            _matrix(self.frame.T_twin_input, (4, 4), where, "frame T_twin_input")
        if self.frame.up_check is not None and not isinstance(self.frame.up_check, dict):
            raise InputError("malformed manifest: frame up_check must be an object", where)
        labels: set[int] = set()
        for o in self.objects:
            object_name(o.name, where)
            if isinstance(o.label, bool) or not isinstance(o.label, int) or o.label < 1 or o.label in labels:
                raise InputError(f"object {o.name!r}: label {o.label!r} must be a unique integer >= 1", where)
            labels.add(o.label)
            _matrix(o.T_world_obj, (4, 4), where, f"object {o.name!r} T_world_obj")
            _numbers(o.bbox_extent, 3, where, f"object {o.name!r} bbox_extent", nonneg=True)
            for k in ("mass", "volume"):
                if getattr(o, k) is not None:
                    _numbers([getattr(o, k)], 1, where, f"object {o.name!r} {k}", nonneg=True)
            if not isinstance(o.convex_parts, list):
                raise InputError(f"object {o.name!r}: convex_parts must be a list of paths", where)
        check_unique([o.name for o in self.objects], where)
        b = self.background
        _numbers(b.table_extent, 4, where, "background table_extent")
        _numbers([b.table_height, b.table_thickness], 2, where, "background table_height / table_thickness")
        if not isinstance(b.convex_parts, list):
            raise InputError("background convex_parts must be a list of paths", where)
        for k in ("exports", "config", "versions", "timings"):
            if not isinstance(getattr(self, k), dict):
                raise InputError(f"malformed manifest: {k} must be an object", where)
        root = Path(twin_dir) if twin_dir is not None else Path("/nonexistent-twin-root")
        for what, rel in self.paths():
            confined(root, rel, where, f"{what} path")

    def object(self, name: str) -> ObjectEntry:
        for o in self.objects:
            if o.name == name:
                return o
        raise InputError(f"no object named {name!r} in the twin (have: {', '.join(o.name for o in self.objects)})")

    # -- load / save ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return asdict(self)

    def save(self, twin_dir: str | Path) -> Path:
        self.validate(twin_dir, Path(twin_dir) / MANIFEST_NAME)  # never write a manifest load() refuses
        return io.write_json(Path(twin_dir) / MANIFEST_NAME, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict, where: str | Path = MANIFEST_NAME) -> "Manifest":
        if not isinstance(d, dict):
            raise InputError("malformed manifest: expected a JSON object", where)
        try:
            if d.get("schema_version") != SCHEMA_VERSION:
                raise InputError(f"unsupported schema_version {d.get('schema_version')!r} (expected {SCHEMA_VERSION})", where)
            m = cls(
                frame=TwinFrame(**d.get("frame", {})),
                objects=[ObjectEntry(**o) for o in d.get("objects", [])],
                background=Background(**d.get("background", {})),
                **{k: d[k] for k in ("cameras", "splats", "labels", "exports", "config", "versions", "timings", "schema_version") if k in d},
            )
        except TypeError as e:  # unknown / missing keys, or an entry that is not an object
            raise InputError(f"malformed manifest: {e}", where) from e
        m.validate(None, where)
        return m

    @classmethod
    def load(cls, twin_dir: str | Path) -> "Manifest":
        path = Path(twin_dir) / MANIFEST_NAME
        m = cls.from_dict(io.read_json(path, missing="no twin manifest here (expected twin.json)"), where=path)
        m.validate(twin_dir, path)
        return m


def _numbers(v, n: int, where, what: str, nonneg: bool = False) -> np.ndarray:
    try:
        if isinstance(v, (str, bytes)):
            raise ValueError("text")
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be {n} number(s), got {str(v)[:60]!r}", where) from None
    if a.shape != (n,) or not np.all(np.isfinite(a)) or (nonneg and np.any(a < 0)):
        raise InputError(f"{what} must be {n} finite{' non-negative' if nonneg else ''} number(s), got "
                         f"{str(v)[:80]}", where)
    return a


def _matrix(v, shape: tuple[int, int], where, what: str) -> np.ndarray:
    try:
        if isinstance(v, (str, bytes)):
            raise ValueError("text")
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a {shape[0]}x{shape[1]} matrix of numbers, got {str(v)[:60]!r}", where) from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(f"{what} must be a finite {shape[0]}x{shape[1]} matrix, got shape {a.shape}"
                         + ("" if a.shape != shape else " with NaN or infinite values"), where)
    return a
