"""Typed plans of a pick-and-place step and the selection report that goes into the results.

Joint paths are [K, n] arrays (rad) of IK waypoints, executed after time parameterisation; poses are
T_world_* [4,4] in the twin frame (m); T_tcp_obj maps object-frame points to the TCP frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from splattwin.robot.grasp import Grasp


@dataclass(frozen=True)
class PlacePlan:
    """Where and how the held object is put down: T_world_obj at release, the pre-place configuration
    (above it by the lift height), the Cartesian descent to it and the retreat after opening."""

    T_world_obj: np.ndarray     # [4,4] object pose at release
    q_preplace: np.ndarray      # [n] rad
    descent: np.ndarray         # [K,n] pre-place -> place
    retreat: np.ndarray         # [K,n] place -> backed off along the approach


@dataclass
class GraspPlan:
    """A feasible grasp: IK and collision-checked approach and lift, and its first feasible place.

    places: further place options of this grasp, computed lazily (each costs IK and collision checks)."""

    grasp: Grasp
    q_pregrasp: np.ndarray      # [n] rad, the approach starts here
    T_world_pregrasp: np.ndarray
    T_world_grasp: np.ndarray
    approach: np.ndarray        # [K,n] pre-grasp -> grasp
    lift: np.ndarray            # [K,n] grasp -> lifted
    T_tcp_obj: np.ndarray       # [4,4] object in the hand as planned
    support: list[str]          # bodies the object rests on / touches before the lift
    place: PlacePlan
    places: Iterator[PlacePlan] = field(default_factory=lambda: iter(()), repr=False)


@dataclass
class GraspReport:
    """How a step's grasp was selected (results.json `grasp`): candidates ranked, tried, rejections by
    reason, the chosen grasp's kind/width (m)/score, motion-planning fallbacks, touch corrections and the
    resulting correction of the believed object position (m, world frame)."""

    candidates: int = 0
    tried: int = 0
    rejections: dict[str, int] = field(default_factory=dict)
    kind: str | None = None
    width: float | None = None
    score: float | None = None
    fallbacks: list[str] = field(default_factory=list)
    touch_corrections: int = 0
    belief_correction_m: list[float] | None = None

    def reject(self, reason: str) -> None:
        self.rejections[reason] = self.rejections.get(reason, 0) + 1

    def restart(self, candidates: int) -> None:
        """A new selection round (after a touch correction): counts start over, fallbacks are kept."""
        self.candidates, self.tried, self.rejections = candidates, 0, {}
        self.kind = self.width = self.score = None

    def chose(self, g: Grasp) -> None:
        self.kind, self.width, self.score = g.kind, float(g.width), float(g.score)
