"""The twin manifest (`twin.json`): one plain data object that loads and saves itself.

All paths inside are relative to the twin folder, so the folder can be moved or copied whole. Frame:
the twin frame named in `frame` (metres, z up, table surface at z = 0 when the frame comes from the
table). Object meshes and convex parts are stored in the object's own frame; `T_world_obj` places them
in the twin frame.

A twin.json is often received from someone else, so `Manifest.load` checks it before anything uses it:
object names are valid, unique names (`splattwin.names`), labels are unique positive integers, poses
are rigid 4x4 matrices, every number is finite and within the bounds below, and every path is relative
and stays inside the twin folder once `..` and symbolic links are resolved (`splattwin.paths`); the
error names the twin folder. Anything else is an InputError naming twin.json (exit 2).

Bounds (generous for real twins, unscaled ones in SfM units included; they exist so that no absurd
value reaches an exporter, e.g. a 1e300 m table MuJoCo cannot load): every coordinate and length at
most MAX_LENGTH in magnitude; the table's sides and thickness at least MIN_LENGTH (MJCF box sizes
must be positive); volumes at most MAX_LENGTH**3, masses at most MAX_MASS; `exports` maps formats
to paths.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.limits import MAX_RECORD_BYTES
from splattwin.names import check_unique, export_id, object_name
from splattwin.paths import confined
from splattwin.poses.twin_frame import TwinFrame

SCHEMA_VERSION = 1
MANIFEST_NAME = "twin.json"

# Bounds on the numbers of a twin.json (module docstring). Twin frames are centred on the scene, so even an
# unscaled twin (SfM units: tens to hundreds of units across) stays far inside 1e6.
MAX_LENGTH = 1e6          # |coordinate|, extent, table height/thickness, nominal metre (m or frame units)
MIN_LENGTH = 1e-6         # table sides and thickness: a positive MJCF box size
MAX_VOLUME = MAX_LENGTH ** 3
MAX_MASS = 1e12           # kg; an unscaled twin's masses are nominal and may be far from real ones
# T_twin_input maps the input's world (e.g. a georeferenced SfM model, coordinates ~1e7) to the twin
# frame: only finiteness and this looser bound
MAX_INPUT_COORD = 1e12
# Labels are stored in 16-bit label images (0 = background), and a label sizes per-label tables (a
# viewer palette of label+1 colours): 1.5e9 cost 9 GB.
MAX_LABEL = 65535
MAX_EXPORT_FILES = 4 * 65536   # export_files entries (a few per object at most)
RIGID_TOL = 1e-3          # |R^T R - I| and |bottom row - [0 0 0 1]| of an object pose

def unscaled_note(frame: TwinFrame) -> str | None:
    """The line every export of an unscaled twin carries (a comment or metadata), None for a metric twin."""
    if frame.scaled:
        return None
    nm = f"; about {frame.nominal_metre:.4g} units stand for 1 m (a guess)" if frame.nominal_metre else ""
    return (f"UNSCALED twin: lengths are in arbitrary SfM units, not metres (frame source {frame.source!r}{nm}); "
            "masses are nominal. Rebuild with --known-length, --marker-size or metric poses for a metric twin.")


# the phrase twin/build.py puts in the `problem` of an unusable object that has no obstacle box because no
# splat of it survived (`obstacle_only` false on purpose); `missing_obstacle_boxes` tells them apart by it
NO_GEOMETRY = "no geometry at all"


def missing_obstacle_boxes(manifest: "Manifest") -> list[str]:
    """Names of the unusable objects that are in no collision export only because the twin.json predates
    obstacle-only boxes: `obstacle_only` false (or absent: the dataclass default) and a `problem` that
    does not say the object has no geometry at all (which a newer build writes when it has no box).
    Rebuilding the twin stage (`splattwin build INPUT --out TWIN --from twin`) gives each its box."""
    return [o.name for o in manifest.objects
            if not o.usable and not o.obstacle_only and NO_GEOMETRY not in (o.problem or "")]


def warn_missing_obstacle_boxes(manifest: "Manifest", twin_dir: str | Path) -> list[str]:
    """Log one warning naming the objects of `missing_obstacle_boxes`: the collision world (MJCF, URDF,
    MoveIt, glTF, the robot's) leaves them out, although the real objects stand there. Called once per
    command, where it loads the twin (`export`: twin/cli.py; `plan` and the pipeline's robot stage:
    robot/stage.py). Returns the names."""
    import logging

    names = missing_obstacle_boxes(manifest)
    if names:
        logging.getLogger(__name__).warning("%s", missing_obstacle_boxes_note(names, twin_dir))
    return names


def missing_obstacle_boxes_note(names: list[str], twin_dir: str | Path = "TWIN") -> str:
    """The sentence of `warn_missing_obstacle_boxes` (also the report's)."""
    which = ", ".join(repr(n) for n in names)
    one = len(names) == 1
    return (f"{'object' if one else 'objects'} {which} {'is' if one else 'are'} unusable and in no collision "
            f"export (MJCF, URDF, MoveIt, glTF) nor in the robot's world, although the real "
            f"{'object stands' if one else 'objects stand'} there: {twin_dir}/twin.json predates obstacle-only "
            f"boxes; rebuilding the twin stage (`splattwin build INPUT --out {twin_dir} --from twin`, INPUT: the "
            f"capture it was built from) keeps {'it' if one else 'each'} as a static obstacle box that the "
            f"robot avoids (when some of {'its' if one else 'their'} splats survive)")


def units_text(frame: TwinFrame) -> str:
    """What a file's lengths are, for comment lines (PLY, OBJ, export headers)."""
    return "units: metres (metric twin)" if frame.scaled else "units: " + (unscaled_note(frame) or "")


def mass_source(density: float, scaled: bool = True) -> str:
    """How an object's mass and inertia were obtained (twin.json `mass_source`, URDF/MJCF comments)."""
    if not scaled:  # the density was rescaled to frame units: its number would mislead
        return ("nominal (unscaled twin): collision-mesh volume x uniform density (--geometry.density per nominal "
                "cubic metre), not weighed; inertia of that uniform solid")
    return (f"estimate: collision-mesh volume x uniform density {density:g} kg/m^3 (--geometry.density), not "
            "weighed; inertia of that uniform solid")


@dataclass
class ObjectEntry:
    """One manipulable object of the twin.

    T_world_obj: [4,4] object frame in the twin frame (object frame = centre of its gravity-aligned
    oriented bounding box, z up). bbox_extent: box side lengths in the object frame (m).
    Paths are relative to the twin folder; None when not produced. usable=False marks an object whose
    geometry failed (problem says why): robot stages refuse to plan with it. Its splats still stand
    where the real object stands, so when some survived, obstacle_only=True and T_world_obj /
    bbox_extent give their padded axis-aligned box (an estimate): every collision export has it as a
    static box (a robot must not sweep through the real object); obstacle_only=False with a zero extent
    means it has no geometry at all (the problem says so). A usable object may carry a problem too (a
    warning: e.g. it covers little of its masks, or floats above its support).
    export_id: the object's ID in every export (`splattwin.names.export_id`; the human name stays in
    `name`); derived from the name when the manifest is validated (a stored value is only a record). mass_source: how mass and inertia were obtained (an estimate: volume x uniform density).
    silhouette_coverage / silhouette_precision: the share of the object's 2D masks its cleaned splats
    cover, and of their silhouette inside the masks (medians over views, `geometry.completeness`); None
    when not measured (no masks, or too few points).
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
    silhouette_coverage: float | None = None
    silhouette_precision: float | None = None
    export_id: str | None = None
    obstacle_only: bool = False
    mass_source: str | None = None

    @property
    def pose(self) -> np.ndarray:
        return np.asarray(self.T_world_obj, dtype=np.float64)


@dataclass
class Background:
    """Static environment: the table (plane z = table_height in the twin frame) and other obstacles.

    Meshes are in the twin frame. table_extent: [xmin, xmax, ymin, ymax] of the table top (m; frame
    units in an unscaled twin). table_default: why the table is assumed, in whole (no table in the splats)
    or in part (extended under the objects), None when the splats' table is used as found.
    convex_parts: part 0 is the table box (every export writes it as a box primitive), the rest the
    obstacles' convex parts.
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
    """A twin folder's twin.json as plain data (module docstring: frame, bounds, checks).

    frame: the twin frame (`TwinFrame`: metric or unscaled, where it came from); objects: `ObjectEntry` per
    manipulable object (pose T_world_obj [4,4] in the twin frame, metres, meshes in the object frame);
    background: the table and static obstacles (`Background`, twin frame); cameras / splats / labels:
    the posed capture, full-scene 3DGS PLY and per-Gaussian labels (.npy, 0 = background); exports:
    format -> file, export_files: what a consumer of each file must know; config: the resolved build
    options (`config.build`) and scene facts; versions, timings (s). Every path is relative to the twin
    folder and stays inside it.

    `Manifest.load(twin_dir)` (the folder or its twin.json) reads and validates; `save(twin_dir)` validates
    and writes atomically; `validate`, `object(name)`, `paths()`, `to_dict()` / `from_dict(d)`.
    """

    frame: TwinFrame = field(default_factory=TwinFrame)
    objects: list[ObjectEntry] = field(default_factory=list)
    background: Background = field(default_factory=Background)
    cameras: str | None = None          # path of a cameras file (nerfstudio transforms.json)
    splats: str | None = None           # full-scene 3DGS PLY
    labels: str | None = None           # per-Gaussian label array (.npy, 0 = background)
    exports: dict[str, Any] = field(default_factory=dict)   # e.g. {"mjcf": "export/scene.xml"}
    # every export file with what a consumer must know: [{path, format, frame, units, scaled, ...}]
    # (`splattwin.twin.build.describe_exports`)
    export_files: list = field(default_factory=list)
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
        out += [("export file", e.get("path")) for e in self.export_files
                if isinstance(e, dict) and isinstance(e.get("path"), str)]
        return [(w, p) for w, p in out if p is not None]

    def validate(self, twin_dir: str | Path | None = None, where: str | Path = MANIFEST_NAME) -> None:
        """Check names, labels, numbers and paths (see module docstring); with `twin_dir` the paths are
        also resolved (symbolic links) and must stay inside it, else they are checked as written, against
        the folder holding `where`. InputError naming `where`."""
        if not isinstance(self.objects, list) or not all(isinstance(o, ObjectEntry) for o in self.objects):
            raise InputError("malformed manifest: objects must be a list of objects", where)
        # True == 1 to Python: a schema_version of true would pass the version test
        if isinstance(self.schema_version, bool) or self.schema_version != SCHEMA_VERSION:
            raise InputError(f"unsupported schema_version {_brief(self.schema_version)} (expected {SCHEMA_VERSION})",
                             where)
        f = self.frame
        f.check(where)
        if f.T_twin_input is not None:
            _matrix(f.T_twin_input, (4, 4), where, "frame T_twin_input", bound=MAX_INPUT_COORD)
        if f.up_check is not None and not isinstance(f.up_check, dict):
            raise InputError("malformed manifest: frame up_check must be an object", where)
        if f.nominal_metre is not None:
            _numbers([f.nominal_metre], 1, where, "frame nominal_metre", low=MIN_LENGTH, high=MAX_LENGTH)
        if f.scale_uncertainty_rel is not None:
            _numbers([f.scale_uncertainty_rel], 1, where, "frame scale_uncertainty_rel", low=0.0, high=1e3)
        labels: set[int] = set()
        for o in self.objects:
            object_name(o.name, where)
            if (isinstance(o.label, bool) or not isinstance(o.label, int) or not 1 <= o.label <= MAX_LABEL
                    or o.label in labels):
                raise InputError(f"object {o.name!r}: label {_brief(o.label)} must be a unique integer in "
                                 f"[1, {MAX_LABEL}]", where)
            labels.add(o.label)
            _pose(o.T_world_obj, where, f"object {o.name!r} T_world_obj")
            _numbers(o.bbox_extent, 3, where, f"object {o.name!r} bbox_extent", low=0.0, high=MAX_LENGTH)
            for k, high in (("mass", MAX_MASS), ("volume", MAX_VOLUME), ("silhouette_coverage", 1.0),
                            ("silhouette_precision", 1.0)):
                if getattr(o, k) is not None:
                    _numbers([getattr(o, k)], 1, where, f"object {o.name!r} {k}", low=0.0, high=high)
            if not isinstance(o.convex_parts, list):
                raise InputError(f"object {o.name!r}: convex_parts must be a list of paths", where)
            # usable "false" (text) is truthy: an object whose geometry failed would count as usable
            if not isinstance(o.usable, bool):
                raise InputError(f"object {o.name!r}: usable must be true or false, got {type(o.usable).__name__}",
                                 where)
            for k in ("prompt", "problem", "mass_source"):
                v = getattr(o, k)
                if not (isinstance(v, str) or (k != "prompt" and v is None)):
                    raise InputError(f"object {o.name!r}: {k} must be text, got {type(v).__name__}", where)
            if not isinstance(o.obstacle_only, bool):
                raise InputError(f"object {o.name!r}: obstacle_only must be true or false", where)
            if o.obstacle_only and (o.usable or min(o.bbox_extent) < MIN_LENGTH):
                raise InputError(f"object {o.name!r}: obstacle_only needs usable false and a bbox_extent of sides "
                                 f">= {MIN_LENGTH:g} (the obstacle box)", where)
            # derived from the name, never trusted: the exporters use export_id(name), and an older twin (or
            # an object renamed since) has none or a stale one; twin.json records the one in use
            o.export_id = export_id(o.name)
        check_unique([o.name for o in self.objects], where)
        b = self.background
        x0, x1, y0, y1 = _numbers(b.table_extent, 4, where, "background table_extent", low=-MAX_LENGTH, high=MAX_LENGTH)
        if not (x1 - x0 >= MIN_LENGTH and y1 - y0 >= MIN_LENGTH):  # MJCF table box half-sizes must be > 0
            raise InputError(f"background table_extent [xmin, xmax, ymin, ymax] must have xmax - xmin and ymax - ymin "
                             f">= {MIN_LENGTH:g}, got {_brief(b.table_extent)}", where)
        _numbers([b.table_height], 1, where, "background table_height", low=-MAX_LENGTH, high=MAX_LENGTH)
        _numbers([b.table_thickness], 1, where, "background table_thickness", low=MIN_LENGTH, high=MAX_LENGTH)
        if not isinstance(b.convex_parts, list):
            raise InputError("background convex_parts must be a list of paths", where)
        if not (b.table_default is None or isinstance(b.table_default, str)):
            raise InputError("background table_default must be text or null", where)
        for k in ("exports", "config", "versions", "timings"):
            if not isinstance(getattr(self, k), dict):
                raise InputError(f"malformed manifest: {k} must be an object", where)
        for k, v in self.exports.items():
            if not isinstance(v, str):
                raise InputError(f"export {k!r} must be a path (text), got {_brief(v)}", where)
        if not isinstance(self.export_files, list) or len(self.export_files) > MAX_EXPORT_FILES:
            raise InputError(f"export_files must be a list of at most {MAX_EXPORT_FILES} entries", where)
        for e in self.export_files:
            if not (isinstance(e, dict) and isinstance(e.get("path"), str) and all(
                    isinstance(k, str) and (v is None or isinstance(v, (str, bool))) for k, v in e.items())):
                raise InputError(f"export_files entries must be objects with a path and text or true/false "
                                 f"values, got {_brief(e)}", where)
        if twin_dir is not None:
            root = Path(twin_dir)
            for what, rel in self.paths():
                confined(root, rel, where, f"{what} path")
        else:
            # no folder to resolve links in (a manifest from a dict): the paths as written must stay
            # inside the folder of `where`; the error names that folder, never a made-up one
            folder = Path(where).parent
            for what, rel in self.paths():
                confined(folder, rel, where, f"{what} path", resolve=False)

    def object(self, name: str) -> ObjectEntry:
        for o in self.objects:
            if o.name == name:
                return o
        raise InputError(f"no object named {name!r} in the twin (have: {', '.join(o.name for o in self.objects)})")

    # -- load / save ------------------------------------------------------------------------
    def render_filter(self, where: str | Path | None = MANIFEST_NAME) -> tuple[str, float]:
        """(rasterize_mode, eps2d px^2) the twin's splats were trained with (config.build.splat, see
        `splattwin.splat.config.trained_filter`; ("classic", 0.3) when not recorded): pass both to
        `splattwin.splat.render_rgb(..., rasterize_mode=, eps2d=)` (or `rasterization`) to draw them as the
        evaluation did (`make demo` trains "antialiased"). InputError naming `where` for a bad record."""
        from splattwin.splat.config import trained_filter

        build = self.config.get("build") if isinstance(self.config, dict) else None
        splat = build.get("splat") if isinstance(build, dict) else None
        try:
            return trained_filter(splat)
        except ValueError as e:
            raise InputError(f"config.build.splat: {e}", where) from None

    def to_dict(self) -> dict:
        return asdict(self)

    def save(self, twin_dir: str | Path) -> Path:
        self.validate(twin_dir, Path(twin_dir) / MANIFEST_NAME)  # never write a manifest load() refuses
        return io.write_json(Path(twin_dir) / MANIFEST_NAME, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict, where: str | Path = MANIFEST_NAME, twin_dir: str | Path | None = None) -> "Manifest":
        """The manifest in `d` (read from `where`), validated; `twin_dir`: the folder its paths are relative
        to (resolved, see `validate`)."""
        if not isinstance(d, dict):
            raise InputError("malformed manifest: expected a JSON object", where)
        try:
            v = d.get("schema_version")
            if isinstance(v, bool) or v != SCHEMA_VERSION:  # True == 1 to Python
                raise InputError(f"unsupported schema_version {_brief(v)} (expected {SCHEMA_VERSION})", where)
            m = cls(
                frame=TwinFrame(**d.get("frame", {})),
                objects=[ObjectEntry(**o) for o in d.get("objects", [])],
                background=Background(**d.get("background", {})),
                **{k: d[k] for k in ("cameras", "splats", "labels", "exports", "export_files", "config", "versions", "timings", "schema_version") if k in d},
            )
        except TypeError as e:  # unknown / missing keys, or an entry that is not an object
            raise InputError(f"malformed manifest: {e}", where) from e
        m.validate(twin_dir, where)
        return m

    @classmethod
    def load(cls, twin_dir: str | Path) -> "Manifest":
        """The manifest of a twin: `twin_dir` is the twin folder or its twin.json (as `TwinFrame.load` and
        `PoseResult.load` take either); validated, paths resolved against the folder (InputError naming
        twin.json; as for the files it names, a twin.json that is a symbolic link out of the folder is one).
        Functions that read the twin's other files still take the folder."""
        twin_dir = Path(twin_dir)
        if twin_dir.name == MANIFEST_NAME and not twin_dir.is_dir():   # (a folder may be named twin.json)
            twin_dir = twin_dir.parent
        path = twin_dir / MANIFEST_NAME
        if path.is_symlink():   # a received folder's twin.json linked to a file elsewhere: not this twin's
            confined(twin_dir, MANIFEST_NAME, path, "twin.json")
        missing = "no twin manifest here (expected twin.json)" + no_twin_yet(twin_dir)
        return cls.from_dict(io.read_json(path, missing=missing, max_bytes=MAX_RECORD_BYTES), path, twin_dir)


def no_twin_yet(folder: str | Path) -> str:
    """The end of a "no twin.json" message: for a build folder that stopped before the twin stage (`--until
    splats`, the only build a capture without masks can make, or a stopped build) why it is no twin yet and
    how to make it one; "" for any other folder."""
    folder = Path(folder)
    if not ((folder / "pipeline.json").is_file() or (folder / "splat" / "point_cloud.ply").is_file()):
        return ""
    return (": this build stopped before the twin stage (splats only, e.g. --until splats); run splattwin build "
            "again with --out this folder and 2D masks (--masks DIR or --prompt '...') to make the twin")


def _brief(v) -> str:
    """A short repr of a value read from twin.json: str() of a 157-million-item list before cutting it cost
    gigabytes; reprlib shows a few items at a few levels."""
    import reprlib

    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxstring, r.maxother = 3, 6, 40, 40
    return r.repr(v)


def _numbers(v, n: int, where, what: str, low: float = -MAX_LENGTH, high: float = MAX_LENGTH) -> np.ndarray:
    """`v` as n finite numbers in [low, high], else InputError naming `where`."""
    try:
        if isinstance(v, (str, bytes)) or (isinstance(v, (list, tuple)) and len(v) > n):
            raise ValueError("text or too many")
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what} must be {n} number(s), got {_brief(v)}", where) from None
    if a.shape != (n,) or not np.all(np.isfinite(a)) or np.any(a < low) or np.any(a > high):
        raise InputError(f"{what} must be {n} finite number(s) in [{low:g}, {high:g}], got {_brief(v)}", where)
    return a


def _matrix(v, shape: tuple[int, int], where, what: str, bound: float = MAX_LENGTH) -> np.ndarray:
    # the rows' lengths first: np.asarray would convert a padded row of millions of items
    if isinstance(v, (list, tuple)) and not (len(v) == shape[0] and all(
            isinstance(r, (list, tuple)) and len(r) == shape[1] for r in v)):
        raise InputError(f"{what} must be a finite {shape[0]}x{shape[1]} matrix, got {_brief(v)}", where)
    try:
        if isinstance(v, (str, bytes)):
            raise ValueError("text")
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what} must be a {shape[0]}x{shape[1]} matrix of numbers, got {_brief(v)}", where) from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(f"{what} must be a finite {shape[0]}x{shape[1]} matrix, got shape {a.shape}"
                         + ("" if a.shape != shape else " with NaN or infinite values"), where)
    if np.any(np.abs(a) > bound):
        raise InputError(f"{what} has a value beyond +-{bound:g}", where)
    return a


def _pose(v, where, what: str) -> np.ndarray:
    """A rigid 4x4 transform (rotation + translation within MAX_LENGTH): exporters turn it into a
    quaternion, which would silently drop any scale or shear."""
    T = _matrix(v, (4, 4), where, what)
    R = T[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or np.linalg.det(R) <= 0
            or np.abs(T[3] - [0, 0, 0, 1]).max() > RIGID_TOL):
        raise InputError(f"{what} must be a rigid transform (rotation, translation, last row 0 0 0 1)", where)
    return T
