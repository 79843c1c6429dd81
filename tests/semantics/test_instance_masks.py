"""Per-instance mask files: BOP mask_visib / mask (obj_id via scene_gt.json, names, repeated objects),
`<view>_<instance>.png` with instances.json, and bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import bop, look_at
from splattwin.cli import main
from splattwin.errors import InputError
from splattwin.semantics.masks import load_masks, save_instance_masks

W, H = 40, 30


def _box(x0, y0, x1, y1) -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    m[y0:y1, x0:x1] = 255
    return m


def _scene(root: Path, gt: list[list[tuple[int, np.ndarray]]], masks: dict[tuple[int, int], np.ndarray],
           poses: bool = True) -> None:
    """BOP scene: len(gt) images seen from two sides of the origin; gt[i] = [(obj_id, T_world_obj)]."""
    cams = [look_at(np.array([0.0, -0.6, 0.5]), np.zeros(3)), look_at(np.array([0.6, 0.0, 0.5]), np.zeros(3))]
    from splattwin.capture import Camera

    K = np.array([[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]])
    cameras = [Camera(K=K, width=W, height=H, T_world_cam=cams[i % 2]) for i in range(len(gt))]
    for i in range(len(gt)):
        io.write_image(root / "rgb" / bop.image_name(i), np.zeros((H, W, 3), np.uint8))
    bop.write_scene_camera(root / bop.SCENE_CAMERA, cameras, with_poses=poses)
    bop.write_scene_gt(root / bop.SCENE_GT, [[(oid, c.T_cam_world @ T) for oid, T in lst]
                                              for lst, c in zip(gt, cameras)])
    for (i, k), m in masks.items():
        io.write_image(root / "mask_visib" / bop.mask_name(i, k), m)


def _at(x, y) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = [x, y]
    return T


A, B, C = _box(2, 2, 10, 10), _box(20, 5, 30, 20), _box(5, 15, 15, 28)


def test_bop_masks_map_to_the_right_objects(tmp_path):
    _scene(tmp_path, [[(5, _at(0, 0)), (7, _at(0.1, 0))], [(7, _at(0.1, 0)), (5, _at(0, 0))]],
           {(0, 0): A, (0, 1): B, (1, 0): C, (1, 1): np.zeros((H, W), np.uint8)})
    io.write_json(tmp_path / bop.NAMES_FILE, {"5": "mug"})
    for path in (tmp_path, tmp_path / "mask_visib"):
        ms = load_masks(path)
        assert sorted(ms.objects.values()) == ["mug", "obj_000007"] and ms.source.startswith("bop:")
        mug, o7 = ms.label_of("mug"), ms.label_of("obj_000007")
        assert np.array_equal(ms.get("000000", mug), A > 0) and np.array_equal(ms.get("000000", o7), B > 0)
        assert np.array_equal(ms.get("000001", o7), C > 0)
        assert ms.get("000001", mug) is None and ms.sizes["000001"] == (H, W)  # empty: not found there
    # a name -> label map (e.g. from scene.json) is honoured
    ms = load_masks(tmp_path, objects={"obj_000007": 3})
    assert ms.objects[3] == "obj_000007" and np.array_equal(ms.get("000000", 3), B > 0)


def test_mask_visib_preferred_and_mask_folder_explicitly(tmp_path):
    _scene(tmp_path, [[(1, _at(0, 0))]], {(0, 0): A})
    io.write_image(tmp_path / "mask" / bop.mask_name(0, 0), B)   # the amodal silhouette differs
    assert np.array_equal(load_masks(tmp_path).get("000000", 1), A > 0)
    assert np.array_equal(load_masks(tmp_path / "mask").get("000000", 1), B > 0)


def test_repeated_objects_told_apart_by_world_position(tmp_path):
    # two copies of obj 2; image 1 lists them in the other order
    p, q = _at(-0.1, 0.05), _at(0.12, -0.04)
    _scene(tmp_path, [[(2, p), (2, q)], [(2, q), (2, p)]], {(0, 0): A, (0, 1): B, (1, 0): C, (1, 1): B})
    ms = load_masks(tmp_path)
    first, second = ms.label_of("obj_000002"), ms.label_of("obj_000002_2")
    assert np.array_equal(ms.get("000000", first), A > 0) and np.array_equal(ms.get("000001", first), B > 0)
    assert np.array_equal(ms.get("000000", second), B > 0) and np.array_equal(ms.get("000001", second), C > 0)


def test_repeated_objects_without_poses_by_order(tmp_path, caplog):
    p, q = _at(-0.1, 0.05), _at(0.12, -0.04)
    _scene(tmp_path, [[(2, p), (2, q)], [(2, q), (2, p)]], {(0, 0): A, (0, 1): B, (1, 0): C, (1, 1): B},
           poses=False)
    with caplog.at_level(logging.WARNING):
        ms = load_masks(tmp_path)
    assert "told apart by their order" in caplog.text
    assert np.array_equal(ms.get("000001", ms.label_of("obj_000002")), C > 0)


def test_bop_mask_size_and_scene_gt_errors_name_the_file(tmp_path):
    _scene(tmp_path, [[(1, _at(0, 0))]], {(0, 0): A})
    with pytest.raises(InputError, match="is 40x30 but its image is 50x30") as e:
        load_masks(tmp_path, image_sizes={"000000": (30, 50)})
    assert e.value.path == tmp_path / "mask_visib" / "000000_000000.png"
    io.write_json(tmp_path / bop.SCENE_GT, {"0": [{"obj_id": "mug"}]})
    with pytest.raises(InputError, match="obj_id must be") as e:
        load_masks(tmp_path)
    assert e.value.path == tmp_path / bop.SCENE_GT


def test_instance_files_with_names(tmp_path):
    d = tmp_path / "masks"
    for view, inst, m in (("img_a", 1, A), ("img_a", 2, B), ("img_b", 2, C)):
        io.write_image(d / f"{view}_{inst:06d}.png", m)
    io.write_json(d / "instances.json", {"1": "mug", "2": "toy hammer"})
    ms = load_masks(d)
    assert sorted(ms.objects.values()) == ["mug", "toy hammer"]
    assert np.array_equal(ms.get("img_b", ms.label_of("toy hammer")), C > 0)
    assert ms.get("img_b", ms.label_of("mug")) is None
    # round trip through the writer
    out = save_instance_masks(ms, tmp_path / "again")
    back = load_masks(out)
    for v in ms.views:
        for k, name in ms.objects.items():
            a, b = ms.get(v, k), back.get(v, back.label_of(name))
            assert (a is None and b is None) or np.array_equal(a, b)
    io.write_json(d / "instances.json", {"1": "mug"})
    with pytest.raises(InputError, match="instance 2 .* has no name") as e:
        load_masks(d)
    assert e.value.path == d / "instances.json"
    io.write_json(d / "instances.json", {"1": "mug", "2": "a/b"})
    with pytest.raises(InputError, match="not allowed"):
        load_masks(d)


def test_instance_files_recognised_by_view_names(tmp_path):
    d = tmp_path / "masks"
    io.write_image(d / "frame_0007_3.png", A)
    io.write_image(d / "frame_0008_3.png", C)
    ms = load_masks(d, image_sizes={"frame_0007": (H, W), "frame_0008": (H, W)})
    assert list(ms.objects.values()) == ["instance_3"] and ms.views == ["frame_0007", "frame_0008"]
    # without the views the same files are label images named after the files (the old reading)
    assert load_masks(d).views == ["frame_0007_3", "frame_0008_3"]


def test_build_preflight_rejects_a_bad_bop_mask_with_exit_2(tmp_path, capsys):
    scene = tmp_path / "scene"
    _scene(scene, [[(1, _at(0, 0))], [(1, _at(0, 0))]], {(0, 0): A, (1, 0): _box(0, 0, 4, 4)[:20]})
    code = main(["build", str(scene), "--out", str(tmp_path / "twin"), "--poses", "known",
                 "--masks", str(scene / "mask_visib"), "--iters", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "000001_000000.png" in err and "but its image is 40x30" in err
    assert not (tmp_path / "twin" / "poses").exists()   # stopped before any stage


# -- untrusted folders: links, keys, counts, names ---------------------------------------------------------
def test_mask_links_leaving_the_folder_are_refused(tmp_path):
    import os

    outside = tmp_path / "outside.png"
    io.write_image(outside, B)
    scene = tmp_path / "scene"
    _scene(scene, [[(1, _at(0, 0)), (2, _at(0.1, 0))]], {(0, 0): A})
    os.symlink(outside, scene / "mask_visib" / bop.mask_name(0, 1))
    for path in (scene, scene / "mask_visib"):
        with pytest.raises(InputError, match="leads outside its folder") as e:
            load_masks(path)
        assert e.value.path == scene / "mask_visib" / bop.mask_name(0, 1)
    d = tmp_path / "inst"
    io.write_image(d / "img_a_1.png", A)
    io.write_json(d / "instances.json", {"1": "mug", "2": "bowl"})
    os.symlink(outside, d / "img_a_2.png")
    with pytest.raises(InputError, match="leads outside its folder") as e:
        load_masks(d)
    assert e.value.path == d / "img_a_2.png"
    # a link that stays inside the folder is a file of the folder
    (d / "img_a_2.png").unlink()
    os.symlink("img_a_1.png", d / "img_a_2.png")
    assert sorted(load_masks(d).objects.values()) == ["bowl", "mug"]


@pytest.mark.parametrize("key", ["²", "٣", "1²"])
def test_non_ascii_digit_keys_are_input_errors(tmp_path, key):
    scene = tmp_path / "scene"
    _scene(scene, [[(1, _at(0, 0))]], {(0, 0): A})
    io.write_json(scene / bop.NAMES_FILE, {key: "mug"})
    with pytest.raises(InputError, match="must be a whole number") as e:
        load_masks(scene)
    assert e.value.path == scene / bop.NAMES_FILE
    (scene / bop.NAMES_FILE).unlink()
    io.write_json(scene / bop.SCENE_GT, {key: [{"obj_id": 1}]})
    with pytest.raises(InputError, match="must be a whole number") as e:
        load_masks(scene)
    assert e.value.path == scene / bop.SCENE_GT
    d = tmp_path / "inst"
    io.write_image(d / "img_a_1.png", A)
    io.write_json(d / "instances.json", {key: "mug"})
    with pytest.raises(InputError, match="must be a whole number") as e:
        load_masks(d)
    assert e.value.path == d / "instances.json"


def test_instances_json_names_must_be_unique(tmp_path):
    d = tmp_path / "inst"
    io.write_image(d / "img_a_1.png", A)
    io.write_image(d / "img_a_2.png", B)
    io.write_json(d / "instances.json", {"1": "mug", "2": "mug"})   # would merge two objects into one
    with pytest.raises(InputError, match="'mug' appears twice") as e:
        load_masks(d)
    assert e.value.path == d / "instances.json"
    io.write_json(d / "instances.json", {"1": "mug", "01": "bowl"})
    with pytest.raises(InputError, match="instance 1 is named twice"):
        load_masks(d)


def test_instances_per_bop_image_are_bounded(tmp_path):
    from splattwin.semantics.masks import MAX_OBJECTS_PER_VIEW

    _scene(tmp_path, [[(1, _at(0, 0))]], {(0, 0): A})
    io.write_json(tmp_path / bop.SCENE_GT, {"0": [{"obj_id": 1}] * (MAX_OBJECTS_PER_VIEW + 1)})
    with pytest.raises(InputError, match=f"{MAX_OBJECTS_PER_VIEW + 1} instances, more than the limit") as e:
        load_masks(tmp_path)
    assert e.value.path == tmp_path / bop.SCENE_GT


def test_many_repeated_instances_are_paired_across_images(tmp_path):
    # 400 copies of one obj_id at distinct places in both images: was a sum per instance over the image and
    # a Python distance list per instance (2000 copies took 26 s)
    n = 400
    _scene(tmp_path, [[(3, _at(0.1 * i, 0)) for i in range(n)]] * 2, {(0, 0): A, (1, n - 1): C})
    ms = load_masks(tmp_path)      # (the quadratic version took ~1 s here, 26 s for 2000: bench-worthy, not timed)
    assert np.array_equal(ms.get("000000", ms.label_of("obj_000003")), A > 0)
    assert np.array_equal(ms.get("000001", ms.label_of(f"obj_000003_{n}")), C > 0)   # the same object again


def test_segment_names_the_wrong_size_mask_file(tmp_path, capsys):
    scene = tmp_path / "scene"
    wide = np.zeros((H, W + 10), np.uint8)
    _scene(scene, [[(1, _at(0, 0)), (2, _at(0.1, 0))]], {(0, 0): wide, (0, 1): B})
    bad = scene / "mask_visib" / bop.mask_name(0, 0)
    code = main(["segment", str(scene), "--masks", str(scene), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and str(bad) in err and "is 50x30 but its image is 40x30" in err
    assert not (tmp_path / "out").exists()
    # without the images' sizes the file that set the view's size is named beside the one that differs
    with pytest.raises(InputError, match=f"is 40x30 but view '000000' is 50x30 .the size of {bad}."):
        load_masks(scene)
