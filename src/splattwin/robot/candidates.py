"""Feasible pick-and-place plans for one step: ranked grasps made feasible, each with its place options.

A grasp is feasible when the pre-grasp (PREGRASP back along the approach) has an IK solution, the
Cartesian approach and lift exist and are collision-free in the planning scene — the open fingers may
touch the target but not penetrate it (TOUCH_DEPTH) on the approach, the lifted object may leave its
support — and at least one place option is. A place option: pre-place IK (LIFT above the place pose),
a collision-free descent with the object in the hand (it may touch the goal surface), and a retreat of
the opened hand that does not land on the released object. Everything is planned on the belief;
rejections are counted by reason in the step's `GraspReport`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

import numpy as np

from splattwin.robot import footprint as fp
from splattwin.robot.grasp import Grasp, too_wide
from splattwin.robot.motion import MotionPlanner
from splattwin.robot.plans import GraspPlan, GraspReport, PlacePlan
from splattwin.robot.selection import GraspSelector, place_targets
from splattwin.robot.task import Step
from splattwin.transforms import invert_pose

log = logging.getLogger(__name__)

PREGRASP = 0.08          # m back along the approach before grasping (and the retreat after placing)
LIFT = 0.10              # m straight up after closing (and the pre-place height above the place pose)
TOUCH_DEPTH = 0.001      # m: fingers may touch the target on the approach, not penetrate it deeper than this
MAX_GRASPS = 16          # ranked candidates tried per selection round


class StepFailed(Exception):
    """A step cannot go on (no feasible plan, the object not lifted, ...); the message says why."""


class StepPlanner:
    """Feasible plans for steps on one world. q_now() -> [n]: the arm configuration held now (IK seed)."""

    def __init__(self, motion: MotionPlanner, selector: GraspSelector, q_now: Callable[[], np.ndarray]):
        self.motion, self.selector, self.q_now = motion, selector, q_now
        self.world = motion.world
        self.robot = motion.robot
        self.belief = motion.belief

    def support_of(self, obj: str) -> list[str]:
        """Bodies the object rests on / touches now in the world (contacts it may break when lifted)."""
        w = self.world
        names = {"world"}
        for other in w.contacts().partners(w.object_body(obj)):
            if not w.is_robot[other]:
                names.add(w.body_name(other))
        return sorted(names)

    def candidates(self, step: Step, report: GraspReport) -> Iterator[GraspPlan]:
        """Feasible plans, best-ranked grasp first (lazily: each costs IK and collision checks)."""
        obj = step.pick
        m, ik = self.motion, self.motion.ik
        T_obj = self.belief[obj]
        cands = self.selector.ranked(obj, self.belief)
        report.restart(len(cands))
        if not cands:
            raise StepFailed(self.no_grasp_message(obj))
        support = self.support_of(obj)
        for g in cands[:MAX_GRASPS]:
            report.tried += 1
            T_grasp = T_obj @ g.T_obj_tcp
            T_pre = T_grasp.copy()
            T_pre[:3, 3] -= T_grasp[:3, 2] * PREGRASP
            q_pre = ik.solve(T_pre, self.q_now(), q_posture=self.robot.home)
            if q_pre is None:
                report.reject("pregrasp IK")
                continue
            approach = m.cartesian(q_pre, T_pre, T_grasp)
            if approach is None:
                report.reject("approach IK")
                continue
            q_grasp = approach[-1]
            m.freeze(self.q_now(), self.robot.max_opening)
            # the open fingers straddle the target: they may touch it, not land on it or push into it
            with m.allowing(obj, self.robot.hand_bodies, penetration=TOUCH_DEPTH):
                ok = m.checker.is_valid(q_pre) and m.path_clear(approach)
                if not ok and log.isEnabledFor(logging.DEBUG):  # name the pair while the exceptions still apply
                    log.debug("approach collision %s", m.first_pair(approach))
            if not ok:
                report.reject("approach collision")
                continue
            T_lift = T_grasp.copy()
            T_lift[:3, 3] += [0, 0, LIFT]
            lift = m.cartesian(q_grasp, T_grasp, T_lift)
            if lift is None:
                report.reject("lift IK")
                continue
            T_tcp_obj = invert_pose(g.T_obj_tcp)
            m.freeze(self.q_now(), g.width)
            with m.carrying(obj, T_tcp_obj), m.allowing(obj, support):
                ok = m.path_clear(lift[1:]) if len(lift) > 2 else True
            if not ok:
                report.reject("lift collision")
                continue
            places = self.place_options(step, g, lift[-1], report)
            first = next(places, None)
            if first is None:
                continue
            report.chose(g)
            yield GraspPlan(grasp=g, q_pregrasp=q_pre, T_world_pregrasp=T_pre, T_world_grasp=T_grasp,
                            approach=approach, lift=lift, T_tcp_obj=T_tcp_obj, support=support, place=first,
                            places=places)

    def place_options(self, step: Step, g: Grasp, q_lift: np.ndarray, report: GraspReport | None,
                      T_obj_tcp: np.ndarray | None = None) -> Iterator[PlacePlan]:
        """Feasible place options for grasp g, best first. T_obj_tcp: the object held at this pose in the
        hand (default: the grasp's planned one). report None: rejections are not counted."""
        obj = step.pick
        m, ik = self.motion, self.motion.ik
        T_obj_tcp = g.T_obj_tcp if T_obj_tcp is None else T_obj_tcp
        T_tcp_obj = invert_pose(T_obj_tcp)
        goal_support = [step.place_on] if step.place_on else ["world"]

        def reject(reason: str) -> None:
            if report is not None:
                report.reject(reason)

        for T_place_obj in place_targets(step, obj, self.belief, self.world.manifest, self.selector.shapes):
            # the checker is shared with other planning between resumptions: set the carrying state anew
            m.freeze(self.q_now(), g.width)
            with m.carrying(obj, T_tcp_obj):
                T_place = T_place_obj @ T_obj_tcp
                T_pp = T_place.copy()
                T_pp[:3, 3] += [0, 0, LIFT]
                q_pp = ik.solve(T_pp, q_lift, q_posture=self.robot.home)
                if q_pp is None or not m.checker.is_valid(q_pp):
                    reject("pre-place IK/collision")
                    continue
                descent = m.cartesian(q_pp, T_pp, T_place)
                if descent is None:
                    reject("descent IK")
                    continue
                with m.allowing(obj, goal_support):
                    ok = m.path_clear(descent[:-1])
                if not ok:
                    reject("descent collision")
                    continue
                T_ret = T_place.copy()
                T_ret[:3, 3] -= T_place[:3, 2] * PREGRASP
                retreat = m.cartesian(descent[-1], T_place, T_ret)
                if retreat is None:
                    reject("retreat IK")
                    continue
            if not self.retreat_clear(obj, T_place_obj, retreat):
                reject("retreat collision")
                continue
            yield PlacePlan(T_world_obj=T_place_obj, q_preplace=q_pp, descent=descent, retreat=retreat)

    def retreat_clear(self, obj: str, T_place_obj: np.ndarray, retreat: np.ndarray) -> bool:
        """The opened hand backs off the released object (at its place pose) without landing on it or
        touching anything else within the margin."""
        m = self.motion
        m.freeze(self.q_now(), self.robot.max_opening, belief={**self.belief, obj: T_place_obj})
        with m.allowing(obj, self.robot.hand_bodies, penetration=TOUCH_DEPTH):
            ok = m.path_clear(retreat)
            if not ok and log.isEnabledFor(logging.DEBUG):
                log.debug("retreat collision %s", m.first_pair(retreat))
        return ok

    def no_grasp_message(self, obj: str) -> str:
        """Why an object has no grasp at all, with what to check: its size against the gripper's opening."""
        ext = np.asarray(self.world.manifest.object(obj).bbox_extent, float)
        sel = self.selector
        # the words of task validation (`validate_task`), which refuses such an object before planning
        wide = too_wide(obj, fp.narrowest_width(sel.shapes(obj)), sel.max_opening)
        if wide is not None:
            return wide
        return (f"no antipodal grasp fits the gripper on {obj!r}: its collision mesh "
                f"({' x '.join(f'{v * 100:.1f}' for v in ext)} cm) offers no pair of opposite faces closer than the "
                f"gripper's {sel.max_opening * 100:.1f} cm opening that the fingers reach while their tips stay "
                f"{sel.floor_clearance * 1000:.1f} mm above its support; check its mesh in the report (a bulging or "
                f"merged mesh after a short training), or pick another object")

    def no_candidate_message(self, step: Step, report: GraspReport) -> str:
        """Why no plan was found: the rejections by reason, and when the places were rejected (pre-place,
        descent, retreat), the objects crowding the goal (`goal_neighbours`)."""
        crowded = ""
        if any(r.startswith(("pre-place", "descent", "retreat")) for r in report.rejections):
            crowded = self.goal_neighbours(step)
        return (f"none of {report.tried} grasp candidates on {step.pick!r} has a reachable, "
                f"collision-free approach, lift and place (rejections: {report.rejections}){crowded}")

    def goal_neighbours(self, step: Step) -> str:
        """`goal_neighbours` of the step in the belief, on the objects' collision meshes."""
        return goal_neighbours(step, self.belief, self.selector.shapes)


def goal_neighbours(step: Step, belief: dict[str, np.ndarray], shape: Callable[[str], fp.Shape]) -> str:
    """'; the goal is crowded: ...' naming the objects (in the belief, T_world_obj [4,4]) whose footprint (the
    union of their convex parts seen from above, `footprint`; their bounding box without a mesh) lies closer to
    the place's centre than the picked object reaches from it at some yaw (the farthest point of its own
    footprint from its centre), else ''. The place goes to the goal's centre (`selection.place_targets`).
    shape: each object's `footprint.Shape` (`footprint.Shapes`)."""
    if step.place_on is not None:
        centre, skip = belief[step.place_on][:2, 3], {step.pick, step.place_on}
    else:
        centre, skip = step.place_in.center[:2], {step.pick}
    reach = fp.reach(shape(step.pick))
    near = sorted((fp.distance(centre, shape(o), T), o) for o, T in belief.items() if o not in skip)
    near = [(d, o) for d, o in near if d < reach]
    if not near:
        return ""
    return ("; the goal is crowded: " + ", ".join(f"{o!r} {d * 100:.1f} cm from its centre" for d, o in near)
            + f" ({step.pick!r} reaches {reach * 100:.1f} cm from it at some yaw): move the goal, or those "
            "objects in an earlier step")
