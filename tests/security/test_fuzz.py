"""Readers found failing by a systematic fuzz pass over a received twin folder (each of its files truncated,
randomised, given wrong JSON types, huge header counts, paths out of the folder): each case here ended in a
traceback of an internal error (CLI exit 1) before its fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _report_twin(tmp_path: Path, test_module) -> Path:
    """A twin with a manifest, eval metrics and robot results of this twin (report/test_build.py's helpers)."""
    from splattwin.robot.outputs import twin_digest

    helpers = test_module("report/test_build.py")
    twin = helpers._manifest_twin(tmp_path, scaled=True)
    helpers._robot_results(twin, twin_digest(twin))
    return twin


@pytest.mark.parametrize("rel, edit, needle", [
    # found: geometry_metrics.json {"cardboard_box": [0, 1, 2, ...]} -> TypeError in the summary's F1 figure
    ("geometry_metrics.json", lambda d: {"cake": [0, 1, 2]}, "geometry_metrics.json is malformed"),
    # found: metrics.json mean_psnr {} -> TypeError in round()
    ("splat/eval/metrics.json", lambda d: {**d, "mean_psnr": {}}, "splat/eval/metrics.json is malformed"),
    ("semantics/fusion.json", lambda d: {"miou_heldout": "x"}, "semantics/fusion.json is malformed"),
    ("robot/results.json", lambda d: {**d, "trials": {"successes": 1}}, "robot/results.json is malformed"),
    ("robot/results.json", lambda d: {**d, "nominal": []}, "robot/results.json is malformed"),
    # a record that is no JSON object at all is left out as unreadable
    ("geometry_metrics.json", lambda d: ["f1"], None),
])
def test_report_summary_of_malformed_records_notes_the_file(tmp_path, test_module, cli, rel, edit, needle):
    """The summary's figures came from the records unguarded (the sections below it are guarded): a received
    twin's record of the wrong shape failed the whole report with an internal error. Now that record's figures
    are left out with a note naming the file; the rest of the report is written."""
    twin = _report_twin(tmp_path, test_module)
    path = twin / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    before = json.loads(path.read_text()) if path.is_file() else {}
    path.write_text(json.dumps(edit(before)))
    res = cli("report", twin, "--no-video")
    assert res.rc == 0, res.err[-2000:]
    html = (twin / "report" / "index.html").read_text()
    assert "Summary" in html and "Collision geometry" in html
    if needle:
        assert needle in html


@pytest.fixture(scope="module")
def gt_twin(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("fuzz_gt_twin")
    twin_from_scene(scene_small, out)
    return out


def test_mesh_vertex_finite_but_huge_is_bad_input(gt_twin, tmp_path, cli):
    """found: a convex part's vertex `v 1e308 1e308 -1e308` (finite, so load_mesh took it) overflowed in the
    convex hull of `export` (a QhullError, internal error). Now load_mesh refuses vertices beyond
    limits.MAX_POSITION, naming the file."""
    import shutil

    from security_helpers import assert_bad_input

    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    part = twin / json.loads((twin / "twin.json").read_text())["objects"][0]["convex_parts"][0]
    lines = part.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("v "))
    lines[i] = "v 1e308 1e308 -1e308"
    part.write_text("\n".join(lines) + "\n")
    assert_bad_input(cli("export", twin), part.name, "from the origin")
    assert_bad_input(cli("plan", twin, "--no-render"), part.name, "from the origin")


def test_viewer_refuses_twin_json_and_robot_track_linked_out_of_the_twin(gt_twin, tmp_path):
    """found: the viewer's loader (and `render`) read a received twin's twin.json and robot/playback.npz
    through symbolic links to files outside the folder (the files twin.json names were already confined).
    Now each is an InputError naming the link."""
    import os
    import shutil

    import numpy as np

    from splattwin.errors import InputError
    from splattwin.playback.view_model import TwinView
    from splattwin.robot.track import RobotTrack

    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    RobotTrack(names=["g1"], vertices=[np.eye(3, dtype=np.float32)], faces=[np.array([[0, 1, 2]], np.uint32)],
               colors=[(1, 2, 3)], positions=np.zeros((4, 1, 3)), rotations=np.tile(np.eye(3), (4, 1, 1, 1)),
               times=np.arange(4.0)).save(elsewhere / "playback.npz")
    (twin / "robot").mkdir(exist_ok=True)
    os.symlink(os.path.relpath(elsewhere / "playback.npz", twin / "robot"), twin / "robot" / "playback.npz")
    with pytest.raises(InputError, match="leads outside") as e:
        TwinView.load(twin)
    assert e.value.path == twin / "robot" / "playback.npz"
    (twin / "robot" / "playback.npz").unlink()
    assert TwinView.load(twin).track is None

    (twin / "twin.json").rename(elsewhere / "twin.json")
    os.symlink(elsewhere / "twin.json", twin / "twin.json")
    with pytest.raises(InputError, match="leads outside") as e:
        TwinView.load(twin)
    assert e.value.path == twin / "twin.json"
    # a link that stays inside the folder is read as before
    (twin / "twin.json").unlink()
    (elsewhere / "twin.json").rename(twin / "kept.json")
    os.symlink("kept.json", twin / "twin.json")
    assert TwinView.load(twin).manifest.objects


def test_a_task_region_number_past_float_range_is_input_error():
    """Second fuzz pass, `plan --task`: a place_in size or centre given as a YAML integer past float range
    (size: 1000...0, 401 digits) raised OverflowError from np.asarray: an internal error. Now it is the task
    file's error, as other bad numbers are."""
    from splattwin.errors import InputError
    from splattwin.robot.task import parse_task

    where = Path("task.yaml")
    for region in ({"center": [0, 0, 0], "size": 10 ** 400}, {"center": [10 ** 400, 0, 0], "size": 0.3}):
        with pytest.raises(InputError, match=r"task\.yaml.*place_in: bad numbers"):
            parse_task([{"pick": "blue_box", "place_in": region}], where)


def test_a_task_step_with_keys_of_mixed_types_is_input_error():
    """Second fuzz pass, `plan --task`: a step `{1: blue_box, ~: cardboard_box}` (an int and a null key) failed
    sorting its unknown keys for the message (TypeError: an internal error). Now the keys are named as text."""
    from splattwin.errors import InputError
    from splattwin.robot.task import parse_task

    with pytest.raises(InputError, match=r"task\.yaml: step 1: unknown key\(s\) \['1', 'None'\]"):
        parse_task([{1: "blue_box", None: "cardboard_box"}], Path("task.yaml"))


def test_a_task_of_too_many_steps_is_refused_before_planning():
    """Second fuzz pass, `plan --task`: a task of 4000 steps (90 kB of YAML) was validated by IK and planned step
    by step, still running after 90 s (a 16 MiB task could hold 400 000). Now more than
    SPLATTWIN_MAX_TASK_STEPS (100) steps is the task file's error before anything is planned."""
    from splattwin import limits
    from splattwin.errors import InputError
    from splattwin.robot.task import parse_task

    step = {"pick": "blue_box", "place_on": "cardboard_box"}
    assert len(parse_task([step] * limits.MAX_TASK_STEPS, Path("task.yaml")).steps) == limits.MAX_TASK_STEPS
    # a pick and its place may also be two items: steps are counted, not items
    assert len(parse_task([{"pick": "blue_box"}, {"place_on": "cardboard_box"}] * limits.MAX_TASK_STEPS,
                          Path("task.yaml")).steps) == limits.MAX_TASK_STEPS
    with pytest.raises(InputError, match=r"task\.yaml: the task has more than 100 steps .*SPLATTWIN_MAX_TASK_STEPS"):
        parse_task([step] * 4000, Path("task.yaml"))


@pytest.mark.parametrize("name", ["task_view_0.mp4", "task_view_0.json"])
def test_report_task_video_where_a_folder_stands_is_noted_not_an_internal_error(tmp_path, name):
    """Second fuzz pass, `report` with its video: report/task_X.mp4 (or its key .json) received as a folder failed
    the video's final rename (IsADirectoryError: an internal error, the whole report lost). Now the playback
    section says the folder stands there, names it and the rest of the report is written; the folder is kept."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from playback.conftest import write_twin
    from playback.rollouts import synthetic_rollout

    from splattwin.report.html import Report
    from splattwin.report.options import ReportOptions
    from splattwin.report.playback import playback_section

    twin = write_twin(tmp_path / "twin")
    synthetic_rollout(0.6).save(twin / "robot" / "rollout.npz")
    (twin / "report" / name).mkdir(parents=True)
    rep = Report("t")
    playback_section(rep.section("motion"), twin, ReportOptions(video_camera="view_0", video_fps=10.0,
                                                                video_width=96))
    assert "a folder stands where the report writes its task video" in rep.to_html()
    assert name in rep.to_html() and (twin / "report" / name).is_dir()
