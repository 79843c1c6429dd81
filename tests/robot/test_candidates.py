"""Step planning helpers that need no MuJoCo world (robot/candidates.py): the 'goal is crowded' hint."""

from __future__ import annotations

import numpy as np
import trimesh

from splattwin.robot import footprint as fp
from splattwin.robot.candidates import goal_neighbours
from splattwin.robot.task import Region, Step
from splattwin.transforms import pose_xyz_yaw


def _box(lo, hi) -> np.ndarray:
    return np.asarray(trimesh.creation.box(bounds=[lo, hi]).vertices, float)


# an L (as in test_footprint): a 20 x 5 cm arm along x, a 5 x 10 cm arm up y at its -x end; its notch is free
L_SHAPE = fp.Shape((_box([-0.1, -0.075, -0.05], [0.1, -0.025, 0.05]),
                     _box([-0.1, -0.025, -0.05], [-0.05, 0.075, 0.05])))


def test_the_crowded_hint_measures_from_the_neighbours_meshes():
    """A goal in the notch of an L, 6 cm from its long arm: the hint named the L '0.0 cm from its centre' (its
    bounding box holds the goal); now 6.0 cm, the distance to its mesh."""
    T_l = pose_xyz_yaw(0.3, -0.1, 0.05, np.pi / 4)
    goal = (T_l @ [0.04, 0.035, 0.0, 1.0])[:2]
    step = Step("big", place_in=Region(center=np.array([goal[0], goal[1], 0.0]), size=np.array([0.3, 0.3])))
    shapes = {"ell": L_SHAPE, "big": fp.box_shape([0.16, 0.12, 0.05]), "far": fp.box_shape([0.05, 0.05, 0.05])}
    belief = {"ell": T_l, "big": pose_xyz_yaw(0.5, 0.3, 0.025, 0.0), "far": pose_xyz_yaw(-0.3, 0.3, 0.025, 0.0)}
    hint = goal_neighbours(step, belief, shapes.__getitem__)
    assert hint.startswith("; the goal is crowded: 'ell' 6.0 cm from its centre ('big' reaches 10.0 cm from it")
    assert "'far'" not in hint


def test_the_picked_object_reaches_as_far_as_its_mesh():
    """A 7 cm round bottle reaches 3.5 cm from its centre at any yaw, not half its bounding box's diagonal
    (4.9 cm): a box 4 cm from the goal does not crowd it; the bottle's bounding box alone would."""
    bottle = trimesh.creation.cylinder(radius=0.035, height=0.16, sections=64)
    shapes = {"bottle": fp.Shape((np.asarray(bottle.vertices, float),)), "box": fp.box_shape([0.04, 0.04, 0.04])}
    step = Step("bottle", place_in=Region(center=np.array([0.3, 0.0, 0.0]), size=np.array([0.2, 0.2])))
    belief = {"bottle": pose_xyz_yaw(0.5, 0.3, 0.08, 0.0), "box": pose_xyz_yaw(0.3, 0.06, 0.02, 0.0)}
    assert goal_neighbours(step, belief, shapes.__getitem__) == ""
    shapes["bottle"] = fp.box_shape([0.07, 0.07, 0.16])
    assert "'box' 4.0 cm from its centre ('bottle' reaches 4.9 cm" in goal_neighbours(step, belief, shapes.__getitem__)
