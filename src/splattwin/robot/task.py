"""Pick-and-place task files (YAML) and their validation against a twin, before any planning.

Format: a list of steps (or a mapping with `steps:` and an optional `name:`). A `pick` is followed by a
place, either in the same item or the next one:

    - pick: blue_box
    - place_on: cardboard_box             # on top of another object (goal: its top face)
    - pick: toy_hammer
    - place_in: {center: [0.05, 0.03, 0.0], size: 0.24}    # square region on the table (m, twin frame)
    - place_in: target_frame              # the named region from the twin (config.target_frame)

A region's size is one side (square) or [sx, sy], metres, finite and > 0, each side at most the table's
(its extent in twin.json); its centre must be on the table, and a centre z, when given, 0 or the table's. An
inline region has no other keys (no yaw: the planner chooses it), nor has a task mapping other than
`name` and `steps`; unknown keys are refused, never ignored.

A step names an object by its name in twin.json (`blue box`) or by its export ID, the name every export
file carries (`blue_box`; `resolve_names` maps it to the name). Validation raises InputError naming the
task file and the step for: unknown or unusable objects (an obstacle-only one too: the arm avoids its
box), a name that is not a string, a place without a pick, an unscaled twin, a goal off the table, a
region larger than the table or too small for the object at any yaw, a goal out of the robot's reach,
and, following the objects through the steps (`TaskScene`), a region centre on another object (on the
footprint of its collision mesh, `robot.footprint`; its bounding box when it has none), a support that
already carries one, or a pick of an object something stands on. Reach is checked in two
stages: the horizontal distance from the base (cheap, [REACH_MIN, REACH_MAX]) and, given the robot,
inverse kinematics (mink) of a grasp pose at the object and of the place pose and the pre-place pose
above it (top-down at 8 yaws, or a horizontal approach pointing away from the base), where the earlier
steps left them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from splattwin import limits
from splattwin.errors import InputError, short_repr
from splattwin.robot import footprint as fp
from splattwin.robot.footprint import Shape, box_shape, object_shape
from splattwin.robot.grasp import MAX_OPENING, too_wide
from splattwin.transforms import make_pose, rot_z
from splattwin.twin.manifest import Manifest
from splattwin.twin.mjcf import check_scaled

REGION_KEYS = {"center", "size"}   # an inline place_in region's keys (a named one from twin.json may carry more)
TASK_KEYS = {"name", "steps"}      # a task given as a mapping
REGION_Z_TOL = 0.02   # m: a region centre's z, when given, is the table's height within this (regions lie on it)
REACH_MAX = 0.80     # m, horizontal distance from the base the Panda reaches top-down with margin
REACH_MIN = 0.20     # m, closer than this the arm folds into itself
GRIP_BELOW_TOP = 0.02   # m: the IK check puts the TCP this far below an object's top (at most half its height)
PRE_PLACE_RISE = 0.10   # m: pre-place pose above the place pose (candidates.LIFT)

log = logging.getLogger(__name__)


@dataclass
class Region:
    """Axis-aligned square/rectangle on a support surface: center [3] (m, twin frame), size [2] (m)."""

    center: np.ndarray
    size: np.ndarray
    name: str = "region"
    z_given: bool = False   # the task gave the centre's z (it must be the table's: `validate_task`)

    def contains_xy(self, xy: np.ndarray, margin: float = 0.0) -> bool:
        d = np.abs(np.asarray(xy)[:2] - self.center[:2])
        return bool(np.all(d <= self.size / 2 - margin))


@dataclass
class Step:
    """pick: object name. Exactly one goal: place_on (object name) or place_in (Region)."""

    pick: str
    place_on: str | None = None
    place_in: Region | None = None

    @property
    def goal_name(self) -> str:
        return self.place_on if self.place_on else (self.place_in.name if self.place_in else "?")


@dataclass
class Task:
    """A pick-and-place task: steps in order, each picks one object and places it on another or in a
    region of the twin frame. Read from YAML by `load_task` (checked against the twin's objects when given
    its manifest) or from plain data by `parse_task`."""

    steps: list[Step]
    name: str = "task"
    path: Path | None = None
    extra: dict = field(default_factory=dict)


def default_task_path() -> Path:
    """The task file shipped with the package (tasks/default.yaml: the embedded scene's pick and place)."""
    return Path(str(resources.files("splattwin.robot") / "tasks" / "default.yaml"))


def _region(v, where: Path, manifest: Manifest | None, k: int = 0) -> Region:
    """The Region a place_in gives (inline, or named in the twin's config); k: the step (1-based) for errors."""
    at = f"step {k}: " if k else ""
    if isinstance(v, str):
        cfg = (manifest.config.get(v) if manifest is not None else None) or None
        if not isinstance(cfg, dict):
            hint = ("; the twin stage copies a generated scene's goal there, and a twin made with build_twin gets it "
                    "from splattwin.twin.add_scene_goal(twin_dir, scene_dir)" if v == "target_frame" else "")
            raise InputError(at + f"place_in: the twin defines no region named {v!r} (its twin.json config has "
                             f"no {v!r}){hint}", where)
        v, name = cfg, v
    else:
        name = "region"
    if not isinstance(v, dict) or "center" not in v or "size" not in v:
        raise InputError(at + "place_in needs {center: [x, y, z], size: s or [sx, sy]} (metres) or a region name",
                         where)
    unknown = sorted(map(str, set(v) - REGION_KEYS)) if name == "region" else []
    if unknown:   # e.g. `yaw: 90`: ignored, the run would succeed without what the user asked for
        raise InputError(at + f"place_in: unknown key(s) {unknown}: a region is {{center: [x, y(, z)], size: s or "
                         f"[sx, sy]}} (metres, twin frame); the object's yaw in it is the planner's choice", where)
    try:
        c = np.asarray(v["center"], dtype=float).reshape(-1)
        s = np.asarray(v["size"], dtype=float).reshape(-1)
    except (TypeError, ValueError, OverflowError) as e:   # OverflowError: a YAML integer past float range (1e309)
        raise InputError(at + f"place_in: bad numbers: {e}", where) from e
    z_given = len(c) == 3
    if len(c) == 2:
        c = np.array([c[0], c[1], 0.0])
    # finite size too: an infinite region contains every position, so any place would be judged a success
    if (len(c) != 3 or len(s) not in (1, 2) or not np.all(np.isfinite(c)) or not np.all(np.isfinite(s))
            or np.any(s <= 0)):
        raise InputError(at + f"place_in: center must be [x, y(, z)] and size finite and > 0, got {v}", where)
    return Region(center=c, size=np.broadcast_to(s, (2,)).astype(float).copy(), name=name, z_given=z_given)


def parse_task(data, where: Path | None = None, manifest: Manifest | None = None) -> Task:
    """A `Task` from plain data: a list of steps `[{pick: a, place_on: b}, {pick: c, place_in: region}]`, or
    `{name, steps: [...]}` (YAML as `load_task` reads it); a region is {center, size} in the twin frame (m) or
    the name of one in the manifest's config (e.g. "target_frame"). `where` names the source in errors
    (InputError); None: data made in Python, the errors name the step alone."""
    name = "task"
    if isinstance(data, dict):
        unknown = sorted(map(str, set(data) - TASK_KEYS))
        if unknown:   # `step:` for `steps:` would read as no steps, `nmae:` be dropped
            raise InputError(f"unknown top-level key(s) {unknown}: a task is a list of steps, or a mapping with "
                             f"'steps:' (that list) and an optional 'name:'", where)
        name = str(data.get("name", name))
        data = data.get("steps")
    if not isinstance(data, list) or not data:
        raise InputError("a task is a non-empty list of steps (pick / place_on / place_in)", where)
    steps: list[Step] = []
    pending: str | None = None
    for item in data:
        n = len(steps) + 1   # the step (a pick and its place) this item belongs to, as results.json counts
        if not isinstance(item, dict) or not item:
            raise InputError(f"step {n}: expected a mapping like 'pick: blue_box', got {item!r}", where)
        unknown = set(item) - {"pick", "place_on", "place_in"}
        if unknown:
            # keys as text: YAML keys may be of mixed types ({1: a, ~: b}) that sorted() cannot compare
            raise InputError(f"step {n}: unknown key(s) {sorted(map(str, unknown))} (use pick, place_on, place_in)",
                             where)
        for key in ("pick", "place_on"):
            if key in item and not isinstance(item[key], str):   # `pick:` (null), `pick: yes` (a bool), a list
                got = "nothing" if item[key] is None else f"{type(item[key]).__name__} {short_repr(item[key], 80)}"
                raise InputError(f"step {n}: {key} needs an object name, got {got} (quote a name that YAML "
                                 f"reads as another type: {key}: '123')", where)
        if "pick" in item:
            if pending is not None:
                raise InputError(f"step {n}: pick of {item['pick']!r} while still holding {pending!r}", where)
            pending = item["pick"]
        if "place_on" in item or "place_in" in item:
            if n > limits.MAX_TASK_STEPS:
                raise InputError(f"the task has more than {limits.MAX_TASK_STEPS} steps (set "
                                 f"SPLATTWIN_MAX_TASK_STEPS to allow more)", where)
            if pending is None:
                raise InputError(f"step {n}: place without a pick before it", where)
            if "place_on" in item and "place_in" in item:
                raise InputError(f"step {n}: give either place_on or place_in, not both", where)
            if "place_on" in item:
                steps.append(Step(pending, place_on=item["place_on"]))
            else:
                steps.append(Step(pending, place_in=_region(item["place_in"], where, manifest, n)))
            pending = None
    if pending is not None:
        raise InputError(f"the task ends while holding {pending!r}: add place_on / place_in", where)
    return Task(steps=steps, name=name, path=where)


def load_task(path: str | Path | None, manifest: Manifest | None = None) -> Task:
    """Load a task YAML (default: the paper's three-step task)."""
    from splattwin.limits import load_yaml

    path = Path(path) if path is not None else default_task_path()
    if not path.is_file():
        raise InputError("task file not found", path)
    data = load_yaml(path)  # safe loader, bounded size and aliases (a task is often received)
    if manifest is not None and path.resolve() == default_task_path().resolve():
        _check_default_task_fits(data, path, manifest)
    return parse_task(data, path, manifest)


def _check_default_task_fits(data, where: Path, manifest: Manifest) -> None:
    """InputError when the twin lacks the objects or the region the default task (the embedded scene's) names.
    `plan` on a user's own twin (without --task, or --task default) said "step 3: place_in: the twin defines no
    region named 'target_frame' ... splattwin.twin.add_scene_goal(twin_dir, scene_dir)": nothing told the
    user that the default task is the demo scene's, nor to write their own."""
    from splattwin.names import export_id

    ids = {export_id(o.name) for o in manifest.objects}
    steps = data.get("steps", []) if isinstance(data, dict) else data
    names = [v for item in steps if isinstance(item, dict) for k, v in item.items()
             if k in ("pick", "place_on") and isinstance(v, str)]
    regions = [v for item in steps if isinstance(item, dict) for k, v in item.items()
               if k == "place_in" and isinstance(v, str)]
    missing = sorted({n for n in names if export_id(n) not in ids}
                     | {r for r in regions if not isinstance(manifest.config.get(r), dict)})
    if missing:
        have = ", ".join(sorted(o.name for o in manifest.objects)) or "none"
        # the demo scene's twin made in Python (build_twin) lacks only the scene's goal region
        goal_hint = ("; a twin of the embedded scene made with build_twin gets its goal region from "
                     "splattwin.twin.add_scene_goal(twin_dir, scene_dir)" if "target_frame" in missing else "")
        raise InputError(f"the default task is the embedded demo scene's rearrangement, and this twin lacks what "
                         f"it names: {', '.join(missing)} (this twin's objects: {have}); write a task for your "
                         f"objects (README, 'Writing a task': pick / place_on / place_in: {{center: [x, y], "
                         f"size: s}}) and give it with --task FILE{goal_hint}", where)


def _tcp_poses(xyz: np.ndarray, base_xy: np.ndarray) -> list[np.ndarray]:
    """Candidate T_world_tcp [4,4] at xyz: top-down (TCP z = -world z) at 8 yaws, then a horizontal
    approach pointing away from the base (TCP z radial, closing axis horizontal)."""
    out = []
    flip = np.diag([1.0, -1.0, -1.0])
    for k in range(8):
        out.append(make_pose(rot_z(k * math.pi / 4) @ flip, xyz))
    radial = np.append(np.asarray(xyz)[:2] - base_xy, 0.0)
    if np.linalg.norm(radial) > 1e-6:
        z = radial / np.linalg.norm(radial)
        y = np.cross([0.0, 0.0, 1.0], z)
        out.append(make_pose(np.column_stack([np.cross(y, z), y, z]), xyz))
    return out


def reachable(ik, xyz: np.ndarray, base_xy: np.ndarray, rise: float = 0.0) -> bool:
    """True if some TCP pose of `_tcp_poses(xyz)` has an IK solution (mink, from the robot's home), and
    with rise > 0 the same orientation also `rise` m above it (the pre-place pose)."""
    home = ik.robot.home
    for T in _tcp_poses(np.asarray(xyz, float), base_xy):
        q = ik.solve(T, home, q_posture=home)
        if q is None:
            continue
        if rise <= 0:
            return True
        T_up = T.copy()
        T_up[2, 3] += rise
        if ik.solve(T_up, q, q_posture=home) is not None:
            return True
    return False


def resolve_names(task: Task, manifest: Manifest, where: Path | None = None) -> None:
    """Each step's object names as the twin's human names, in place: a step may also name an object by
    its export ID (`splattwin.names.export_id`, the only name MJCF / URDF / MoveIt / glTF files carry:
    `blue_box` for `blue box`) when exactly one object has that ID. A name that is neither is an
    InputError listing the objects, with a "did you mean" when it matches an export ID ignoring case."""
    from splattwin.names import export_id

    where = where or task.path
    names = {o.name for o in manifest.objects}
    by_id: dict[str, list[str]] = {}
    for o in manifest.objects:
        by_id.setdefault(export_id(o.name), []).append(o.name)

    def human(n: str, k: int, role: str) -> str:
        if n in names:
            return n
        hit = by_id.get(n, [])
        if len(hit) == 1:
            log.info("step %d: %s %r is the export ID of object %r", k, role, n, hit[0])
            return hit[0]
        near = sorted(m for i, ms in by_id.items() if i.lower() == export_id(n).lower() for m in ms)
        hint = "; did you mean " + " or ".join(f"{m!r} (export ID {export_id(m)})" for m in near) if near else ""
        if not near and export_id(n).lower() == "table":   # the table is no object: a region on it is the goal
            hint = "; to put an object on the table, give a region there: place_in: {center: [x, y], size: s}"
        raise InputError(f"step {k}: {role} names {n!r}, which is not in the twin (objects: "
                         f"{', '.join(sorted(names))}; a step may name an object or its export ID){hint}", where)

    for k, s in enumerate(task.steps, start=1):
        s.pick = human(s.pick, k, "pick")
        if s.place_on is not None:
            s.place_on = human(s.place_on, k, "place_on")


def validate_task(task: Task, manifest: Manifest, twin_dir: str | Path, T_world_base: np.ndarray,
                  robot=None, warn: bool = True) -> None:
    """Everything that can be checked without planning; raises InputError naming the task file.

    The steps are followed through the scene as the planner will believe it (`TaskScene`): an object an
    earlier step placed is checked where it was placed (reach, IK, what stands on what), not at its twin
    pose. Refused, since the step could never succeed: picking an object another one stands on (the
    carried object would touch it), placing on an object that already carries another, a goal region
    whose centre (where the object is placed) lies on another object's footprint (its collision mesh's
    convex parts seen from above, read from twin_dir; its bounding box without a mesh), a region the object
    fits in at no yaw, a region centre z off the table, an object too wide for the gripper to close on
    (`footprint.narrowest_width` against the robot's opening, the Panda's without a robot).

    robot: a `RobotModel`; when given, the pick and place poses must also have IK solutions (mink).
    warn: log the warnings (a goal that may be crowded); False for the trials, which repeat the nominal run's."""
    where = task.path or Path(twin_dir) / "twin.json"
    check_scaled(manifest, Path(twin_dir) / "twin.json")
    names = {o.name: o for o in manifest.objects}
    base_xy = np.asarray(T_world_base)[:2, 3]
    x0, x1, y0, y1 = manifest.background.table_extent
    table_z = float(manifest.background.table_height)

    def reach(xy, what: str) -> None:
        if not np.all(np.isfinite(np.asarray(xy, dtype=float)[:2])):
            raise InputError(f"{what}: its position is not finite (NaN or infinite pose in the twin)", where)
        d = float(np.linalg.norm(np.asarray(xy)[:2] - base_xy))
        if not REACH_MIN <= d <= REACH_MAX:
            raise InputError(f"{what} is {d:.2f} m from the robot base, outside its reach "
                             f"[{REACH_MIN:.2f}, {REACH_MAX:.2f}] m (move the base with --base-pose)", where)

    resolve_names(task, manifest, where)
    scene = TaskScene.of(manifest, twin_dir)
    states: list[dict[str, np.ndarray]] = []   # the believed poses before each step (for the IK check)
    opening = robot.max_opening if robot is not None else MAX_OPENING
    widths: dict[str, float | None] = {}       # each picked object's narrowest width (m), measured once
    for k, s in enumerate(task.steps, start=1):
        for role, n in (("pick", s.pick), ("place_on", s.place_on)):
            if n is None:
                continue
            if not names[n].usable:
                kept = (": it is kept as a static obstacle box (an estimate of its extent) that the arm avoids, and "
                        "cannot be picked or placed on" if names[n].obstacle_only else "")
                raise InputError(f"step {k}: object {n!r} is not usable ({names[n].problem}){kept}", where)
        if s.place_on == s.pick:
            raise InputError(f"step {k}: cannot place {s.pick!r} on itself", where)
        states.append(dict(scene.poses))
        for o in scene.riders(s.pick):
            raise InputError(f"step {k}: {o!r} stands on {s.pick!r} ({scene.since(o)}): lifted, {s.pick!r} "
                             f"would carry it against itself, a collision that fails the step; pick {o!r} "
                             f"off first", where)
        # an object left out of the scene (a non-finite pose) is checked at its twin pose: reach says why
        reach(scene.poses.get(s.pick, names[s.pick].pose)[:3, 3], f"step {k}: object {s.pick!r}"
              + scene.moved_note(s.pick))
        if s.pick not in widths:   # what planning would find only in physics ("not lifted") or as "no grasp"
            widths[s.pick] = fp.narrowest_width(scene.shapes.get(s.pick) or object_shape(names[s.pick], twin_dir))
        wide = too_wide(s.pick, widths[s.pick], opening)
        if wide is not None:
            raise InputError(f"step {k}: {wide}", where)
        if s.place_in is not None:
            c = s.place_in.center
            if not (x0 <= c[0] <= x1 and y0 <= c[1] <= y1):
                raise InputError(f"step {k}: goal region centre {np.round(c, 3).tolist()} is off the table "
                                 f"(extent {manifest.background.table_extent}){_units_hint(s.place_in)}", where)
            # a region wider than the table is no goal: every place on the table would be inside it
            sx, sy = s.place_in.size
            if sx > x1 - x0 or sy > y1 - y0:
                raise InputError(f"step {k}: goal region {s.place_in.name!r} of size "
                                 f"{np.round(s.place_in.size, 3).tolist()} m is larger than the table "
                                 f"({x1 - x0:.3f} x {y1 - y0:.3f} m, extent {manifest.background.table_extent})"
                                 f"{_units_hint(s.place_in)}", where)
            # z 0 as written in the examples ([x, y, 0.0]) stays accepted on a table a few cm off z = 0
            if s.place_in.z_given and c[2] != 0.0 and abs(c[2] - table_z) > REGION_Z_TOL:
                # the object is placed on the table whatever z says: a shelf height would pass unnoticed
                raise InputError(f"step {k}: goal region centre z = {c[2]:g} m, but a region lies on the table "
                                 f"(z = {table_z:g} m in the twin frame): give center [x, y] (to put "
                                 f"{s.pick!r} on an object, use place_on)", where)
            reach(c, f"step {k}: goal region {s.place_in.name!r}")
            _check_fits(s, k, np.asarray(names[s.pick].bbox_extent, float), where)
            scene.check_free(s, k, where, warn)
        elif s.place_on is not None:
            for o in scene.riders(s.place_on):
                if o != s.pick:
                    raise InputError(f"step {k}: {s.place_on!r} already carries {o!r} ({scene.since(o)}): "
                                     f"place_on puts {s.pick!r} at the centre of its top, where {o!r} stands; "
                                     f"pick {o!r} off first or place {s.pick!r} elsewhere", where)
            reach(scene.poses.get(s.place_on, names[s.place_on].pose)[:3, 3], f"step {k}: goal object {s.place_on!r}"
                  + scene.moved_note(s.place_on))
        scene.place(s, k, table_z)
    if not all(math.isfinite(v) for v in np.asarray(T_world_base).ravel()):
        raise InputError("robot base pose is not finite", where)
    if robot is not None:
        _check_ik(task, manifest, names, states, np.asarray(T_world_base), robot, where, scene)


def _units_hint(region: Region) -> str:
    """A hint for a region's numbers that look like millimetres (10 or more: the task is in metres)."""
    parts = []
    if float(np.max(np.abs(region.center[:2]))) >= 10:
        parts.append(f"center {np.round(region.center[:2] / 1000, 4).tolist()}")
    if float(np.max(region.size)) >= 10:
        parts.append(f"size {np.round(region.size / 1000, 4).tolist()}")
    return f"; the task is in metres: {' and '.join(parts)} if you meant millimetres" if parts else ""


def footprint_fits(extent_xy: np.ndarray, size: np.ndarray, step_deg: float = 0.5) -> bool:
    """True if a rectangle of extent_xy (m) fits inside an axis-aligned one of `size` (m) at some yaw
    (searched every step_deg over a quarter turn: the fit is symmetric in the other quarters)."""
    ex, ey = (float(v) for v in extent_xy[:2])
    for a in np.radians(np.arange(0.0, 90.0 + step_deg / 2, step_deg)):
        c, s = abs(math.cos(a)), abs(math.sin(a))
        if c * ex + s * ey <= size[0] and s * ex + c * ey <= size[1]:
            return True
    return False


def _check_fits(s: Step, k: int, extent: np.ndarray, where: Path) -> None:
    """InputError when the picked object's footprint fits the goal region at no yaw: the judge wants every
    footprint corner inside it (`judge.placed_in`), so the step could never succeed."""
    if not footprint_fits(extent, s.place_in.size):
        raise InputError(f"step {k}: {s.pick!r} (footprint {extent[0]:.3f} x {extent[1]:.3f} m) does not fit in "
                         f"goal region {s.place_in.name!r} ({s.place_in.size[0]:.3f} x {s.place_in.size[1]:.3f} m) "
                         f"at any yaw: a place is judged inside only with all its footprint corners in the region; "
                         f"make the region larger", where)


def _half_height(T: np.ndarray, extent: np.ndarray) -> float:
    """Half the world-z span (m) of a box of `extent` (object frame) posed at T."""
    return float(np.abs(np.asarray(T)[2, :3]) @ np.asarray(extent, float)) / 2


def footprint_distance(xy: np.ndarray, T: np.ndarray, extent: np.ndarray) -> float:
    """Horizontal distance (m) from the point xy to the footprint of a box of `extent` (object frame) posed
    at T (its bounding box cut at the height of its centre); 0 inside."""
    p = np.linalg.inv(T) @ np.array([xy[0], xy[1], T[2, 3], 1.0])
    return float(np.linalg.norm(np.maximum(np.abs(p[:2]) - np.asarray(extent, float)[:2] / 2, 0.0)))


STACK_TOL = 0.02   # m: an object whose bottom is this close to another's top, over it, stands on it


@dataclass
class TaskScene:
    """The scene as a task's steps leave it, as the planner believes it (`selection.place_targets`):
    T_world_obj per object (twin frame, m), what each stands on (None: the table, or nothing known) and
    the step that put it there (0: the twin). shapes: each object's collision mesh (`footprint.Shape`,
    object frame) for its footprint; an object without one is its bounding box (`extents`)."""

    extents: dict[str, np.ndarray]
    poses: dict[str, np.ndarray]
    on: dict[str, str | None]
    placed_in: dict[str, int]
    shapes: dict[str, Shape] = field(default_factory=dict)

    @classmethod
    def of(cls, manifest: Manifest, twin_dir: str | Path | None = None) -> "TaskScene":
        """The twin's scene: objects with a finite pose and geometry in the robot's world (usable ones
        and obstacle-only boxes), their collision meshes read from `twin_dir` (None, and for an object
        without a usable mesh: its bounding box). An object stands on another when its centre is over
        the other's footprint (the union of its convex parts' projections on the table) and its bottom
        within STACK_TOL of the other's top there (the highest part over that point): an object beside a
        thin one, or in the notch of an L-shaped one, is not on it."""
        objs = {o.name: o for o in manifest.objects
                if (o.usable or o.obstacle_only) and np.all(np.isfinite(np.asarray(o.pose, float)))}
        ext = {n: np.asarray(o.bbox_extent, float) for n, o in objs.items()}
        poses = {n: np.asarray(o.pose, float).copy() for n, o in objs.items()}
        shapes = {n: object_shape(o, twin_dir) for n, o in objs.items()}
        posed = {n: fp.Posed(shapes[n], T) for n, T in poses.items()}
        on: dict[str, str | None] = {}
        for n, T in poses.items():
            low = posed[n].bottom()
            gaps = []
            for m in poses:
                top = posed[m].top_at(T[:2, 3]) if m != n else None
                if top is not None and abs(low - top) < STACK_TOL:
                    gaps.append((abs(low - top), m))
            on[n] = min(gaps)[1] if gaps else None
        return cls(ext, poses, on, {n: 0 for n in poses}, shapes)

    def shape(self, obj: str) -> Shape:
        """The object's Shape: its collision mesh, else its bounding box."""
        return self.shapes.get(obj) or box_shape(self.extents[obj])

    def riders(self, obj: str) -> list[str]:
        """The objects standing on `obj` now."""
        return sorted(o for o, s in self.on.items() if s == obj)

    def since(self, obj: str) -> str:
        k = self.placed_in.get(obj, 0)
        return f"placed there in step {k}" if k else "in the twin"

    def moved_note(self, obj: str) -> str:
        k = self.placed_in.get(obj, 0)
        return f" (where step {k} placed it)" if k else ""

    def check_free(self, s: Step, k: int, where: Path, warn: bool = True) -> None:
        """InputError when the goal region's centre, where the object is placed, lies on another object's
        footprint (the union of its convex parts' projections, `footprint`; its bounding box when it has no
        mesh): a certain collision; a warning when the object, whatever its yaw there, reaches into one
        (the disc about its centre that its own footprint covers, `footprint.inradius`, meets the other's
        footprint: their heights may still clear). A goal in the free notch of an L-shaped object is free."""
        c = s.place_in.center[:2]
        r = fp.inradius(self.shape(s.pick))
        for o, T in sorted(self.poses.items()):
            if o == s.pick:
                continue
            d = fp.distance(c, self.shape(o), T)
            if d == 0.0:
                raise InputError(f"step {k}: goal region {s.place_in.name!r} is occupied: its centre "
                                 f"{np.round(c, 3).tolist()}, where {s.pick!r} is placed, lies on {o!r} "
                                 f"({self.since(o)}, at {np.round(T[:2, 3], 3).tolist()}); move the region, or "
                                 f"move {o!r} away in an earlier step", where)
            if d < r and warn:
                log.warning("step %d: %r placed at the centre of goal region %r reaches %.1f cm into the "
                            "footprint of %r at every yaw (%.1f cm from the centre): the place may collide with it",
                            k, s.pick, s.place_in.name, (r - d) * 100, o, d * 100)

    def place(self, s: Step, k: int, table_z: float) -> None:
        """Move the step's object to its goal as the planner places it: upright, its yaw kept, at the
        region's centre on the table or centred on the support, resting on the support's mesh under its
        footprint (`support_top`)."""
        from splattwin.transforms import yaw_of

        if s.pick not in self.poses:
            return
        ext = self.extents[s.pick]
        T = make_pose(rot_z(yaw_of(self.poses[s.pick])), [0.0, 0.0, 0.0])
        if s.place_on is not None and s.place_on in self.poses:
            T[:2, 3] = self.poses[s.place_on][:2, 3]
            z = self.support_top(s.place_on, s.pick, T)
        elif s.place_in is not None:
            T[:2, 3], z = s.place_in.center[:2], table_z
        else:
            return
        T[2, 3] = z + ext[2] / 2
        self.poses[s.pick], self.on[s.pick], self.placed_in[s.pick] = T, s.place_on, k

    def support_top(self, support: str, obj: str, T_obj: np.ndarray, T_support: np.ndarray | None = None) -> float:
        """World z (m) where `obj` at T_obj (its x, y and yaw) rests on `support` at T_support (default: its
        pose now): the highest point of the support's mesh under obj's footprint (as `selection.release_height`
        releases it), the top of the support's bounding box where no mesh lies under it."""
        S = self.poses[support] if T_support is None else np.asarray(T_support, float)
        top = fp.Posed(self.shape(support), S).top_under(fp.polygons(self.shape(obj), T_obj))
        return float(S[2, 3] + _half_height(S, self.extents[support])) if top is None else top


def _grip_point(top_z: float, height: float, xy: np.ndarray) -> np.ndarray:
    """World TCP position (m) of a top grasp of an object whose top is at top_z."""
    return np.array([xy[0], xy[1], top_z - min(GRIP_BELOW_TOP, height / 2)])


def _check_ik(task: Task, manifest: Manifest, names: dict, states: list[dict[str, np.ndarray]],
              T_world_base: np.ndarray, robot, where: Path, scene: TaskScene) -> None:
    """IK (mink) of each step's grasp pose at the object and of its place and pre-place poses, with the
    objects where the steps before it left them (`states[k - 1]`: T_world_obj per object); a place on an
    object at the height of its mesh under the placed object's footprint (`TaskScene.support_top`; scene:
    the objects' shapes)."""
    from splattwin.robot.ik import ArmIK
    from splattwin.transforms import yaw_of

    ik = ArmIK(robot, T_world_base)
    base_xy = T_world_base[:2, 3]
    table_z = float(manifest.background.table_height)

    for k, s in enumerate(task.steps, start=1):
        poses = states[k - 1]

        def pose(name: str) -> np.ndarray:
            return poses.get(name, names[name].pose)

        def top(name: str) -> float:
            return float(pose(name)[2, 3] + _half_height(pose(name), names[name].bbox_extent))

        h = float(np.asarray(names[s.pick].bbox_extent, float)[2])
        p = _grip_point(top(s.pick), h, pose(s.pick)[:2, 3])
        if not reachable(ik, p, base_xy):
            raise InputError(f"step {k}: object {s.pick!r} at {np.round(p, 3).tolist()} is out of the robot's "
                             f"reach: no IK solution for a grasp pose there (top-down at 8 yaws or from the "
                             f"side; base at {np.round(T_world_base[:3, 3], 3).tolist()}; move it with "
                             f"--base-pose)", where)
        if s.place_on is not None and s.place_on in scene.poses and s.pick in scene.poses:
            T = make_pose(rot_z(yaw_of(pose(s.pick))), pose(s.place_on)[:3, 3])   # upright, its yaw kept (place)
            goal, xy = f"goal object {s.place_on!r}", T[:2, 3]
            z = scene.support_top(s.place_on, s.pick, T, pose(s.place_on))
        elif s.place_on is not None:
            goal, xy, z = f"goal object {s.place_on!r}", pose(s.place_on)[:2, 3], top(s.place_on)
        else:
            goal, xy, z = f"goal region {s.place_in.name!r}", s.place_in.center[:2], table_z
        p = _grip_point(z + h, h, xy)
        if not reachable(ik, p, base_xy, rise=PRE_PLACE_RISE):
            raise InputError(f"step {k}: {goal}: the place pose of {s.pick!r} at {np.round(p, 3).tolist()} is "
                             f"out of the robot's reach: no IK solution for it and the pre-place pose "
                             f"{PRE_PLACE_RISE:.2f} m above (top-down at 8 yaws or from the side; base at "
                             f"{np.round(T_world_base[:3, 3], 3).tolist()}; move it with --base-pose)", where)
