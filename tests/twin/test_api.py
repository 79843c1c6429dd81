"""The twin stage used from Python (audit 8A): build_twin checks its objects, and a twin built with it
gets the scene's goal region the stage would have copied in."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses.twin_frame import TwinFrame
from splattwin.twin.build import build_twin, check_objects


def test_check_objects_names_the_bad_entry():
    """A dict entry gave a bare KeyError: 1 (L3)."""
    assert check_objects([("a", 1, "an a"), ["b", np.int64(2)], {"name": "c", "label": 3}]) == [
        ("a", 1, "an a"), ("b", 2, ""), ("c", 3, "")]
    for bad, needle in (([{"name": "a"}], "needs 'name' and 'label'"), ([("a",)], "must be \\(name, label, prompt\\)"),
                        ([("a", 0, "")], "label must be a whole number >= 1"), ([("a", 1.5, "")], "whole number"),
                        ([("", 1, "")], "non-empty"), ([("a", 1, ""), ("b", 1, "")], "label 1 is used twice"),
                        ([("a", 1, ""), ("a", 2, "")], "name 'a' is used twice"), ("abc", "list of")):
        with pytest.raises(InputError, match=needle):
            check_objects(bad)


def test_build_twin_refuses_malformed_objects_before_writing(tmp_path):
    from splattwin.scene.synthetic import synthetic_scene

    g, labels, objects, _ = synthetic_scene(2000, seed=1)
    with pytest.raises(InputError, match="needs 'name' and 'label'"):
        build_twin(g, labels, [{"name": "blue_box", "label": 2}, {"label": 1}], tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()


def test_add_scene_goal_gives_a_python_twin_the_scenes_target(scene_small, tmp_path):
    """The default task's place_in target_frame was copied only by the twin stage (L5)."""
    from splattwin.io import read_json
    from splattwin.robot.task import load_task, default_task_path
    from splattwin.scene import synthetic_gaussians
    from splattwin.twin import add_scene_goal
    from splattwin.twin.manifest import Manifest

    g, labels = synthetic_gaussians(scene_small, density=6000, artefacts=False)
    scene = read_json(scene_small / "scene.json")
    objects = [(o["name"], int(o["label"]), o.get("prompt", "")) for o in scene["objects"]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        build_twin(g, labels, objects, tmp_path / "twin", TwinFrame("ground_truth", scaled=True), formats=(),
                   progress=False)
    with pytest.raises(InputError, match="add_scene_goal"):
        load_task(default_task_path(), Manifest.load(tmp_path / "twin"))
    man = add_scene_goal(tmp_path / "twin", scene_small)
    assert man.config["target_frame"]["center"] == pytest.approx(scene["target_frame"]["center"])
    assert Manifest.load(tmp_path / "twin").config["target_frame"] == man.config["target_frame"]
    load_task(default_task_path(), Manifest.load(tmp_path / "twin"))   # the default task's region is there now
    with pytest.raises(InputError, match="scene.json"):
        add_scene_goal(tmp_path / "twin", tmp_path)


def test_build_twin_takes_a_splat_path_and_refuses_other_types_before_writing(tmp_path):
    """build_twin("splats.ply", ...) failed with "'str' object has no attribute 'means'" after it had made
    the twin folder (audit 10A L18); a PLY path is read as fuse_to_dir reads it."""
    from splattwin.scene.synthetic import synthetic_scene

    g, labels, objects, _ = synthetic_scene(2000, seed=1)
    with pytest.raises(TypeError, match="gaussians must be a Gaussians or a 3DGS PLY path, got list"):
        build_twin([1, 2], labels, objects, tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()
    with pytest.raises(InputError, match="missing.ply"):
        build_twin(str(tmp_path / "missing.ply"), labels, objects, tmp_path / "t", progress=False)
    assert not (tmp_path / "t").exists()
    ply = g.save_ply(tmp_path / "splats.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        man = build_twin(str(ply), labels, objects, tmp_path / "t", formats=(), progress=False)
    assert sorted(o.name for o in man.objects) == sorted(o[0] for o in objects)
