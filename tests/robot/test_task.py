from __future__ import annotations

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
