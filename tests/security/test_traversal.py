"""Path traversal from every entry point: names (COCO categories, polygon JSON, mask files, `--object`,
twin.json, scene.json) and paths read from files (mask index, twin.json, transforms.json, COLMAP,
cameras.json, metrics.json). Each is refused with exit 2 naming the file, and nothing outside the
folders involved is read, written or deleted."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.errors import InputError
from splattwin.semantics.masks import load_masks

from security_helpers import assert_bad_input, tree_snapshot


@pytest.fixture
def victim(tmp_path) -> Path:
    """A folder outside every twin that must survive untouched."""
    v = tmp_path / "victim"
    v.mkdir()
    (v / "precious.txt").write_text("do not delete")
    return v


# -- names -------------------------------------------------------------------------------------------
def _coco(path: Path, cat_name: str) -> Path:
    io.write_json(path, {"images": [{"id": 1, "file_name": "train_000.png", "height": 36, "width": 48}],
                         "categories": [{"id": 1, "name": cat_name}],
                         "annotations": [{"image_id": 1, "category_id": 1,
                                          "segmentation": [[2, 2, 20, 2, 20, 20, 2, 20]]}]})
    return path


@pytest.mark.parametrize("name", ["../../victim", "/abs/victim", "a/b", "..", ".", "x" * 100])
def test_coco_category_names_are_checked(tmp_path, victim, cli, tiny_dataset, name):
    coco = _coco(tmp_path / "ann.json", name)
    with pytest.raises(InputError) as e:
        load_masks(coco)
    assert e.value.path == coco
    before = tree_snapshot(tmp_path)
    res = cli("segment", tiny_dataset, "--masks", coco, "--out", tmp_path / "seg")
    assert_bad_input(res, "ann.json", "not allowed")
    after = tree_snapshot(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith("seg")} == before
    assert (victim / "precious.txt").read_text() == "do not delete"


def test_polygon_json_and_mask_file_names_are_checked(tmp_path):
    f = tmp_path / "poly" / "img7_mask.json"
    io.write_json(f, {"image_filename": "img7.png", "image_height": 10, "image_width": 12, "object": "../../x",
                      "segmentation_polygons": [[[2, 2], [6, 2], [6, 5], [2, 5]]]})
    with pytest.raises(InputError, match="not allowed") as e:
        load_masks(tmp_path / "poly")
    assert e.value.path == f
    io.write_json(f, {"image_filename": "../../img7.png", "image_height": 10, "image_width": 12,
                      "segmentation_polygons": [[[2, 2], [6, 2], [6, 5], [2, 5]]]})
    load_masks(tmp_path / "poly")  # the view is the file *stem*: "img7", harmless
    io.write_json(f, {"image_filename": "..", "image_height": 10, "image_width": 12,
                      "segmentation_polygons": [[[2, 2], [6, 2], [6, 5], [2, 5]]]})
    with pytest.raises(InputError, match="image_filename"):
        load_masks(tmp_path / "poly")
    png = tmp_path / "png" / "train_000" / "...png"   # stem ".." as an object name: a hidden file, never read
    io.write_image(png, np.full((4, 4), 255, np.uint8))
    with pytest.raises(InputError, match="no <view>/<object>.png masks"):
        load_masks(tmp_path / "png")
    io.write_image(tmp_path / "png" / "train_000" / "a b..png", np.full((4, 4), 255, np.uint8))   # stem "a b."
    with pytest.raises(InputError, match="not allowed"):
        load_masks(tmp_path / "png")


def test_mask_index_paths_stay_inside(tmp_path, victim):
    from splattwin.semantics.masks import MaskSet

    ms = MaskSet(objects={1: "box"})
    ms.add("v0", 1, np.ones((4, 5), bool))
    ms.save(tmp_path / "m")
    io.write_image(victim / "secret.png", np.full((4, 5), 255, np.uint8))
    index = json.loads((tmp_path / "m" / "masks.json").read_text())
    for bad in ("../victim/secret.png", str(victim / "secret.png")):
        index["views"]["v0"]["masks"]["box"]["file"] = bad
        io.write_json(tmp_path / "m" / "masks.json", index)
        with pytest.raises(InputError) as e:
            load_masks(tmp_path / "m")
        assert e.value.path == tmp_path / "m" / "masks.json"
    index["views"]["../../v0"] = index["views"].pop("v0")
    index["views"]["../../v0"]["masks"]["box"]["file"] = "v0/box.png"
    io.write_json(tmp_path / "m" / "masks.json", index)
    with pytest.raises(InputError, match="view name"):
        load_masks(tmp_path / "m")


def test_object_option_is_checked(tmp_path, cli):
    from splattwin.scene.synthetic import synthetic_scene

    g, labels, _, _ = synthetic_scene(2000, seed=3)
    ply = g.save_ply(tmp_path / "s.ply")
    np.save(tmp_path / "l.npy", labels)
    res = cli("geometry", ply, "--labels", tmp_path / "l.npy", "--object", "../../victim=1", "--out", tmp_path / "t")
    assert_bad_input(res, "--object", "not allowed")
    assert not (tmp_path / "victim").exists()


def test_unusable_object_named_as_a_path_deletes_nothing(tmp_path, victim):
    """The issue's data loss: an object that got no Gaussians had its folder objects/<name> removed."""
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.twin.build import build_twin

    g, labels, _, _ = synthetic_scene(2000, seed=3)
    out = tmp_path / "a" / "b" / "twin"   # objects/../../victim would be tmp_path/a/b/victim; try deeper too
    for name in ("../../victim", "../../../../victim"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(InputError, match="not allowed"):
                build_twin(g, labels, [(name, 99, "")], out, formats=(), progress=False)
    assert (victim / "precious.txt").read_text() == "do not delete"


def test_symlinked_object_folder_is_not_followed(tmp_path, victim):
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.twin.build import build_twin

    g, labels, objects, _ = synthetic_scene(3000, seed=2)
    out = tmp_path / "twin"
    (out / "objects").mkdir(parents=True)
    os.symlink(victim, out / "objects" / objects[0][0])   # planted by whoever sent the folder
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(InputError, match="leads outside"):
            build_twin(g, labels, objects, out, formats=(), progress=False)
    assert sorted(p.name for p in victim.iterdir()) == ["precious.txt"]


# -- twin.json ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gt_twin(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.build import export_twin
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_twin") / "twin"
    twin_from_scene(scene_small, out)
    export_twin(out, formats=("urdf",))
    return out


def _tampered(gt_twin: Path, tmp_path: Path, edit) -> Path:
    twin = tmp_path / "twins" / "t"
    shutil.copytree(gt_twin, twin)
    d = json.loads((twin / "twin.json").read_text())
    edit(d)
    (twin / "twin.json").write_text(json.dumps(d))
    return twin


@pytest.mark.parametrize("case", ["name", "mesh_up", "mesh_abs", "part_up", "export_abs", "splats_up"])
def test_twin_json_paths_and_names_are_confined(gt_twin, tmp_path, victim, cli, case):
    (tmp_path / "twins").mkdir()
    outside = tmp_path / "twins" / "outside.obj"
    shutil.copy(gt_twin / gt_twin_first_part(gt_twin), outside)   # a valid mesh, just outside the twin

    def edit(d):
        o = d["objects"][0]
        if case == "name":
            o["name"] = "../../victim"
        elif case == "mesh_up":
            o["collision_mesh"] = "../outside.obj"
        elif case == "mesh_abs":
            o["visual_mesh"] = str(outside)
        elif case == "part_up":
            o["convex_parts"] = ["objects/../../outside.obj"]
        elif case == "export_abs":
            d["exports"]["urdf"] = "/etc/passwd"
        else:
            d["splats"] = "../../../../../etc/passwd"

    twin = _tampered(gt_twin, tmp_path, edit)
    before = tree_snapshot(tmp_path / "twins")
    for cmd in (["export", twin, "--formats", "urdf"], ["report", twin], ["plan", twin, "--no-render"]):
        res = cli(*cmd)
        assert_bad_input(res, "twin.json")
        if case != "name":  # the error names the real twin folder (it once named a placeholder folder)
            assert f"its folder {twin}" in res.err and "nonexistent" not in res.err, res.err
    from splattwin.viewer.app import serve

    with pytest.raises(InputError):
        serve(twin, port=0, block=False)
    after = tree_snapshot(tmp_path / "twins")
    changed = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}
    assert all(k.startswith("t/.splattwin") or k == "t" for k in changed), changed  # only the lock
    assert (victim / "precious.txt").read_text() == "do not delete"


def gt_twin_first_part(twin: Path) -> str:
    return json.loads((twin / "twin.json").read_text())["objects"][0]["convex_parts"][0]


def test_scene_json_mesh_paths_are_confined(scene_small, tmp_path):
    from splattwin.twin.groundtruth import twin_from_scene

    scene = tmp_path / "scene"
    shutil.copytree(scene_small, scene)
    meta = json.loads((scene / "scene.json").read_text())
    meta["objects"][0]["mesh"] = "../../../etc/hostname"
    (scene / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="leads outside") as e:
        twin_from_scene(scene, tmp_path / "gt")
    assert e.value.path == scene / "scene.json"


# -- datasets ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("key,value", [("file_path", "../outside.png"), ("file_path", "ABS"),
                                       ("depth_file_path", "../outside.npy"), ("mask_path", "/etc/passwd"),
                                       ("label_path", "images/../../outside.png")])
def test_transforms_json_paths_are_confined(tiny_dataset, tmp_path, cli, key, value):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    shutil.copy(ds / "images" / "train_000.png", tmp_path / "outside.png")   # a real image, outside
    np.save(tmp_path / "outside.npy", np.ones((36, 48), np.float32))
    meta = json.loads((ds / "transforms.json").read_text())
    meta["frames"][0][key] = str(tmp_path / "outside.png") if value == "ABS" else value
    (ds / "transforms.json").write_text(json.dumps(meta))
    assert_bad_input(cli("capture", "info", ds), "transforms.json", key)
    meta = json.loads((tiny_dataset / "transforms.json").read_text())
    meta["ply_file_path"] = "../../outside.ply"
    (ds / "transforms.json").write_text(json.dumps(meta))
    assert_bad_input(cli("capture", "info", ds), "transforms.json", "ply_file_path")


@pytest.mark.parametrize("key", ["file_path", "depth_file_path", "mask_path", "label_path"])
@pytest.mark.parametrize("value", ["images/" + "y" * 300 + ".png", "LOOP"])
def test_transforms_json_paths_the_file_system_cannot_look_up_are_bad_input(tiny_dataset, tmp_path, cli, key, value):
    """A name longer than the file system allows (the reader's is_file() raised OSError ENAMETOOLONG) and a
    symbolic link that points to itself (Path.resolve raised RuntimeError) were internal errors (exit 1)."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    if value == "LOOP":
        (ds / "images" / "loop.png").symlink_to(ds / "images" / "loop.png")
        value = "images/loop.png"
    meta = json.loads((ds / "transforms.json").read_text())
    meta["frames"][0][key] = value
    (ds / "transforms.json").write_text(json.dumps(meta))
    assert_bad_input(cli("capture", "info", ds), "transforms.json", key, "cannot be looked up" if "y" * 300 in value
                     else "loop of symbolic links")


def test_colmap_image_name_too_long_is_bad_input(tiny_dataset, tmp_path, cli):
    """The same long name in images.txt: OSError from is_file() before (exit 1)."""
    from splattwin.capture import colmap, load_dataset

    proj = tmp_path / "proj"
    shutil.copytree(tiny_dataset / "images", proj / "images")
    colmap.write_text(load_dataset(tiny_dataset), proj / "sparse" / "0")
    text = (proj / "sparse" / "0" / "images.txt").read_text().replace(" train_000.png", " " + "y" * 300 + ".png")
    (proj / "sparse" / "0" / "images.txt").write_text(text)
    assert_bad_input(cli("capture", "info", proj), "image name", "cannot be looked up")


def test_colmap_image_names_are_confined(tiny_dataset, tmp_path, cli):
    from splattwin.capture import colmap, load_dataset

    proj = tmp_path / "proj"
    shutil.copytree(tiny_dataset / "images", proj / "images")
    colmap.write_text(load_dataset(tiny_dataset), proj / "sparse" / "0")
    shutil.copy(proj / "images" / "train_000.png", tmp_path / "outside.png")
    text = (proj / "sparse" / "0" / "images.txt").read_text().replace(" train_000.png", " ../outside.png")
    (proj / "sparse" / "0" / "images.txt").write_text(text)
    assert_bad_input(cli("capture", "info", proj), "image name", "leads outside")


def test_cameras_json_image_names_are_confined(tiny_dataset, tmp_path, cli):
    from splattwin.capture import cameras_json, load_dataset

    d = tmp_path / "cj"
    shutil.copytree(tiny_dataset / "images", d / "images")
    cameras_json.write(load_dataset(tiny_dataset), d / "cameras.json")
    shutil.copy(d / "images" / "train_000.png", tmp_path / "outside.png")
    cams = json.loads((d / "cameras.json").read_text())
    cams[0]["img_name"] = "../../outside"
    (d / "cameras.json").write_text(json.dumps(cams))
    assert_bad_input(cli("capture", "info", d), "cameras.json", "img_name")


def test_report_never_embeds_files_from_outside(gt_twin, tmp_path, cli):
    twin = tmp_path / "t"
    shutil.copytree(gt_twin, twin)
    io.write_image(tmp_path / "private.png", np.full((8, 8, 3), 200, np.uint8))
    io.write_json(twin / "splat" / "eval" / "metrics.json",
                  {"split": "heldout", "mean_psnr": 30.0, "mean_ssim": 0.9, "gaussians": 10,
                   "views": [{"name": "v", "psnr": 30.0, "ssim": 0.9, "image": str(tmp_path / "private.png")}]})
    assert_bad_input(cli("report", twin), "metrics.json", "absolute")
    assert not (twin / "report" / "index.html").exists() or b"base64" not in (twin / "report" / "index.html").read_bytes()


def test_links_out_of_the_output_folder_are_refused(tmp_path, victim, cli, tiny_dataset):
    """A received folder reused as --out whose splat/ is a link elsewhere: nothing is written there."""
    from splattwin.scene.synthetic import synthetic_scene

    g, _, _, _ = synthetic_scene(500, seed=0)
    ply = g.save_ply(tmp_path / "s.ply")
    out = tmp_path / "received"
    out.mkdir()
    os.symlink(victim, out / "splat")
    before = tree_snapshot(victim)
    assert_bad_input(cli("geometry", ply, "--out", out), "received/splat", "symbolic link")
    assert_bad_input(cli("build", tiny_dataset, "--out", out, "--iters", "5"), "received/splat")
    assert tree_snapshot(victim) == before
