"""One object, one label id on every route (COCO category ids kept, as `segment` and `build` keep them),
and the fused labels scored against the ground truth by object name, so that masks numbered otherwise
than the ground-truth label images cannot read as a low mIoU."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import nerfstudio
from splattwin.errors import InputError
from splattwin.semantics import lift
from splattwin.semantics.masks import load_masks
from splattwin.semantics.rle import encode

H, W = 8, 10


def _coco(path, cats: dict[int, str]):
    """One image, one square mask per category (category id k at columns 2k..2k+1)."""
    anns = []
    for i, cid in enumerate(sorted(cats)):
        m = np.zeros((H, W), bool)
        m[2:6, 2 * i:2 * i + 2] = True
        anns.append({"id": i + 1, "image_id": 1, "category_id": cid, "segmentation": encode(m)})
    path.write_text(json.dumps({"images": [{"id": 1, "file_name": "v0.png", "height": H, "width": W}],
                                "categories": [{"id": k, "name": n} for k, n in cats.items()],
                                "annotations": anns}))
    return path


def test_coco_category_ids_are_the_labels(tmp_path):
    """Not 1..K by sorted name (that made `fuse --masks coco.json` number zebra=1, apple=2 differently
    from `segment`/`build`); a scene's objects still win, and a taken or < 1 id gets a fresh label."""
    p = _coco(tmp_path / "c.json", {1: "zebra", 2: "apple", 7: "mango"})
    assert load_masks(p).objects == {1: "zebra", 2: "apple", 7: "mango"}
    assert load_masks(p, objects={"apple": 1, "zebra": 2}).objects == {1: "apple", 2: "zebra", 7: "mango"}
    p0 = _coco(tmp_path / "c0.json", {0: "zebra", 1: "apple"})
    assert load_masks(p0).objects == {1: "apple", 2: "zebra"}
    # an id no 16-bit label image can hold (an untrusted file's 10**12) is not a label: a fresh one
    big = _coco(tmp_path / "big.json", {10**12: "zebra", 1: "apple"})
    assert load_masks(big).objects == {1: "apple", 2: "zebra"}


def test_label_maps_are_scored_by_object_name(tmp_path, monkeypatch):
    """The GT numbers box=1, cube=2; the fusion numbered them cube=1, box=2 and drew both exactly: mIoU 1
    by name (0 by label id, the old score). An object the GT lacks counts as wrong, not as a match."""
    gt = np.zeros((H, W), np.uint8)
    gt[0:4, 0:4] = 1
    gt[5:8, 5:9] = 2
    io.write_image(tmp_path / "gt.png", gt)
    fused = np.where(gt == 1, 2, np.where(gt == 2, 1, 0)).astype(np.int32)
    monkeypatch.setattr(lift, "render_label_maps", lambda *a, **k: [fused])
    frame = SimpleNamespace(name="v0", camera=None, image_path=tmp_path / "none.png", label_path=tmp_path / "gt.png",
                            split="heldout")
    names = {1: "cube", 2: "box"}
    out = lift.write_label_maps(None, np.zeros(1), [frame], names, tmp_path / "o1", gt_objects={"box": 1, "cube": 2})
    assert out["miou_heldout"] == 1.0 and out["miou_matched_by"] == "name"
    out = lift.write_label_maps(None, np.zeros(1), [frame], names, tmp_path / "o2")
    assert out["miou_heldout"] == 0.0 and out["miou_matched_by"] == "label id"
    out = lift.write_label_maps(None, np.zeros(1), [frame], names, tmp_path / "o3", gt_objects={"box": 1, "ball": 2})
    assert out["miou_heldout"] == 0.5                                  # box right; cube is no GT object


def test_label_names_travel_with_the_posed_dataset(tmp_path):
    """transforms.json's label_objects (a generated scene writes it, the poses stage keeps it) names the GT
    ids, so a twin's poses/ without its scene still matches by name. The capture reader does not parse a
    scene.json beside the file (that is the semantics stage's fallback, `lift.label_objects`)."""
    import dataclasses
    import shutil

    from splattwin.capture import load_dataset

    src = tmp_path / "scene"
    src.mkdir()
    io.write_image(src / "v0.png", np.zeros((H, W, 3), np.uint8))
    tf = {"camera_model": "PINHOLE", "fl_x": 10.0, "fl_y": 10.0, "cx": 5.0, "cy": 4.0, "w": W, "h": H,
          "frames": [{"file_path": "v0.png", "transform_matrix": np.eye(4).tolist()}]}
    (src / "transforms.json").write_text(json.dumps(tf))
    (src / "scene.json").write_text(json.dumps({"objects": [{"name": "table", "label": 0}, {"name": "box", "label": 3}]}))
    assert "label_objects" not in load_dataset(src).meta
    assert lift.label_objects(load_dataset(src)) == {"box": 3}       # the semantics stage's scene.json fallback
    tf["label_objects"] = {"box": 3}
    (src / "transforms.json").write_text(json.dumps(tf))
    ds = load_dataset(src)
    assert ds.meta["label_objects"] == {"box": 3} and lift.label_objects(ds) == {"box": 3}
    out = tmp_path / "poses"
    out.mkdir()
    shutil.copy(src / "v0.png", out / "v0.png")
    ds.root = out
    ds.frames = [dataclasses.replace(f, image_path=out / "v0.png") for f in ds.frames]
    nerfstudio.write(ds, out / "transforms.json")
    assert lift.label_objects(load_dataset(out)) == {"box": 3}       # no scene.json there
    bad = json.loads((out / "transforms.json").read_text())
    bad["label_objects"] = {"box": 10**12}
    (out / "transforms.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match="at most 65535"):
        load_dataset(out)


def test_generated_scene_names_its_label_ids(tmp_path):
    """`scene generate` writes the ground-truth label images' names into transforms.json."""
    from splattwin.capture import load_dataset
    from splattwin.scene.generator import generate
    from splattwin.scene.options import SceneOptions

    d = generate(tmp_path / "s", SceneOptions(seed=0, width=48, height=36, views=2, heldout=1), progress=False)
    scene = json.loads((d / "scene.json").read_text())
    want = {o["name"]: o["label"] for o in scene["objects"] if o["label"] > 0}
    assert json.loads((d / "transforms.json").read_text())["label_objects"] == want
    assert load_dataset(d).meta["label_objects"] == want and len(want) >= 3

