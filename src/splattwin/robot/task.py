"""Pick-and-place task files (YAML) and their validation against a twin, before any planning.

Format: a list of steps (or a mapping with `steps:` and an optional `name:`). A `pick` is followed by a
place, either in the same item or the next one:

    - pick: blue_box
    - place_on: cardboard_box             # on top of another object (goal: its top face)
    - pick: toy_hammer
    - place_in: {center: [0.05, 0.03, 0.0], size: 0.24}    # square region on the table (m, twin frame)
    - place_in: target_frame              # the named region from the twin (config.target_frame)

A region's size is one side (square) or [sx, sy], metres, finite and > 0, each side at most the table's
(its extent in twin.json); its centre must be on the table.

A step names an object by its name in twin.json (`blue box`) or by its export ID, the name every export
file carries (`blue_box`; `resolve_names` maps it to the name). Validation raises InputError naming the
task file for: unknown or unusable objects (an obstacle-only one too: the arm avoids its box), a place without a
pick, an unscaled twin, a goal off the table, a region larger than the table, or out of the robot's reach. Reach is checked in two stages:
the horizontal distance from the base (cheap, [REACH_MIN, REACH_MAX]) and, given the robot, inverse
kinematics (mink) of a grasp pose at the object and of the place pose and the pre-place pose above it
(top-down at 8 yaws, or a horizontal approach pointing away from the base).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.transforms import make_pose, rot_z
from splattwin.twin.manifest import Manifest
from splattwin.twin.mjcf import check_scaled

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


def _region(v, where: Path, manifest: Manifest | None) -> Region:
    if isinstance(v, str):
        cfg = (manifest.config.get(v) if manifest is not None else None) or None
        if not isinstance(cfg, dict):
            hint = ("; the twin stage copies a generated scene's goal there, and a twin made with build_twin gets it "
                    "from splattwin.twin.add_scene_goal(twin_dir, scene_dir)" if v == "target_frame" else "")
            raise InputError(f"place_in: the twin defines no region named {v!r} (its twin.json config has no {v!r})"
                             f"{hint}", where)
        v, name = cfg, v
    else:
        name = "region"
    if not isinstance(v, dict) or "center" not in v or "size" not in v:
        raise InputError("place_in needs {center: [x, y, z], size: s or [sx, sy]} (metres) or a region name", where)
    try:
        c = np.asarray(v["center"], dtype=float).reshape(-1)
        s = np.asarray(v["size"], dtype=float).reshape(-1)
    except (TypeError, ValueError) as e:
        raise InputError(f"place_in: bad numbers: {e}", where) from e
    if len(c) == 2:
        c = np.array([c[0], c[1], 0.0])
    # finite size too: an infinite region contains every position, so any place would be judged a success
    if (len(c) != 3 or len(s) not in (1, 2) or not np.all(np.isfinite(c)) or not np.all(np.isfinite(s))
            or np.any(s <= 0)):
        raise InputError(f"place_in: center must be [x, y(, z)] and size finite and > 0, got {v}", where)
    return Region(center=c, size=np.broadcast_to(s, (2,)).astype(float).copy(), name=name)


def parse_task(data, where: Path, manifest: Manifest | None = None) -> Task:
    """A `Task` from plain data: a list of steps `[{pick: a, place_on: b}, {pick: c, place_in: region}]`, or
    `{name, steps: [...]}` (YAML as `load_task` reads it); a region is {center, size} in the twin frame (m) or
    the name of one in the manifest's config (e.g. "target_frame"). `where` names the source in errors
    (InputError)."""
    name = "task"
    if isinstance(data, dict):
        name = str(data.get("name", name))
        data = data.get("steps")
    if not isinstance(data, list) or not data:
        raise InputError("a task is a non-empty list of steps (pick / place_on / place_in)", where)
    steps: list[Step] = []
    pending: str | None = None
    for k, item in enumerate(data):
        if not isinstance(item, dict) or not item:
            raise InputError(f"step {k + 1}: expected a mapping like 'pick: blue_box', got {item!r}", where)
        unknown = set(item) - {"pick", "place_on", "place_in"}
        if unknown:
            raise InputError(f"step {k + 1}: unknown key(s) {sorted(unknown)} (use pick, place_on, place_in)", where)
        if "pick" in item:
            if pending is not None:
                raise InputError(f"step {k + 1}: pick of {item['pick']!r} while still holding {pending!r}", where)
            pending = str(item["pick"])
        if "place_on" in item or "place_in" in item:
            if pending is None:
                raise InputError(f"step {k + 1}: place without a pick before it", where)
            if "place_on" in item and "place_in" in item:
                raise InputError(f"step {k + 1}: give either place_on or place_in, not both", where)
            if "place_on" in item:
                steps.append(Step(pending, place_on=str(item["place_on"])))
            else:
                steps.append(Step(pending, place_in=_region(item["place_in"], where, manifest)))
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
    return parse_task(data, path, manifest)


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
        raise InputError(f"step {k}: {role} names {n!r}, which is not in the twin (objects: "
                         f"{', '.join(sorted(names))}; a step may name an object or its export ID){hint}", where)

    for k, s in enumerate(task.steps, start=1):
        s.pick = human(s.pick, k, "pick")
        if s.place_on is not None:
            s.place_on = human(s.place_on, k, "place_on")


def validate_task(task: Task, manifest: Manifest, twin_dir: str | Path, T_world_base: np.ndarray,
                  robot=None) -> None:
    """Everything that can be checked without planning; raises InputError naming the task file.

    robot: a `RobotModel`; when given, the pick and place poses must also have IK solutions (mink)."""
    where = task.path or Path(twin_dir) / "twin.json"
    check_scaled(manifest, Path(twin_dir) / "twin.json")
    names = {o.name: o for o in manifest.objects}
    base_xy = np.asarray(T_world_base)[:2, 3]
    x0, x1, y0, y1 = manifest.background.table_extent

    def reach(xy, what: str) -> None:
        if not np.all(np.isfinite(np.asarray(xy, dtype=float)[:2])):
            raise InputError(f"{what}: its position is not finite (NaN or infinite pose in the twin)", where)
        d = float(np.linalg.norm(np.asarray(xy)[:2] - base_xy))
        if not REACH_MIN <= d <= REACH_MAX:
            raise InputError(f"{what} is {d:.2f} m from the robot base, outside its reach "
                             f"[{REACH_MIN:.2f}, {REACH_MAX:.2f}] m (move the base with --base-pose)", where)

    resolve_names(task, manifest, where)
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
        reach(names[s.pick].pose[:3, 3], f"step {k}: object {s.pick!r}")
        if s.place_in is not None:
            c = s.place_in.center
            if not (x0 <= c[0] <= x1 and y0 <= c[1] <= y1):
                raise InputError(f"step {k}: goal region centre {np.round(c, 3).tolist()} is off the table "
                                 f"(extent {manifest.background.table_extent})", where)
            # a region wider than the table is no goal: every place on the table would be inside it
            sx, sy = s.place_in.size
            if sx > x1 - x0 or sy > y1 - y0:
                raise InputError(f"step {k}: goal region {s.place_in.name!r} of size "
                                 f"{np.round(s.place_in.size, 3).tolist()} m is larger than the table "
                                 f"({x1 - x0:.3f} x {y1 - y0:.3f} m, extent {manifest.background.table_extent})",
                                 where)
            reach(c, f"step {k}: goal region {s.place_in.name!r}")
        elif s.place_on is not None:
            reach(names[s.place_on].pose[:3, 3], f"step {k}: goal object {s.place_on!r}")
    if not all(math.isfinite(v) for v in np.asarray(T_world_base).ravel()):
        raise InputError("robot base pose is not finite", where)
    if robot is not None:
        _check_ik(task, manifest, names, np.asarray(T_world_base), robot, where)


def _grip_point(top_z: float, height: float, xy: np.ndarray) -> np.ndarray:
    """World TCP position (m) of a top grasp of an object whose top is at top_z."""
    return np.array([xy[0], xy[1], top_z - min(GRIP_BELOW_TOP, height / 2)])


def _check_ik(task: Task, manifest: Manifest, names: dict, T_world_base: np.ndarray, robot, where: Path) -> None:
    """IK (mink) of each step's grasp pose at the object and of its place and pre-place poses."""
    from splattwin.robot.ik import ArmIK

    ik = ArmIK(robot, T_world_base)
    base_xy = T_world_base[:2, 3]
    table_z = float(manifest.background.table_height)

    def top(name: str) -> float:
        o = names[name]
        return float(o.pose[2, 3] + abs(o.pose[2, 2]) * np.asarray(o.bbox_extent, float)[2] / 2)

    for k, s in enumerate(task.steps, start=1):
        obj = names[s.pick]
        h = float(np.asarray(obj.bbox_extent, float)[2])
        p = _grip_point(top(s.pick), h, obj.pose[:2, 3])
        if not reachable(ik, p, base_xy):
            raise InputError(f"step {k}: object {s.pick!r} at {np.round(p, 3).tolist()} is out of the robot's "
                             f"reach: no IK solution for a grasp pose there (top-down at 8 yaws or from the "
                             f"side; base at {np.round(T_world_base[:3, 3], 3).tolist()}; move it with "
                             f"--base-pose)", where)
        if s.place_on is not None:
            goal, xy, z = f"goal object {s.place_on!r}", names[s.place_on].pose[:2, 3], top(s.place_on)
        else:
            goal, xy, z = f"goal region {s.place_in.name!r}", s.place_in.center[:2], table_z
        p = _grip_point(z + h, h, xy)
        if not reachable(ik, p, base_xy, rise=PRE_PLACE_RISE):
            raise InputError(f"step {k}: {goal}: the place pose of {s.pick!r} at {np.round(p, 3).tolist()} is "
                             f"out of the robot's reach: no IK solution for it and the pre-place pose "
                             f"{PRE_PLACE_RISE:.2f} m above (top-down at 8 yaws or from the side; base at "
                             f"{np.round(T_world_base[:3, 3], 3).tolist()}; move it with --base-pose)", where)
