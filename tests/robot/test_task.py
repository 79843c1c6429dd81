from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.robot.task import default_task_path, load_task, parse_task, validate_task
from splattwin.robot.world import BasePose
from splattwin.twin.manifest import Manifest


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "task.yaml"
    p.write_text(text)
    return p


def _record_reachable(monkeypatch) -> list[np.ndarray]:
    """The world positions (m) task validation asks `task.reachable` about, in order (the real answer kept)."""
    import splattwin.robot.task as task_mod

    asked: list[np.ndarray] = []
    real = task_mod.reachable
    monkeypatch.setattr(task_mod, "reachable", lambda ik, xyz, base_xy, rise=0.0: (asked.append(np.asarray(xyz)),
                                                                                    real(ik, xyz, base_xy, rise))[1])
    return asked


def test_default_task_is_the_paper_rearrangement(gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    t = load_task(None, m)
    assert default_task_path().is_file()
    assert [(s.pick, s.goal_name) for s in t.steps] == [
        ("blue_box", "cardboard_box"), ("yellow_cube", "blue_box"), ("toy_hammer", "target_frame")]
    np.testing.assert_allclose(t.steps[2].place_in.center, m.config["target_frame"]["center"])
    assert t.steps[2].place_in.size.tolist() == [0.24, 0.24]
    validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_forms_of_steps(tmp_path: Path):
    t = parse_task([{"pick": "a", "place_on": "b"}, {"pick": "c"},
                    {"place_in": {"center": [0.1, 0.2], "size": [0.1, 0.2]}}], tmp_path)
    assert t.steps[0].place_on == "b" and t.steps[1].place_in.size.tolist() == [0.1, 0.2]
    assert t.steps[1].place_in.contains_xy([0.14, 0.29]) and not t.steps[1].place_in.contains_xy([0.16, 0.2])


@pytest.mark.parametrize("text,match", [
    ("- place_on: blue_box\n", "without a pick"),
    ("- pick: blue_box\n", "holding"),
    ("- pick: blue_box\n- pick: yellow_cube\n", "still holding"),
    ("- pick: blue_box\n- put: x\n", "unknown key"),
    ("- pick: blue_box\n- place_in: {center: [0, 0]}\n", "size"),
    ("- pick: blue_box\n- place_in: nowhere\n", "no region named"),
    ("[unclosed", "YAML"),
])
def test_malformed_tasks(tmp_path: Path, gt_twin_small: Path, text, match):
    with pytest.raises(InputError, match=match) as e:
        load_task(_write(tmp_path, text), Manifest.load(gt_twin_small))
    assert e.value.path == tmp_path / "task.yaml"


def test_validation_errors_before_planning(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    base = BasePose().matrix()
    t = load_task(_write(tmp_path, "- pick: purple_unicorn\n- place_on: blue_box\n"), m)
    with pytest.raises(InputError, match="purple_unicorn"):
        validate_task(t, m, gt_twin_small, base)
    t = load_task(_write(tmp_path, "- pick: blue_box\n- place_in: {center: [0.4, 0.5, 0], size: 0.1}\n"), m)
    with pytest.raises(InputError, match="reach"):
        validate_task(t, m, gt_twin_small, base)
    t = load_task(_write(tmp_path, "- pick: blue_box\n- place_in: {center: [0.9, 0, 0], size: 0.1}\n"), m)
    with pytest.raises(InputError, match="off the table"):
        validate_task(t, m, gt_twin_small, base)
    t = load_task(None, m)
    m.frame.scaled, m.frame.source = False, "unscaled"
    with pytest.raises(InputError, match="not metrically scaled"):
        validate_task(t, m, gt_twin_small, base)


def test_unreachable_place_pose_found_by_ik_before_planning(tmp_path: Path, gt_twin_small: Path, panda):
    """A goal region 0.78 m from a base mounted 30 cm below the table passes the distance check but has
    no IK solution: a clear InputError naming the step, the goal and the task file."""
    m = Manifest.load(gt_twin_small)
    path = _write(tmp_path, "- pick: yellow_cube\n- place_in: {center: [0.28, 0.0, 0.0], size: 0.1}\n")
    t = load_task(path, m)
    low = BasePose(z=-0.3).matrix()
    validate_task(t, m, gt_twin_small, low)                       # reach distance alone lets it through
    with pytest.raises(InputError, match=r"step 1: goal region 'region'.*no IK solution") as e:
        validate_task(t, m, gt_twin_small, low, robot=panda)
    assert e.value.path == path and "yellow_cube" in str(e.value)
    validate_task(t, m, gt_twin_small, BasePose().matrix(), robot=panda)   # reachable from the default base
    validate_task(load_task(None, m), m, gt_twin_small, BasePose().matrix(), robot=panda)


def test_unreachable_pick_found_by_ik(tmp_path: Path, gt_twin_small: Path, panda):
    m = Manifest.load(gt_twin_small)
    t = load_task(None, m)
    with pytest.raises(InputError, match=r"step 1: object 'blue_box'.*no IK solution"):
        validate_task(t, m, gt_twin_small, BasePose(z=-1.0).matrix(), robot=panda)


@pytest.mark.parametrize("size", ["1e400", ".inf", "[0.1, .nan]"])
def test_region_size_must_be_finite(tmp_path: Path, gt_twin_small: Path, size):
    """An infinite region contains every place: it would make any place a success."""
    path = _write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: [0.1, 0.0], size: {size}}}\n")
    with pytest.raises(InputError, match="finite") as e:
        load_task(path, Manifest.load(gt_twin_small))
    assert e.value.path == path


def test_region_larger_than_the_table_is_refused(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    x0, x1, y0, y1 = m.background.table_extent
    base = BasePose().matrix()
    for size in ("1e6", f"{x1 - x0 + 0.01}", f"[0.1, {y1 - y0 + 0.01}]"):
        path = _write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: [0.1, 0.0], size: {size}}}\n")
        t = load_task(path, m)
        with pytest.raises(InputError, match="larger than the table") as e:
            validate_task(t, m, gt_twin_small, base)
        assert e.value.path == path
    # the whole table is still a region
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: [0.1, 0.0], "
                                   f"size: [{x1 - x0}, {y1 - y0}]}}\n"), m)
    validate_task(t, m, gt_twin_small, base)


def _renamed(gt_twin_small: Path) -> Manifest:
    """The small twin with human names that differ from their export IDs (`blue box` -> blue_box)."""
    m = Manifest.load(gt_twin_small)
    for o in m.objects:
        o.name = o.name.replace("_", " ")
    return m


def test_a_step_may_name_an_object_by_its_export_id(tmp_path: Path, gt_twin_small: Path):
    # the MJCF / URDF / MoveIt / glTF files carry only export IDs: a task copied from them names those
    m = _renamed(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: blue_box\n- place_on: cardboard box\n"), m)
    validate_task(t, m, gt_twin_small, BasePose().matrix())
    assert (t.steps[0].pick, t.steps[0].place_on) == ("blue box", "cardboard box")   # the human names


def test_an_unknown_name_near_an_export_id_gets_a_hint(tmp_path: Path, gt_twin_small: Path):
    m = _renamed(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: Blue-Box\n- place_on: cardboard box\n"), m)
    with pytest.raises(InputError, match=r"'Blue-Box', which is not in the twin .*did you mean 'blue box' "
                                         r"\(export ID blue_box\)") as e:
        validate_task(t, m, gt_twin_small, BasePose().matrix())
    assert e.value.path == tmp_path / "task.yaml"


def test_an_obstacle_only_object_cannot_be_picked_or_placed_on(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    o = m.object("yellow_cube")
    o.usable, o.obstacle_only, o.problem = False, True, "too few points after cleaning (41 < 50)"
    for text in ("- pick: yellow_cube\n- place_on: cardboard_box\n", "- pick: blue_box\n- place_on: yellow_cube\n"):
        t = load_task(_write(tmp_path, text), m)
        with pytest.raises(InputError, match=r"'yellow_cube' is not usable \(too few points.*\): it is kept as a "
                                             r"static obstacle box .* the arm avoids, and cannot be picked or placed on"):
            validate_task(t, m, gt_twin_small, BasePose().matrix())


# ---- audit 12C: what a user writes in their own task -------------------------------------------------


@pytest.mark.parametrize("text,match", [
    # an ignored key would let the run succeed without what the user asked for
    ("- pick: toy_hammer\n- place_in: {center: [0, 0], size: 0.24, yaw: 90}\n",
     r"step 1: place_in: unknown key.*yaw"),
    ("- pick: toy_hammer\n- place_in: {centre: [0, 0], center: [0, 0], size: 0.24}\n", r"unknown key.*centre"),
    ("name: t\nstep:\n  - pick: blue_box\n  - place_on: cardboard_box\n", r"unknown top-level key.*'step'"),
    ("nmae: t\nsteps:\n  - pick: blue_box\n  - place_on: cardboard_box\n", r"unknown top-level key.*'nmae'"),
    # YAML reads these as null, a bool, a list: before, the step named 'None', 'True', "['blue_box']"
    ("- pick:\n- place_on: blue_box\n", r"step 1: pick needs an object name, got nothing"),
    ("- pick: yes\n- place_on: blue_box\n", r"step 1: pick needs an object name, got bool True"),
    ("- pick: blue_box\n- place_on: [cardboard_box]\n", r"step 1: place_on needs an object name, got list"),
])
def test_a_task_says_what_it_does_not_understand(tmp_path: Path, gt_twin_small: Path, text, match):
    with pytest.raises(InputError, match=match) as e:
        load_task(_write(tmp_path, text), Manifest.load(gt_twin_small))
    assert e.value.path == tmp_path / "task.yaml"


def test_a_named_region_may_carry_more_keys(tmp_path: Path, gt_twin_small: Path):
    """The scene's target_frame has tape_width and 'for' beside centre and size: still a region."""
    m = Manifest.load(gt_twin_small)
    assert set(m.config["target_frame"]) > {"center", "size"}
    t = load_task(_write(tmp_path, "- pick: toy_hammer\n- place_in: target_frame\n"), m)
    validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_a_region_centre_z_off_the_table_is_refused(tmp_path: Path, gt_twin_small: Path):
    """Regions lie on the table: a z of 0.1 m was ignored and the cube put on the table, 'success'."""
    m = Manifest.load(gt_twin_small)
    base = BasePose().matrix()
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_in: {center: [0.0, 0.0, 0.1], size: 0.1}\n"), m)
    with pytest.raises(InputError, match=r"step 1: goal region centre z = 0.1 m, but a region lies on the table"):
        validate_task(t, m, gt_twin_small, base)
    for centre in ("[0.0, 0.0, 0.0]", "[0.0, 0.0]"):
        t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {centre}, size: 0.1}}\n"), m)
        validate_task(t, m, gt_twin_small, base)
    m.background.table_height = 0.03   # a table a few cm off z = 0: [x, y, 0.0], as the examples write it, is fine
    validate_task(load_task(_write(tmp_path, "- pick: yellow_cube\n- place_in: {center: [0.0, 0.0, 0.0], size: 0.1}\n"),
                            m), m, gt_twin_small, base)


def test_a_goal_in_millimetres_gets_a_units_hint(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: toy_hammer\n- place_in: {center: [300, 30], size: 0.2}\n"), m)
    with pytest.raises(InputError, match=r"off the table .*the task is in metres: center \[0.3, 0.03\] if you "
                                         r"meant millimetres") as e:
        validate_task(t, m, gt_twin_small, BasePose().matrix())
    assert "size" not in str(e.value).split("metres:")[-1]   # 0.2 is metres already
    t = load_task(_write(tmp_path, "- pick: toy_hammer\n- place_in: {center: [0, 0.03], size: 240}\n"), m)
    with pytest.raises(InputError, match=r"larger than the table .*size \[0.24, 0.24\] if you meant millimetres"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_footprint_fits_at_some_yaw():
    from splattwin.robot.task import footprint_fits

    assert footprint_fits(np.array([0.19, 0.08]), np.array([0.24, 0.24]))
    assert footprint_fits(np.array([0.19, 0.08]), np.array([0.09, 0.2]))        # turned a quarter
    assert footprint_fits(np.array([0.20, 0.01]), np.array([0.16, 0.16]))       # only across the diagonal
    assert not footprint_fits(np.array([0.20, 0.01]), np.array([0.12, 0.12]))
    assert not footprint_fits(np.array([0.19, 0.08]), np.array([0.01, 0.01]))


def test_a_region_the_object_cannot_fit_in_is_refused(tmp_path: Path, gt_twin_small: Path):
    """Before, a 1 cm region for the 19 cm hammer ran the whole plan, then failed: '4 of its 4 corners outside'."""
    m = Manifest.load(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: toy_hammer\n- place_in: {center: [0.0, 0.0], size: 0.01}\n"), m)
    with pytest.raises(InputError, match=r"step 1: 'toy_hammer' \(footprint 0.190 x 0.080 m\) does not fit in goal "
                                         r"region 'region' \(0.010 x 0.010 m\) at any yaw"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_an_occupied_goal_region_is_refused_until_cleared(tmp_path: Path, gt_twin_small: Path):
    """A region centred where the bottle stands: before, the plan failed with 'pre-place IK/collision: 24'."""
    m = Manifest.load(gt_twin_small)
    xy = np.round(m.object("bottle").pose[:2, 3], 3).tolist()
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {xy}, size: 0.1}}\n"), m)
    with pytest.raises(InputError, match=r"step 1: goal region 'region' is occupied: .* lies on 'bottle' \(in the "
                                         r"twin"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())
    # the bottle moved away in an earlier step frees it
    t = load_task(_write(tmp_path, f"- pick: bottle\n- place_in: {{center: [0.0, -0.05], size: 0.12}}\n"
                                   f"- pick: yellow_cube\n- place_in: {{center: {xy}, size: 0.1}}\n"), m)
    validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_an_object_under_another_cannot_be_picked(tmp_path: Path, gt_twin_small: Path):
    """Before: 'none of 16 grasp candidates on blue_box ... approach collision: 16', the cube never named."""
    m = Manifest.load(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_on: blue_box\n"
                                   "- pick: blue_box\n- place_in: {center: [-0.1, 0.0], size: 0.15}\n"), m)
    with pytest.raises(InputError, match=r"step 2: 'yellow_cube' stands on 'blue_box' \(placed there in step 1\).*"
                                         r"pick 'yellow_cube' off first"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_on: blue_box\n"
                                   "- pick: yellow_cube\n- place_in: {center: [0.0, -0.1], size: 0.1}\n"
                                   "- pick: blue_box\n- place_in: {center: [-0.1, 0.1], size: 0.15}\n"), m)
    validate_task(t, m, gt_twin_small, BasePose().matrix())


def test_a_support_that_already_carries_an_object_is_refused(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_on: cardboard_box\n"
                                   "- pick: blue_box\n- place_on: cardboard_box\n"), m)
    with pytest.raises(InputError, match=r"step 2: 'cardboard_box' already carries 'yellow_cube' \(placed there in "
                                         r"step 1\)"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())
    # the paper's stack: the cube onto the blue box that stands on the cardboard box
    validate_task(load_task(None, m), m, gt_twin_small, BasePose().matrix())


def test_a_stack_in_the_twin_is_seen(gt_twin_small: Path):
    """An object standing on another in the twin itself counts as carried by it."""
    from splattwin.robot.task import TaskScene

    m = Manifest.load(gt_twin_small)
    assert all(v is None for v in TaskScene.of(m).on.values())
    box, cube = m.object("cardboard_box"), m.object("yellow_cube")
    T = box.pose.copy()
    T[2, 3] += box.bbox_extent[2] / 2 + cube.bbox_extent[2] / 2
    cube.T_world_obj = T.tolist()
    scene = TaskScene.of(m)
    assert scene.on["yellow_cube"] == "cardboard_box" and scene.riders("cardboard_box") == ["yellow_cube"]
    assert scene.since("yellow_cube") == "in the twin"


def test_ik_checks_an_object_where_an_earlier_step_placed_it(tmp_path: Path, gt_twin_small: Path, panda,
                                                             monkeypatch):
    """Step 2 picks the cube that step 1 put on the cardboard box: its grasp is checked there (on the box's
    top), not at its twin pose on the table; and the cube's place on the moved blue box at the box's new top."""
    m = Manifest.load(gt_twin_small)
    asked = _record_reachable(monkeypatch)
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_on: cardboard_box\n"
                                   "- pick: yellow_cube\n- place_in: {center: [0.0, -0.05], size: 0.1}\n"), m)
    validate_task(t, m, gt_twin_small, BasePose().matrix(), robot=panda)
    box, cube = m.object("cardboard_box"), m.object("yellow_cube")
    box_top = box.pose[2, 3] + box.bbox_extent[2] / 2
    grasp2 = asked[2]   # step 1: grasp, place; step 2: grasp, place
    np.testing.assert_allclose(grasp2[:2], box.pose[:2, 3], atol=1e-9)
    assert grasp2[2] > box_top and abs(grasp2[2] - (box_top + cube.bbox_extent[2] - 0.0125)) < 1e-6
    asked.clear()
    validate_task(load_task(None, m), m, gt_twin_small, BasePose().matrix(), robot=panda)
    blue = m.object("blue_box")
    place2 = asked[3]   # the cube's place: on the blue box where step 1 left it, on the cardboard box
    np.testing.assert_allclose(place2[:2], box.pose[:2, 3], atol=1e-9)
    assert place2[2] > box_top + blue.bbox_extent[2]


def test_place_on_the_table_says_how_to_put_it_there(tmp_path: Path, gt_twin_small: Path):
    m = Manifest.load(gt_twin_small)
    t = load_task(_write(tmp_path, "- pick: yellow_cube\n- place_on: Table\n"), m)
    with pytest.raises(InputError, match=r"step 1: place_on names 'Table', which is not in the twin .*to put an object "
                                         r"on the table, give a region there: place_in: \{center: \[x, y\], size: s\}"):
        validate_task(t, m, gt_twin_small, BasePose().matrix())


# ---- footprints: the objects' collision meshes, not their bounding boxes -------------------------------


def _reshaped(gt_twin_small: Path, tmp_path: Path, parts: list, extent: list, z: float | None = None) -> Path:
    """A copy of the small twin whose cardboard box is made of the boxes `parts` ([lo, hi] corners, object
    frame, m) with bounding box `extent`; its centre at height z when given (the box stands at its place)."""
    import shutil

    import trimesh

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    m = Manifest.load(twin)
    box = m.object("cardboard_box")
    rels = []
    for k, (lo, hi) in enumerate(parts):
        rel = f"objects/cardboard_box/parts/shaped_{k}.obj"
        trimesh.creation.box(bounds=[lo, hi]).export(twin / rel)
        rels.append(rel)
    T = box.pose
    if z is not None:
        T[2, 3] = z
    box.convex_parts, box.bbox_extent, box.T_world_obj = rels, list(extent), T.tolist()
    m.save(twin)
    return twin


# the cardboard box's 20 x 15 cm bounding box as an L: a 5 cm arm along x at -y and one along y at -x
L_ARMS = [([-0.1, -0.075, -0.05], [0.1, -0.025, 0.05]), ([-0.1, -0.025, -0.05], [-0.05, 0.075, 0.05])]


def _at(m: Manifest, name: str, x: float, y: float) -> list[float]:
    """The twin-frame [x, y] of the point (x, y) of an object's frame."""
    return np.round((m.object(name).pose @ [x, y, 0.0, 1.0])[:2], 4).tolist()


def test_a_goal_in_the_notch_of_an_l_is_free(tmp_path: Path, gt_twin_small: Path, caplog):
    """Before, a goal centre anywhere in an object's bounding box was refused ('occupied'): the free notch of
    an L-shaped object too. Now its collision mesh's footprint counts; a goal on an arm is still refused."""
    import logging

    twin = _reshaped(gt_twin_small, tmp_path, L_ARMS, [0.2, 0.15, 0.1])
    m = Manifest.load(twin)
    base = BasePose().matrix()
    notch = _at(m, "cardboard_box", 0.04, 0.035)      # 6 cm from one arm, 9 cm from the other
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {notch}, size: 0.1}}\n"), m)
    with caplog.at_level(logging.WARNING, logger="splattwin.robot.task"):
        validate_task(t, m, twin, base)
    assert not caplog.records
    arm = _at(m, "cardboard_box", 0.05, -0.05)
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {arm}, size: 0.1}}\n"), m)
    with pytest.raises(InputError, match=r"step 1: goal region 'region' is occupied: .* lies on 'cardboard_box'"):
        validate_task(t, m, twin, base)
    # 1 cm from the arm the 2.5 cm cube (1.25 cm inradius) reaches into it whatever its yaw: a warning
    near = _at(m, "cardboard_box", 0.04, -0.015)
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {near}, size: 0.1}}\n"), m)
    with caplog.at_level(logging.WARNING, logger="splattwin.robot.task"):
        validate_task(t, m, twin, base)
    assert [r.getMessage() for r in caplog.records] == [
        "step 1: 'yellow_cube' placed at the centre of goal region 'region' reaches 0.2 cm into the footprint of "
        "'cardboard_box' at every yaw (1.0 cm from the centre): the place may collide with it"]


def test_a_goal_beside_the_hammers_handle_is_free(tmp_path: Path, gt_twin_small: Path):
    """The hammer's bounding box (19 x 8 cm) holds a 2.7 cm strip either side of its 2.5 cm handle: before,
    a goal there was refused. Its head and handle (two convex parts) leave it free; on the handle, refused."""
    m = Manifest.load(gt_twin_small)
    base = BasePose().matrix()
    beside = _at(m, "toy_hammer", -0.05, 0.03)
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {beside}, size: 0.1}}\n"), m)
    validate_task(t, m, gt_twin_small, base)
    on = _at(m, "toy_hammer", -0.05, 0.0)
    t = load_task(_write(tmp_path, f"- pick: yellow_cube\n- place_in: {{center: {on}, size: 0.1}}\n"), m)
    with pytest.raises(InputError, match=r"lies on 'toy_hammer'"):
        validate_task(t, m, gt_twin_small, base)


def test_a_tall_object_beside_a_thin_one_does_not_stand_on_it(tmp_path: Path, gt_twin_small: Path):
    """A 1.5 cm thin L on the table and the bottle in its notch: the bottle's centre is in the L's bounding box
    and its bottom within 2 cm of the L's top, so before it 'stood on' the L (the L could not be picked: 'bottle
    stands on cardboard_box'). Its centre is over no part of the L: it stands on the table."""
    from splattwin.robot.task import TaskScene

    thin = [([lo[0], lo[1], -0.0075], [hi[0], hi[1], 0.0075]) for lo, hi in L_ARMS]
    twin = _reshaped(gt_twin_small, tmp_path, thin, [0.2, 0.15, 0.015], z=0.0075)
    m = Manifest.load(twin)
    bottle, cube = m.object("bottle"), m.object("yellow_cube")
    T = bottle.pose
    T[:2, 3] = _at(m, "cardboard_box", 0.04, 0.035)      # 3.5 cm radius: 2.5 cm clear of either arm
    bottle.T_world_obj = T.tolist()
    assert T[2, 3] - bottle.bbox_extent[2] / 2 == pytest.approx(0.0, abs=1e-6)   # on the table
    t = load_task(_write(tmp_path, "- pick: cardboard_box\n- place_in: {center: [-0.02, 0.03], size: 0.25}\n"), m)
    validate_task(t, m, twin, BasePose().matrix())
    scene = TaskScene.of(m, twin)
    assert scene.on["bottle"] is None and scene.riders("cardboard_box") == []
    # the cube on an arm does stand on it
    C = cube.pose
    C[:2, 3] = _at(m, "cardboard_box", 0.05, -0.05)
    C[2, 3] = 0.015 + cube.bbox_extent[2] / 2
    cube.T_world_obj = C.tolist()
    assert TaskScene.of(m, twin).riders("cardboard_box") == ["yellow_cube"]


def test_an_object_on_the_lower_step_of_a_support_stands_on_it(tmp_path: Path, gt_twin_small: Path):
    """A box 10 cm high at -x and 4 cm at +x, the cube on the low step: before, its bottom was compared with
    the top of the bounding box (6 cm above it) and the stack missed, so picking the box was let through."""
    from splattwin.robot.task import TaskScene

    steps = [([-0.1, -0.075, -0.05], [0.0, 0.075, 0.05]), ([0.0, -0.075, -0.05], [0.1, 0.075, -0.01])]
    twin = _reshaped(gt_twin_small, tmp_path, steps, [0.2, 0.15, 0.1])
    m = Manifest.load(twin)
    cube = m.object("yellow_cube")
    C = cube.pose
    C[:2, 3] = _at(m, "cardboard_box", 0.05, 0.0)
    C[2, 3] = 0.04 + cube.bbox_extent[2] / 2
    cube.T_world_obj = C.tolist()
    t = load_task(_write(tmp_path, "- pick: cardboard_box\n- place_in: {center: [-0.02, 0.03], size: 0.25}\n"), m)
    with pytest.raises(InputError, match=r"step 1: 'yellow_cube' stands on 'cardboard_box' \(in the twin\)"):
        validate_task(t, m, twin, BasePose().matrix())
    assert TaskScene.of(m, twin).on["yellow_cube"] == "cardboard_box"


def test_a_place_on_a_tray_is_checked_where_the_box_rests_on_it(tmp_path: Path, gt_twin_small: Path, panda,
                                                                monkeypatch):
    """The cardboard box as a 2 cm tray with a 10 cm post in a corner (bounding box 20 x 15 x 10 cm): the blue
    box placed on it rests on the tray (as the planner releases it, `selection.release_height`), not on its
    bounding-box top. Before, the scene put it 8 cm higher, so the place pose and the next step's grasp of it
    were IK-checked 8 cm above where they are."""
    from splattwin.robot.task import TaskScene

    tray = [([-0.1, -0.075, -0.05], [0.1, 0.075, -0.03]), ([0.08, 0.055, -0.05], [0.1, 0.075, 0.05])]
    twin = _reshaped(gt_twin_small, tmp_path, tray, [0.2, 0.15, 0.1])
    m = Manifest.load(twin)
    asked = _record_reachable(monkeypatch)
    t = load_task(_write(tmp_path, "- pick: blue_box\n- place_on: cardboard_box\n"
                                   "- pick: blue_box\n- place_in: {center: [0.0, 0.05], size: 0.15}\n"), m)
    validate_task(t, m, twin, BasePose().matrix(), robot=panda)
    box, blue = m.object("cardboard_box"), m.object("blue_box")
    tray_top = box.pose[2, 3] - 0.03                     # 2 cm above the table
    h = blue.bbox_extent[2]
    place1, grasp2 = asked[1], asked[2]                  # step 1: grasp, place; step 2: grasp, place
    np.testing.assert_allclose(place1[:2], box.pose[:2, 3], atol=1e-9)
    assert place1[2] == pytest.approx(tray_top + h - 0.02)           # the TCP 2 cm below the placed box's top
    assert grasp2[2] == pytest.approx(tray_top + h - 0.02)
    scene = TaskScene.of(m, twin)
    scene.place(t.steps[0], 1, 0.0)
    assert scene.poses["blue_box"][2, 3] == pytest.approx(tray_top + h / 2)
    assert scene.on["blue_box"] == "cardboard_box"


def test_the_default_task_on_a_twin_without_its_objects_says_to_write_a_task(tmp_path: Path, gt_twin_small: Path):
    """`splattwin plan` (no --task: the default task) on a user's twin of a cake said "step 3: place_in: the twin
    defines no region named 'target_frame' ... splattwin.twin.add_scene_goal(twin_dir, scene_dir)": nothing said
    that the default task is the demo scene's, nor to write one for the twin's own objects."""
    from splattwin.twin.manifest import ObjectEntry

    cake = Manifest(objects=[ObjectEntry("cake", 1)])
    for path in (None, default_task_path()):
        with pytest.raises(InputError, match="the default task is the embedded demo scene's") as e:
            load_task(path, cake)
        msg = str(e.value)
        assert "blue_box" in msg and "target_frame" in msg and "objects: cake" in msg and "--task FILE" in msg
    no_frame = Manifest.load(gt_twin_small)
    no_frame.config.pop("target_frame")
    with pytest.raises(InputError, match="lacks what it names: target_frame \\("):
        load_task(None, no_frame)
    # a task file of the user's own keeps its step-by-step messages
    with pytest.raises(InputError, match="step 1: place_in: the twin defines no region named 'target_frame'"):
        load_task(_write(tmp_path, "- pick: cake\n- place_in: target_frame\n"), cake)


def _widened(gt_twin_small: Path, tmp_path: Path, name: str, xy_scale: float) -> Path:
    """A copy of the small twin whose object `name` has its collision mesh and convex parts scaled by xy_scale
    in x and y (object frame, about its origin): a wide cake where a small object was."""
    import shutil

    import trimesh

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    m = Manifest.load(twin)
    o = m.object(name)
    S = np.diag([xy_scale, xy_scale, 1.0, 1.0])
    for rel in {*o.convex_parts, o.collision_mesh}:
        mesh = trimesh.load(twin / rel, force="mesh", process=False)
        mesh.apply_transform(S)
        mesh.export(twin / rel)
    o.bbox_extent = [o.bbox_extent[0] * xy_scale, o.bbox_extent[1] * xy_scale, o.bbox_extent[2]]
    m.save(twin)
    return twin


def test_an_object_wider_than_the_gripper_is_refused_before_planning(tmp_path: Path, gt_twin_small: Path, panda,
                                                                     capsys):
    """A metric twin of a 23 x 22 cm cake was planned and failed in physics ('not lifted (rose -0.0 cm)'): the
    8 cm gripper cannot close on it. Now validation refuses it, naming its narrowest width and the opening."""
    from splattwin.cli import main

    ext = Manifest.load(gt_twin_small).object("yellow_cube").bbox_extent
    twin = _widened(gt_twin_small, tmp_path, "yellow_cube", 0.22 / ext[0])
    m = Manifest.load(twin)
    task = _write(tmp_path, "- pick: blue_box\n- place_in: {center: [0.1, -0.05], size: 0.1}\n"
                            "- pick: yellow_cube\n- place_in: {center: [0.1, 0.1], size: 0.3}\n")
    msg = ("step 2: object 'yellow_cube' is too wide for the gripper: its narrowest width is 22.0 cm (the gripper "
           "opens 8.0 cm)")
    with pytest.raises(InputError, match=re.escape(msg)):
        validate_task(load_task(task, m), m, twin, BasePose().matrix(), robot=panda)
    with pytest.raises(InputError, match=re.escape(msg)):        # without a robot model: the Panda's opening
        validate_task(load_task(task, m), m, twin, BasePose().matrix())
    assert main(["plan", str(twin), "--task", str(task), "--out", str(tmp_path / "o"), "--no-render",
                 "--no-report"]) == 2
    assert msg in capsys.readouterr().err
    # the small twin's own objects pass (the hammer: its head and handle, not its 19 cm length)
    t = _write(tmp_path, "- pick: toy_hammer\n- place_in: {center: [0.1, -0.05], size: 0.25}\n")
    validate_task(load_task(t, Manifest.load(gt_twin_small)), Manifest.load(gt_twin_small), gt_twin_small,
                  BasePose().matrix(), robot=panda)
