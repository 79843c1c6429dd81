"""TUM-style pose lists + intrinsics: parsing, quaternion order, id and timestamp matching, depth units,
malformed input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import Camera, load_dataset, load_depth, look_at, tum
from splattwin.cli import main
from splattwin.errors import InputError

W, H = 40, 30
INTR = "fx: 35.0\nfy: 36.0\ncx: 19.5\ncy: 15.25\nwidth: 40\nheight: 30\n"


def _poses(n: int) -> list[np.ndarray]:
    return [look_at(np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.3]), np.zeros(3))
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def _images(folder: Path, stems: list[str]) -> None:
    rng = np.random.default_rng(0)
    for s in stems:
        io.write_image(folder / f"{s}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))


def test_pose_list_quaternion_order_and_comments(tmp_path):
    # 90 degrees about z: qx qy qz qw = 0 0 sin45 cos45; commas and comments allowed
    s = math.sqrt(0.5)
    (tmp_path / "poses.txt").write_text(f"# id tx ty tz qx qy qz qw\n\n7, 1.0, 2.0, 3.0, 0, 0, {s}, {s}\n"
                                        f"  # indented comment\n8 0 0 0 0 0 0 1\n")
    poses = tum.read_pose_list(tmp_path / "poses.txt")
    assert [k for k, _ in poses] == ["7", "8"]
    T = poses[0][1]
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    # round trip through the writer
    tum.write_pose_list(tmp_path / "back.txt", poses)
    back = tum.read_pose_list(tmp_path / "back.txt")
    for (ka, a), (kb, b) in zip(poses, back):
        assert ka == kb
        np.testing.assert_allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("line, msg", [
    ("1 0 0 0 0 0 0", "line 2: expected 8 fields"),
    ("1 0 0 x 0 0 0 1", "line 2: tx ty tz qx qy qz qw must be numbers"),
    ("1 0 0 nan 0 0 0 1", "line 2: pose holds a non-finite"),
    ("1 0 0 0 0 0 0 2", "line 2: quaternion .* norm 2.0000"),
    ("0 0 0 0 0 0 0 1", "'0' appears twice"),
    # a finite but huge translation (1e308) hung `poses` in an SVD of the table plane fit
    ("1 1e308 0 0 0 0 0 1", r"line 2: translation 1e308 0 0 is more than 1e\+09 m from the origin"),
    ("1 0 -2e9 0 0 0 0 1", "line 2: translation .* more than"),
])
def test_pose_list_malformed_names_file_and_line(tmp_path, line, msg):
    (tmp_path / "poses.txt").write_text(f"0 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(InputError, match=msg) as e:
        tum.read_pose_list(tmp_path / "poses.txt")
    assert e.value.path == tmp_path / "poses.txt"


def test_ids_match_image_names_with_leading_zeros(tmp_path):
    _images(tmp_path / "images", [f"{i:06d}" for i in range(4)])
    tum.write_pose_list(tmp_path / "poses.txt", [(str(i), T) for i, T in enumerate(_poses(4))][::-1])
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    ds = load_dataset(tmp_path)
    assert ds.meta["format"] == "tum" and ds.meta["matched_by"] == "id" and ds.has_poses
    for i, f in enumerate(ds.frames):
        assert f.name == f"{i:06d}"
        np.testing.assert_allclose(f.camera.T_world_cam, _poses(4)[i], atol=1e-12)
        # the file's principal point is OpenCV's (integer pixel centres), ours is +0.5
        np.testing.assert_allclose(f.camera.K, [[35, 0, 20.0], [0, 36, 15.75], [0, 0, 1]])
    assert ds.depth_scale is None and all(f.depth_path is None for f in ds.frames)


def _moving(t: float, t0: float = 1305031102.0) -> np.ndarray:
    """A camera turning about z at 2 rad/s while moving 0.5 m/s along x: SLERP + lerp between any two of its
    poses gives the pose in between exactly."""
    a = 2.0 * (t - t0)
    T = look_at(np.array([0.5, 0.0, 0.3]), np.zeros(3))
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    T[:3, :3] = Rz @ T[:3, :3]
    T[:3, 3] = [0.5 * (t - t0), 0.0, 0.3]
    return T


def test_tum_rgbd_timestamps_interpolated_within_tolerance_and_depth_5000(tmp_path, caplog):
    t_img = [1305031102.175304, 1305031102.211214, 1305031102.243211, 1305031102.275326, 1305031109.0]
    stems = [f"{t:.6f}" for t in t_img]
    _images(tmp_path / "rgb", stems)
    raw = np.arange(H * W, dtype=np.uint16).reshape(H, W) * 7
    for t in t_img:
        io.write_image(tmp_path / "depth" / f"{t + 0.004:.6f}.png", raw)
    (tmp_path / "rgb.txt").write_text("# color images\n" + "".join(f"{s} rgb/{s}.png\n" for s in stems))
    (tmp_path / "depth.txt").write_text("".join(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png\n" for t in t_img))
    # mocap at 100 Hz, offset from the images; nothing near the last image (7 s later)
    t_gt = np.arange(1305031102.10, 1305031102.40, 0.01)
    T_all = [_moving(t) for t in t_gt]
    tum.write_pose_list(tmp_path / "groundtruth.txt", [(f"{t:.4f}", T) for t, T in zip(t_gt, T_all)])
    (tmp_path / "camera.yaml").write_text("%YAML:1.0\n---\nCamera.fx: 35.0\nCamera.fy: 36.0\nCamera.cx: 19.5\n"
                                         "Camera.cy: 15.25\nCamera.width: 40\nCamera.height: 30\n")
    ds = load_dataset(tmp_path)
    assert ds.meta["matched_by"] == "timestamp" and len(ds.frames) == 4
    assert "1 of 5 images have no pose" in caplog.text
    for f in ds.frames:
        # interpolated between the bracketing poses (TUM's tools), not the nearest (up to 2.5 mm / 0.57 deg off)
        np.testing.assert_allclose(f.camera.T_world_cam, _moving(float(f.name)), atol=1e-5)
    assert "assuming the TUM RGB-D benchmark's 5000 units per metre" in caplog.text
    # TUM RGB-D layout: 5000 depth units per metre by default, metres = raw / 5000 exactly rounded
    assert ds.depth_scale == pytest.approx(1 / 5000)
    d = load_depth(ds.frames[1].depth_path, ds.depth_scale)
    np.testing.assert_array_equal(d, (raw.astype(np.float64) / 5000).astype(np.float32))


def test_depth_folder_needs_an_explicit_unit(tmp_path):
    _images(tmp_path / "rgb", ["000000", "000001", "000002"])
    for i in range(3):
        io.write_image(tmp_path / "depth" / f"{i:06d}.png", np.full((H, W), 1234, np.uint16))
    tum.write_pose_list(tmp_path / "poses.txt", [(f"{i:06d}", T) for i, T in enumerate(_poses(3))])
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    with pytest.raises(InputError, match="no depth unit") as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "intrinsics.yaml"
    (tmp_path / "intrinsics.yaml").write_text(INTR + "depth_factor: 1000\n")
    ds = load_dataset(tmp_path)
    assert ds.depth_scale == pytest.approx(1e-3) and ds.frames[0].depth_path.name == "000000.png"
    assert load_depth(ds.frames[0].depth_path, ds.depth_scale)[0, 0] == np.float32(1.234)
    (tmp_path / "intrinsics.yaml").write_text(INTR + "depth_scale: 0.001\n")   # RealSense: metres per unit
    assert load_dataset(tmp_path).depth_scale == pytest.approx(1e-3)


def test_intrinsics_variants_and_writer(tmp_path):
    p = tmp_path / "camera.json"
    io.write_json(p, {"camera": {"K": [[35, 0, 19.5], [0, 36, 15.25], [0, 0, 1]], "w": 40, "h": 30,
                                 "distortion": [0.1, -0.01, 0.001, 0.002, 0.0]}})
    intr = tum.read_intrinsics(p)
    assert (intr.width, intr.height) == (40, 30) and intr.K[1, 1] == 36
    np.testing.assert_allclose(intr.dist, [0.1, -0.01, 0.001, 0.002])
    cam = Camera(K=intr.K, width=40, height=30, dist=intr.dist)
    tum.write_intrinsics(tmp_path / "intrinsics.yaml", cam, depth_factor=5000)
    back = tum.read_intrinsics(tmp_path / "intrinsics.yaml")
    np.testing.assert_allclose(back.K, intr.K)
    np.testing.assert_allclose(back.dist, intr.dist)
    assert back.depth_scale == pytest.approx(2e-4)


@pytest.mark.parametrize("text, msg", [
    ("fx: 35\nfy: 36\ncx: 19.5\nwidth: 40\nheight: 30\n", "lacks cy"),
    ("fx: 35\nfy: 36\ncx: 19.5\ncy: 15\n", "lacks width/height"),
    (INTR.replace("fx: 35.0", "fx: -35.0"), "positive focal"),
    (INTR.replace("fx: 35.0", "fx: abc"), "fx must be a number, got str 'abc'"),
    (INTR + "depth_scale: 5000\n", "depth_scale is metres per depth unit"),
    (INTR + "depth_factor: 5000\ndepth_scale: 0.0002\n", "give the depth unit once"),
    (INTR + "distortion: [1, 2]\n", "4 or 5 finite numbers"),
    ("width: 100000\nheight: 100000\nfx: 1\nfy: 1\ncx: 0\ncy: 0\n", "megapixels"),
    ("a: &a [1, *a]\n", "recursive|YAML"),
    ("- 1\n- 2\n", "must hold a mapping"),
])
def test_intrinsics_malformed_names_the_file(tmp_path, text, msg):
    p = tmp_path / "intrinsics.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=msg) as e:
        tum.read_intrinsics(p)
    assert e.value.path == p


def test_rgb_txt_paths_stay_inside_the_folder(tmp_path):
    _images(tmp_path / "rgb", ["1.000000"])
    (tmp_path / "rgb.txt").write_text("1.0 ../../etc/passwd\n")
    tum.write_pose_list(tmp_path / "groundtruth.txt", [("1.0", np.eye(4))])
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    with pytest.raises(InputError, match="leads outside") as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "rgb.txt"


def test_no_pose_matches_and_missing_intrinsics(tmp_path, capsys):
    _images(tmp_path / "rgb", ["1.000000", "2.000000"])
    tum.write_pose_list(tmp_path / "groundtruth.txt", [("5.0", np.eye(4))])
    (tmp_path / "rgb.txt").write_text("1.0 rgb/1.000000.png\n2.0 rgb/2.000000.png\n")
    with pytest.raises(InputError, match="no intrinsics file"):
        load_dataset(tmp_path)
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    assert main(["poses", str(tmp_path), str(tmp_path / "out"), "--known"]) == 2
    err = capsys.readouterr().err
    assert "groundtruth.txt" in err and "no image has a pose" in err


def test_duplicate_pose_ids_are_found_and_both_lines_named(tmp_path):
    """The duplicate check was keys.count(k) per key: 100k lines took ~2 minutes. Now a set, and the message
    names both lines."""
    n = 30_000
    (tmp_path / "poses.txt").write_text("".join(f"{i} 0 0 0 0 0 0 1\n" for i in range(n)) + "7 0 0 0 0 0 0 1\n")
    # (quadratic: ~10 s here; linear: ~0.3 s; the message names both lines)
    with pytest.raises(InputError, match=f"line {n + 1}: id/timestamp '7' appears twice \\(first on line 8\\)"):
        tum.read_pose_list(tmp_path / "poses.txt")


def test_unicode_digit_pose_ids_are_not_numbers(tmp_path, caplog):
    """'²' passes str.isdigit(), then int() raised (exit 1): it is an id that names no image."""
    _images(tmp_path / "images", [f"{i:06d}" for i in range(3)])
    tum.write_pose_list(tmp_path / "poses.txt", [(k, T) for k, T in zip(("0", "1", "²"), _poses(3))])
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    ds = load_dataset(tmp_path)
    assert [f.name for f in ds.frames] == ["000000", "000001"] and "1 of 3 images have no pose" in caplog.text


@pytest.mark.parametrize("text, msg", [
    # integers beyond float range (OverflowError / TypeError before)
    (INTR.replace("fx: 35.0", "fx: " + "9" * 400), "fx <an integer of about 400 digits> is too large"),
    (INTR + "K: [" + "9" * 400 + ", 0, 19.5, 0, 36, 15.25, 0, 0, 1]\n", r"K \(3x3\) element 1 .* too large"),
    (INTR + "depth_factor: " + "9" * 400 + "\n", "depth_factor .* too large"),
    (INTR + "k1: " + "9" * 400 + "\n", "k1 .* too large"),
    (INTR.replace("width: 40", "width: " + "9" * 400), "width x height claims <an integer of about 400 digits>x30"),
    # bools and text are not numbers (width: true was read as 1; text in K was accepted, '153.75' as fx not)
    (INTR.replace("width: 40", "width: true"), "size must be whole numbers, got True x 30"),
    (INTR + "K: ['35', 0, 19.5, 0, 36, 15.25, 0, 0, 1]\n", r"K \(3x3\) element 1 must be a number, got str '35'"),
    (INTR.replace("fx: 35.0", "fx: '35.5'"), "fx must be a number, got str '35.5' .write numbers without quotes"),
    (INTR + "depth_factor: 1e3\n", r"got str '1e3' .*YAML .*write 1\.0e\+3"),   # PyYAML reads 1e3 as text
    # absurd finite values
    (INTR + "depth_factor: 1.0e-300\n", r"depth_factor \(depth units per metre\) must be within"),
    (INTR + "depth_scale: 1.0e-300\n", r"depth_scale \(metres per depth unit\) must be within"),
    (INTR + "k1: 1.0e+300\n", r"distortion coefficients must be within \+-1000"),
    (INTR.replace("fx: 35.0", "fx: 1.0e+308"), "focal length fx = 1e\\+308 px is implausible"),
    ("K: [[35, 0, 19.5], [0, 36, 15.25], [3, 4, 0]]\nwidth: 40\nheight: 30\n", r"K must be .*\[0, 0, 1\]"),
    (INTR.replace("cx: 19.5", "cx: 800"), r"principal point .* far outside the 40x30 image"),
])
def test_intrinsics_numbers_are_checked(tmp_path, text, msg):
    p = tmp_path / "intrinsics.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=msg) as e:
        tum.read_intrinsics(p)
    assert e.value.path == p


def _rgbd(folder: Path, depth_times: list[float], depth=None) -> None:
    """TUM RGB-D layout: images at 1.0, 1.1, 1.2 s with rgb.txt, poses by timestamp, depth.txt at depth_times."""
    t_img = [1.0, 1.1, 1.2]
    _images(folder / "rgb", [f"{t:.6f}" for t in t_img])
    (folder / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in t_img))
    tum.write_pose_list(folder / "groundtruth.txt", [(f"{t:.6f}", T) for t, T in zip(t_img, _poses(3))])
    (folder / "intrinsics.yaml").write_text(INTR)
    for t in depth_times:
        io.write_image(folder / "depth" / f"{t:.6f}.png", np.full((H, W), 5000, np.uint16) if depth is None else depth)
    (folder / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_times))


def test_depth_txt_matching_no_image_is_an_error_and_some_a_warning(tmp_path, caplog):
    """Depth that matched no image was dropped silently (the capture then had no depth at all)."""
    _rgbd(tmp_path / "none", [5.0, 5.1, 5.2])
    with pytest.raises(InputError, match=r"none of its 3 depth images is within 0.02 s of one of the 3 posed") as e:
        load_dataset(tmp_path / "none")
    assert e.value.path == tmp_path / "none" / "depth.txt"
    _rgbd(tmp_path / "some", [1.005, 5.1, 1.205])
    ds = load_dataset(tmp_path / "some")
    assert [f.depth_path is not None for f in ds.frames] == [True, False, True]
    assert "depth.txt: 1 of 3 posed images have no depth image within 0.02 s (of 3 depth images)" in caplog.text


def test_depth_txt_naming_a_colour_image_is_refused(tmp_path):
    _rgbd(tmp_path, [1.0, 1.1, 1.2], depth=np.full((H, W, 3), 50, np.uint8))
    with pytest.raises(InputError, match="depth image must be single-channel 16-bit.*'RGB'") as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "depth" / "1.000000.png"


def test_tum_folder_links_out_are_refused(tmp_path):
    """The images of rgb/ (no rgb.txt) and depth/ are files of the capture: a link out of it is refused."""
    import os

    cap = tmp_path / "cap"
    _images(cap / "rgb", ["000000", "000001"])
    tum.write_pose_list(cap / "poses.txt", [(f"{i:06d}", T) for i, T in enumerate(_poses(2))])
    (cap / "intrinsics.yaml").write_text(INTR + "depth_factor: 1000\n")
    (cap / "rgb" / "000001.png").rename(tmp_path / "outside.png")
    os.symlink(tmp_path / "outside.png", cap / "rgb" / "000001.png")
    with pytest.raises(InputError, match="leads outside its folder") as e:
        load_dataset(cap)
    assert e.value.path == cap / "rgb" / "000001.png"
    (cap / "rgb" / "000001.png").unlink()
    (tmp_path / "outside.png").rename(cap / "rgb" / "000001.png")
    io.write_image(tmp_path / "d.png", np.full((H, W), 1000, np.uint16))
    (cap / "depth").mkdir()
    os.symlink(tmp_path / "d.png", cap / "depth" / "000000.png")
    with pytest.raises(InputError, match="leads outside its folder") as e:
        load_dataset(cap)
    assert e.value.path == cap / "depth" / "000000.png"


# -- other tools' calibration files, float depth, pixel convention, nanosecond timestamps ---------------
ORB3 = """%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
Camera1.fx: 35.0
Camera1.fy: 36.0
Camera1.cx: 19.5
Camera1.cy: 15.25
Camera1.k1: 0.0
Camera1.k2: 0.0
Camera1.p1: 0.0
Camera1.p2: 0.0
Camera.width: 40
Camera.height: 30
Stereo.ThDepth: 40.0
RGBD.DepthMapFactor: 1000.0
IMU.T_b_c1: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
"""


def test_orb_slam3_settings_depth_map_factor_and_opencv_matrix(tmp_path):
    """ORB-SLAM3 spells the depth unit RGBD.DepthMapFactor (ignored before: TUM's 5000 taken, depth 5x short)
    and stores matrices as !!opencv-matrix (refused before)."""
    raw = np.full((H, W), 823, np.uint16)   # 0.823 m in millimetres
    _rgbd(tmp_path, [1.0, 1.1, 1.2], depth=raw)
    (tmp_path / "intrinsics.yaml").write_text(ORB3)
    ds = load_dataset(tmp_path)
    assert ds.depth_scale == pytest.approx(1e-3)
    assert load_depth(ds.frames[0].depth_path, ds.depth_scale)[0, 0] == np.float32(0.823)
    np.testing.assert_allclose(ds.frames[0].camera.K, [[35, 0, 20.0], [0, 36, 15.75], [0, 0, 1]])


@pytest.mark.parametrize("text", [
    # ROS camera_calibration / camera_info_manager YAML
    "image_width: 40\nimage_height: 30\ncamera_name: cam\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
    "  data: [35.0, 0.0, 19.5, 0.0, 36.0, 15.25, 0.0, 0.0, 1.0]\ndistortion_model: plumb_bob\n"
    "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.1, -0.01, 0.001, 0.002, 0.0]\n",
    # a sensor_msgs/CameraInfo message (ROS 2 field names)
    "header: {frame_id: cam}\nwidth: 40\nheight: 30\ndistortion_model: plumb_bob\n"
    "d: [0.1, -0.01, 0.001, 0.002, 0.0]\nk: [35.0, 0.0, 19.5, 0.0, 36.0, 15.25, 0.0, 0.0, 1.0]\n"
    "r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n",
    # OpenCV FileStorage calibration output (the calibration sample's keys)
    "%YAML:1.0\n---\nimage_width: 40\nimage_height: 30\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
    "   dt: d\n   data: [ 35., 0., 19.5, 0., 36., 15.25, 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n"
    "   rows: 5\n   cols: 1\n   dt: d\n   data: [ 0.1, -0.01, 0.001, 0.002, 0. ]\n",
])
def test_ros_camera_info_and_opencv_calibration_files(tmp_path, text):
    p = tmp_path / "calibration.yaml"
    p.write_text(text)
    intr = tum.read_intrinsics(p)
    assert (intr.width, intr.height) == (40, 30)
    np.testing.assert_allclose(intr.K, [[35, 0, 20.0], [0, 36, 15.75], [0, 0, 1]])
    np.testing.assert_allclose(intr.dist, [0.1, -0.01, 0.001, 0.002])


@pytest.mark.parametrize("text, msg", [
    (INTR + "distortion_model: equidistant\nD: [0.1, 0.01, 0.0, 0.0]\n", "distortion_model 'equidistant'"),
    (ORB3.replace('"PinHole"', '"KannalaBrandt8"'), "camera type 'KannalaBrandt8'"),
    ("width: 40\nheight: 30\ncamera_matrix: {rows: 3, cols: 3, data: [35.0, 0.0, 19.5, 0.0, 36.0]}\n",
     "3x3 matrix with 5 numbers"),
    ("%YAML:1.0\nK: !!opencv-matrix [35.0, 0.0]\nwidth: 40\nheight: 30\n", "opencv-matrix on line 2 must be a mapping"),
    ("%YAML:1.0\na: &a !!opencv-matrix {rows: 1, cols: 1, data: [*a]}\n", "recursive|YAML"),
])
def test_other_calibration_files_malformed_or_unsupported(tmp_path, text, msg):
    p = tmp_path / "camera.yaml"
    p.write_text(text)
    with pytest.raises(InputError, match=msg) as e:
        tum.read_intrinsics(p)
    assert e.value.path == p


def test_float_depth_in_metres_is_not_scaled_by_the_tum_default(tmp_path):
    """ROS 32FC1 depth (metres) exported as float TIFF with a TUM depth.txt was divided by 5000."""
    from PIL import Image

    _rgbd(tmp_path, [])
    metres = np.full((H, W), 0.823, np.float32)
    (tmp_path / "depth").mkdir()
    for t in (1.0, 1.1, 1.2):
        Image.fromarray(metres, mode="F").save(tmp_path / "depth" / f"{t:.6f}.tif")
    (tmp_path / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.tif\n" for t in (1.0, 1.1, 1.2)))
    ds = load_dataset(tmp_path)
    assert ds.depth_scale is None
    assert load_depth(ds.frames[0].depth_path, ds.depth_scale)[0, 0] == np.float32(0.823)
    # .npy float arrays in depth/ without depth.txt: metres too (the 'no depth unit' error is for integers)
    (tmp_path / "depth.txt").unlink()
    for t in (1.0, 1.1, 1.2):
        (tmp_path / "depth" / f"{t:.6f}.tif").unlink()
        np.save(tmp_path / "depth" / f"{t:.6f}.npy", metres)
    ds = load_dataset(tmp_path)
    assert ds.depth_scale is None and ds.frames[0].depth_path.suffix == ".npy"
    # mixing integer and float depth: refused
    np.save(tmp_path / "depth" / "1.100000.npy", np.full((H, W), 823, np.uint16))
    with pytest.raises(InputError, match="mix integer and float"):
        load_dataset(tmp_path)


def test_principal_point_pixel_convention_matches_opencv_projection(tmp_path):
    """A point projected by OpenCV with the file's K lands on the same pixel as our camera's projection
    minus 0.5 (ours: pixel centres at +0.5, COLMAP; OpenCV/TUM/ROS: at integers)."""
    import cv2

    p = tmp_path / "intrinsics.yaml"
    p.write_text(INTR + "distortion: [0.05, -0.01, 0.001, 0.002, 0.003]\n")
    intr = tum.read_intrinsics(p)
    T = _poses(3)[1]
    cam = Camera(K=intr.K, width=W, height=H, T_world_cam=T, dist=intr.dist)
    pts = np.array([[0.02, -0.03, 0.01], [0.0, 0.0, 0.0], [-0.05, 0.04, 0.02]])
    uv, _ = cam.project(pts)
    K_file = np.array([[35.0, 0, 19.5], [0, 36.0, 15.25], [0, 0, 1]])
    T_cw = np.linalg.inv(T)
    uv_cv, _ = cv2.projectPoints(pts, cv2.Rodrigues(T_cw[:3, :3])[0], T_cw[:3, 3], K_file,
                                 np.array([0.05, -0.01, 0.001, 0.002, 0.003]))
    np.testing.assert_allclose(uv - 0.5, uv_cv[:, 0], atol=1e-9)
    # and the writer gives the file's values back
    tum.write_intrinsics(tmp_path / "back.yaml", cam)
    assert "cx: 19.5" in (tmp_path / "back.yaml").read_text()
    np.testing.assert_allclose(tum.read_intrinsics(tmp_path / "back.yaml").K, intr.K)


def test_nanosecond_timestamps(tmp_path):
    """ROS / EuRoC exports stamp in whole nanoseconds (19 digits): read as seconds, so the 0.02 s tolerance holds."""
    t_img = [1403636579.763555584 + 0.05 * i for i in range(3)]
    ns = [f"{int(round(t * 1e9))}" for t in t_img]
    _images(tmp_path / "rgb", ns)
    (tmp_path / "rgb.txt").write_text("".join(f"{s} rgb/{s}.png\n" for s in ns))
    # poses 3 ms later, also in nanoseconds
    tum.write_pose_list(tmp_path / "groundtruth.txt",
                        [(str(int(s) + 3_000_000), T) for s, T in zip(ns, _poses(3))])
    (tmp_path / "intrinsics.yaml").write_text(INTR)
    ds = load_dataset(tmp_path)
    assert ds.meta["matched_by"] == "timestamp" and len(ds.frames) == 3
    for f, T in zip(ds.frames, _poses(3)):
        np.testing.assert_allclose(f.camera.T_world_cam, T, atol=1e-12)
