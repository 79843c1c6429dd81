from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splattwin.errors import InputError
from splattwin.splat.eval import evaluate

_spec = importlib.util.spec_from_file_location("_splat_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def test_eval_ground_truth_vs_degraded(tmp_path):
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    g = helpers.gt_gaussians()
    ply = g.save_ply(tmp_path / "gt.ply")
    res = evaluate(ply, ds_root, tmp_path / "eval", progress=False)
    assert res.split == "heldout" and len(res.views) == 2
    assert res.mean_psnr > 40 and res.mean_ssim > 0.99  # only PNG quantisation differs
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["mean_psnr"] == pytest.approx(res.mean_psnr) and len(m["views"]) == 2
    im = np.asarray(Image.open(tmp_path / "eval" / m["views"][0]["image"]))
    assert im.shape == (helpers.H, 3 * helpers.W + 8, 3)
    bad = g.subset(np.arange(len(g)) % 2 == 0)
    res2 = evaluate(bad, ds_root, None, progress=False)
    assert res2.mean_psnr < res.mean_psnr - 5 and res2.mean_ssim < res.mean_ssim


def test_eval_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        evaluate(tmp_path / "nope.ply", tmp_path, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="point_cloud.ply"):
        evaluate(tmp_path / "empty", tmp_path, progress=False)
