"""Densification strategies: how the set of Gaussians changes during training, outside the trainer.

Modelled on gsplat's `strategy/` (`Strategy`, `DefaultStrategy`, `MCMCStrategy`): the trainer owns the
loop (render, loss, backward, optimizer step) and calls a strategy's hooks at fixed points of each step;
the strategy edits the parameters and their Adam moments (through `splattwin.splat.densify`'s
operations) and keeps its statistics in a state object of its own. Swapping the strategy
(`Trainer(..., strategy=MyStrategy())`) needs no change to the trainer.

One training step, `step` = 1, 2, ... (the number of steps done once this one ends):

    render -> loss
    strategy.step_pre_backward(model, state, step, info)     # e.g. keep gradients of extra tensors
    loss.backward(); optimizer step; zero_grad; pose step
    stats = strategy.step_post_backward(model, state, step, info)  # grow / prune / relocate / reset

`info` (dict): the rasterizer's meta of this step ("means2d" [C,N,2] pixels, whose `.grad` is filled
after backward, "radii" [C,N], "depths", "conics", ...) plus "width", "height" (pixels of the view),
"view" (its index), "iters" (the run's length) and "generator" (a seeded CPU torch.Generator that the
trainer checkpoints: every random choice of a strategy must come from it for exact resume).
`step_post_backward` returns a dict of counts for the training log (e.g. {"cloned": 3, "split": 1,
"pruned": 2}), empty when nothing was done. The model's row count may change only in the hooks.

State: whatever `initialize_state(model)` returns, holding only tensors and plain data (it is saved in
every checkpoint, see `splattwin.splat.checkpoint`); `load_state` moves a checkpointed one to the
model's device. `describe()` (plain data) names the strategy and its options: it is written to train.json
and checkpoints, and a checkpoint made with another strategy is not resumed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from splattwin.splat import densify
from splattwin.splat.densify import DensifyConfig
from splattwin.splat.model import GaussianModel

__all__ = ["Strategy", "DefaultStrategy"]


class Strategy:
    """Base strategy: no densification (the Gaussians keep their number). Subclass and override the hooks."""

    name = "none"

    def initialize_state(self, model: GaussianModel) -> dict[str, Any]:
        """State at the start of a run (`model` holds the initial Gaussians)."""
        return {}

    def step_pre_backward(self, model: GaussianModel, state: dict[str, Any], step: int, info: dict) -> None:
        """Called after rendering and the loss, before `loss.backward()`."""

    def step_post_backward(self, model: GaussianModel, state: dict[str, Any], step: int, info: dict
                           ) -> dict[str, int]:
        """Called after backward and the optimizer step; may change the Gaussians. -> counts for the log."""
        return {}

    def describe(self) -> dict:
        """Plain data naming the strategy and its options (train.json, checkpoints)."""
        return {"name": self.name}

    def load_state(self, state: dict[str, Any], model: GaussianModel) -> dict[str, Any]:
        """A checkpointed state, its tensors moved to the model's device."""
        return {k: v.to(model.device) if torch.is_tensor(v) else v for k, v in state.items()}


@dataclass
class DefaultStrategy(Strategy):
    """Adaptive density control of 3DGS (Kerbl et al. 2023) on the schedule of `cfg` (see
    `splattwin.splat.densify`): up to `cfg.refine_stop`, accumulate the view-space gradient norms of the
    visible Gaussians every step; after `cfg.refine_start`, every `cfg.refine_every` steps clone, split
    and prune (`densify.refine`); every `cfg.reset_every` steps (0: never) reset the opacities.

    State: {"grad2d": [N], "count": [N]} (`densify.new_state`)."""

    cfg: DensifyConfig = field(default_factory=DensifyConfig)
    name = "default"

    def initialize_state(self, model: GaussianModel) -> dict[str, Any]:
        return densify.new_state(len(model), model.device)

    def step_post_backward(self, model: GaussianModel, state: dict[str, Any], step: int, info: dict
                           ) -> dict[str, int]:
        cfg = self.cfg
        if step > cfg.refine_stop:
            return {}
        if info["means2d"].grad is not None:
            densify.accumulate(state, info["means2d"].grad, info["radii"], info["width"], info["height"])
        stats: dict[str, int] = {}
        if step > cfg.refine_start and step % cfg.refine_every == 0:
            r = densify.refine(model, state, cfg, step, info["generator"])
            stats = {"cloned": r.cloned, "split": r.split, "pruned": r.pruned}
        if cfg.reset_every and step % cfg.reset_every == 0:
            densify.reset_opacity(model, 2.0 * cfg.prune_opacity)
        return stats

    def describe(self) -> dict:
        return {"name": self.name, "cfg": asdict(self.cfg)}
