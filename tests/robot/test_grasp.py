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


def test_top_grasps_keep_fingertips_clear_of_the_support():
    """The fingertips (tip_depth beyond the TCP) stay floor_clearance above the support surface, also
    when the support lies above the mesh bottom (a reconstructed object sunk into the table)."""
    box = _box((0.10, 0.03, 0.03))                         # bottom at z = -0.015
    tip, clear = 0.009, 0.0065
    for floor in (None, -0.012):
        gs = [g for g in synthesize(box.vertices, box.faces, floor=floor, tip_depth=tip, floor_clearance=clear)
              if g.kind == "top"]
        assert gs
        f = -0.015 if floor is None else floor
        for g in gs:
            assert g.T_obj_tcp[2, 3] - tip >= f + clear - 1e-9
            assert g.T_obj_tcp[2, 3] <= 0.015 - 0.004 + 1e-9     # pads still below the top face
    # 1.5 cm tall: no room for the fingertips above the support and the pads on the object
    flat = _box((0.10, 0.03, 0.015))
    assert not [g for g in synthesize(flat.vertices, flat.faces, tip_depth=tip, floor_clearance=clear)
                if g.kind == "top"]


def _hammer(yaw_handle: float = 0.0, offset_y: float = 0.0) -> trimesh.Trimesh:
    """Handle 17.5 x 2.5 x 2.5 cm (rotated by yaw_handle about its head end, shifted by offset_y) plus a
    3 x 8 x 3 cm head at +x; centred on its bounding box like a twin's collision mesh."""
    handle = trimesh.creation.box(extents=(0.175, 0.025, 0.025))
    handle.apply_translation((-0.0875, 0, -0.0025))
    c, s = math.cos(yaw_handle), math.sin(yaw_handle)
    handle.apply_transform(np.array([[c, -s, 0, 0], [s, c, 0, offset_y], [0, 0, 1, 0], [0, 0, 0, 1]]))
    head = trimesh.creation.box(extents=(0.03, 0.08, 0.03))
    m = trimesh.boolean.union([handle, head], engine="manifold")
    m.apply_translation(-m.bounds.mean(axis=0))
    return m


@pytest.mark.parametrize("yaw_handle,offset_y", [(0.0, 0.0), (0.18, 0.0), (0.0, 0.015)])
def test_hammer_grasps_along_the_whole_handle_and_on_the_head(yaw_handle, offset_y):
    """Stations are centred on the material at each station (not on the bounding box's centre line), so a
    handle that is tilted or off-centre in the box is grasped along its length, and the head across its
    3 cm thickness (closing along the hammer's long axis)."""
    m = _hammer(yaw_handle, offset_y)
    gs = [g for g in synthesize(m.vertices, m.faces) if g.kind == "top"]
    x = np.array([g.T_obj_tcp[0, 3] for g in gs])
    y_close = np.array([abs(g.T_obj_tcp[1, 1]) for g in gs])      # |closing axis . y_obj|
    handle = (y_close > 0.9) & (np.array([g.width for g in gs]) < 0.03)
    assert handle.sum() >= 10
    assert np.ptp(x[handle]) > 0.10                                # along most of the 17.5 cm handle
    head = [g for g in gs if abs(g.T_obj_tcp[0, 1]) > 0.9]         # closing along the long axis
    assert head and all(g.width == pytest.approx(0.03, abs=2e-3) for g in head)
    assert all(g.T_obj_tcp[0, 3] > m.bounds[1, 0] - 0.04 for g in head)
    # every candidate's contacts lie on the surface, antipodal
    for g in gs:
        _, dist, _ = trimesh.proximity.closest_point(m, g.contacts)
        assert np.all(dist < 1e-6)


def test_no_grasp_lands_a_pad_on_a_neighbouring_part():
    """Two parallel 3 cm bars 1 cm apart: the opened jaws (8 cm) cannot straddle one bar without a pad
    landing on the other, and both together (7 cm + clearance) do not fit either."""
    a = trimesh.creation.box(extents=(0.10, 0.03, 0.03))
    b = a.copy()
    a.apply_translation((0, -0.02, 0))
    b.apply_translation((0, 0.02, 0))
    m = trimesh.util.concatenate([a, b])
    across = [g for g in synthesize(m.vertices, m.faces, side=False) if abs(g.T_obj_tcp[1, 1]) > 0.9]
    assert across == []
    # the same bars 6 cm apart are each graspable across
    b.apply_translation((0, 0.05, 0))
    m = trimesh.util.concatenate([a, b])
    across = [g for g in synthesize(m.vertices, m.faces, side=False) if abs(g.T_obj_tcp[1, 1]) > 0.9]
    assert across and all(g.width == pytest.approx(0.03, abs=1e-6) for g in across)
