"""Contact monitoring on hand-made contact lists: which touches are collisions, counted once per onset."""

from __future__ import annotations

import numpy as np

from splattwin.robot.monitor import ContactEvent, ContactKind, MonitorState, landing_side, scan
from splattwin.robot.world import Contacts
from splattwin.transforms import make_pose

# bodies: 0 world/table, 1 crate (goal support), 2 target box, 3 other object, 4 link7, 5 left finger, 6 right finger
IS_ROBOT = np.array([False, False, False, False, True, True, True])


def _scan(state: MonitorState, pairs, dist, t: float = 0.0) -> None:
    scan(state, np.array(pairs, dtype=int).reshape(-1, 2), np.array(dist, float), IS_ROBOT, t=t)


def test_robot_touching_anything_but_the_target_is_a_collision_once_per_onset():
    mon = MonitorState(target=2)
    _scan(mon, [[5, 2], [6, 2], [4, 5]], [-1e-3, -1e-3, -1e-3])     # fingers on the target, link7-finger: fine
    assert mon.events == []
    _scan(mon, [[5, 2], [0, 5]], [-1e-3, -2e-4], t=1.0)               # a finger scrapes the table
    assert mon.events == [ContactEvent(ContactKind.ROBOT, 0, 5, 1.0)]
    _scan(mon, [[5, 0]], [-1e-4], t=1.1)                              # still touching (other order): same contact
    assert len(mon.events) == 1
    _scan(mon, [[5, 0]], [2e-3], t=1.2)                               # within the margin, not touching: ends it
    assert mon.active == set()
    _scan(mon, [[0, 5], [4, 3]], [-1e-4, -1e-4], t=2.0)              # touches again, and link7 hits another object
    assert [e.key for e in mon.events[1:]] == [(ContactKind.ROBOT, 0, 5), (ContactKind.ROBOT, 3, 4)]
    assert mon.count(ContactKind.ROBOT) == 3 and mon.count(ContactKind.OBJECT) == 0


def test_carried_object_may_touch_only_allowed_bodies():
    mon = MonitorState(target=2)
    _scan(mon, [[2, 1], [2, 3]], [-1e-3, -1e-3])                       # not carried: object contacts are not judged
    assert mon.events == []
    mon.carrying, mon.allowed = True, frozenset({1, 0})              # lifting off the crate
    _scan(mon, [[2, 1], [2, 0], [5, 2]], [-1e-3, -1e-3, -1e-3])
    assert mon.events == []
    _scan(mon, [[3, 2]], [-1e-3], t=3.0)                              # brushes the other object in transfer
    assert mon.events == [ContactEvent(ContactKind.OBJECT, 2, 3, 3.0)]
    _scan(mon, [[1, 3]], [-1e-3], t=3.5)                              # two other bodies touching: not ours
    assert len(mon.events) == 1


def _contacts(body1, body2, dist, normal, pos) -> Contacts:
    return Contacts(np.array(body1), np.array(body2), np.array(dist, float), np.array(normal, float),
                    np.array(pos, float))


def test_landing_side_is_the_finger_pushing_along_the_approach():
    # TCP at the origin approaching along world -z (TCP z = down), closing axis TCP y = world +y
    T = make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.1])
    left = _contacts([5], [2], [-1e-3], [[0, 0, 1.0]], [[0.0, -0.04, 0.09]])     # on top of the target, world -y
    assert landing_side(left, 2, IS_ROBOT, T) == 1.0          # TCP y = world -y: the +y side in the TCP frame
    right = _contacts([2], [6], [-1e-3], [[0, 0, -1.0]], [[0.0, 0.04, 0.09]])
    assert landing_side(right, 2, IS_ROBOT, T) == -1.0
    grazing = _contacts([5], [2], [-1e-3], [[0, 1.0, 0]], [[0.0, -0.03, 0.05]])   # normal across the approach
    assert landing_side(grazing, 2, IS_ROBOT, T) is None
    not_touching = _contacts([5], [2], [1e-3], [[0, 0, 1.0]], [[0.0, -0.04, 0.09]])
    assert landing_side(not_touching, 2, IS_ROBOT, T) is None
    other = _contacts([5], [3], [-1e-3], [[0, 0, 1.0]], [[0.0, -0.04, 0.09]])      # landed on another object
    assert landing_side(other, 2, IS_ROBOT, T) is None
    assert landing_side(_contacts([], [], [], np.zeros((0, 3)), np.zeros((0, 3))), 2, IS_ROBOT, T) is None
