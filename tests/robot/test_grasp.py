from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from splattwin.robot.grasp import FRICTION_CONE, rank_grasps, synthesize


def _box(extent, yaw=0.0):
    m = trimesh.creation.box(extents=extent)
    c, s = math.cos(yaw), math.sin(yaw)
    m.apply_transform(np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    return m


@pytest.mark.parametrize("yaw", [0.0, 0.4])
def test_box_grasps_are_antipodal_and_fit(yaw):
    ext = (0.08, 0.06, 0.05)
    box = _box(ext, yaw)
    gs = synthesize(box.vertices, box.faces, max_width=0.08)
    assert gs and {g.kind for g in gs} == {"top", "side"}
    for g in gs:
        assert 0 < g.width <= 0.08
        R = g.T_obj_tcp[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        y = R[:, 1]                                   # closing axis
        # contacts lie on the surface, opposite each other along the closing axis
        d = g.contacts[0] - g.contacts[1]
        assert np.linalg.norm(np.cross(d, y)) < 1e-6 and d @ y == pytest.approx(g.width)
        _, dist, tri = trimesh.proximity.closest_point(box, g.contacts)
        assert np.all(dist < 1e-6)
        n = box.face_normals[tri]
        assert n[0] @ y > math.cos(FRICTION_CONE) and -(n[1] @ y) > math.cos(FRICTION_CONE)
        # the only side under 8 cm is the 6 cm one
        assert g.width == pytest.approx(0.06, abs=1e-6)
        if g.kind == "top":
            assert R[:, 2] @ [0, 0, -1] == pytest.approx(1.0)
            assert g.T_obj_tcp[2, 3] < ext[2] / 2           # pads below the top face


def test_too_wide_object_has_no_grasp():
    box = _box((0.12, 0.10, 0.05))
    assert synthesize(box.vertices, box.faces, max_width=0.08) == []


def test_hammer_like_shape_grasped_on_handle():
    handle = trimesh.creation.box(extents=(0.175, 0.025, 0.025))
    handle.apply_translation((0.0875, 0, 0))
    head = trimesh.creation.box(extents=(0.03, 0.08, 0.03))
    head.apply_translation((0.175, 0, 0))
    m = trimesh.boolean.union([handle, head], engine="manifold")
    gs = synthesize(m.vertices, m.faces)
    top = [g for g in gs if g.kind == "top"]
    assert top
    # narrow handle grasps (2.5 cm) exist; nothing claims the 8 cm head across its long side
    assert any(g.width == pytest.approx(0.025, abs=1e-3) for g in top)
    assert all(g.width < 0.08 - 1e-3 for g in gs)


def test_ranking_prefers_upright_top_grasps():
    box = _box((0.05, 0.05, 0.05))
    gs = synthesize(box.vertices, box.faces)
    T_world_obj = np.eye(4)
    T_world_obj[:3, 3] = [0.1, 0.0, 0.025]
    ranked = rank_grasps(gs, T_world_obj, np.eye(4))
    assert ranked[0].kind == "top"
    # tipped over by 90 degrees: no grasp may approach from the object's (now sideways) top
    tipped = T_world_obj.copy()
    tipped[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    for g in rank_grasps(gs, tipped, np.eye(4)):
        a = (tipped @ g.T_obj_tcp)[:3, 2]
        assert a[2] < -0.8 or abs(a[2]) < 0.6
