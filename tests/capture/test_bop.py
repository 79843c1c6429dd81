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
        # cam_K's pixel centres are at integers (bop_toolkit / OpenCV), ours at +0.5
        np.testing.assert_allclose(f.camera.K, w["K"] + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
        np.testing.assert_allclose(f.camera.T_world_cam, w["cams"][i], atol=1e-9)  # mm -> m, inverted
        assert (f.camera.width, f.camera.height) == (W, H)
    # depth_scale 0.1: raw x 0.1 = mm, so metres = raw / 10000, correctly rounded
    assert ds.depth_scale == pytest.approx(1e-4)
    d = load_depth(ds.frames[2].depth_path, ds.depth_scale)
    np.testing.assert_array_equal(d, (w["raw"][2].astype(np.float64) / 10000.0).astype(np.float32))
    assert d[0, :4].tolist() == [0.0, np.float32(1e-4), np.float32(1.0), np.float32(6.5535)]
    # the scene_camera.json path is detected as well
    assert load_dataset(tmp_path / "scene_camera.json").meta["format"] == "bop"


def test_bop_principal_point_matches_opencv_projection_and_writer_round_trips(tmp_path):
    """A world point projected by OpenCV with the file's cam_K and pose lands on our projection minus 0.5."""
    import cv2

    w = write_scene(tmp_path, n=2)
    ds = load_dataset(tmp_path)
    pts = np.array([[0.03, -0.02, 0.01], [0.0, 0.0, 0.0], [-0.04, 0.05, 0.02]])
    for f, T in zip(ds.frames, w["cams"]):
        uv, _ = f.camera.project(pts)
        T_cw = np.linalg.inv(T)
        uv_cv, _ = cv2.projectPoints(pts, cv2.Rodrigues(T_cw[:3, :3])[0], T_cw[:3, 3], w["K"], None)
        np.testing.assert_allclose(uv - 0.5, uv_cv[:, 0], atol=1e-6)
    bop.write_scene_camera(tmp_path / "back" / "scene_camera.json", ds.cameras)
    back = json.loads((tmp_path / "back" / "scene_camera.json").read_text())
    np.testing.assert_allclose(back["0"]["cam_K"], w["K"].reshape(-1))


def test_bop_amodal_masks_only_warn(tmp_path, caplog):
    write_scene(tmp_path, n=2)
    io.write_image(tmp_path / "mask" / "000000_000000.png", np.full((H, W), 255, np.uint8))
    with caplog.at_level("WARNING"):
        load_dataset(tmp_path)
    assert "only mask/ (amodal" in caplog.text
    caplog.clear()
    both = tmp_path / "both"   # another scene: the note is said once per scene
    write_scene(both, n=2)
    io.write_image(both / "mask" / "000000_000000.png", np.full((H, W), 255, np.uint8))
    io.write_image(both / "mask_visib" / "000000_000000.png", np.full((H, W), 255, np.uint8))
    with caplog.at_level("WARNING"):
        load_dataset(both)
    assert "amodal" not in caplog.text


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
    (lambda d: d["3"].update(depth_scale=-1), r"depth_scale \(mm per raw depth unit\) must be within"),
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


def _edit_text(path: Path, old: str, new: str) -> None:
    """Replace the first `old` in a file's text: for JSON that json.dumps cannot write (duplicate keys,
    5000-digit integers)."""
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize("fn, msg", [
    # ids: ASCII digits only ("²" passes str.isdigit, then int() failed), one entry per image
    (lambda d: d.update({"²": d["0"]}), "image id '²' must be a whole number"),
    (lambda d: d.update({"00": d["0"]}), r"scene_camera.json has two entries for image 0 \('0' and '00'\)"),
    # an entry that is not an object is named as such (it was "some images have camera poses...")
    (lambda d: d.update({"1": [1, 2]}), "image 1: entry must be an object with cam_K, got list"),
    (lambda d: d.update({"1": None}), "image 1: entry must be an object with cam_K, got NoneType"),
    # numbers: huge integers, text and bools are not numbers (strings in cam_K were accepted)
    (lambda d: d["1"].update(cam_K=[10**400] + d["1"]["cam_K"][1:]), "image 1 cam_K element 1 .*too large"),
    (lambda d: d["1"].update(cam_K=[str(x) for x in d["1"]["cam_K"]]), "cam_K element 1 must be a number, got str"),
    (lambda d: d["1"].update(depth_scale=10**400), "depth_scale .* too large"),
    (lambda d: d["1"].update(depth_scale=True), "depth_scale .* must be a number, got bool"),
    # absurd but finite values
    (lambda d: [e.update(depth_scale=1e300) for e in d.values()], r"depth_scale \(mm per raw depth unit\) must be within"),
    (lambda d: [e.update(depth_scale=1e-300) for e in d.values()], r"depth_scale \(mm per raw depth unit\) must be within"),
    (lambda d: d["1"].update(cam_K=[1e308, 0, 31.5, 0, 61, 24.25, 0, 0, 1]), "focal length fx = 1e\\+308 px is implausible"),
    (lambda d: d["1"].update(cam_K=[60, 0, 31.5, 0, 61, 24.25, 5, 7, 0]), r"K must be \[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
    (lambda d: d["1"].update(cam_K=[60, 0, 500, 0, 61, 24.25, 0, 0, 1]), r"principal point .* far outside the 64x48 image"),
    (lambda d: d["1"].update(cam_t_w2c=[1e308, 0, 0]), r"translation \(mm\) element 1 must be within"),
])
def test_bop_scene_camera_values_are_checked(tmp_path, fn, msg):
    write_scene(tmp_path)
    _mutate(tmp_path / "scene_camera.json", fn)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "scene_camera.json"


@pytest.mark.parametrize("old, new, msg", [
    ('"0": {', '"0": {"cam_K": [1], "0": 1}, "0": {', "the key '0' twice"),     # json would keep the last
    ('"depth_scale": 0.1', '"depth_scale": ' + "1" * 5000, "number too long to read"),  # > 4300 digits
])
def test_bop_scene_camera_json_oddities_are_input_errors(tmp_path, old, new, msg):
    write_scene(tmp_path)
    _edit_text(tmp_path / "scene_camera.json", old, new)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path)
    assert e.value.path == tmp_path / "scene_camera.json"


def test_scene_gt_ids_are_ascii_and_unique(tmp_path):
    bop.write_scene_gt(tmp_path / "scene_gt.json", [[(3, np.eye(4))], [(7, np.eye(4))]])
    _mutate(tmp_path / "scene_gt.json", lambda d: d.update({"01": d["1"]}))
    with pytest.raises(InputError, match=r"two entries for image 1 \('1' and '01'\)"):
        bop.read_scene_gt(tmp_path)
    _mutate(tmp_path / "scene_gt.json", lambda d: d.update({"٣": d.pop("01")}))  # an Arabic-Indic 3
    with pytest.raises(InputError, match="must be a whole number"):
        bop.read_scene_gt(tmp_path)


def test_bop_links_out_of_the_scene_are_refused(tmp_path):
    """rgb/ and depth/ files that are symbolic links leading out of the scene folder are refused (they were
    followed, and hard-linked into the poses output), as paths named in a file are; links inside are fine."""
    import os

    scene = tmp_path / "scene"
    write_scene(scene)
    outside = tmp_path / "outside.png"
    (scene / "rgb" / "000002.png").rename(outside)
    os.symlink(outside, scene / "rgb" / "000002.png")
    with pytest.raises(InputError, match="leads outside its folder") as e:
        load_dataset(scene)
    assert e.value.path == scene / "rgb" / "000002.png"
    # a link that stays inside the scene is read as before
    (scene / "rgb" / "000002.png").unlink()
    (scene / "kept").mkdir()
    outside.rename(scene / "kept" / "000002.png")
    os.symlink(scene / "kept" / "000002.png", scene / "rgb" / "000002.png")
    assert len(load_dataset(scene).frames) == 4
    # depth/ likewise
    (scene / "depth" / "000001.png").rename(tmp_path / "d.png")
    os.symlink(tmp_path / "d.png", scene / "depth" / "000001.png")
    with pytest.raises(InputError, match="leads outside its folder") as e:
        load_dataset(scene)
    assert e.value.path == scene / "depth" / "000001.png"


@pytest.mark.parametrize("kind", ["8-bit", "rgb", "size", "garbage", "truncated"])
def test_bop_depth_images_must_be_16_bit_depth_of_the_camera_size(tmp_path, kind):
    """An 8-bit or colour depth PNG was read as millimetres; a wrong-sized one failed (rc 1) only when
    back-projected; a corrupt one was called an unreadable "mask"."""
    write_scene(tmp_path)
    bad = tmp_path / "depth" / "000002.png"
    if kind == "8-bit":
        io.write_image(bad, np.full((H, W), 100, np.uint8))
    elif kind == "rgb":
        io.write_image(bad, np.full((H, W, 3), 100, np.uint8))
    elif kind == "size":
        io.write_image(bad, np.full((H + 2, W), 100, np.uint16))
    elif kind == "garbage":
        bad.write_bytes(b"not a png at all")
    else:
        bad.write_bytes(bad.read_bytes()[:200])
    msg = {"8-bit": "single-channel 16-bit.*mode 'L'", "rgb": "single-channel 16-bit.*mode 'RGB'",
           "size": f"depth map is {W}x{H + 2} but its camera is {W}x{H}", "garbage": "unreadable depth image",
           "truncated": "depth image is truncated"}[kind]
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path)
    assert e.value.path == bad
    # and where it is read (the poses stage's back-projection): named as a depth image, with its size
    if kind == "truncated":
        msg = "unreadable depth image .*truncated"
    with pytest.raises(InputError, match=msg) as e:
        load_depth(bad, 1e-4, size=(W, H))
    assert e.value.path == bad


def test_object_names_keys_are_ascii_obj_ids(tmp_path):
    io.write_json(tmp_path / "object_names.json", {"\u00b2": "mug"})    # '²' passed str.isdigit, int() failed
    with pytest.raises(InputError, match="obj_id '²' must be a whole number") as e:
        bop.object_names(tmp_path, [1])
    assert e.value.path == tmp_path / "object_names.json"


def test_bop_notes_are_logged_once_per_scene(tmp_path, caplog):
    """'no camera poses ... poses will be estimated' came six times in one build (every stage reads the scene)."""
    write_scene(tmp_path, n=2, poses=False)
    with caplog.at_level("INFO", logger="splattwin.capture.bop"):
        for _ in range(3):
            load_dataset(tmp_path)
    assert caplog.text.count("poses will be estimated") == 1
