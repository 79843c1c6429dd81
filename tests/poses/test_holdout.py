"""Held-out views (`splattwin.poses.holdout`): the default rule, the three options, captures with their own
split, and the split reaching transforms.json through the poses stage."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import load_dataset
from splattwin.errors import InputError
from splattwin.io import write_image
from splattwin.poses.holdout import apply_holdout, select_heldout
from splattwin.poses.options import HoldoutOptions, PoseOptions

_spec = importlib.util.spec_from_file_location("_holdout_trainer_helpers",
                                               Path(__file__).parents[1] / "splat" / "test_trainer.py")
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)

NAMES = [f"img_{i:03d}" for i in range(20)]


def test_default_every_8th_from_the_first_with_6_views_or_more():
    h = select_heldout(NAMES)
    assert h.indices == [0, 8, 16] and h.names == ["img_000", "img_008", "img_016"]
    assert h.source == "default" and h.every == 8
    assert select_heldout(NAMES[:6]).indices == [0]
    assert select_heldout(NAMES[:5]).indices == []      # below 6 views: none
    assert "fewer than 6" in select_heldout(NAMES[:5]).rule


def test_capture_split_is_kept_unless_an_option_is_given():
    assert select_heldout(NAMES, own_split=True).indices is None
    assert select_heldout(NAMES, HoldoutOptions(heldout_every=5), own_split=True).indices == [0, 5, 10, 15]


def test_options_every_count_and_listed_views():
    assert select_heldout(NAMES, HoldoutOptions(heldout_every=4)).indices == [0, 4, 8, 12, 16]
    assert select_heldout(NAMES, HoldoutOptions(heldout_every=0)).indices == []
    assert select_heldout(NAMES, HoldoutOptions(heldout=4)).indices == [0, 5, 10, 15]
    assert select_heldout(NAMES, HoldoutOptions(heldout=0)).indices == []
    h = select_heldout(NAMES, HoldoutOptions(heldout_views="3, img_011,img_019.jpg"))
    assert h.indices == [3, 11, 19] and h.source == "option"


@pytest.mark.parametrize("opts, match", [
    (HoldoutOptions(heldout_every=8, heldout=2), "at most one of --heldout-every, --heldout"),
    (HoldoutOptions(heldout_every=1), "at least 2"),
    (HoldoutOptions(heldout_every=-3), "at least 2"),
    (HoldoutOptions(heldout=20), "only 20 views"),
    (HoldoutOptions(heldout_views="img_999"), "no view named 'img_999'"),
    (HoldoutOptions(heldout_views="25"), "index 25 is out of range"),
    (HoldoutOptions(heldout_views=",".join(NAMES)), "leaves no view for training"),
])
def test_bad_options_are_input_errors(opts, match):
    with pytest.raises(InputError, match=match):
        select_heldout(NAMES, opts)


def _image_folder(root: Path, n: int) -> Path:
    rng = np.random.default_rng(0)
    for i in range(n):
        write_image(root / f"photo_{i:02d}.png", rng.integers(0, 255, (12, 16, 3), dtype=np.uint8))
    return root


def test_image_folder_gets_the_default_split_in_name_order(tmp_path):
    ds = load_dataset(_image_folder(tmp_path / "imgs", 10))
    h = apply_holdout(ds)
    assert [f.name for f in ds.heldout()] == ["photo_00", "photo_08"] == h.names
    assert len(ds.train()) == 8 and ds.meta["heldout"]["rule"].startswith("every 8th")


@pytest.mark.parametrize("opts, rule", [
    (HoldoutOptions(heldout_every=2), "every 2nd view from the first"),
    (HoldoutOptions(heldout_every=3), "every 3rd view from the first"),
    (HoldoutOptions(heldout_every=11), "every 11th view from the first"),
    (HoldoutOptions(heldout_every=12), "every 12th view from the first"),
    (HoldoutOptions(heldout_every=13), "every 13th view from the first"),
    (HoldoutOptions(heldout=1), "1 view spread evenly from the first"),
    (HoldoutOptions(heldout=2), "2 views spread evenly from the first"),
    (HoldoutOptions(), "every 8th view from the first"),
])
def test_rules_in_words(opts, rule):
    """Ordinals and plurals in the rule that poses, train and the report print ("every 3th", "1 views" before)."""
    assert select_heldout(NAMES, opts).rule.startswith(rule)


@pytest.mark.parametrize("n", [5, 10, 17])
def test_capture_info_reports_the_split_poses_will_use(tmp_path, capsys, n):
    """`capture info` on an image folder (no split of its own) reports the default rule's split, as
    apply_holdout makes it (it said "0 held-out" where poses/build hold out every 8th view)."""
    from splattwin.cli import main

    folder = _image_folder(tmp_path / "imgs", n)
    assert main(["capture", "info", str(folder)]) == 0
    out = capsys.readouterr().out
    ds = load_dataset(folder)
    h = apply_holdout(ds)
    assert f"({len(ds.train())} train, {len(ds.heldout())} held-out by the default rule: {h.rule})" in out
    assert len(ds.heldout()) == {5: 0, 10: 2, 17: 3}[n]


def test_capture_info_reports_a_captures_own_split(tmp_path, capsys):
    from splattwin.cli import main

    root = helpers.make_dataset(tmp_path / "ds", n_train=8, n_heldout=2)
    assert main(["capture", "info", str(root)]) == 0
    assert "(8 train, 2 held-out: the capture's own split)" in capsys.readouterr().out


def test_transforms_split_survives_and_own_split_detected(tmp_path):
    root = helpers.make_dataset(tmp_path / "ds", n_train=8, n_heldout=2)
    ds = load_dataset(root)
    assert ds.meta.get("split")                       # the file lists train/test: its own split
    h = apply_holdout(ds)
    assert h.indices is None and [f.name for f in ds.heldout()] == ["heldout_008", "heldout_009"]
    # the same file without any split information: the default rule applies (10 views -> 0 and 8)
    helpers.drop_split(root)
    bare = load_dataset(root)
    assert not bare.meta.get("split") and not bare.heldout()
    apply_holdout(bare)
    assert [f.name for f in bare.heldout()] == ["train_000", "heldout_008"]


def test_poses_stage_writes_the_split_and_its_rule(tmp_path):
    from splattwin.poses.estimate import estimate_poses

    root = helpers.drop_split(helpers.make_dataset(tmp_path / "ds", n_train=9, n_heldout=0))
    res = estimate_poses(load_dataset(root), PoseOptions(method="known", up="keep", progress=False,
                                                         holdout=HoldoutOptions(heldout_views="2,train_005")))
    out = res.save(tmp_path / "poses")
    written = json.loads(out.read_text())
    assert written["heldout"]["views"] == ["train_002", "train_005"]
    assert written["heldout"]["source"] == "option" and "--heldout-views" in written["heldout"]["rule"]
    again = load_dataset(out)
    assert [f.name for f in again.heldout()] == ["train_002", "train_005"]
    assert again.meta["heldout"]["source"] == "option"   # the rule travels with the posed dataset
    h = apply_holdout(again)                               # its own split now: kept, rule kept
    assert h.indices is None and h.names == ["train_002", "train_005"] and "--heldout-views" in h.rule
