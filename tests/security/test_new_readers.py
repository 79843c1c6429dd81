"""Readers and writers added with the real-capture, export and robot work, fed crafted input: XML comments
that closed early, overlong timestamps, a record nested deeply, degenerate ground truth, tiny depth maps
and masks, a frame source that is no source, a huge robot base. Each is refused or neutralised, never an
internal error (exit 1) or an element injected into an export."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError


def test_xml_comment_text_cannot_close_the_comment():
    from splattwin.twin.xmltext import comment_text

    for evil in ("x --->\n<body name='injected'/><!--", "a-----b", "ends with -", "nul\x00 and \x1b esc"):
        c = comment_text(evil)
        assert "--" not in c and not c.endswith("-") and "\x00" not in c and "\x1b" not in c
    import xml.dom.minidom

    doc = xml.dom.minidom.parseString("<r><!-- " + comment_text("x --->\n<body name='i'/><!-- y") + " --></r>")
    assert doc.getElementsByTagName("body") == []


def test_frame_source_must_be_a_known_source():
    from splattwin.poses.twin_frame import TwinFrame

    TwinFrame(source="table_plane+depth", scaled=True).check("frame.json")
    with pytest.raises(InputError, match="source"):
        TwinFrame(source="x --->\n<worldbody/>", scaled=False).check("twin.json")


def test_overlong_all_digit_timestamps_are_no_timestamps():
    from splattwin.capture.tum import _as_time

    assert _as_time("1700000000123456789") == pytest.approx(1700000000.123456789)
    assert _as_time("9" * 400) is None and _as_time("9" * 5000) is None


def test_ground_truth_alignment_of_degenerate_centres_and_malformed_goal(tmp_path):
    from splattwin.twin.stage import _moved_region

    T = np.eye(4)
    T[:3, 3] = [1, 0, 0]
    for bad in ("abc", [1, 2], {"center": ["x", 0]}, {"center": []}, {"center": [1, 2], "size": True}):
        out = _moved_region(bad, T)   # kept for the robot stage to name, never an exception here
        assert out == bad or out["center"] == [2.0, 2.0, 0.0]
    from splattwin.poses.align import umeyama

    with pytest.raises(ValueError):   # what gt_alignment catches (objects in a line)
        umeyama(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]))


def test_video_record_nested_deeply_is_no_record(tmp_path):
    from splattwin.capture.video import _read_record

    (tmp_path / "frames.json").write_text("[" * 100000 + "]" * 100000)
    assert _read_record(tmp_path / "frames.json") is None
    (tmp_path / "frames.json").write_text(json.dumps({"stamp": None, "frames": ["frame_00000.png"]}))
    assert _read_record(tmp_path / "frames.json")["frames"] == ["frame_00000.png"]


def test_tiny_depth_maps_and_loss_masks_are_not_stretched_over_a_photo():
    from splattwin.capture.dataset import _mask_downscale, depth_needs_resize

    assert depth_needs_resize((256, 192), (1920, 1440), Path("d.png"))          # a phone's LiDAR depth: 1/7.5
    with pytest.raises(InputError, match="at most 16 times"):
        depth_needs_resize((1, 1), (640, 480), Path("d.png"))
    assert _mask_downscale((80, 60), (640, 480)) == 8
    assert _mask_downscale((1, 1), (640, 480)) is None


def test_a_robot_frame_base_far_away_is_not_taken(tmp_path):
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.robot.world import BasePose

    T = np.eye(4)
    T[:3, 3] = [1e9, 0, 0]
    base, why = BasePose.default_for(TwinFrame(source="robot", scaled=True, T_twin_input=T.tolist()))
    assert base == BasePose() and "--base-pose" in why


def test_moveit_frame_names_are_tf_frame_ids():
    from splattwin.twin.options import ExportOptions

    for ok in ("twin", "/map", "ns/base_link"):
        ExportOptions(moveit_frame=ok).check()
    for bad in ("a//b/", "a/", "1a", "x y", "a\nb: 1"):
        with pytest.raises(InputError, match="moveit_frame"):
            ExportOptions(moveit_frame=bad).check()


def test_nerfstudio_depth_check_reads_no_more_than_its_cameras_pixels(tmp_path):
    """capture info on a transforms.json whose first .npy depth claims 30000x30000: the mm-looking check
    loaded all of it (3.6 GB) on every read."""
    from splattwin import io
    from splattwin.capture import load_dataset

    io.write_image(tmp_path / "images" / "a.png", np.zeros((48, 64, 3), np.uint8))
    big = np.lib.format.open_memmap(tmp_path / "depth.npy", mode="w+", dtype=np.float32, shape=(3000, 3000))
    del big
    meta = {"fl_x": 50, "fl_y": 50, "cx": 32, "cy": 24, "w": 64, "h": 48,
            "frames": [{"file_path": "images/a.png", "depth_file_path": "depth.npy",
                        "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    import tracemalloc

    tracemalloc.start()
    try:
        load_dataset(tmp_path / "transforms.json", validate=False)
    except InputError:
        pass   # the size mismatch may be named here; what matters is that nothing big was read
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 20 * 2**20


def test_twin_text_in_export_comments_injects_nothing(scene_small, tmp_path):
    """mass_source '--->' closed the URDF/MJCF comment: MuJoCo then loaded an injected body."""
    import mujoco

    from splattwin.cli import main
    from splattwin.twin.groundtruth import twin_from_scene

    twin = tmp_path / "twin"
    twin_from_scene(scene_small, twin)
    d = json.loads((twin / "twin.json").read_text())
    for o in d["objects"]:
        o["mass_source"] = "x --->\n<worldbody><body name='injected'/></worldbody><!-- "
    (twin / "twin.json").write_text(json.dumps(d))
    assert main(["export", str(twin), "--formats", "urdf,mjcf"]) == 0
    m = mujoco.MjModel.from_xml_path(str(twin / "export" / "scene.xml"))
    assert "injected" not in [m.body(i).name for i in range(m.nbody)]
    import xml.dom.minidom

    urdf = xml.dom.minidom.parse(str(twin / "export" / "scene.urdf"))
    assert all(link.getAttribute("name") != "injected" for link in urdf.getElementsByTagName("link"))
