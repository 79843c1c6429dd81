"""Footprints of objects' collision meshes on the table plane (robot/footprint.py), on hand-made shapes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from splattwin.errors import InputError
from splattwin.robot import footprint as fp
from splattwin.robot.task import footprint_distance
from splattwin.transforms import pose_xyz_yaw
from splattwin.twin.manifest import ObjectEntry


def _box(lo, hi) -> np.ndarray:
    return np.asarray(trimesh.creation.box(bounds=[lo, hi]).vertices, float)


# an L in the object frame: a 20 x 5 cm arm along x and a 5 x 10 cm arm up y at its -x end; the notch
# x in [-0.05, 0.1], y in [-0.025, 0.075] is free although inside the 20 x 15 cm bounding box
L_SHAPE = fp.Shape((_box([-0.1, -0.075, -0.05], [0.1, -0.025, 0.05]),
                     _box([-0.1, -0.025, -0.05], [-0.05, 0.075, 0.05])))


def test_a_box_shape_gives_the_bounding_box_footprint():
    """The fallback for an object without a mesh is the old rule: the distance to its bounding box."""
    ext = np.array([0.2, 0.15, 0.1])
    shape = fp.box_shape(ext)
    assert not shape.from_mesh
    rng = np.random.default_rng(0)
    for _ in range(50):
        T = pose_xyz_yaw(*rng.uniform(-0.2, 0.2, 2), 0.05, rng.uniform(-np.pi, np.pi))
        xy = rng.uniform(-0.3, 0.3, 2)
        assert fp.distance(xy, shape, T) == pytest.approx(footprint_distance(xy, T, ext), abs=1e-9)
    T = pose_xyz_yaw(0.1, 0.0, 0.05, 0.3)
    assert fp.distance(T[:2, 3], shape, T) == 0.0
    assert fp.inradius(shape) == pytest.approx(0.075)
    assert fp.top_at(shape, T, T[:2, 3]) == pytest.approx(0.1) and fp.bottom(shape, T) == pytest.approx(0.0)


def test_the_footprint_of_an_l_is_its_arms_not_its_box():
    T = pose_xyz_yaw(0.3, -0.1, 0.05, np.pi / 4)          # turned 45 degrees in the twin frame

    def at(x, y):
        return (T @ [x, y, 0.0, 1.0])[:2]

    assert fp.distance(at(0.04, 0.035), L_SHAPE, T) == pytest.approx(0.06)       # in the notch: 6 cm from arm A
    assert fp.distance(at(0.05, -0.05), L_SHAPE, T) == 0.0                         # on arm A
    assert fp.distance(at(-0.07, 0.05), L_SHAPE, T) == 0.0                         # on arm B
    assert fp.distance(at(0.1, -0.025), L_SHAPE, T) == 0.0                         # on an edge
    assert fp.distance(at(0.15, 0.035), L_SHAPE, T) == pytest.approx(np.hypot(0.05, 0.06))   # beyond both
    assert fp.inradius(L_SHAPE) == 0.0      # its centre, in the notch, is on no part: no disc it surely covers
    assert fp.top_at(L_SHAPE, T, at(0.04, 0.035)) is None
    assert fp.top_at(L_SHAPE, T, at(0.05, -0.05)) == pytest.approx(0.1)


def test_the_inradius_is_the_disc_the_parts_cover_together():
    """A reconstructed 2.5 cm cube came as 4 convex parts: its inradius is still 1.25 cm, not one part's."""
    h = 0.0125
    quarters = fp.Shape(tuple(_box([min(0, sx * h), min(0, sy * h), 0], [max(0, sx * h), max(0, sy * h), 0.025])
                              for sx in (-1, 1) for sy in (-1, 1)))
    assert fp.inradius(quarters) == pytest.approx(h, rel=1e-4)
    # a cross of a 20 x 2 cm and a 4 x 20 cm bar: the nearest free point is the corner (2, 1) cm
    cross = fp.Shape((_box([-0.1, -0.01, 0], [0.1, 0.01, 0.02]), _box([-0.02, -0.1, 0], [0.02, 0.1, 0.02])))
    # (by rays every 0.5 degrees: a ray just beside a concave corner ends 0.05 mm beyond it)
    assert fp.inradius(cross) == pytest.approx(np.hypot(0.02, 0.01), rel=3e-3)
    off = fp.Shape((_box([0.01, -0.02, 0], [0.05, 0.02, 0.02]),))     # the centre beside the only part
    assert fp.inradius(off) == 0.0
    turned = fp.Shape((fp._posed(_box([-0.05, -0.02, 0], [0.05, 0.02, 0.02]), pose_xyz_yaw(0, 0, 0, 0.4)),))
    assert fp.inradius(turned) == pytest.approx(0.02, rel=1e-4)


def test_the_top_is_the_mesh_under_the_point():
    """A step: high at -x, 4 cm at +x; a wedge whose top rises from 0 to 10 cm along x."""
    step = fp.Shape((_box([-0.1, -0.05, 0.0], [0.0, 0.05, 0.1]), _box([0.0, -0.05, 0.0], [0.1, 0.05, 0.04])))
    T = pose_xyz_yaw(0.0, 0.0, 0.0, 0.0)
    assert fp.top_at(step, T, [-0.05, 0.0]) == pytest.approx(0.1)
    assert fp.top_at(step, T, [0.05, 0.0]) == pytest.approx(0.04)
    wedge = fp.Shape((np.array([[0, -0.05, 0], [0.1, -0.05, 0], [0.1, -0.05, 0.1],
                                [0, 0.05, 0], [0.1, 0.05, 0], [0.1, 0.05, 0.1]], float),))
    T = pose_xyz_yaw(0.2, 0.1, 0.01, 0.0)    # on a table 1 cm high
    for x in (0.0, 0.025, 0.05, 0.1):
        assert fp.top_at(wedge, T, [0.2 + x, 0.1]) == pytest.approx(0.01 + x)


def test_the_top_under_a_footprint_is_the_highest_mesh_point_there():
    """What an object lowered onto a support touches first: the highest point of the support's parts over its
    footprint (a wedge rising from 0 to 10 cm along x: 6 cm under a 4 cm square at its middle, 6.41 cm when the
    square is turned 45 degrees; a post in a corner of a tray counts only under it)."""
    wedge = fp.Shape((np.array([[-0.1, -0.05, -0.05], [0.1, -0.05, -0.05], [0.1, -0.05, 0.05],
                                [-0.1, 0.05, -0.05], [0.1, 0.05, -0.05], [0.1, 0.05, 0.05]], float),))
    T = pose_xyz_yaw(0.3, 0.1, 0.05, 0.0)
    cube = fp.box_shape([0.04, 0.04, 0.04])
    assert fp.Posed(wedge, T).top_under(fp.polygons(cube, pose_xyz_yaw(0.3, 0.1, 0.2, 0.0))) == pytest.approx(0.06)
    turned = fp.polygons(cube, pose_xyz_yaw(0.3, 0.1, 0.2, np.pi / 4))
    assert fp.Posed(wedge, T).top_under(turned) == pytest.approx(0.05 + 0.02 * np.sqrt(2) / 2, abs=2e-9)
    tray = fp.Shape((_box([-0.1, -0.1, 0.0], [0.1, 0.1, 0.02]), _box([0.08, 0.08, 0.0], [0.1, 0.1, 0.1])))
    posed = fp.Posed(tray, np.eye(4))
    assert posed.top_under(fp.polygons(cube, np.eye(4))) == pytest.approx(0.02)
    assert posed.top_under(fp.polygons(cube, pose_xyz_yaw(0.07, 0.07, 0.0, 0.0))) == pytest.approx(0.1)
    assert posed.top_under(fp.polygons(cube, pose_xyz_yaw(0.3, 0.0, 0.0, 0.0))) is None      # beside it
    # a footprint touching the part's edge meets it; a part seen edge-on (a plate) and a segment footprint too
    assert posed.top_under(fp.polygons(cube, pose_xyz_yaw(0.12, 0.0, 0.0, 0.0))) == pytest.approx(0.02)
    plate = fp.Shape((np.array([[-0.05, 0, 0], [0.05, 0, 0], [-0.05, 0, 0.1], [0.05, 0, 0.1]], float),))
    assert fp.Posed(plate, np.eye(4)).top_under(fp.polygons(cube, np.eye(4))) == pytest.approx(0.1, abs=1e-6)
    assert posed.top_under(fp.polygons(plate, pose_xyz_yaw(0.09, 0.09, 0.0, 0.0))) == pytest.approx(0.1)


def test_a_part_seen_edge_on_is_a_segment():
    plate = fp.Shape((np.array([[-0.05, 0, 0], [0.05, 0, 0], [-0.05, 0, 0.1], [0.05, 0, 0.1]], float),))
    T = np.eye(4)
    assert fp.distance([0.02, 0.0], plate, T) == 0.0
    assert fp.distance([0.02, 0.03], plate, T) == pytest.approx(0.03)
    assert fp.distance([0.08, 0.0], plate, T) == pytest.approx(0.03)
    assert fp.top_at(plate, T, [0.0, 0.0]) == pytest.approx(0.1)
    assert fp.inradius(plate) == 0.0


def test_object_shape_reads_the_convex_parts_or_falls_back_to_the_box(tmp_path: Path):
    (tmp_path / "objects").mkdir()
    trimesh.creation.box(bounds=[[-0.1, -0.075, -0.05], [0.1, -0.025, 0.05]]).export(tmp_path / "objects" / "a.obj")
    trimesh.creation.box(bounds=[[-0.1, -0.025, -0.05], [-0.05, 0.075, 0.05]]).export(tmp_path / "objects" / "b.obj")
    o = ObjectEntry(name="l", label=1, bbox_extent=[0.2, 0.15, 0.1], convex_parts=["objects/a.obj", "objects/b.obj"])
    shape = fp.object_shape(o, tmp_path)
    assert shape.from_mesh and len(shape.parts) == 2
    assert fp.distance([0.04, 0.035], shape, np.eye(4)) == pytest.approx(0.06)
    assert not fp.object_shape(o, None).from_mesh                       # no twin folder: its box
    o.usable, o.obstacle_only = False, True                             # an obstacle-only box has no mesh
    assert not fp.object_shape(o, tmp_path).from_mesh
    o.usable, o.obstacle_only, o.convex_parts = True, False, []
    assert not fp.object_shape(o, tmp_path).from_mesh
    o.collision_mesh = "objects/a.obj"                                  # no parts: the collision mesh, as one
    assert fp.object_shape(o, tmp_path).from_mesh


def test_object_shape_confines_and_checks_its_files(tmp_path: Path):
    (tmp_path / "twin").mkdir()
    trimesh.creation.box(extents=[0.1, 0.1, 0.1]).export(tmp_path / "outside.obj")
    o = ObjectEntry(name="x", label=1, bbox_extent=[0.1, 0.1, 0.1], convex_parts=["../outside.obj"])
    with pytest.raises(InputError, match=r"convex part of object 'x' .*leads outside") as e:
        fp.object_shape(o, tmp_path / "twin")
    assert e.value.path == tmp_path / "twin" / "twin.json"
    (tmp_path / "twin" / "bad.obj").write_text("not a mesh\n")
    o.convex_parts = ["bad.obj"]
    with pytest.raises(InputError, match=r"convex part of object 'x'") as e:
        fp.object_shape(o, tmp_path / "twin")
    assert e.value.path == tmp_path / "twin" / "bad.obj"


def _disc_wedges(radius: float, height: float, n: int) -> fp.Shape:
    """A disc (a cake) cut into n pie wedges, each a convex part: their union is the disc."""
    parts = []
    for k in range(n):
        a = np.linspace(2 * np.pi * k / n, 2 * np.pi * (k + 1) / n, 9)
        xy = np.vstack([[0.0, 0.0], np.column_stack([np.cos(a), np.sin(a)]) * radius])
        parts.append(np.vstack([np.column_stack([xy, np.full(len(xy), z)]) for z in (0.0, height)]))
    return fp.Shape(tuple(parts))


def test_narrowest_width_is_what_the_jaws_must_span():
    """The narrowest run of material a horizontal closing could hold between faces within the friction cone."""
    from splattwin.robot.grasp import FRICTION_CONE

    assert fp.narrowest_width(fp.box_shape([0.23, 0.22, 0.08])) == pytest.approx(0.22, abs=1e-9)  # shorter side
    assert fp.narrowest_width(L_SHAPE) == pytest.approx(0.05, abs=1e-9)                             # an arm
    # a 22 cm cake cut into 8 wedges: the wedges continue each other (each alone is narrower); a disc's
    # opposite faces within the cone are at least cos(cone) of its diameter apart
    w = fp.narrowest_width(_disc_wedges(0.11, 0.08, 8))
    assert 0.22 * math.cos(FRICTION_CONE) - 0.005 < w < 0.22 * math.cos(FRICTION_CONE) + 0.002
    # a hammer (handle and head, two parts): not its 8 cm wide head nor its 19 cm bounding box, but the head's
    # 2 cm thickness; with a 9 cm thick head, the 2.5 cm handle
    handle = _box([-0.1, -0.0125, 0.0], [0.07, 0.0125, 0.025])
    assert fp.narrowest_width(fp.Shape((handle, _box([0.07, -0.04, 0.0], [0.09, 0.04, 0.025])))) == pytest.approx(0.02)
    assert fp.narrowest_width(fp.Shape((handle, _box([0.07, -0.04, 0.0], [0.16, 0.04, 0.025])))) == pytest.approx(0.025)
    # a bottle on a 12 cm foot: its 3 cm neck, above the foot (the footprint is the foot's)
    foot = trimesh.creation.cylinder(radius=0.06, height=0.02, sections=32).vertices
    neck = trimesh.creation.cylinder(radius=0.015, height=0.1, sections=32).vertices + [0.0, 0.0, 0.06]
    assert 0.025 < fp.narrowest_width(fp.Shape((np.asarray(foot), np.asarray(neck)))) < 0.03
    assert fp.narrowest_width(fp.Shape((np.zeros((4, 3)),))) is None          # nothing solid to close on
