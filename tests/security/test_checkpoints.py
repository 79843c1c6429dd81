"""Checkpoints hold tensors and plain data only: a planted pickle never runs, and a checkpoint of
another run (other options or data) is never silently resumed."""

from __future__ import annotations

import logging
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from splattwin.capture import load_dataset
from splattwin.errors import InputError
from splattwin.splat import checkpoint as ckpt_io
from splattwin.splat.trainer import CheckpointMismatch, TrainConfig, Trainer, train

from security_helpers import assert_bad_input

SRC = Path(__file__).parents[2] / "src" / "splattwin"


class _Payload:
    """Unpickling this creates `marker` (any code could run instead)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _plant_pickle(path: Path, marker: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump({"step": 10**6, "model": _Payload(marker)}, f)
    return path


def _cfg(**kw) -> TrainConfig:
    base = dict(iters=12, sh_degree=0, checkpoint_every=6, progress=False, backend="cpu", max_gaussians=500,
                init="random", init_points=200)
    base.update(kw)
    return TrainConfig(**base)


def test_the_payload_works_when_unpickled(tmp_path):
    """Control: the planted file really runs code under pickle.load (so its absence below means something)."""
    p = _plant_pickle(tmp_path / "x.pt", tmp_path / "control_marker")
    with open(p, "rb") as f:
        pickle.load(f)  # noqa: S301 - on purpose
    assert (tmp_path / "control_marker").exists()


@pytest.mark.parametrize("name", ["ckpt_999999.pt", "ckpt_999999.safetensors"])
def test_planted_pickle_never_runs(tiny_dataset, tmp_path, cli, caplog, name):
    out = tmp_path / "out"
    marker = tmp_path / "PWNED"
    _plant_pickle(out / "checkpoints" / name, marker)
    ds = load_dataset(tiny_dataset)
    if name.endswith(".pt"):
        with caplog.at_level(logging.WARNING):
            res = train(ds, out, _cfg(), resume=True)
        assert res.steps == 12
        assert "never loaded" in caplog.text
        # the CLI, asked to resume, does the same
        assert cli("train", tiny_dataset, out, "--iters", "12", "--resume", "--no-progress", "--device", "cpu",
                   "--sh-degree", "0", "--init", "random", "--init-points", "200", "--max-gaussians", "500").rc == 0
    else:  # a pickle under the new name: refused as not a checkpoint, exit 2 naming it
        with pytest.raises(InputError, match="unreadable checkpoint|not a splattwin checkpoint"):
            train(ds, out, _cfg(), resume=True)
        res = cli("train", tiny_dataset, out, "--iters", "12", "--resume", "--no-progress", "--device", "cpu")
        assert_bad_input(res, name)
    assert not marker.exists()


def test_no_pickle_loading_in_the_code():
    """Every torch.load / np.load / pickle use in src is pickle-free (static check)."""
    bad = []
    for p in SRC.rglob("*.py"):
        text = p.read_text()
        for m in re.finditer(r"torch\.load\(([^)]*)\)", text):
            if "weights_only=True" not in m.group(1):
                bad.append(f"{p.name}: torch.load({m.group(1)})")
        if re.search(r"allow_pickle\s*=\s*True|^import pickle|pickle\.loads?\(", text, re.M):
            bad.append(f"{p.name}: pickle")
    assert not bad, bad


def test_checkpoint_round_trip_is_plain_data(tmp_path):
    state = {"step": 3, "t": torch.arange(6.0).reshape(2, 3), "opt": {0: {"exp_avg": torch.ones(2)}},
             "betas": (0.9, 0.999), "hist": [{"psnr": float("nan")}], "rng": torch.Generator().get_state(),
             "arr": np.arange(3, dtype=np.int32), "none": None, "name": "x"}
    p = ckpt_io.save(tmp_path / "c.safetensors", state)
    back = ckpt_io.load(p)
    assert back["step"] == 3 and back["betas"] == (0.9, 0.999) and back["name"] == "x" and back["none"] is None
    assert torch.equal(back["t"], state["t"]) and torch.equal(back["opt"][0]["exp_avg"], torch.ones(2))
    assert np.isnan(back["hist"][0]["psnr"]) and torch.equal(back["rng"], state["rng"])
    assert back["arr"].tolist() == [0, 1, 2]
    with pytest.raises(TypeError, match="plain data"):
        ckpt_io.save(tmp_path / "d.safetensors", {"f": _Payload(tmp_path / "m")})
    assert not (tmp_path / "m").exists()


def test_other_options_are_not_resumed(tiny_dataset, tmp_path, caplog):
    """The issue's case: a 300-step checkpoint, then a 150-step run into the same folder."""
    ds = load_dataset(tiny_dataset)
    long = train(ds, tmp_path / "a", _cfg(iters=18))
    assert long.steps == 18
    fresh = train(ds, tmp_path / "fresh", _cfg(iters=12))
    # explicit resume (`train --resume`): refused, naming what differs by its flag, first; the densification
    # schedule scaled from --iters only as a note (its 600-character dict led the message, audit 9 F14)
    with pytest.raises(CheckpointMismatch) as e:
        train(ds, tmp_path / "a", _cfg(iters=12), resume=True)
    assert e.value.problem.startswith("checkpoint was made with other options: --iters 18 (checkpoint) vs 12 "
                                      "(this run); derived from them: the densification schedule")
    assert "refine" not in e.value.problem and len(e.value.problem.split("; not resumed")[0]) < 150
    # build semantics: say why, start over, and give exactly what a fresh 12-step run gives
    with caplog.at_level(logging.WARNING):
        short = train(ds, tmp_path / "a", _cfg(iters=12), resume=True, on_mismatch="restart")
    assert "starting over" in caplog.text and "--iters 18 (checkpoint)" in caplog.text
    assert short.steps == 12
    np.testing.assert_array_equal(short.gaussians.means, fresh.gaussians.means)
    assert not any("000018" in p.name for p in (tmp_path / "a" / "checkpoints").iterdir())


def test_other_data_is_not_resumed(tiny_dataset, tmp_path):
    from PIL import Image

    ds_dir = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds_dir)
    train(load_dataset(ds_dir), tmp_path / "out", _cfg())
    img = ds_dir / "images" / "train_002.png"
    a = np.asarray(Image.open(img)).copy()
    a[0, 0] = 255 - a[0, 0]   # one pixel of one photo changed
    Image.fromarray(a).save(img)
    with pytest.raises(CheckpointMismatch, match="other training data"):
        Trainer(load_dataset(ds_dir), tmp_path / "out", _cfg()).run(resume=True)


def test_a_checkpoint_from_before_an_option_resumes_with_its_default(tiny_dataset, tmp_path):
    """A checkpoint written before an option existed (its run_options lack the key) ran with the option's
    default behaviour: a run with the default resumes it, a run that sets the option is refused."""
    ds = load_dataset(tiny_dataset)
    train(ds, tmp_path / "a", _cfg(iters=18))
    ckpt = sorted((tmp_path / "a" / "checkpoints").iterdir())[-1]
    sd = ckpt_io.load(ckpt)
    for k in ("robust_quantile", "robust_start"):
        sd["run_options"].pop(k)
    ckpt_io.save(ckpt, sd)
    assert Trainer(ds, tmp_path / "a", _cfg(iters=18)).run(resume=True).steps == 18
    with pytest.raises(CheckpointMismatch, match=r"--robust-quantile 0.0 \(checkpoint\) vs 0.8 \(this run\)"):
        Trainer(ds, tmp_path / "a", _cfg(iters=18, robust_quantile=0.8)).run(resume=True)
