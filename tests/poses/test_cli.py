"""`splattwin poses` command line: help, known poses, robot poses, outputs, bad input exit code."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import load_dataset
from splattwin.cli import main
from splattwin.poses import load_frame


def test_help_works(capsys):
    with pytest.raises(SystemExit) as e:
        main(["poses", "--help"])
    assert e.value.code == 0
    assert "--robot-poses" in capsys.readouterr().out


def test_sfm_and_up_flags_set_pose_options():
    """sfm's and formats' flags are generated from PoseOptions; their old spellings still work."""
    from splattwin.cli import build_parser
    from splattwin.options import from_args
    from splattwin.poses import PoseOptions

    p = build_parser()
    old = from_args(PoseOptions, p.parse_args(["poses", "in", "out", "--max-features", "2000", "--threads", "1",
                                                "--no-retry", "--no-triangulate", "--up=-z", "--max-image-size", "0",
                                                "--matcher", "retrieval"]))
    new = from_args(PoseOptions, p.parse_args(["poses", "in", "out", "--max-num-features", "2000", "--num-threads",
                                                "1", "--no-retry", "--no-triangulate", "--up", "+y"]))
    assert (old.max_num_features, old.num_threads, old.retry, old.triangulate, old.up, old.max_image_size,
            old.matcher) == (2000, 1, False, False, "-z", 0, "retrieval")
    assert (new.max_num_features, new.num_threads, new.retry, new.triangulate, new.up) == (2000, 1, False, False, "+y")
    d = from_args(PoseOptions, p.parse_args(["poses", "in", "out"]))
    assert (d.max_image_size, d.max_num_features, d.retry, d.num_threads, d.triangulate, d.up) == \
        (1600, 4096, True, 0, True, "auto")
    with pytest.raises(SystemExit):
        p.parse_args(["poses", "in", "out", "--up", "down"])
    assert d.check_registration is True
    off = from_args(PoseOptions, p.parse_args(["poses", "in", "out", "--no-check-registration"]))
    assert off.check_registration is False
    from splattwin.poses.estimate import _sfm_options

    assert _sfm_options(off).check_registration is False and _sfm_options(d).check_registration is True


def test_known_poses_round_trip(scene_small: Path, tmp_path: Path):
    out = tmp_path / "out"
    assert main(["poses", str(scene_small), str(out), "--known"]) == 0
    frame = load_frame(out)
    assert frame.source == "known_poses" and frame.scaled
    assert (out / "cameras.png").stat().st_size > 1000
    report = json.loads((out / "poses_report.json").read_text())
    assert report["registered"] == report["total"] == 11
    ds = load_dataset(out)
    gt = load_dataset(scene_small)
    assert ds.has_poses and len(ds.frames) == len(gt.frames)
    for a, b in zip(ds.frames, gt.frames):
        # the output is a self-contained dataset: the input's images are linked/copied into it
        assert a.image_path.resolve().is_relative_to(out.resolve()) and a.split == b.split
        assert a.image_path.name == b.image_path.name and a.image_path.read_bytes() == b.image_path.read_bytes()
        np.testing.assert_allclose(a.camera.T_world_cam, b.camera.T_world_cam, atol=1e-9)
        assert a.depth_path is not None
    assert ds.points_xyz is not None and len(ds.points_xyz) > 1000  # depth back-projection as the initial cloud
    # chained run keeps the frame definition written beside the dataset
    out2 = tmp_path / "out2"
    (out / "frame.json").write_text(json.dumps({**json.loads((out / "frame.json").read_text()), "source": "marker"}))
    assert main(["poses", str(out), str(out2), "--known", "--no-depth-points"]) == 0
    assert load_frame(out2).source == "marker"


def test_robot_cli_and_bad_input(scene_small: Path, tmp_path: Path, capsys):
    gt = load_dataset(scene_small)
    T_ee_cam = np.eye(4)
    T_ee_cam[:3, 3] = [0, 0, 0.1]
    poses = [{"image": f.image_path.name, "T_base_ee": (f.camera.T_world_cam @ np.linalg.inv(T_ee_cam)).tolist()}
             for f in gt.frames]
    (tmp_path / "poses.json").write_text(json.dumps({"poses": poses, "T_ee_cam": T_ee_cam.tolist()}))
    out = tmp_path / "out"
    assert main(["poses", str(scene_small), str(out), "--robot-poses", str(tmp_path / "poses.json"),
                 "--no-depth-points"]) == 0
    assert load_frame(out).source == "robot"
    ds = load_dataset(out)
    np.testing.assert_allclose(ds.frames[3].camera.T_world_cam, gt.frames[3].camera.T_world_cam, atol=1e-9)
    # malformed pose file -> exit code 2 with the file named
    (tmp_path / "bad.yaml").write_text("- {image: a.png, position: [0, 0, 0], orientation: [0, 0, 0, 1]}\n")
    capsys.readouterr()
    assert main(["poses", str(scene_small), str(tmp_path / "o2"), "--robot-poses", str(tmp_path / "bad.yaml")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "quat_xyzw" in err
    assert main(["poses", str(scene_small), str(tmp_path / "o3"), "--intrinsics", "1,2,3"]) == 2
    assert main(["poses", str(tmp_path / "missing"), str(tmp_path / "o4")]) == 2


def test_sfm_cli_with_known_length_writes_depth_cloud(default_unscaled, sfm_default_dir: Path, tmp_path: Path):
    """CLI on an image folder: SfM (re-using the session's model) + camera height -> metric frame + RGB-D cloud."""
    import shutil

    gt, _ = default_unscaled
    imgs = tmp_path / "in"
    shutil.copytree(gt.root / "images", imgs / "images")
    h = float(np.mean([f.camera.center[2] for f in gt.frames]))
    out = tmp_path / "out"
    shutil.copytree(sfm_default_dir, out / "sfm")  # resume: same images by name, same options
    assert main(["poses", str(imgs), str(out), "--known-length", f"camera_height={h}"]) == 0
    frame = load_frame(out)
    assert frame.source == "table_plane+known_length" and frame.scaled
    # the table plane was checked against the cameras' horizon: the embedded table is level, not a wall
    chk = frame.up_check
    assert chk["camera_cue"] == "horizon" and chk["table"] == "dominant plane" and chk["dominant_plane_tilt_deg"] < 5
    report = json.loads((out / "poses_report.json").read_text())
    assert report["timings"] == {}  # the finished model was re-used
    assert report["registered"] == 20 and "depth_ply" not in report  # an image folder has no depth
    ds = load_dataset(out)
    assert len(ds.points_xyz) == report["num_points"]


def test_result_round_trips_through_its_dataset(scene_small: Path):
    """PoseResult.to_dataset() carries the frame; estimating again with --known keeps it."""
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.poses.twin_frame import TwinFrame

    gt = load_dataset(scene_small)
    res = estimate_poses(gt, PoseOptions(method="known", depth_points=False, progress=False))
    ds = res.to_dataset(scene_small)
    ds.meta["frame"]["source"] = "marker"
    again = estimate_poses(ds, PoseOptions(method="known", depth_points=False, progress=False))
    assert isinstance(again.frame, TwinFrame) and again.frame.source == "marker"


def test_capture_of_symlinked_photos_works_like_the_photos(default_unscaled, sfm_default_dir: Path, tmp_path: Path):
    """A photo folder of symbolic links (to photos kept elsewhere, in several folders, under other names) is
    the user's own capture: the links' names are the images' names (SfM, report, transforms.json) and the
    poses folder holds the photos themselves, so training reads it. Links used to be followed: file_path
    was the targets' path (`../../elsewhere/...`, refused by `train`) and names were relative to `/`."""
    import os
    import shutil

    gt, _ = default_unscaled
    cap = tmp_path / "cap"
    cap.mkdir()
    for i, f in enumerate(gt.frames):  # targets in two folders, named otherwise than the links
        target = tmp_path / "elsewhere" / "ab"[i % 2] / f"IMG_{i:04d}{f.image_path.suffix}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f.image_path, target)
        os.symlink(target, cap / f.image_path.name)
    h = float(np.mean([f.camera.center[2] for f in gt.frames]))
    out = tmp_path / "out"
    shutil.copytree(sfm_default_dir, out / "sfm")  # resumes only if SfM names the images by the links' names
    assert main(["poses", str(cap), str(out), "--known-length", f"camera_height={h}", "--no-progress"]) == 0
    report = json.loads((out / "poses_report.json").read_text())
    assert report["timings"] == {} and report["registered"] == 20
    names = sorted(f.image_path.name for f in gt.frames)
    assert sorted(report["registration_check"]["per_image"]) == names
    meta = json.loads((out / "transforms.json").read_text())
    assert sorted(fr["file_path"] for fr in meta["frames"]) == [f"images/{n}" for n in names]
    for n in names:  # the photos themselves, not links leading out of the twin
        p = out / "images" / n
        assert not p.is_symlink() and p.read_bytes() == (cap / n).read_bytes()
    # training reads the poses folder (it used to stop: "file_path ... leads outside its folder")
    assert main(["train", str(out), str(tmp_path / "splat"), "--iters", "2", "--no-progress"]) == 0
    assert (tmp_path / "splat" / "point_cloud.ply").is_file()


@pytest.mark.parametrize("flag, value, msg", [
    ("--intrinsics", "nan,50,32,24", "expected four finite numbers"),     # reached COLMAP's extractor: exit 1
    ("--intrinsics", "50,inf,32,24", "expected four finite numbers"),
    ("--intrinsics", "50,50,nan,24", "expected four finite numbers"),
    ("--marker-size", "inf", "must be a positive number of metres, got inf"),   # passed `> 0`
    ("--marker-size", "1e308", "is outside 0.0001 to 10000 m"),   # failed later, naming something else
    ("--known-length", "camera_height=1e-300", "is outside 0.0001 to 10000 m"),
])
def test_non_finite_intrinsics_and_marker_size_are_bad_input(tmp_path: Path, capsys, flag, value, msg):
    """Flags given nan or inf: exit 2 naming the flag, and no poses written."""
    from splattwin import io

    rng = np.random.default_rng(0)
    for i in range(3):
        io.write_image(tmp_path / "photos" / f"p{i}.png", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["poses", str(tmp_path / "photos"), str(out), f"{flag}={value}", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err, err
    assert not (out / "transforms.json").exists()
