"""Densification strategies plug into the trainer without editing it (splattwin.splat.strategy)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch

from splattwin.capture import load_dataset
from splattwin.splat import densify
from splattwin.splat.densify import DensifyConfig
from splattwin.splat.model import PARAM_NAMES
from splattwin.splat.strategy import DefaultStrategy, Strategy
from splattwin.splat.trainer import CheckpointMismatch, Trainer, train

from .test_trainer import make_dataset, tiny_config


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("synth_strategy"))


@dataclass
class RelocateStrategy(Strategy):
    """An MCMC-style strategy (as gsplat's MCMCStrategy, much reduced), written only against the hooks:
    every `every` steps from `start`, Gaussians with opacity below `dead` are moved onto copies of live
    ones drawn in proportion to opacity (count unchanged), then `grow` x N more are added the same way
    up to `cap`. The trainer is used as is."""

    every: int = 10
    start: int = 10
    dead: float = 0.1
    grow: float = 0.05
    cap: int = 150
    calls: list = field(default_factory=list)
    name = "relocate"

    def initialize_state(self, model):
        return {"rounds": 0, "moved": torch.zeros(len(model))}

    def step_pre_backward(self, model, state, step, info):
        self.calls.append(("pre", step, len(model)))

    def step_post_backward(self, model, state, step, info):
        self.calls.append(("post", step, len(model)))
        if step < self.start or step % self.every:
            return {}
        with torch.no_grad():
            p = {k: v.detach() for k, v in model.params.items()}
            opac = torch.sigmoid(p["opacities"])
            dead = opac < self.dead
            live_w = torch.where(dead, torch.zeros_like(opac), opac)
            n_new = max(0, min(self.cap - len(model), int(self.grow * len(model))))
            k = int(dead.sum()) + n_new
            if k == 0 or float(live_w.sum()) == 0:
                return {}
            src = torch.multinomial(live_w, k, replacement=True, generator=info["generator"])
            densify.remove(model, ~dead)
            densify.append(model, {name: p[name][src] for name in PARAM_NAMES})
            moved = torch.cat([state["moved"][~dead], torch.ones(k)])
        state["rounds"] += 1
        state["moved"] = moved
        return {"relocated": int(dead.sum()), "added": n_new}

    def describe(self):
        return {"name": self.name, "every": self.every, "dead": self.dead, "cap": self.cap}


def test_a_new_strategy_needs_no_trainer_change(synth, tmp_path):
    ds = load_dataset(synth)
    strat = RelocateStrategy()
    cfg = tiny_config(iters=40, max_gaussians=10_000)  # the config's own schedule is not used
    seen = []
    res = train(ds, tmp_path / "r", cfg, strategy=strat, callback=seen.append)
    rounds = [i for i in seen if i["densified"]]
    assert [i["step"] for i in rounds] == [10, 20, 30, 40] and all(i["relocated"] > 0 for i in rounds)
    # hooks: pre then post, once per step, with the 1-based step number
    assert [c[:2] for c in strat.calls] == [(kind, s) for s in range(1, 41) for kind in ("pre", "post")]
    counts = {s: n for kind, s, n in strat.calls if kind == "pre"}
    n0 = counts[1]
    # the count only changes in the strategy's rounds (steps 10, 20, 30, 40), by its growth rule
    expect, n = {}, n0
    for s in range(1, 41):
        expect[s] = n
        if s >= 10 and s % 10 == 0:
            n = min(150, n + int(0.05 * n))
    assert counts == expect and len(res.gaussians) == n
    logged = [h for h in res.history if h["step"] % 10 == 0]
    assert [h["n"] for h in logged] == [min(150, expect[s] + int(0.05 * expect[s])) for s in (10, 20, 30, 40)]
    meta = json.loads((tmp_path / "r" / "train.json").read_text())
    assert meta["strategy"] == {"name": "relocate", "every": 10, "dead": 0.1, "cap": 150}
    assert np.all(res.gaussians.opacities[-int(0.05 * expect[40]):] >= 0.1)  # copies of live ones


def test_custom_strategy_state_resumes_exactly_and_another_strategy_is_refused(synth, tmp_path):
    ds = load_dataset(synth)
    cfg = tiny_config(iters=30, checkpoint_every=10)
    full = train(ds, tmp_path / "a", cfg, strategy=RelocateStrategy())

    class Killed(Exception):
        pass

    def kill(info):
        if info["step"] == 25:
            raise Killed

    with pytest.raises(Killed):
        train(ds, tmp_path / "b", cfg, callback=kill, strategy=RelocateStrategy())
    tr = Trainer(ds, tmp_path / "b", cfg, strategy=RelocateStrategy())
    res = tr.run(resume=True)
    assert tr.strategy_state["rounds"] == 3 and tr.strategy_state["moved"].shape == (len(res.gaussians),)
    np.testing.assert_array_equal(res.gaussians.means, full.gaussians.means)
    np.testing.assert_array_equal(res.gaussians.sh, full.gaussians.sh)
    # the checkpoint names its strategy: the default one does not continue it
    with pytest.raises(CheckpointMismatch, match="another densification strategy"):
        train(ds, tmp_path / "b", cfg, resume=True)
    with pytest.raises(CheckpointMismatch, match="another densification strategy"):
        train(ds, tmp_path / "b", cfg, resume=True, strategy=RelocateStrategy(every=5))


def test_default_strategy_is_the_config_schedule_and_none_keeps_the_count(synth, tmp_path):
    ds = load_dataset(synth)
    dcfg = DensifyConfig(refine_start=10, refine_stop=40, refine_every=10, reset_every=20, grad_threshold=1e-4,
                         max_gaussians=400)
    cfg = tiny_config(iters=50, densify_cfg=dcfg)
    seen = []
    res = train(ds, tmp_path / "d", cfg, callback=seen.append)
    refined = [i["step"] for i in seen if i["densified"]]
    assert refined == [20, 30, 40]            # s > refine_start, every refine_every, up to refine_stop
    assert all(("cloned" in i) == i["densified"] for i in seen)
    assert len({i["n"] for i in seen if i["step"] > 40}) == 1 and seen[0]["n"] < res.history[-1]["n"]
    # passing the same default strategy explicitly gives the same run, bit for bit
    same = train(ds, tmp_path / "d2", cfg, strategy=DefaultStrategy(dcfg))
    np.testing.assert_array_equal(same.gaussians.means, res.gaussians.means)
    np.testing.assert_array_equal(same.gaussians.opacities, res.gaussians.opacities)
    # the base Strategy is "no densification": the same as densify=False
    a = train(ds, tmp_path / "n1", tiny_config(iters=20), strategy=Strategy())
    b = train(ds, tmp_path / "n2", tiny_config(iters=20, densify=False))
    assert len(a.gaussians) == len(b.gaussians) == seen[0]["n"]
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
