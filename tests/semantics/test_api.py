"""The semantics stage used from Python (audit 8A): fusion scales its lengths to the frame, checks its
arguments, its results and mask sets load back and compare, and mask mistakes are named early."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.semantics.fusion import FusionResult, View, fuse, naive_fusion
from splattwin.semantics.masks import MaskSet, load_masks


@pytest.fixture(scope="module")
def synth():
    from splattwin.scene.synthetic import make_synth

    return make_synth()


def _dataset(tmp_path, h):
    """A small dataset (h: tests/splat/test_trainer.py's helpers) with half-image masks and its GT splats."""
    from splattwin.capture import load_dataset

    root = h.make_dataset(tmp_path / "ds", n_train=3, n_heldout=1)
    ds = load_dataset(root)
    ms = h.half_image_masks(ds.frames)
    return root, ds, ms, h.gt_gaussians()


def test_fuse_to_dir_scales_lengths_to_an_unscaled_frame(tmp_path, monkeypatch, test_module):
    """fuse_to_dir used the metre tolerances as SfM units (M1); the stage and CLI scaled them themselves."""
    from pathlib import Path

    from splattwin.capture import load_dataset
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.semantics import lift

    root, ds, ms, g = _dataset(tmp_path, test_module("splat/test_trainer.py"))
    seen = []
    real = lift.fuse
    monkeypatch.setattr(lift, "fuse", lambda m, v, s, o=None, **kw: seen.append(o) or real(m, v, s, o, **kw))
    lift.fuse_to_dir(g, ds, ms, tmp_path / "metric", label_maps=False, progress=False)
    folder = Path(ds.meta["path"]).parent
    TwinFrame(source="unscaled", scaled=False, nominal_metre=10.0).save(folder / "frame.json")
    lift.fuse_to_dir(g, load_dataset(root), ms, tmp_path / "unscaled", label_maps=False, progress=False)
    lift.fuse_to_dir(g, root, ms, tmp_path / "by_path", label_maps=False, progress=False)
    lift.fuse_to_dir(g, ds, ms, tmp_path / "none", label_maps=False, progress=False, frame=None)
    lift.fuse_to_dir(g, ds, ms, tmp_path / "given", label_maps=False, progress=False,
                     frame=TwinFrame(source="unscaled", scaled=False, nominal_metre=3.0))
    assert [o.depth_tol for o in seen] == pytest.approx([0.02, 0.2, 0.2, 0.02, 0.06])
    assert [o.eps for o in seen] == pytest.approx([0.02, 0.2, 0.2, 0.02, 0.06])
    with pytest.raises(ValueError, match="TwinFrame"):
        lift.fuse_to_dir(g, ds, ms, tmp_path / "bad", label_maps=False, progress=False, frame=3.0)


def test_fuse_checks_its_arguments(synth):
    """means.T gave 3 labels, [N,2] an IndexError, a list of Camera an AttributeError (M5)."""
    s = synth
    with pytest.raises(InputError, match=r"\[N,3\].*transposed"):
        fuse(s.means.T, s.views, s.masks)
    with pytest.raises(InputError, match=r"\[N,3\]"):
        fuse(s.means[:, :2], s.views, s.masks)
    with pytest.raises(InputError, match="View.*Camera"):
        fuse(s.means, [v.camera for v in s.views], s.masks)
    with pytest.raises(InputError, match="MaskSet"):
        fuse(s.means, s.views, {"a": 1})
    with pytest.raises(InputError, match="normals"):
        fuse(s.means, s.views, s.masks, normals=np.zeros((2, 3)))
    bad = s.means.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        fuse(bad, s.views, s.masks)
    with pytest.raises(InputError, match=r"\[N,3\]"):
        naive_fusion(s.means.T, s.views, s.masks)


def test_views_named_unlike_the_masks_are_named_in_the_error(synth):
    """Views named after the image files ("train_000.png") while the masks were added under the stems said
    "empty mask set: no object mask with any pixel", though every mask had pixels (api13 C2): the error now
    gives both sets of names."""
    s = synth
    renamed = [View(v.name + ".png", v.camera) for v in s.views]
    for f in (fuse, naive_fusion):
        with pytest.raises(InputError, match=r"no view has masks: the views are named \[.*\.png.*the mask set's "
                                             r"views \[.*Frame\.name"):
            f(s.means, renamed, s.masks)


def test_fusion_result_round_trips(synth, tmp_path):
    s = synth
    res = fuse(s.means, s.views, s.masks)
    res.save(tmp_path, extra={"miou_train": 0.5})
    back = FusionResult.load(tmp_path)
    assert np.array_equal(back.labels, res.labels) and back.labels.dtype == np.int32
    assert back.names == res.names and back.label_ids == res.label_ids and back.options == res.options
    assert back.history == res.history and back.counts() == res.counts() and back.extra == {"miou_train": 0.5}
    back.save(tmp_path / "again")   # extra written again
    assert FusionResult.load(tmp_path / "again").extra == {"miou_train": 0.5}
    assert FusionResult.load(tmp_path / "again") == back   # by value (audit 10A L1: raised ValueError)
    assert res == copy.deepcopy(res) and back != res   # back has no votes
    with pytest.raises(ValueError, match="votes"):
        back.relabel(1.0)
    with pytest.raises(InputError, match="fusion.json"):
        FusionResult.load(tmp_path / "nothing")


def test_maskset_equality(synth, tmp_path):
    """MaskSet == MaskSet raised 'truth value of an array is ambiguous' (M9)."""
    s = synth
    s.masks.save(tmp_path / "ms")
    back = MaskSet.load(tmp_path / "ms")
    assert back == s.masks and not (back != s.masks)
    other = MaskSet.load(tmp_path / "ms")
    v = next(iter(other.masks))
    k = next(iter(other.masks[v]))
    other.masks[v][k] = ~other.masks[v][k]
    assert other != s.masks and s.masks != "x"


def test_float_masks_must_be_binary():
    """A probability mask of 0.1 became a full mask (L7)."""
    ms = MaskSet()
    with pytest.raises(InputError, match="threshold"):
        ms.add("v", 1, np.full((4, 4), 0.1), name="t")
    ms.add("v", 1, np.eye(4, dtype=np.float32), name="t")    # 0/1 floats are masks
    ms.add("w", 1, np.eye(4, dtype=np.uint8) * 255, name="t")  # so are 0/255 integers
    assert ms.get("v", 1).sum() == 4 and ms.get("w", 1).sum() == 4


def test_a_scene_masks_folder_is_refused_with_the_folder_to_pass(scene_small):
    """scene/masks (gt/ + noisy/) was read as view 'gt' with objects named like images (L4)."""
    with pytest.raises(InputError, match="noisy.*scene_masks"):
        load_masks(scene_small / "masks")
    gt = scene_small / "masks"
    sizes = {p.stem: (120, 160) for p in (scene_small / "images").glob("*.png")}
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:   # only the label-image folder: named like the images
        shutil.copytree(gt / "gt", f"{tmp}/m/gt")
        with pytest.raises(InputError, match="named like the images"):
            load_masks(f"{tmp}/m", image_sizes=sizes)
    assert load_masks(scene_small / "masks" / "noisy").objects   # the right folder still loads


def test_prompt_labels_maps_phrases_to_a_scenes_ids(scene_small):
    """The prompt -> scene label mapping lived only in `splattwin segment` (L5): now a helper it uses."""
    import json

    from splattwin.capture import load_dataset
    from splattwin.semantics import prompt_labels

    ds = load_dataset(scene_small)
    objs = {o["name"]: (o.get("prompt", o["name"]).lower(), o["label"])
            for o in json.loads((scene_small / "scene.json").read_text())["objects"]}
    (p1, l1), (p2, l2) = objs["blue_box"], objs["yellow_cube"]
    got = prompt_labels(ds, f"{p1}. {p2}")
    assert got[p1] == l1 and got[p2] == l2
    assert prompt_labels(ds, "a unicorn") is None
