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
