"""Held-out label quality against the user's own 2D masks (splattwin.semantics.lift.heldout_mask_miou)."""

from types import SimpleNamespace

import numpy as np

from splattwin import io
from splattwin.semantics.lift import heldout_mask_miou
from splattwin.semantics.masks import MaskSet


def _frame(name: str, split: str):
    return SimpleNamespace(name=name, split=split)


def test_heldout_mask_miou_scores_only_the_views_the_fusion_did_not_use(tmp_path):
    """Two objects; the held-out view's rendered labels overlap its masks by known areas: object 1 IoU
    1/2 (4x8 rendered vs 4x4 mask inside it), object 2 IoU 1 -> mIoU 0.75. The training view, whose masks
    the fusion used, is not scored even though its labels are wrong; without held-out masks: nothing."""
    h, w = 12, 16
    ms = MaskSet()
    m1 = np.zeros((h, w), bool)
    m1[0:4, 0:4] = True
    m2 = np.zeros((h, w), bool)
    m2[8:12, 8:16] = True
    for view in ("train0", "held0"):
        ms.add(view, 1, m1, name="box")
        ms.add(view, 2, m2, name="cube")
    raw = tmp_path / "label_maps" / "raw"
    fused = np.zeros((h, w), np.uint8)
    fused[0:4, 0:8] = 1
    fused[8:12, 8:16] = 2
    io.write_image(raw / "held0.png", fused)
    io.write_image(raw / "train0.png", np.zeros((h, w), np.uint8))  # all wrong, but a fused view
    ds = SimpleNamespace(frames=[_frame("train0", "train"), _frame("held0", "heldout")])
    out = heldout_mask_miou(ms, ds, tmp_path, [1, 2])
    assert out["miou_heldout_masks_views"] == ["held0"]
    assert np.isclose(out["miou_heldout_masks"], 0.75)
    assert heldout_mask_miou(ms, SimpleNamespace(frames=[_frame("train0", "train")]), tmp_path, [1, 2]) == {}


def test_dataset_objects_finds_the_scene_of_a_twins_poses_folder(tmp_path):
    """A twin's poses/ holds the scene's ground-truth label images, whose ids are the scene's: `fuse
    --dataset TWIN/poses/transforms.json` must read them from TWIN/scene/scene.json (it numbered the mask
    objects by name instead, and scored mIoU 0.19 for labels that score 0.92)."""
    from splattwin.semantics.lift import dataset_objects

    twin = tmp_path / "twin"
    (twin / "poses").mkdir(parents=True)
    (twin / "scene").mkdir()
    io.write_json(twin / "scene" / "scene.json", {"objects": [{"name": "table", "label": 0},
                                                             {"name": "yellow_cube", "label": 1},
                                                             {"name": "blue_box", "label": 2}]})
    (twin / "poses" / "transforms.json").write_text("{}")
    assert dataset_objects(twin / "poses" / "transforms.json") == {"yellow_cube": 1, "blue_box": 2}
    assert dataset_objects(twin / "scene") == {"yellow_cube": 1, "blue_box": 2}
    assert dataset_objects(tmp_path / "elsewhere") is None
