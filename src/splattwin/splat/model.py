"""The trainable Gaussian model: raw (unactivated) torch parameters, one Adam optimizer each.

Parameters (gsplat layout), N Gaussians, K = (max_sh_degree + 1)^2:
    means      [N,3]     world frame, metres
    scales     [N,3]     log of the standard deviations (metres)
    quats      [N,4]     wxyz, unnormalised (normalised by the renderer)
    opacities  [N]       logits
    sh0        [N,1,3]   DC SH coefficient
    shN        [N,K-1,3] higher-order SH coefficients

One optimizer per parameter (as gsplat does) so densification can rewrite a parameter and its Adam
moments together, and so learning rates are set per parameter.
"""

from __future__ import annotations

import numpy as np
import torch

from splattwin.splat.config import LearningRates
from splattwin.splat.gaussians import Gaussians, num_sh_bases

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


def make_adam(param: torch.nn.Parameter, lr: float) -> torch.optim.Adam:
    """Adam (eps 1e-15, as 3DGS) with the fused kernel where torch has one for the device.

    Why fused: the default multi-tensor ("foreach") Adam makes several passes over the parameters; the
    fused kernel one (same update rule and state layout). Training step at 40k Gaussians, SH degree 3,
    2 idle cores: 83 ms fused vs 88-99 ms default."""
    try:
        return torch.optim.Adam([param], lr=lr, eps=1e-15, fused=True)
    except (RuntimeError, ValueError, TypeError):  # a device/dtype without a fused Adam
        return torch.optim.Adam([param], lr=lr, eps=1e-15)


class GaussianModel:
    """Raw parameters + their Adam optimizers. `params[name]` is a leaf `torch.nn.Parameter`."""

    def __init__(self, params: dict[str, torch.Tensor], lrs: LearningRates | None = None,
                 scene_scale: float = 1.0, device: str | torch.device = "cpu",
                 scene_center: torch.Tensor | None = None):
        self.lrs = lrs or LearningRates()
        self.scene_scale = float(scene_scale)
        self.scene_center = torch.zeros(3) if scene_center is None else torch.as_tensor(scene_center,
                                                                                         dtype=torch.float32)
        self.params: dict[str, torch.nn.Parameter] = {
            k: torch.nn.Parameter(params[k].detach().to(device=device, dtype=torch.float32).contiguous())
            for k in PARAM_NAMES}
        self.optimizers: dict[str, torch.optim.Adam] = {
            k: make_adam(self.params[k], self.base_lr(k)) for k in PARAM_NAMES}

    # -- construction --------------------------------------------------------------------------
    @classmethod
    def from_gaussians(cls, g: Gaussians, max_sh_degree: int = 3, **kw) -> GaussianModel:
        """Raw parameters from activated `Gaussians` (SH padded/truncated to `max_sh_degree`)."""
        g = g.with_sh_degree(max_sh_degree)
        op = np.clip(g.opacities, 1e-6, 1 - 1e-6)
        params = {
            "means": torch.from_numpy(g.means),
            "scales": torch.from_numpy(np.log(np.maximum(g.scales, 1e-10))),
            "quats": torch.from_numpy(g.quats),
            "opacities": torch.from_numpy(np.log(op) - np.log1p(-op)),
            "sh0": torch.from_numpy(g.sh[:, :1]),
            "shN": torch.from_numpy(g.sh[:, 1:]),
        }
        return cls(params, **kw)

    def to_gaussians(self) -> Gaussians:
        """Activated numpy `Gaussians` (a copy)."""
        with torch.no_grad():
            p = {k: v.detach().cpu().to(torch.float64) for k, v in self.params.items()}
            quats = p["quats"] / p["quats"].norm(dim=1, keepdim=True).clamp_min(1e-12)
            sh = torch.cat([p["sh0"], p["shN"]], dim=1)
            return Gaussians(means=p["means"].numpy(), quats=quats.numpy(), scales=p["scales"].exp().numpy(),
                             opacities=torch.sigmoid(p["opacities"]).numpy(), sh=sh.numpy())

    # -- activated views (differentiable) ------------------------------------------------------
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def max_sh_degree(self) -> int:
        return int(round(np.sqrt(self.params["shN"].shape[1] + 1))) - 1

    def activated(self) -> dict[str, torch.Tensor]:
        """means [N,3], quats [N,4] (unnormalised), scales [N,3] m, opacities [N], sh [N,K,3]."""
        p = self.params
        return {"means": p["means"], "quats": p["quats"], "scales": torch.exp(p["scales"]),
                "opacities": torch.sigmoid(p["opacities"]), "sh": torch.cat([p["sh0"], p["shN"]], dim=1)}

    # -- optimisation --------------------------------------------------------------------------
    def base_lr(self, name: str) -> float:
        lr = getattr(self.lrs, name)
        return lr * self.scene_scale if name == "means" else lr

    def set_step(self, step: int, max_steps: int) -> None:
        """Exponential decay of the position learning rate (start -> start * final_factor)."""
        t = min(max(step / max(max_steps, 1), 0.0), 1.0)
        lr = self.base_lr("means") * self.lrs.means_final_factor**t
        for grp in self.optimizers["means"].param_groups:
            grp["lr"] = lr

    def zero_grad(self) -> None:
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        for opt in self.optimizers.values():
            opt.step()

    # -- persistence ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.params.items()},
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "scene_scale": self.scene_scale, "scene_center": self.scene_center.clone(),
                "lrs": vars(self.lrs).copy()}

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @classmethod
    def from_state_dict(cls, sd: dict, device: str | torch.device = "cpu") -> GaussianModel:
        m = cls(sd["params"], lrs=LearningRates(**sd["lrs"]), scene_scale=sd["scene_scale"], device=device,
                scene_center=sd.get("scene_center"))
        for k, o in m.optimizers.items():
            o.load_state_dict(sd["optimizers"][k])
        return m


def empty_sh(n: int, degree: int) -> torch.Tensor:
    return torch.zeros(n, num_sh_bases(degree) - 1, 3)
