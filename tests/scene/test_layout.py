from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from splattwin.scene.objects import (REACH, ROBOT_BASE_XY, TABLE_EXTENT, TARGET_FRAME_SIZE, make_objects,
                                     sample_layout)


def _surface_points(mesh: trimesh.Trimesh, n: int = 4000) -> np.ndarray:
    pts, _ = trimesh.sample.sample_surface_even(mesh, n, seed=0)
    return np.vstack([pts, mesh.vertices])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_layout_constraints(seed):
    objs = make_objects(seed)
    layout = sample_layout(objs, seed)
    pts = {o.name: _surface_points(o.mesh_world()) for o in objs}
    x0, x1, y0, y1 = TABLE_EXTENT
    for o in objs:
        p = pts[o.name]
        assert abs(p[:, 2].min()) < 1e-9, f"{o.name} does not rest on the table"
        d = np.linalg.norm(p[:, :2] - ROBOT_BASE_XY, axis=1)
        assert REACH[0] <= d.min() and d.max() <= REACH[1], o.name
        assert x0 < p[:, 0].min() and p[:, 0].max() < x1 and y0 < p[:, 1].min() and p[:, 1].max() < y1
    names = list(pts)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            gap = cKDTree(pts[names[i]][:, :2]).query(pts[names[j]][:, :2])[0].min()
            assert gap > 0.02, (names[i], names[j], gap)
    # the hammer's target frame is free of objects and within reach
    c, s = np.array(layout["target_frame"]["center"][:2]), layout["target_frame"]["size"]
    assert s == TARGET_FRAME_SIZE
    for name, p in pts.items():
        inside = np.all(np.abs(p[:, :2] - c) < s / 2 + 0.01, axis=1)
        assert not inside.any(), name
    corners = c + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * s / 2
    d = np.linalg.norm(corners - ROBOT_BASE_XY, axis=1)
    assert REACH[0] <= d.min() and d.max() <= REACH[1]


def test_object_shapes_match_the_brief():
    objs = {o.name: o for o in make_objects(0)}
    assert set(objs) == {"cardboard_box", "blue_box", "yellow_cube", "toy_hammer", "bottle"}
    assert sorted(o.label for o in objs.values()) == [1, 2, 3, 4, 5]
    card, blue = objs["cardboard_box"].extent, objs["blue_box"].extent
    assert np.all(card[:2] > blue[:2] + 0.05)  # the blue box fits on the cardboard box with room to spare
    assert min(blue) <= 0.06  # graspable by the Panda (0.08 m max opening)
    np.testing.assert_allclose(objs["yellow_cube"].extent, 0.025)
    for o in objs.values():
        assert o.mesh_obj.is_watertight, o.name
        np.testing.assert_allclose(o.mesh_obj.bounds[1] - o.mesh_obj.bounds[0], o.extent, atol=1e-9)
        np.testing.assert_allclose(o.mesh_obj.bounds.mean(axis=0), 0.0, atol=1e-9)  # frame at bbox centre
    assert not objs["toy_hammer"].convex
    assert all(objs[n].convex for n in ("cardboard_box", "blue_box", "yellow_cube", "bottle"))


def test_layout_is_deterministic_and_seed_dependent():
    a, b, c = make_objects(0), make_objects(0), make_objects(5)
    la, lb, lc = sample_layout(a, 0), sample_layout(b, 0), sample_layout(c, 5)
    assert json.dumps([o.to_json() for o in a]) == json.dumps([o.to_json() for o in b])
    assert la["target_frame"] == lb["target_frame"]
    assert not np.allclose(a[0].T_world_obj, c[0].T_world_obj)
