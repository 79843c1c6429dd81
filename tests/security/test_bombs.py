"""Bombs: tiny files that claim enormous sizes (image headers, COCO masks, .npy and PLY headers) or
expand enormously (YAML aliases, deeply nested JSON) are refused, naming the file, before memory is
allocated for them (traced with tracemalloc: numpy reports its allocations to it)."""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from splattwin import io
from splattwin.errors import InputError

from security_helpers import assert_bad_input, npy_header_bomb, png_header_bomb, yaml_alias_bomb

PEAK_LIMIT = 64 << 20   # bytes: far below what any of the claims would allocate


def _bounded(fn, *args, **kw) -> InputError:
    """Run fn expecting an InputError, with the peak traced allocation below PEAK_LIMIT."""
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as e:
            fn(*args, **kw)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < PEAK_LIMIT, f"{peak / 2**20:.0f} MiB allocated before refusing"
    return e.value


def test_png_header_bomb(tmp_path, cli, tiny_dataset):
    from splattwin.capture import load_image
    from splattwin.semantics.masks import load_masks

    bomb = png_header_bomb(tmp_path / "imgs" / "a.png")
    assert bomb.stat().st_size < 200
    e = _bounded(load_image, bomb)
    assert e.path == bomb and "megapixels" in e.problem
    assert_bad_input(cli("capture", "info", tmp_path / "imgs"), "a.png", "megapixels")
    png_header_bomb(tmp_path / "masks" / "train_000" / "box.png")
    e = _bounded(load_masks, tmp_path / "masks")
    assert e.path.name == "box.png"
    # PIL's own guard (DecompressionBombError above 179 MP) also ends as exit 2, not a traceback
    png_header_bomb(tmp_path / "imgs2" / "b.png", 20000, 20000)
    assert_bad_input(cli("capture", "info", tmp_path / "imgs2"), "b.png")


def test_yaml_alias_bomb(tmp_path, cli, gt_twin_small):
    from splattwin.limits import load_yaml
    from splattwin.poses.robot import load_robot_poses
    from splattwin.robot.task import load_task

    task = tmp_path / "task.yaml"
    task.write_text(yaml_alias_bomb())   # 9**12 = 2.8e11 leaves in ~600 bytes
    assert task.stat().st_size < 1000
    e = _bounded(load_task, task)
    assert e.path == task and "aliases" in e.problem
    assert_bad_input(cli("plan", gt_twin_small, "--task", task, "--no-render"), "task.yaml", "aliases")
    poses = tmp_path / "poses.yaml"
    poses.write_text(yaml_alias_bomb().replace("steps:", "poses:"))
    _bounded(load_robot_poses, poses)
    (tmp_path / "rec.yaml").write_text("a: &a [*a]\n")
    with pytest.raises(InputError):
        load_yaml(tmp_path / "rec.yaml")
    (tmp_path / "deep.yaml").write_text("[" * 50000 + "]" * 50000)
    with pytest.raises(InputError, match="nested too deeply|not valid YAML"):
        load_yaml(tmp_path / "deep.yaml")
    # ordinary anchors are fine
    (tmp_path / "ok.yaml").write_text("base: &b {x: 1}\nsteps: [*b, *b]\n")
    assert load_yaml(tmp_path / "ok.yaml")["steps"] == [{"x": 1}, {"x": 1}]


@pytest.mark.parametrize("case", ["image_size", "rle_size", "rle_counts", "polygon"])
def test_coco_size_bomb(tmp_path, case):
    from splattwin.semantics.masks import load_masks

    H = W = 100_000   # 10^10 pixels: a 9+ GiB allocation before any check in the old loader
    im = {"id": 1, "file_name": "a.png", "height": H if case in ("image_size", "polygon") else 40,
          "width": W if case in ("image_size", "polygon") else 40}
    seg = {"size": [H, W], "counts": [0, H * W]} if case != "polygon" else [[0, 0, 10, 0, 10, 10]]
    if case == "rle_counts":
        seg = {"size": [40, 40], "counts": [0, 10**12]}
    coco = io.write_json(tmp_path / "ann.json", {"images": [im], "categories": [{"id": 1, "name": "box"}],
                                                 "annotations": [{"image_id": 1, "category_id": 1,
                                                                  "segmentation": seg}]})
    assert coco.stat().st_size < 1000
    e = _bounded(load_masks, coco)
    assert e.path == coco   # the COCO file is named, also for RLE errors


def test_npy_and_ply_header_bombs(tmp_path, cli):
    from splattwin.scene.synthetic import synthetic_scene
    from splattwin.limits import load_npy
    from splattwin.splat.gaussians import Gaussians

    g, labels, _, _ = synthetic_scene(1000, seed=1)
    ply = g.save_ply(tmp_path / "s.ply")
    bomb = npy_header_bomb(tmp_path / "labels.npy")
    _bounded(load_npy, bomb)
    assert_bad_input(cli("geometry", ply, "--labels", bomb, "--out", tmp_path / "t"), "labels.npy", "claims shape")
    head = ply.read_bytes().split(b"end_header\n")[0].decode()
    big = tmp_path / "big.ply"
    big.write_bytes(head.replace(f"element vertex {len(g)}", "element vertex 1000000000000").encode()
                    + b"end_header\n" + b"\0" * 100)
    _bounded(Gaussians.load_ply, big)
    assert_bad_input(cli("geometry", big, "--out", tmp_path / "t2"), "big.ply")
    empty = tmp_path / "empty.ply"
    empty.write_bytes(head.replace(f"element vertex {len(g)}", "element vertex 0").encode() + b"end_header\n")
    assert_bad_input(cli("geometry", empty, "--out", tmp_path / "t3"), "empty.ply", "no Gaussians")


def test_json_nesting_and_size(tmp_path):
    from splattwin.limits import read_json

    (tmp_path / "deep.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(InputError, match="nested too deeply") as e:
        read_json(tmp_path / "deep.json")
    assert e.value.path == tmp_path / "deep.json"
    with pytest.raises(InputError, match="limit"):
        read_json(tmp_path / "deep.json", max_bytes=1000)


def test_json_long_integers_and_duplicate_keys(tmp_path):
    """Python refuses to parse integers of more than 4300 digits with a ValueError that read_json let through
    (exit 1); a key given twice in one object was silently the last one's."""
    from splattwin.limits import read_json

    p = tmp_path / "long.json"
    p.write_text('{"id": ' + "7" * 5000 + "}")
    with pytest.raises(InputError, match="number too long to read") as e:
        read_json(p)
    assert e.value.path == p and len(str(e.value)) < 300
    p.write_text('{"a": {"0": {"cam_K": 1}, "0": {"cam_K": 2}}}')
    with pytest.raises(InputError, match="the key '0' twice") as e:
        read_json(p)
    assert e.value.path == p
    p.write_text('{"a": [{"0": 1}, {"0": 2}]}')   # one key in two objects is fine
    assert read_json(p) == {"a": [{"0": 1}, {"0": 2}]}


def test_numbers_read_from_files_are_numbers(tmp_path):
    """The shared number parsing of the capture readers: bools, text, integers beyond float range and
    non-finite values are InputErrors naming the file; YAML's 1e3-as-text gets a hint."""
    from splattwin.limits import ascii_uint, check_pixels, number, numbers

    where = tmp_path / "f.json"
    assert number(3, where, "x") == 3.0 and numbers([[1, 2], [3, 4]], 4, where, "M").tolist() == [1, 2, 3, 4]
    for v, msg in [(True, "must be a number, got bool"), ("1.5", "got str '1.5' .write numbers without quotes"),
                   ("1e3", r"YAML .* write 1\.0e\+3"), (10**400, "about 400 digits> is too large"),
                   (float("inf"), "finite"), (None, "must be a number"), (2e6, r"within \[0, 1e\+06\]")]:
        with pytest.raises(InputError, match=msg) as e:
            number(v, where, "x", 0, 1e6)
        assert e.value.path == where
    for v, msg in [(["1", 2], "element 1 must be a number"), ([1], "must hold 2 numbers, got 1"),
                   ("12", "must be a list of 2 numbers"), ([[[[[1, 2]]]]] * 1000, "must hold 2 numbers")]:
        with pytest.raises(InputError, match=msg):
            numbers(v, 2, where, "v")
    for w, msg in [(True, "whole numbers, got True"), (10**5000, "about 5000 digits")]:
        with pytest.raises(InputError, match=msg):
            check_pixels(w, 10, where)
    assert [ascii_uint(s) for s in ("12", "0012", "²", "٣", "", "-1", "1" * 19)] == [12, 12, None, None, None, None, None]


@pytest.fixture(scope="module")
def gt_twin_small(tmp_path_factory, scene_small) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_small") / "twin"
    twin_from_scene(scene_small, out)
    return out


def test_mesh_bombs_in_a_twin(gt_twin_small, tmp_path, cli):
    import shutil

    twin = tmp_path / "t"
    shutil.copytree(gt_twin_small, twin)
    d = json.loads((twin / "twin.json").read_text())
    part = twin / d["objects"][0]["convex_parts"][0]
    part.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\nproperty float x\n"
                     b"end_header\n")
    d["objects"][0]["convex_parts"][0] = d["objects"][0]["convex_parts"][0].replace(".obj", ".ply")
    part.rename(part.with_suffix(".ply"))
    (twin / "twin.json").write_text(json.dumps(d))
    assert_bad_input(cli("export", twin, "--formats", "mjcf"), part.with_suffix(".ply").name)


@pytest.mark.parametrize("fmt", ["nerfstudio", "cameras.json", "bop"])
def test_capture_files_listing_too_many_views_are_refused(tmp_path, monkeypatch, fmt):
    """A transforms.json of 1.2 M frames (600 MB, under the JSON limit) or a cameras.json of 500 000 cameras ran
    for minutes (each view costs its reader ~0.1 ms and validate() ~3 ms): the number of views a capture file
    lists is bounded by SPLATTWIN_MAX_VIEWS (here lowered to 5 so that the test writes 6)."""
    from splattwin import limits
    from splattwin.capture import bop, cameras_json, load_dataset, look_at, nerfstudio
    from splattwin.capture.camera import Camera
    from splattwin.capture.dataset import Dataset, Frame

    for mod in (limits, nerfstudio, bop):
        monkeypatch.setattr(mod, "MAX_VIEWS", 5, raising=False)
    frames = []
    for i in range(6):
        img = tmp_path / "images" / f"v{i}.png"
        io.write_image(img, np.zeros((12, 16, 3), np.uint8))
        K = np.array([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
        T = look_at(np.array([np.cos(i), np.sin(i), 0.5]), np.zeros(3))
        frames.append(Frame(image_path=img, camera=Camera(K=K, width=16, height=12, T_world_cam=T, name=img.stem)))
    ds = Dataset(root=tmp_path, frames=frames, has_poses=True)
    if fmt == "nerfstudio":
        where = nerfstudio.write(ds, tmp_path / "transforms.json")
    elif fmt == "cameras.json":
        where = cameras_json.write(ds, tmp_path / "cameras.json")
    else:
        (tmp_path / "images").rename(tmp_path / "rgb")
        for i in range(6):
            (tmp_path / "rgb" / f"v{i}.png").rename(tmp_path / "rgb" / bop.image_name(i))
        where = bop.write_scene_camera(tmp_path / "scene_camera.json", [f.camera for f in frames])
    with pytest.raises(InputError, match=r"6 (frames|cameras|images) is outside \[0, 5\] \(set SPLATTWIN_MAX_VIEWS") as e:
        load_dataset(where)
    assert e.value.path == where
