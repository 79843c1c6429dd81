"""Judging a pick-and-place step, as in the paper: grasped and lifted, placed in the goal at rest, no collisions.

The geometric tests are plain functions of poses and extents or collision meshes (`footprint.Shape`; twin
frame, metres, radians) so they can be checked on hand-made cases; `judge_grasp` / `judge_place` read them off
the simulated world (and its contacts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from splattwin.robot import footprint as fp
from splattwin.robot.monitor import ContactKind, MonitorState
from splattwin.robot.task import Region, Step

LIFT_FRACTION = 0.6          # grasped: the object rose at least this fraction of the commanded lift
REST_SPEED = 0.01            # m/s: at rest below this linear speed
TILT_MAX = math.radians(10)  # at rest: upright within this tilt
HEIGHT_TOL = 0.015           # m: resting on its support within this height error


def criteria(lift_m: float, settle_s: float) -> dict:
    """The success criteria of a step as results.json records them (`criteria`): the thresholds (SI units)
    and what each means. lift_m: the commanded lift after closing (m); settle_s: the wait after the
    retreat before the placement is judged (s)."""
    return {
        "lift_fraction": LIFT_FRACTION, "lift_m": lift_m, "rest_speed_m_s": REST_SPEED,
        "tilt_max_deg": round(math.degrees(TILT_MAX), 6), "height_tol_m": HEIGHT_TOL, "settle_s": settle_s,
        "definition": (
            "a step succeeds when: grasped (the object rose at least lift_fraction of the lift_m lift and both "
            "fingers touch it); placed (place_on, on the collision meshes: its centre over the support's "
            "footprint, its bottom within height_tol_m of the support's top under its footprint, and a contact "
            "between the two in the simulation; place_in: "
            "all 4 corners of its bounding-box footprint inside the region and its bottom within height_tol_m "
            "of the table); at rest settle_s after the retreat (slower "
            "than rest_speed_m_s and tilted less than tilt_max_deg from upright); no collision (the robot "
            "touched nothing but the object, and the carried object nothing but the hand, during the step). "
            "Each step is judged when it ends, and at the end of the task each placed object that no later step "
            "picks is judged again (a later place may have pushed or tipped it); the task succeeds when every "
            "step does"),
    }


@dataclass(frozen=True)
class Placement:
    """Verdict on where a released object ended: inside the goal and on it (placed), still and upright
    (at_rest); speed m/s, tilt rad from upright."""

    placed: bool
    at_rest: bool
    speed: float
    tilt: float
    why: str = ""   # what is wrong, in words ("" when placed and at rest)


def tilt_of(T_world_obj: np.ndarray) -> float:
    """rad between the object's z axis and the world's +z."""
    return math.acos(float(np.clip(np.asarray(T_world_obj)[2, 2], -1, 1)))


def at_rest(speed: float, T_world_obj: np.ndarray) -> bool:
    return bool(speed < REST_SPEED and tilt_of(T_world_obj) < TILT_MAX)


def _on_check(T_world_obj: np.ndarray, shape: fp.Shape, T_world_support: np.ndarray,
              support_shape: fp.Shape) -> tuple[float, float | None]:
    """(beyond, dz) of the object at T_world_obj on the support at T_world_support, from their Shapes
    (collision meshes, else bounding boxes): beyond, the horizontal distance (m) from the object's centre to
    the support's footprint (0 over it); dz, the height (m) of the object's bottom above the support's top
    under the object's footprint (`footprint.Posed.top_under`: where an object lowered onto it rests, as
    `selection.release_height` releases it), < 0 below it; None when no part of the support lies under it."""
    obj = fp.Posed(shape, T_world_obj)
    sup = fp.Posed(support_shape, T_world_support)
    beyond = sup.distance(np.asarray(T_world_obj)[:2, 3])
    top = sup.top_under(obj.polygons)
    return beyond, None if top is None else obj.bottom() - top


def placed_on(T_world_obj: np.ndarray, shape: fp.Shape, T_world_support: np.ndarray,
              support_shape: fp.Shape) -> bool:
    """The object rests on the support, judged on their collision meshes (`footprint.Shape`: convex parts,
    else the bounding box): its centre lies over the support's footprint (exactly, within footprint.EPS, as
    the bounding-box test was: an object whose centre overhangs the support is not on it) and its bottom
    (its mesh's lowest point) is within HEIGHT_TOL of the highest point of the support's mesh under its
    footprint. So an object on a 2 cm tray with a 10 cm corner post is on it (the bounding-box top was 8 cm
    higher), and one on the table in the free notch of an L-shaped support is not (its centre is over the
    L's bounding box, but over none of its parts). T_world_*: [4, 4], twin frame, m."""
    beyond, dz = _on_check(T_world_obj, shape, T_world_support, support_shape)
    return bool(beyond == 0.0 and dz is not None and abs(dz) < HEIGHT_TOL)


def placed_in(T_world_obj: np.ndarray, extent: np.ndarray, region: Region, table_height: float) -> bool:
    """Every bounding-box corner of the object's footprint lies inside the region, resting on the table."""
    T, ext = np.asarray(T_world_obj), np.asarray(extent, float)
    corners = np.array([[sx * ext[0] / 2, sy * ext[1] / 2, 0, 1] for sx in (-1, 1) for sy in (-1, 1)])
    xy = (T @ corners.T).T[:, :2]
    inside = all(region.contains_xy(c) for c in xy)
    on_table = abs(T[2, 3] - ext[2] / 2 - table_height) < HEIGHT_TOL
    return bool(inside and on_table)


def is_held(world, obj: str) -> bool:
    """Both fingers touch the object now."""
    fingers = world.finger_bodies
    touched = world.contacts().partners(world.object_body(obj))
    return len(fingers & touched) >= min(2, len(fingers))


def judge_grasp(lifted_m: float, lift_m: float, held: bool) -> bool:
    """Grasped: the object rose with the hand (at least LIFT_FRACTION of the lift, m) and both fingers hold it."""
    return bool(lifted_m > LIFT_FRACTION * lift_m and held)


def touches(world, obj: str, support: str) -> bool:
    """The simulation has a contact between `obj` and `support` now (within the contact margin)."""
    return world.object_body(support) in world.contacts().partners(world.object_body(obj))


def judge_place(world, step: Step, obj: str, shapes: fp.Shapes | None = None) -> Placement:
    """Where the released object `obj` ended, against the step's goal (an object to stand on or a region).
    shapes: the objects' Shapes (`footprint.Shapes`, read once by the caller); None: read from the world's
    twin folder now.

    On an object, placed means both where (`placed_on`, on the collision meshes) and touching it (a MuJoCo
    contact between the two, `touches`); neither alone is enough. Settled in MuJoCo on the small
    ground-truth twin: a box on a 1 cm slab lying on the support is at the height of resting on it within
    HEIGHT_TOL, but does not touch it (no contact between the two: the geometry alone said placed). A contact
    alone does not say where the object is: any touch counts, from the side too (an object on the table
    leaning on the support), which the geometry rejects; so contacts decide only together with it. Where
    both were tried (a box on a tray with a corner post, a cube on an L's arm or on the table in its notch,
    the three steps of the default task, 3 perturbed trials) they agree."""
    T = world.object_pose(obj)
    ext = np.asarray(world.manifest.object(obj).bbox_extent, float)
    speed = world.object_speed(obj)
    if step.place_on is not None:
        shapes = shapes or fp.Shapes(world.manifest, world.twin_dir)
        sup = step.place_on
        T_sup = world.object_pose(sup)
        over = placed_on(T, shapes(obj), T_sup, shapes(sup))
        touching = touches(world, obj, sup)
        placed = over and touching
        miss = ("" if placed else miss_on(T, shapes(obj), T_sup, shapes(sup), sup) if not over else
                f"not on {sup!r}: it does not touch it (it rests on something else at that height)")
    else:
        h = world.manifest.background.table_height
        placed = placed_in(T, ext, step.place_in, h)
        miss = "" if placed else miss_in(T, ext, step.place_in, h)
    rest = at_rest(speed, T)
    return Placement(placed=placed, at_rest=rest, speed=speed, tilt=tilt_of(T),
                     why=place_failure(obj, step, placed, rest, speed, tilt_of(T), miss))


def miss_on(T_world_obj: np.ndarray, shape: fp.Shape, T_world_support: np.ndarray, support_shape: fp.Shape,
            support: str) -> str:
    """Why `placed_on` is False, in words: how far the object's centre lies beyond the support's footprint
    and how far its bottom is from the support's top under it (cm)."""
    beyond, dz = _on_check(T_world_obj, shape, T_world_support, support_shape)
    parts = []
    if beyond > 0:
        parts.append(f"its centre lies {beyond * 100:.1f} cm beyond the top of {support!r}")   # not 'box''s
    if dz is None:
        parts.append(f"no part of {support!r} lies under it")
    elif abs(dz) >= HEIGHT_TOL:
        parts.append(f"its bottom is {abs(dz) * 100:.1f} cm {'above' if dz > 0 else 'below'} the top of "
                     f"{support!r} under it")
    return f"not on {support!r}: " + (", ".join(parts) or "off its top")


def miss_in(T_world_obj: np.ndarray, extent: np.ndarray, region: Region, table_height: float) -> str:
    """Why `placed_in` is False, in words: footprint corners outside the region, height off the table (cm)."""
    T, ext = np.asarray(T_world_obj), np.asarray(extent, float)
    corners = np.array([[sx * ext[0] / 2, sy * ext[1] / 2, 0, 1] for sx in (-1, 1) for sy in (-1, 1)])
    out = sum(not region.contains_xy(c) for c in (T @ corners.T).T[:, :2])
    dz = float(T[2, 3] - ext[2] / 2 - table_height)
    parts = []
    if out:
        parts.append(f"{out} of its 4 footprint corners lie outside")
    if abs(dz) >= HEIGHT_TOL:
        parts.append(f"it rests {abs(dz) * 100:.1f} cm {'above' if dz > 0 else 'below'} the table")
    return f"not inside the region {region.name!r}: " + (", ".join(parts) or "outside it")


def place_failure(obj: str, step: Step, placed: bool, rest: bool, speed: float, tilt: float, miss: str) -> str:
    """A failed placement in words ("" when placed and at rest): tipped over, still moving, or where it
    missed the goal. A tipped object on another object gets the usual cause in a twin: an uneven top."""
    if placed and rest:
        return ""
    parts = []
    if tilt >= TILT_MAX:
        parts.append(f"{obj!r} tipped over: it ended tilted {math.degrees(tilt):.0f} deg "
                     f"(upright means within {math.degrees(TILT_MAX):.0f} deg)")
    elif speed >= REST_SPEED:
        parts.append(f"{obj!r} was still moving at {speed * 100:.1f} cm/s")
    if not placed:
        parts.append(miss if parts else f"{obj!r} {miss}")
    text = "; ".join(parts)
    if tilt >= TILT_MAX and step.place_on is not None:
        text += (f" (an uneven top of {step.place_on!r} in the twin, e.g. after a short training, tips what is "
                 "released on it: see its collision mesh in the report)")
    return text


@dataclass(frozen=True)
class Collisions:
    """Collision counts of a step by kind and the pairs as 'kind: body - body' text (sorted)."""

    robot: int
    object: int
    pairs: list[str]


def collisions(monitor: MonitorState, body_name) -> Collisions:
    return Collisions(robot=monitor.count(ContactKind.ROBOT), object=monitor.count(ContactKind.OBJECT),
                      pairs=sorted({e.describe(body_name) for e in monitor.events}))
