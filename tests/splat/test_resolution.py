"""Training resolution (`splattwin.splat.resolution`): auto size on the CPU, full size with CUDA, explicit
values; the trainer records the rule and evaluation renders held-out views at it by default."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from splattwin.errors import InputError
from splattwin.splat.resolution import FULL, Resolution, resolve

_spec = importlib.util.spec_from_file_location("_res_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def test_auto_caps_the_longest_side_on_the_cpu_only():
    cpu = resolve(0, 640, "cpu")
    assert cpu.size(4032, 3024) == (640, 480)
    assert cpu.size(3024, 4032) == (480, 640)          # portrait: the longest side is the height
    assert cpu.size(320, 240) == (320, 240)            # the embedded scene: unchanged
    assert cpu.size(640, 427) == (640, 427)
    assert "640 px" in cpu.how
    assert resolve(0, 640, "cuda").size(4032, 3024) == (4032, 3024)
    assert resolve(0, 1000, "cpu").size(4032, 3024) == (1000, 750)


def test_explicit_resolution_overrides_auto():
    assert resolve(1, 640, "cpu").size(4032, 3024) == (4032, 3024)
    assert resolve(2, 640, "cpu").size(4032, 3024) == (2016, 1512)
    assert resolve(800, 640, "cpu").size(4000, 3000) == (800, 600)
    assert resolve(-1, 640, "cpu").size(4000, 3000) == (1600, 1200)
    assert FULL.size(33, 17) == (33, 17)


@pytest.mark.parametrize("res, side, match", [(3, 640, "--resolution"), (0, 8, "--cpu-max-side")])
def test_bad_values(res, side, match):
    with pytest.raises(InputError, match=match):
        resolve(res, side, "cpu")


def test_record_round_trip():
    r = resolve(0, 512, "cpu")
    assert Resolution.from_record(json.loads(json.dumps(r.record()))) == r
    assert Resolution.from_record({"resolution": "x"}) is None and Resolution.from_record(None) is None


def test_training_and_default_eval_at_the_auto_size_full_size_as_an_option(tmp_path):
    from splattwin.capture import load_dataset
    from splattwin.splat.eval import evaluate
    from splattwin.splat.trainer import TrainConfig, train

    # images 96x72 with the CPU cap at 48 px: trained at 48x36
    ds = load_dataset(helpers.make_dataset(tmp_path / "ds", n_train=4, n_heldout=2, width=96, height=72))
    cfg = TrainConfig(iters=15, cpu_max_side=48, checkpoint_every=0, progress=False, sh_degree=0,
                      init_points=500, densify=False, device="cpu")
    out = tmp_path / "train"
    train(ds, out, cfg)
    rec = json.loads((out / "train.json").read_text())
    assert {(v["width"], v["height"]) for v in rec["views"]} == {(48, 36)}
    assert rec["resolution"] == {"resolution": 1, "max_side": 48, "how": rec["resolution"]["how"]}
    assert rec["heldout"]["views"] == ["heldout_004", "heldout_005"]   # always listed, not only the rule
    ev = evaluate(out, ds, tmp_path / "eval", progress=False)
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["eval_resolution"]["mode"] == "training" and m["eval_resolution"]["sizes"] == "48x36"
    assert m["eval_resolution"]["full_sizes"] == "96x72" and m["eval_resolution"]["scale"] == 0.5
    assert m["heldout"]["views"] == ["heldout_004", "heldout_005"] and ev.split == "heldout"
    # the folder's point_cloud.ply by its path: the same splat, evaluated the same way
    by_ply = evaluate(out / "point_cloud.ply", ds, tmp_path / "eval_ply", progress=False)
    mp = json.loads((tmp_path / "eval_ply" / "metrics.json").read_text())
    assert mp["eval_resolution"] == m["eval_resolution"] and by_ply.mean_psnr == ev.mean_psnr
    full = evaluate(out, ds, tmp_path / "eval_full", progress=False, full_resolution=True)
    mf = json.loads((tmp_path / "eval_full" / "metrics.json").read_text())
    assert mf["eval_resolution"]["mode"] == "full" and mf["eval_resolution"]["sizes"] == "96x72"
    assert full.mean_psnr != ev.mean_psnr


def test_train_command_holds_out_views_and_eval_finds_them(tmp_path):
    from splattwin.cli import main as cli

    root = helpers.drop_split(helpers.make_dataset(tmp_path / "ds", n_train=8, n_heldout=0))
    out = tmp_path / "train"
    assert cli(["train", str(root), str(out), "--iters", "10", "--heldout-every", "4", "--no-densify",
                "--init-points", "300", "--checkpoint-every", "0", "--no-progress", "--sh-degree", "0"]) == 0
    rec = json.loads((out / "train.json").read_text())
    assert [v["name"] for v in rec["views"]] == [f"train_{i:03d}" for i in (1, 2, 3, 5, 6, 7)]
    assert rec["heldout"]["views"] == ["train_000", "train_004"]
    assert cli(["eval", str(out), "--dataset", str(root), "--no-progress"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert m["split"] == "heldout" and [v["name"] for v in m["views"]] == ["train_000", "train_004"]
