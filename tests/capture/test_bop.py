"""BOP scenes: poses (mm, world-to-camera) and intrinsics, depth units, detection, malformed input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import bop, load_dataset, load_depth, look_at
from splattwin.cli import main
from splattwin.errors import InputError

W, H = 64, 48


def _cams(n: int = 4) -> list[np.ndarray]:
    """T_world_cam of n cameras on a circle looking at the origin (metres)."""
    return [look_at(np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.4]), np.zeros(3))
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def write_scene(root: Path, n: int = 4, depth_scale: float = 0.1, poses: bool = True, suffix: str = ".png",
                image_dir: str = "rgb") -> dict:
    """A tiny BOP scene written by hand (not with our writer): returns what was written."""
    rng = np.random.default_rng(1)
    K = [60.0, 0.0, 31.5, 0.0, 61.0, 24.25, 0.0, 0.0, 1.0]
    cam, raw = {}, {}
    for i, T in enumerate(_cams(n)):
        io.write_image(root / image_dir / f"{i:06d}{suffix}", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        r = rng.integers(1, 60000, (H, W)).astype(np.uint16)
        r[0, :4] = [0, 1, 10000, 65535]
        io.write_image(root / "depth" / f"{i:06d}.png", r)
        raw[i] = r
        T_cw = np.linalg.inv(T)
        e = {"cam_K": K, "depth_scale": depth_scale}
        if poses:
            e["cam_R_w2c"] = T_cw[:3, :3].reshape(-1).tolist()
            e["cam_t_w2c"] = (T_cw[:3, 3] * 1000.0).tolist()   # millimetres
        cam[str(i)] = e
    io.write_json(root / "scene_camera.json", cam)
    return {"cams": _cams(n), "raw": raw, "K": np.array(K).reshape(3, 3)}


def test_bop_scene_poses_intrinsics_and_depth(tmp_path):
    w = write_scene(tmp_path)
    ds = load_dataset(tmp_path)
    assert ds.meta["format"] == "bop" and ds.has_poses and len(ds.frames) == 4
    for i, f in enumerate(ds.frames):
        assert f.name == f"{i:06d}" and f.image_path.parent.name == "rgb"
        np.testing.assert_allclose(f.camera.K, w["K"])
        np.testing.assert_allclose(f.camera.T_world_cam, w["cams"][i], atol=1e-9)  # mm -> m, inverted
        assert (f.camera.width, f.camera.height) == (W, H)
    # depth_scale 0.1: raw x 0.1 = mm, so metres = raw / 10000, correctly rounded
    assert ds.depth_scale == pytest.approx(1e-4)
    d = load_depth(ds.frames[2].depth_path, ds.depth_scale)
    np.testing.assert_array_equal(d, (w["raw"][2].astype(np.float64) / 10000.0).astype(np.float32))
    assert d[0, :4].tolist() == [0.0, np.float32(1e-4), np.float32(1.0), np.float32(6.5535)]
    # the scene_camera.json path is detected as well
    assert load_dataset(tmp_path / "scene_camera.json").meta["format"] == "bop"


def test_bop_without_poses_is_an_image_set_and_gray_images(tmp_path):
    write_scene(tmp_path, poses=False, image_dir="gray")
    ds = load_dataset(tmp_path)
    assert not ds.has_poses and len(ds.frames) == 4
    assert all(np.allclose(f.camera.T_world_cam, np.eye(4)) for f in ds.frames)


def test_bop_split_folder_asks_for_one_scene(tmp_path):
    write_scene(tmp_path / "test" / "000048")
    write_scene(tmp_path / "test" / "000049")
    with pytest.raises(InputError, match="2 BOP scenes.*000048"):
        load_dataset(tmp_path / "test")


def _mutate(path: Path, fn) -> None:
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


@pytest.mark.parametrize("fn, msg", [
    (lambda d: d["0"].pop("cam_R_w2c"), "some images have camera poses"),
    (lambda d: d["1"].update(cam_K=[1, 2, 3]), "image 1 cam_K must hold 9 numbers"),
    (lambda d: d["1"].update(cam_K="fx"), "image 1 cam_K must be a list"),
    (lambda d: d["2"].update(cam_R_w2c=[2, 0, 0, 0, 1, 0, 0, 0, 1]), "not a proper rotation"),
    (lambda d: d["2"].update(cam_t_w2c=[0, float("nan"), 0]), "non-finite"),
    (lambda d: d.update({"../x": d["0"]}), "must be a whole number"),
    (lambda d: d["3"].update(depth_scale=1.0), "depth_scale differs"),
    (lambda d: d["3"].update(depth_scale=-1), "depth_scale must be a positive"),
])
def test_bop_malformed_scene_camera_names_the_file(tmp_path, fn, msg):
    write_scene(tmp_path)
    _mutate(tmp_path / "scene_camera.json", fn)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "scene_camera.json"


def test_bop_malformed_input_exits_2_naming_the_file(tmp_path, capsys):
    write_scene(tmp_path)
    (tmp_path / "scene_camera.json").write_text("{not json")
    assert main(["poses", str(tmp_path), str(tmp_path / "out"), "--known"]) == 2
    err = capsys.readouterr().err
    assert "scene_camera.json" in err and "not valid JSON" in err


def test_scene_gt_and_object_names(tmp_path):
    tmp_path = tmp_path / "test" / "000001"    # dataset root / split / scene
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.5]
    bop.write_scene_gt(tmp_path / "scene_gt.json", [[(3, T), (7, T)], [(7, T)]])
    gt = bop.read_scene_gt(tmp_path)
    assert [(g.obj_id, g.index) for g in gt[0]] == [(3, 0), (7, 1)] and [g.obj_id for g in gt[1]] == [7]
    np.testing.assert_allclose(gt[0][0].T_cam_obj, T, atol=1e-12)
    assert json.loads((tmp_path / "scene_gt.json").read_text())["0"][0]["cam_t_m2c"] == pytest.approx([10, -20, 500])
    # names: default obj_XXXXXX, then object_names.json one folder up (the split), then models_info names
    assert bop.object_names(tmp_path, [3, 7]) == {3: "obj_000003", 7: "obj_000007"}
    io.write_json(tmp_path.parent / "object_names.json", {"3": "mug"})
    assert bop.object_names(tmp_path, [3, 7]) == {3: "mug", 7: "obj_000007"}
    io.write_json(tmp_path.parent / "object_names.json", {"3": "../../etc"})
    with pytest.raises(InputError, match="not allowed") as e:
        bop.object_names(tmp_path, [3])
    assert e.value.path == tmp_path.parent / "object_names.json"


@pytest.mark.parametrize("entry, msg", [
    ({"obj_id": "1"}, "obj_id must be a positive whole number"),
    ({"obj_id": True}, "obj_id must be a positive whole number"),
    ({"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1]}, "expected an object with obj_id"),
    ({"obj_id": 1, "cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 0]}, "must hold 9 numbers"),
])
def test_scene_gt_malformed(tmp_path, entry, msg):
    io.write_json(tmp_path / "scene_gt.json", {"0": [entry]})
    with pytest.raises(InputError, match=msg) as e:
        bop.read_scene_gt(tmp_path / "scene_gt.json")
    assert e.value.path == tmp_path / "scene_gt.json"
