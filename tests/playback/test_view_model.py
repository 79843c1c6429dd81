"""The viewer's model of a twin: label colours and label files read from a twin we did not write."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.playback.view_model import TwinView, collision_parts, label_colors
from splattwin.semantics.label_render import palette
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.twin.manifest import Manifest, ObjectEntry


def _twin(tmp_path: Path, labels: np.ndarray) -> Path:
    n = len(labels)
    means = np.random.default_rng(0).uniform(-0.05, 0.05, (n, 3))
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.006),
                  opacities=np.full(n, 0.9), sh=rgb_to_sh0(np.full((n, 3), 0.5))[:, None, :])
    (tmp_path / "splat").mkdir()
    g.save_ply(tmp_path / "splat" / "point_cloud.ply")
    np.save(tmp_path / "labels.npy", labels)
    Manifest(objects=[ObjectEntry(name="box", label=1)], splats="splat/point_cloud.ply",
             labels="labels.npy").save(tmp_path)
    return tmp_path


def test_label_colors_are_the_label_maps_palette_and_refuse_huge_labels():
    labels = np.array([0, 3, 12, 3, 65535])
    np.testing.assert_array_equal(label_colors(labels), palette(65535)[labels])
    # a label read from a file must not size the palette (1.5e9 allocated 9 GB; 10**30 overflowed)
    with pytest.raises(InputError, match=r"twin\.json.*65535"):
        label_colors(np.array([70_000]), Path("twin.json"))
    with pytest.raises(InputError, match=r"twin\.json.*whole numbers"):
        label_colors(np.array([10**30]), Path("twin.json"))


@pytest.mark.parametrize("bad", [np.full(200, 1.5), np.full(200, -5), np.full(200, 70_000)],
                         ids=["float", "negative", "over-16-bit"])
def test_view_refuses_a_bad_labels_npy_naming_it(tmp_path: Path, bad: np.ndarray):
    twin = _twin(tmp_path, bad)
    with pytest.raises(InputError, match=r"labels\.npy"):
        TwinView.load(twin, meshes=False, robot=False)


def test_view_shows_good_labels(tmp_path: Path):
    twin = _twin(tmp_path, np.r_[np.zeros(100, np.int32), np.ones(100, np.int32)])
    view = TwinView.load(twin, meshes=False, robot=False)
    assert view.label_rgb is not None and len({tuple(c) for c in view.label_rgb}) == 2


def test_collision_parts_refuse_a_huge_object_label_naming_twin_json(tmp_path: Path):
    import trimesh

    trimesh.creation.box(extents=[0.05, 0.05, 0.05]).export(tmp_path / "box.obj")
    man = Manifest(objects=[ObjectEntry(name="box", label=70_000, collision_mesh="box.obj")])
    with pytest.raises(InputError, match=r"twin\.json.*'box'"):
        collision_parts(tmp_path, man)
    man.objects[0].label = 2
    assert len(collision_parts(tmp_path, man)) == 1


def test_collision_parts_draw_an_obstacle_only_box_translucent_red(tmp_path: Path):
    """audit 6b D2: the viewer's collision layer left out an unusable object's obstacle box, which every
    collision export and the robot's world have; an unusable object without a box stays out."""
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.15, 0.02]
    man = Manifest(objects=[ObjectEntry(name="yellow cube", label=3, usable=False, obstacle_only=True,
                                        T_world_obj=T.tolist(), bbox_extent=[0.036, 0.04, 0.05],
                                        problem="too few points after cleaning (41 < 50)"),
                            ObjectEntry(name="ghost", label=4, usable=False,
                                        problem="no splats of it survive, so it has no geometry at all")])
    parts = collision_parts(tmp_path, man)
    assert [p.owner for p in parts] == ["yellow cube"]
    p = parts[0]
    assert p.obstacle and p.opacity == pytest.approx(0.5) and p.color[0] > 200 > 100 > p.color[1]
    V = p.world_vertices()
    np.testing.assert_allclose(V.min(0), T[:3, 3] - [0.018, 0.02, 0.025], atol=1e-6)
    np.testing.assert_allclose(V.max(0), T[:3, 3] + [0.018, 0.02, 0.025], atol=1e-6)


def test_view_opacity_is_the_parts_own_else_the_layers(tmp_path: Path):
    """audit 7B: the viewer drew every collision part at one fixed opacity, ignoring an obstacle box's 0.5."""
    import trimesh

    from splattwin.playback.view_model import (OBSTACLE_OPACITY, OBSTACLE_RGB, VIEW_OPACITY_BACKGROUND,
                                               VIEW_OPACITY_OBJECT)

    trimesh.creation.box(extents=[0.05, 0.05, 0.05]).export(tmp_path / "box.obj")
    trimesh.creation.box(extents=[0.6, 0.6, 0.02]).export(tmp_path / "table.obj")
    man = Manifest(objects=[ObjectEntry(name="box", label=1, collision_mesh="box.obj"),
                            ObjectEntry(name="cube", label=3, usable=False, obstacle_only=True,
                                        T_world_obj=np.eye(4).tolist(), bbox_extent=[0.045, 0.045, 0.045],
                                        problem="too few points after cleaning")])
    man.background.collision_mesh = "table.obj"
    by_owner = {p.owner: p for p in collision_parts(tmp_path, man)}
    assert by_owner["cube"].view_opacity() == pytest.approx(OBSTACLE_OPACITY) and by_owner["cube"].color == OBSTACLE_RGB
    assert by_owner["box"].view_opacity() == pytest.approx(VIEW_OPACITY_OBJECT)
    assert by_owner["background"].view_opacity() == pytest.approx(VIEW_OPACITY_BACKGROUND)
    by_owner["box"].opacity = 0.25   # any part's own opacity wins
    assert by_owner["box"].view_opacity() == pytest.approx(0.25)


def test_a_track_made_on_an_earlier_state_of_the_twin_is_not_shown(tiny_twin: Path, tmp_path: Path, caplog):
    """robot/playback.npz of a run made before the twin changed (a stage command re-run into the folder): the
    viewer played it, objects starting where they no longer are; `render` refused the same run's rollout."""
    import json
    import shutil

    from splattwin import io
    from splattwin.playback.view_model import load_robot_track
    from splattwin.robot.outputs import twin_digest
    from splattwin.robot.track import RobotTrack

    twin = tmp_path / "twin"
    shutil.copytree(tiny_twin, twin)
    V = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], np.float32)
    F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.uint32)
    track = RobotTrack(names=["link"], vertices=[V], faces=[F], colors=[(200, 40, 40)], positions=np.zeros((3, 1, 3)),
                       rotations=np.tile(np.eye(3), (3, 1, 1, 1)), times=np.arange(3) * 0.1)
    track.save(twin / "robot" / "playback.npz")
    assert load_robot_track(twin) is not None                         # no results.json: shown, as before
    io.write_json(twin / "robot" / "results.json", {"twin_digest": twin_digest(twin)})
    assert load_robot_track(twin) is not None                         # made on this twin
    man = json.loads((twin / "twin.json").read_text())                # the object re-posed since
    man["objects"][0]["T_world_obj"][0][3] += 0.05
    (twin / "twin.json").write_text(json.dumps(man))
    assert load_robot_track(twin) is None
    assert "earlier state of this twin" in caplog.text
    assert TwinView.load(twin, meshes=False).track is None
