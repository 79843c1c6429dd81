"""Robot poses + hand-eye: exact cameras in the robot base frame; SfM aligned to them; bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.capture import load_dataset
from splattwin.errors import InputError
from splattwin.poses import PoseOptions, estimate_poses
from splattwin.poses.robot import load_hand_eye, load_robot_poses

# Robot base beside the table edge (docs/CONTRACTS.md): x = -0.5, facing +x.
T_WORLD_BASE = np.eye(4)
T_WORLD_BASE[:3, 3] = [-0.5, 0.0, 0.0]


def _hand_eye() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [3.0, -2.0, 91.0], degrees=True).as_matrix()
    T[:3, 3] = [0.05, -0.02, 0.07]
    return T


def _write_robot_files(gt, folder: Path, style: str) -> tuple[Path, Path]:
    T_ee_cam = _hand_eye()
    T_base_world = np.linalg.inv(T_WORLD_BASE)
    entries = []
    for f in gt.frames:
        T_base_ee = T_base_world @ f.camera.T_world_cam @ np.linalg.inv(T_ee_cam)
        if style == "matrix":
            entries.append({"image": f.image_path.name, "T_base_ee": T_base_ee.tolist()})
        else:
            x, y, z, w = Rotation.from_matrix(T_base_ee[:3, :3]).as_quat()
            x, y, z, w = (float(v) for v in (x, y, z, w))
            q = {"quat_xyzw": [x, y, z, w]} if style == "xyzw" else {"quat_wxyz": [w, x, y, z]}
            entries.append({"image": f.image_path.stem, "position": T_base_ee[:3, 3].tolist(), **q})
    poses = folder / f"poses_{style}.{'yaml' if style == 'xyzw' else 'json'}"
    if poses.suffix == ".yaml":
        import yaml

        poses.write_text(yaml.safe_dump(entries))
    else:
        poses.write_text(json.dumps(entries))
    he = folder / "hand_eye.json"
    he.write_text(json.dumps({"T_ee_cam": T_ee_cam.tolist()}))
    return poses, he


@pytest.mark.parametrize("style", ["matrix", "xyzw", "wxyz"])
def test_robot_poses_reproduce_ground_truth_cameras(scene_default: Path, tmp_path: Path, style: str):
    gt = load_dataset(scene_default)
    poses, he = _write_robot_files(gt, tmp_path, style)
    res = estimate_poses(gt, PoseOptions(robot_poses=poses, hand_eye=he, progress=False, depth_points=False))
    assert res.frame.source == "robot" and res.frame.scaled
    assert len(res.frames) == len(gt.frames)
    g = {f.image_path.name: f.camera for f in gt.frames}
    for f in res.frames:
        T_base_cam_gt = np.linalg.inv(T_WORLD_BASE) @ g[f.image_path.name].T_world_cam
        np.testing.assert_allclose(f.camera.T_world_cam, T_base_cam_gt, atol=1e-9)
        np.testing.assert_allclose(f.camera.K, g[f.image_path.name].K)


def test_sfm_aligned_to_robot_poses(default_unscaled, sfm_default_dir: Path, scene_default: Path, tmp_path: Path):
    from tests.poses.conftest import stripped

    gt, _ = default_unscaled
    poses, he = _write_robot_files(gt, tmp_path, "matrix")
    res = estimate_poses(stripped(gt), PoseOptions(method="sfm", robot_poses=poses, hand_eye=he,
                                                   work_dir=sfm_default_dir, progress=False))
    assert res.frame.source == "sfm+robot" and res.frame.scaled
    assert res.stats["umeyama"]["residual_rms_m"] < 0.005
    assert 0 < res.frame.scale_uncertainty_rel < 0.01
    g = {f.image_path.name: f.camera for f in gt.frames}
    for f in res.frames:
        c_gt = (np.linalg.inv(T_WORLD_BASE) @ g[f.image_path.name].T_world_cam)[:3, 3]
        assert np.linalg.norm(f.camera.center - c_gt) < 0.01
    assert res.depth_xyz is not None and len(res.depth_xyz) > 1000  # metric frame: RGB-D cloud available


def _bad(tmp_path: Path, text: str, suffix: str = ".json") -> Path:
    p = tmp_path / f"bad{suffix}"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text,match", [
    ("{not json", "not valid JSON"),
    ("[]", "non-empty list"),
    ('[{"image": "a.png", "position": [0, 0, 0], "quat": [1, 0, 0, 0]}]', "quat_xyzw"),
    ('[{"image": "a.png", "position": [0, 0], "quat_wxyz": [1, 0, 0, 0]}]', "position"),
    ('[{"image": "a.png", "position": [0, 0, 0], "quat_wxyz": [2, 0, 0, 0]}]', "unit length"),
    ('[{"image": "a.png", "T_base_ee": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]', "rigid"),
    ('[{"image": "a.png", "T_base_ee": [[1, 0], [0, 1]]}]', "4x4"),
    ('[{"image": "a.png", "T_base_ee": "eye"}]', "numeric"),
])
def test_malformed_robot_pose_file(tmp_path: Path, text: str, match: str):
    p = _bad(tmp_path, text)
    with pytest.raises(InputError, match=match) as e:
        load_robot_poses(p)
    assert e.value.path == p


def test_robot_pose_file_mismatches_dataset(scene_default: Path, tmp_path: Path):
    gt = load_dataset(scene_default)
    he = tmp_path / "he.yaml"
    he.write_text("position: [0, 0, 0.1]\nquat_wxyz: [1, 0, 0, 0]\n")
    np.testing.assert_allclose(load_hand_eye(he)[:3, 3], [0, 0, 0.1])
    eye = np.eye(4).tolist()
    too_few = _bad(tmp_path, json.dumps([{"T_base_ee": eye}] * 3))
    with pytest.raises(InputError, match="3 robot poses but 20 images"):
        estimate_poses(gt, PoseOptions(robot_poses=too_few, hand_eye=he, progress=False))
    unknown = _bad(tmp_path, json.dumps([{"image": "nope.png", "T_base_ee": eye}]))
    with pytest.raises(InputError, match="nope.png"):
        estimate_poses(gt, PoseOptions(robot_poses=unknown, hand_eye=he, progress=False))
    no_he = _bad(tmp_path, json.dumps([{"T_base_ee": eye}] * 20))
    with pytest.raises(InputError, match="hand-eye"):
        estimate_poses(gt, PoseOptions(robot_poses=no_he, progress=False))


def test_unregistered_views_get_their_robot_pose(scene_small: Path, tmp_path: Path):
    """SfM + robot: a view SfM cannot register (replaced by noise) is still posed, exactly, from the robot."""
    import shutil

    from splattwin import io
    from tests.poses.conftest import stripped

    imgs = tmp_path / "imgs"
    shutil.copytree(scene_small / "images", imgs)
    io.write_image(imgs / "train_003.png", np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8))
    gt = load_dataset(scene_small)
    ds = load_dataset(imgs)
    poses, he = _write_robot_files(gt, tmp_path, "matrix")
    res = estimate_poses(stripped(ds), PoseOptions(method="sfm", robot_poses=poses, hand_eye=he, min_registered=6,
                                                   work_dir=tmp_path / "w", progress=False))
    assert res.frame.source == "sfm+robot"
    filled = res.stats["posed_from_robot_only"]
    assert any(Path(n).name == "train_003.png" for n in filled)
    assert len(res.frames) == len(gt.frames) and not res.unregistered
    g = {f.image_path.name: f.camera for f in gt.frames}
    cam = next(f.camera for f in res.frames if f.image_path.name == "train_003.png")
    np.testing.assert_allclose(cam.T_world_cam, np.linalg.inv(T_WORLD_BASE) @ g["train_003.png"].T_world_cam, atol=1e-9)
    other = next(f.camera for f in res.frames if f.image_path.name == "train_000.png")
    np.testing.assert_array_equal(cam.K, other.K)  # the shared SfM camera
