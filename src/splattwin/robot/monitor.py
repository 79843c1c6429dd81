"""Contact monitoring during execution: which touches are collisions, and when a finger lands on the target.

A collision is the onset of a penetrating contact (signed distance < 0) that the task does not allow:
* `ContactKind.ROBOT`: the robot touches anything but the target object (robot-robot contacts are the
  arm's own business and not counted);
* `ContactKind.OBJECT`: while carried, the target touches anything but the robot and its allowed bodies
  (the support it leaves while lifting, the goal surface while descending).
A contact that stays on counts once (`MonitorState.active` remembers the pairs touching now).
Bodies are ids of one MuJoCo model (the monitor runs every other physics step, so no names there).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

LANDING_COS = math.cos(math.radians(45))  # hand-target contact normal this close to the approach axis = landing


class ContactKind(enum.Enum):
    ROBOT = "robot"      # the robot touched something other than the target
    OBJECT = "object"    # the carried target touched something other than the robot or an allowed body


@dataclass(frozen=True)
class ContactEvent:
    """The onset of a collision: its kind, the two bodies (ids, body_a < body_b) and the time (s)."""

    kind: ContactKind
    body_a: int
    body_b: int
    t: float = 0.0

    @property
    def key(self) -> tuple[ContactKind, int, int]:
        return (self.kind, self.body_a, self.body_b)

    def describe(self, body_name) -> str:
        """'robot: link7 - world' with `body_name(id) -> str`."""
        return f"{self.kind.value}: {body_name(self.body_a)} - {body_name(self.body_b)}"


@dataclass
class MonitorState:
    """What the monitor knows during one task step.

    target: body id of the object being manipulated. carrying: the target is in the hand (its contacts
    count as OBJECT collisions). allowed: bodies the carried target may touch. events: collisions so far.
    """

    target: int
    carrying: bool = False
    allowed: frozenset[int] = frozenset()
    active: set[tuple[ContactKind, int, int]] = field(default_factory=set)
    events: list[ContactEvent] = field(default_factory=list)

    def count(self, kind: ContactKind) -> int:
        return sum(1 for e in self.events if e.kind is kind)


def scan(state: MonitorState, pairs: np.ndarray, dist: np.ndarray, is_robot: np.ndarray, t: float = 0.0) -> None:
    """Update `state` with one instant's contacts: body pairs [K,2] (ids), signed distances [K] (m) and
    is_robot [nbody] bool. New collisions are appended to state.events."""
    b = np.asarray(pairs)[np.asarray(dist) < 0.0]
    if not len(b):
        state.active = set()
        return
    rob = is_robot[b]
    target = state.target
    active: set[tuple[ContactKind, int, int]] = set()
    for (b1, b2), (r1, r2) in zip(b.tolist(), rob.tolist()):
        if r1 and r2:
            continue
        if r1 or r2:
            other = b2 if r1 else b1
            if other == target:
                continue
            active.add((ContactKind.ROBOT, min(b1, b2), max(b1, b2)))
        elif state.carrying and target in (b1, b2):
            other = b2 if b1 == target else b1
            if other in state.allowed:
                continue
            active.add((ContactKind.OBJECT, min(b1, b2), max(b1, b2)))
    for key in sorted(active - state.active, key=lambda k: (k[0].value, k[1], k[2])):
        state.events.append(ContactEvent(*key, t=t))
    state.active = active


def landing_side(contacts, target: int, is_robot: np.ndarray, T_world_tcp: np.ndarray) -> float | None:
    """+1 / -1: the side (along the TCP y = closing axis) of a hand contact that pushes on the target
    along the approach direction — a finger landing on top of it instead of straddling it; None if
    there is none. (A Franka senses this as an external force along the approach axis; its torque
    about the TCP x axis gives the side.) Contacts with a normal across the approach (a finger
    grazing the target's side) do not count. contacts: a `world.Contacts`."""
    if not len(contacts):
        return None
    b1, b2 = contacts.body1, contacts.body2
    sel = (((b1 == target) & is_robot[b2]) | ((b2 == target) & is_robot[b1])) & (contacts.dist < 0)
    if not sel.any():
        return None
    along = np.abs(contacts.normal[sel] @ T_world_tcp[:3, 2]) > LANDING_COS
    if not along.any():
        return None
    side = (contacts.pos[sel][along] - T_world_tcp[:3, 3]) @ T_world_tcp[:3, 1]
    return float(np.sign(side.mean())) or 1.0
