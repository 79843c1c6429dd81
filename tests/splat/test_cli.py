from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from splattwin.cli import main
from splattwin.splat.gaussians import Gaussians

_spec = importlib.util.spec_from_file_location("_splat_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


@pytest.mark.parametrize("cmd", ["train", "eval"])
def test_help(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    assert "usage" in capsys.readouterr().out


def test_train_and_eval_cli(tmp_path, capsys):
    ds = helpers.make_dataset(tmp_path / "ds", n_train=4, n_heldout=1)
    out = tmp_path / "out"
    rc = main(["train", str(ds), str(out), "--iters", "30", "--sh-degree", "0", "--checkpoint-every", "10",
               "--no-progress", "--device", "cpu"])
    assert rc == 0
    g = Gaussians.load_ply(out / "point_cloud.ply")
    assert len(g) > 0 and g.sh_degree == 0
    assert json.loads((out / "train.json").read_text())["steps"] == 30
    # resuming a finished run does no more steps and rewrites the same result
    assert main(["train", str(ds), str(out), "--iters", "30", "--sh-degree", "0", "--resume", "--no-progress",
                 "--device", "cpu"]) == 0
    assert (Gaussians.load_ply(out / "point_cloud.ply").means == g.means).all()
    assert main(["eval", str(out), "--dataset", str(ds), "--no-progress", "--device", "cpu"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert m["n_views"] == 1 and m["mean_psnr"] > 10
    assert "PSNR" in capsys.readouterr().out
    assert main(["eval", str(out), "--dataset", str(ds), "--no-progress", "--device", "cpu", "--align-poses",
                 "--out", str(tmp_path / "aligned")]) == 0
    ma = json.loads((tmp_path / "aligned" / "metrics.json").read_text())
    assert ma["poses"].startswith("aligned") and "pose_correction_deg" in ma["views"][0]
    assert ma["mean_psnr"] >= m["mean_psnr"] - 0.5  # fitting the camera to the image cannot make it much worse
    assert "pose fit" in capsys.readouterr().out


def test_bad_inputs_exit_2(tmp_path, capsys):
    assert main(["train", str(tmp_path / "missing"), str(tmp_path / "o"), "--no-progress"]) == 2
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "transforms.json").write_text("{not json")
    assert main(["train", str(tmp_path / "junk"), str(tmp_path / "o"), "--no-progress"]) == 2
    assert main(["eval", str(tmp_path / "missing.ply"), "--dataset", str(tmp_path), "--no-progress"]) == 2
    # images without poses
    import numpy as np
    from splattwin.io import write_image
    write_image(tmp_path / "unposed" / "a.png", np.zeros((20, 30, 3), np.uint8))
    assert main(["train", str(tmp_path / "unposed"), str(tmp_path / "o"), "--no-progress"]) == 2
    assert "poses" in capsys.readouterr().err
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main(["eval", str(tmp_path / "bad.ply"), "--dataset", str(tmp_path), "--no-progress"]) == 2


def test_train_flags_come_from_train_config():
    """`splattwin train` without flags trains with TrainConfig's defaults; every option has a flag."""
    from splattwin.cli import build_parser
    from splattwin.options import from_args
    from splattwin.splat.config import TrainConfig

    p = build_parser()
    args = p.parse_args(["train", "data", "out"])
    assert from_args(TrainConfig, args) == TrainConfig()
    args = p.parse_args(["train", "data", "out", "--depth-lambda", "0.1", "--opacity-reg", "0.05", "--refine-poses",
                         "--init", "depth", "--lrs.means", "1e-3", "--background", "1", "1", "1", "--no-progress"])
    cfg = from_args(TrainConfig, args)
    assert (cfg.depth_lambda, cfg.opacity_reg, cfg.refine_poses, cfg.init) == (0.1, 0.05, True, "depth")
    assert cfg.lrs.means == 1e-3 and cfg.background == (1.0, 1.0, 1.0) and cfg.progress is False
    assert cfg.iters == TrainConfig.iters


def test_eval_prints_an_unscaled_pose_correction_in_units_never_cm():
    from splattwin.splat.cli import _pose_length

    assert _pose_length({"pose_correction": 0.0743, "pose_correction_units": "unscaled"}) == "0.0743 units (SfM, unscaled)"
    assert _pose_length({"pose_correction": 0.0743, "pose_correction_units": "m"}) == "7.43 cm"
    assert _pose_length({"pose_correction_m": 0.0743}) == "7.43 cm"  # a metrics.json of an older version
