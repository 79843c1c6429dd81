"""Judging a pick-and-place step, as in the paper: grasped and lifted, placed in the goal at rest, no collisions.

The geometric tests are plain functions of poses and extents (twin frame, metres, radians) so they can
be checked on hand-made cases; `judge_grasp` / `judge_place` read them off the simulated world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
            "fingers touch it); placed (place_on: its centre over the support's top face and its centre within "
            "height_tol_m of resting on it; place_in: all 4 corners of its bounding-box footprint inside the "
            "region and its bottom within height_tol_m of the table); at rest settle_s after the retreat (slower "
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


def placed_on(T_world_obj: np.ndarray, extent: np.ndarray, T_world_support: np.ndarray,
              support_extent: np.ndarray) -> bool:
    """The object's centre lies over the support's top face and at the height of resting on it."""
    ext, sup = np.asarray(extent, float), np.asarray(support_extent, float)
    p = np.linalg.inv(T_world_support) @ np.append(np.asarray(T_world_obj)[:3, 3], 1.0)
    inside = abs(p[0]) <= sup[0] / 2 and abs(p[1]) <= sup[1] / 2
    on_top = abs(p[2] - (sup[2] / 2 + ext[2] / 2)) < HEIGHT_TOL
    return bool(inside and on_top)


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


def judge_place(world, step: Step, obj: str) -> Placement:
    """Where the released object `obj` ended, against the step's goal (an object to stand on or a region)."""
    T = world.object_pose(obj)
    ext = np.asarray(world.manifest.object(obj).bbox_extent, float)
    speed = world.object_speed(obj)
    if step.place_on is not None:
        T_sup = world.object_pose(step.place_on)
        sup = np.asarray(world.manifest.object(step.place_on).bbox_extent, float)
        placed = placed_on(T, ext, T_sup, sup)
        miss = "" if placed else miss_on(T, ext, T_sup, sup, step.place_on)
    else:
        h = world.manifest.background.table_height
        placed = placed_in(T, ext, step.place_in, h)
        miss = "" if placed else miss_in(T, ext, step.place_in, h)
    rest = at_rest(speed, T)
    return Placement(placed=placed, at_rest=rest, speed=speed, tilt=tilt_of(T),
                     why=place_failure(obj, step, placed, rest, speed, tilt_of(T), miss))


def miss_on(T_world_obj: np.ndarray, extent: np.ndarray, T_world_support: np.ndarray, support_extent: np.ndarray,
            support: str) -> str:
    """Why `placed_on` is False, in words: how far the object's centre lies beyond the support's top face
    and how far it is from the height of resting on it (cm)."""
    ext, sup = np.asarray(extent, float), np.asarray(support_extent, float)
    p = np.linalg.inv(T_world_support) @ np.append(np.asarray(T_world_obj)[:3, 3], 1.0)
    beyond = float(np.max(np.maximum(np.abs(p[:2]) - sup[:2] / 2, 0.0)))
    dz = float(p[2] - (sup[2] / 2 + ext[2] / 2))
    parts = []
    if beyond > 0:
        parts.append(f"its centre lies {beyond * 100:.1f} cm beyond the top face of {support!r}")   # not 'box''s
    if abs(dz) >= HEIGHT_TOL:
        parts.append(f"{abs(dz) * 100:.1f} cm {'above' if dz > 0 else 'below'} the height of resting on it")
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
