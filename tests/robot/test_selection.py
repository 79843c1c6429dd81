"""Grasp and place-pose selection on hand-made beliefs (no MuJoCo)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from splattwin.robot import footprint as fp
from splattwin.robot.selection import PLACE_CLEARANCE, GraspSelector, place_targets, support_height
from splattwin.robot.task import Region, Step
from splattwin.transforms import pose_xyz_yaw, yaw_of
from splattwin.twin.manifest import Background, Manifest, ObjectEntry


def _manifest(table: float = 0.0) -> Manifest:
    return Manifest(objects=[ObjectEntry(name="crate", label=1, bbox_extent=[0.20, 0.20, 0.10]),
                             ObjectEntry(name="box", label=2, bbox_extent=[0.08, 0.06, 0.05],
                                         collision_mesh="box.obj")],
                    background=Background(table_height=table))


def test_support_height_is_the_table_or_the_object_below():
    man = _manifest(table=0.01)
    crate = pose_xyz_yaw(0.3, 0.0, 0.06, 0.0)                      # top at 0.11
    on_table = {"crate": crate, "box": pose_xyz_yaw(0.0, 0.3, 0.035, 0.0)}
    assert support_height("box", on_table, man) == pytest.approx(0.01)
    stacked = {"crate": crate, "box": pose_xyz_yaw(0.35, 0.05, 0.136, 0.0)}   # over the crate's top face
    assert support_height("box", stacked, man) == pytest.approx(0.11)
    beside = {"crate": crate, "box": pose_xyz_yaw(0.45, 0.0, 0.136, 0.0)}    # centre off the crate's footprint
    assert support_height("box", beside, man) == pytest.approx(0.01)
    # the crate under the box rests on the table (the box's top is above the crate's centre anyway)
    assert support_height("crate", stacked, man) == pytest.approx(0.01)


def _box(lo, hi) -> np.ndarray:
    return np.asarray(trimesh.creation.box(bounds=[lo, hi]).vertices, float)


# a thin L (1.5 cm high) in its object frame, as in test_footprint: a 20 x 5 cm arm along x, a 5 x 10 cm arm up y
# at its -x end; its free notch x in [-0.05, 0.1], y in [-0.025, 0.075] lies inside its 20 x 15 cm bounding box
L_PARTS = ([[-0.1, -0.075, -0.0075], [0.1, -0.025, 0.0075]], [[-0.1, -0.025, -0.0075], [-0.05, 0.075, 0.0075]])
L_SHAPE = fp.Shape(tuple(_box(*b) for b in L_PARTS))


def _l_manifest() -> Manifest:
    return Manifest(objects=[ObjectEntry(name="ell", label=1, bbox_extent=[0.20, 0.15, 0.015]),
                             ObjectEntry(name="tall", label=2, bbox_extent=[0.04, 0.04, 0.10],
                                         collision_mesh="tall.obj")],
                    background=Background(table_height=0.0))


def test_support_height_follows_the_mesh_not_the_bounding_box():
    """A 10 cm tall box standing in the notch of a 1.5 cm thin L stands on the table (before: on the L, its
    centre being inside the L's bounding box and above its top); on the L's arm it stands on the L."""
    man = _l_manifest()
    shapes = {"ell": L_SHAPE, "tall": fp.box_shape(man.object("tall").bbox_extent)}.__getitem__
    T_l = pose_xyz_yaw(0.3, -0.1, 0.0075, math.pi / 4)

    def at(x, y, z):
        return pose_xyz_yaw(*(T_l @ [x, y, 0.0, 1.0])[:2], z, 0.3)

    in_notch = {"ell": T_l, "tall": at(0.04, 0.035, 0.05)}
    assert support_height("tall", in_notch, man, shapes) == 0.0
    on_arm = {"ell": T_l, "tall": at(0.05, -0.05, 0.065)}
    assert support_height("tall", on_arm, man, shapes) == pytest.approx(0.015)
    on_arm["tall"][2, 3] = 0.062             # sunk 3 mm into the L (a reconstructed pose): still on it
    assert support_height("tall", on_arm, man, shapes) == pytest.approx(0.015)
    assert support_height("ell", on_arm, man, shapes) == 0.0


def test_grasp_selector_keeps_the_fingertips_above_the_mesh_under_the_object(tmp_path: Path, monkeypatch):
    """The selector reads the twin's convex parts: in the L's notch the fingertips may go down to the table
    (before: kept 1.5 cm higher, above the L's bounding-box top, throwing low grasps away)."""
    from splattwin.robot import grasp as grasp_mod

    for k, b in enumerate(L_PARTS):
        trimesh.creation.box(bounds=b).export(tmp_path / f"ell_{k}.obj")
    trimesh.creation.box(extents=(0.04, 0.04, 0.10)).export(tmp_path / "tall.obj")
    man = _l_manifest()
    man.objects[0].convex_parts = ["ell_0.obj", "ell_1.obj"]
    floors = []
    real = grasp_mod.synthesize
    monkeypatch.setattr(grasp_mod, "synthesize", lambda *a, **k: floors.append(k["floor"]) or real(*a, **k))
    sel = GraspSelector(man, tmp_path, pose_xyz_yaw(-0.5, 0.0, 0.0, 0.0), max_opening=0.08, tip_depth=0.009,
                        floor_clearance=0.0065)
    T_l = pose_xyz_yaw(0.3, 0.0, 0.0075, 0.0)
    assert sel.ranked("tall", {"ell": T_l, "tall": pose_xyz_yaw(0.34, 0.035, 0.05, 0.0)})
    assert floors == [pytest.approx(-0.05)]          # the table, 5 cm below the centre (before: the L's 1.5 cm top)
    assert sel.ranked("tall", {"ell": T_l, "tall": pose_xyz_yaw(0.35, -0.05, 0.07, 0.0)})
    assert floors[1:] == [pytest.approx(-0.055)]     # on the L's arm: its top, 5.5 cm below the centre


def test_place_targets_on_an_object_align_with_it_nearest_yaw_first():
    man = _manifest()
    crate = pose_xyz_yaw(0.3, 0.1, 0.05, 0.3)
    belief = {"crate": crate, "box": pose_xyz_yaw(0.0, 0.3, 0.025, 1.6)}
    targets = place_targets(Step("box", place_on="crate"), "box", belief, man)
    assert len(targets) == 4
    for T in targets:
        np.testing.assert_allclose(T[:2, 3], [0.3, 0.1])
        assert T[2, 3] == pytest.approx(0.10 + 0.025 + PLACE_CLEARANCE)   # crate top + half the box + release gap
        assert T[2, 2] == pytest.approx(1.0)
        assert math.cos(4 * (yaw_of(T) - 0.3)) == pytest.approx(1.0)       # crate yaw + k * 90 deg
    # best first: the yaw closest to the box's current yaw (1.6 rad -> 0.3 + pi/2)
    assert yaw_of(targets[0]) == pytest.approx(0.3 + math.pi / 2)


def test_place_targets_on_an_object_release_above_its_mesh_under_the_footprint():
    """On a 2 cm tray with a 10 cm post in a corner (bounding box 20 x 20 x 10 cm) an 8 x 6 x 5 cm box at the
    centre is released 4 mm above the tray, not above the post's height (an 8 cm drop before); on a wedge
    rising along x the height depends on the yaw (the box's footprint reaches further up the slope when its
    long side lies along x); on a box-shaped mesh it is the bounding-box top as before; on the thin L whose
    centre lies in its notch, no mesh is under the box there: the L's bounding-box top."""
    man = Manifest(objects=[ObjectEntry(name="tray", label=1, bbox_extent=[0.20, 0.20, 0.10]),
                            ObjectEntry(name="box", label=2, bbox_extent=[0.08, 0.06, 0.05])],
                   background=Background(table_height=0.0))
    box = fp.box_shape([0.08, 0.06, 0.05])
    belief = {"tray": pose_xyz_yaw(0.4, 0.1, 0.05, 0.2), "box": pose_xyz_yaw(0.3, -0.2, 0.025, 0.2)}
    tray = fp.Shape((_box([-0.1, -0.1, -0.05], [0.1, 0.1, -0.03]), _box([0.08, 0.08, -0.05], [0.1, 0.1, 0.05])))
    step = Step("box", place_on="tray")
    targets = place_targets(step, "box", belief, man, {"tray": tray, "box": box}.__getitem__)
    assert [T[2, 3] for T in targets] == pytest.approx([0.02 + 0.025 + PLACE_CLEARANCE] * 4)
    before = place_targets(step, "box", belief, man)     # bounding boxes: the post's height
    assert [T[2, 3] for T in before] == pytest.approx([0.10 + 0.025 + PLACE_CLEARANCE] * 4)
    for T, T0 in zip(targets, before):                   # same place, yaws and order
        np.testing.assert_array_equal(T[:3, :3], T0[:3, :3])
        np.testing.assert_array_equal(T[:2, 3], T0[:2, 3])
    wedge = fp.Shape((np.array([[-0.1, -0.1, -0.05], [0.1, -0.1, -0.05], [0.1, -0.1, 0.05],
                                [-0.1, 0.1, -0.05], [0.1, 0.1, -0.05], [0.1, 0.1, 0.05]], float),))
    belief["tray"] = pose_xyz_yaw(0.4, 0.1, 0.05, 0.0)
    targets = place_targets(step, "box", belief, man, {"tray": wedge, "box": box}.__getitem__)
    along_x = [T[2, 3] for T in targets if abs(math.cos(yaw_of(T))) > 0.5]    # reaches 4 cm up the slope: 7 cm
    along_y = [T[2, 3] for T in targets if abs(math.cos(yaw_of(T))) < 0.5]    # 3 cm: 6.5 cm
    assert along_x == pytest.approx([0.07 + 0.025 + PLACE_CLEARANCE] * 2)
    assert along_y == pytest.approx([0.065 + 0.025 + PLACE_CLEARANCE] * 2)
    mesh_box = fp.Shape((_box([-0.1, -0.1, -0.05], [0.1, 0.1, 0.05]),))
    targets = place_targets(step, "box", belief, man, {"tray": mesh_box, "box": box}.__getitem__)
    assert [T[2, 3] for T in targets] == [T[2, 3] for T in place_targets(step, "box", belief, man)]
    man = _l_manifest()
    belief = {"ell": pose_xyz_yaw(0.3, 0.0, 0.0075, 0.0), "tall": pose_xyz_yaw(0.5, 0.2, 0.05, 0.0)}
    targets = place_targets(Step("tall", place_on="ell"), "tall", belief, man,
                            {"ell": L_SHAPE, "tall": fp.box_shape([0.04, 0.04, 0.10])}.__getitem__)
    assert [T[2, 3] for T in targets] == pytest.approx([0.015 + 0.05 + PLACE_CLEARANCE] * 4)


def test_place_targets_in_a_region_keep_only_fitting_yaws():
    man = _manifest(table=0.02)
    belief = {"crate": pose_xyz_yaw(0.5, 0.0, 0.07, 0.0), "box": pose_xyz_yaw(0.0, 0.3, 0.045, 0.0)}
    # 0.11 x 0.09 region: the 8 x 6 cm box fits only axis-aligned (its diagonal orientations are 9.9 cm wide)
    reg = Region(center=np.array([0.1, -0.1, 0.0]), size=np.array([0.11, 0.09]))
    targets = place_targets(Step("box", place_in=reg), "box", belief, man)
    yaws = sorted(round(math.degrees(yaw_of(T)) % 360) for T in targets)
    assert yaws == [0, 180]
    assert all(T[2, 3] == pytest.approx(0.02 + 0.025 + PLACE_CLEARANCE) for T in targets)
    assert yaw_of(targets[0]) == pytest.approx(0.0)
    # a region nothing fits in still gives every yaw (the planner then reports the failed placement)
    tiny = Region(center=np.array([0.1, -0.1, 0.0]), size=np.array([0.05, 0.05]))
    assert len(place_targets(Step("box", place_in=tiny), "box", belief, man)) == 8


def test_grasp_selector_follows_the_support_and_caches(tmp_path: Path, monkeypatch):
    """Candidates are synthesised once per (object, support height); a box sunk 3 mm into the table keeps
    its fingertips above the table, not above the sunken mesh bottom; ranking prefers a wrist that points
    away from the base."""
    from splattwin.robot import grasp as grasp_mod

    trimesh.creation.box(extents=(0.08, 0.06, 0.05)).export(tmp_path / "box.obj")
    man = _manifest()
    calls = []
    real = grasp_mod.synthesize
    monkeypatch.setattr(grasp_mod, "synthesize", lambda *a, **k: calls.append(k["floor"]) or real(*a, **k))
    sel = GraspSelector(man, tmp_path, pose_xyz_yaw(-0.5, 0.0, 0.0, 0.0), max_opening=0.08, tip_depth=0.009,
                        floor_clearance=0.0065)
    # yawed by 90 deg: the 6 cm side (the only one that fits the gripper) lies along the radial x axis
    sunk = {"crate": pose_xyz_yaw(0.5, 0.4, 0.05, 0.0), "box": pose_xyz_yaw(0.2, 0.0, 0.022, math.pi / 2)}
    ranked = sel.ranked("box", sunk)
    assert calls == [pytest.approx(-0.022)]          # the table (z = 0) in the box frame, not the mesh bottom
    assert ranked and ranked == sel.ranked("box", sunk) and len(calls) == 1
    top = [g for g in ranked if g.kind == "top"]
    assert top
    for g in top:   # fingertips (9 mm beyond the TCP) stay 6.5 mm above the table
        z_tcp_world = 0.022 + g.T_obj_tcp[2, 3]
        assert z_tcp_world - 0.009 >= 0.0065 - 1e-9
    # best first: the closing axis (TCP y) points radially away from the base, as the Panda's home wrist
    assert (sunk["box"] @ top[0].T_obj_tcp)[0, 1] == pytest.approx(1.0, abs=1e-6)
    assert any((sunk["box"] @ g.T_obj_tcp)[0, 1] == pytest.approx(-1.0, abs=1e-6) for g in top[1:])
    sel.ranked("box", {**sunk, "box": pose_xyz_yaw(0.2, 0.0, 0.025, 0.0)})
    assert len(calls) == 2                           # another support height: synthesised again


@pytest.mark.parametrize("content,name", [
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n", "box.ply"),
    (b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
     b"element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 9\n"
     b"3 0 1 3\n", "box.ply"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "box.obj"),
    (b"", "box.obj")], ids=["ply-header-claims-1e12", "ascii-ply-bad-index", "flat", "empty-obj"])
def test_grasp_selector_refuses_a_bad_collision_mesh_naming_it(tmp_path: Path, content: bytes, name: str):
    """A received twin's collision mesh goes through the checked loader (meshio.load_mesh): an InputError
    naming the file, not trimesh's ValueError / IndexError."""
    from splattwin.errors import InputError

    (tmp_path / name).write_bytes(content)
    man = _manifest()
    man.objects[1].collision_mesh = name
    sel = GraspSelector(man, tmp_path, pose_xyz_yaw(-0.5, 0.0, 0.0, 0.0), max_opening=0.08, tip_depth=0.009,
                        floor_clearance=0.0065)
    with pytest.raises(InputError, match=name.replace(".", r"\.")):
        sel.ranked("box", {"crate": pose_xyz_yaw(0.5, 0.4, 0.05, 0.0), "box": pose_xyz_yaw(0.2, 0.0, 0.025, 0.0)})
