"""The trainer's optional per-view and far-field parts, behind five calls (so `trainer.py` stays small):

    make(cfg, views, device)          -> (AppearanceModel | None, BackgroundModel | None)
    with_background_sphere(g, cfg, views, center, scale) -> Gaussians (+ the background sphere, if on)
    apply(appearance, bg_model, img, alpha, idx, K, viewmat, rendered_bg) -> (image, extra loss)
    step(appearance, bg_model, idx)   after the backward pass
    write(out_dir, appearance, bg_model, names) / read(out_dir): OUT/extras.safetensors

OUT/extras.safetensors (written by `splattwin.splat.checkpoint.save`: tensors + JSON, no pickle) holds
the learnt background (evaluation and later renders composite it) and the per-view colour corrections
(with the view names; for inspection: held-out views are rendered without a correction). It is absent
when both are off.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from splattwin.splat.appearance import AppearanceModel
from splattwin.splat.background import BackgroundModel, sphere_points, sphere_radius

if TYPE_CHECKING:  # pragma: no cover
    from splattwin.splat.config import TrainConfig
    from splattwin.splat.gaussians import Gaussians

log = logging.getLogger(__name__)

EXTRAS_FILE = "extras.safetensors"


def make(cfg: TrainConfig, views: list, device, init_gains: np.ndarray | None = None
         ) -> tuple[AppearanceModel | None, BackgroundModel | None]:
    """init_gains: [V,3] the colour corrections' starting gains (`appearance.initial_gains`), None: 1."""
    app = None
    if cfg.appearance != "off":
        app = AppearanceModel(len(views), cfg.appearance, cfg.appearance_lr, cfg.appearance_reg, device,
                              init_gains=init_gains)
    bg = None
    if cfg.background_mode != "fixed":
        # start at the training images' mean colour (what an empty ray should show first)
        mean = torch.stack([v.image.reshape(-1, 3).mean(0) for v in views]).mean(0).cpu().numpy()
        bg = BackgroundModel(cfg.background_mode, mean, (cfg.env_size, 2 * cfg.env_size), cfg.background_lr, device)
    return app, bg


def with_background_sphere(g: Gaussians, cfg: TrainConfig, views: list, center: np.ndarray, scale: float
                           ) -> Gaussians:
    """`g` plus `cfg.bg_sphere_points` Gaussians on the background sphere (`background.sphere_points`)."""
    if cfg.bg_sphere_points <= 0:
        return g
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.init import gaussians_from_points

    r = sphere_radius(g.means, center, scale, cfg.bg_sphere_radius)
    xyz, rgb = sphere_points([v.camera for v in views], [v.image.cpu().numpy() for v in views], center, r,
                             cfg.bg_sphere_points)
    s = gaussians_from_points(xyz, rgb, sh_degree=g.sh_degree)
    log.info("background sphere: %d Gaussians at radius %.3g (scene scale %.3g)", len(xyz), r, scale)
    return Gaussians(means=np.concatenate([g.means, s.means]), quats=np.concatenate([g.quats, s.quats]),
                     scales=np.concatenate([g.scales, s.scales]), opacities=np.concatenate([g.opacities, s.opacities]),
                     sh=np.concatenate([g.sh, s.sh]))


def apply(app: AppearanceModel | None, bg: BackgroundModel | None, img: torch.Tensor, alpha: torch.Tensor, idx: int,
          K: torch.Tensor, viewmat: torch.Tensor, rendered_bg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Training view idx's render img [H,W,3] (alpha [H,W,1], drawn over rendered_bg [3]) over the learnt
    background, then colour-corrected; and the corrections' regulariser (0 when off). K [3,3], viewmat
    [4,4] world->camera (the input pose; a pose correction does not move the far field)."""
    extra = img.new_zeros(())
    if bg is not None:
        img = bg.composite(img, alpha, K, torch.linalg.inv(viewmat), rendered_bg)
    if app is not None:
        img = app.apply(img, idx)
        extra = extra + app.regularizer(idx)
    return img, extra


def step(app: AppearanceModel | None, bg: BackgroundModel | None, idx: int) -> None:
    if app is not None:
        app.step([idx])
    if bg is not None:
        bg.step()


def load_state(app: AppearanceModel | None, bg: BackgroundModel | None, sd: dict) -> None:
    """Restore from a trainer checkpoint `sd` (ValueError when it was made with other settings)."""
    for name, obj in (("appearance", app), ("bg_model", bg)):
        st = sd.get(name)
        if (st is None) != (obj is None):
            raise ValueError(f"checkpoint {'has' if st is not None else 'lacks'} a {name} state, this run "
                             f"{'does not use one' if obj is None else 'needs one'}")
        if obj is not None:
            obj.load_state_dict(st)


def write(out_dir: Path, app: AppearanceModel | None, bg: BackgroundModel | None, names: list[str]) -> Path | None:
    from splattwin.splat import checkpoint as ckpt_io

    path = Path(out_dir) / EXTRAS_FILE
    if app is None and bg is None:
        if path.exists():
            path.unlink()  # a stale one from an earlier run with other options
        return None
    state: dict = {"background": None, "appearance": None}
    if bg is not None:
        state["background"] = {"mode": bg.mode, "param": bg.param.detach().cpu()}
    if app is not None:
        A, b = app.as_arrays()
        state["appearance"] = {"mode": app.mode, "names": list(names), "A": torch.from_numpy(A),
                               "b": torch.from_numpy(b)}
    return ckpt_io.save(path, state)


def read_background(folder: Path, device="cpu") -> BackgroundModel | None:
    """The learnt background saved in a training folder (None when there is none). InputError for a bad file."""
    from splattwin.errors import InputError
    from splattwin.splat import checkpoint as ckpt_io

    path = Path(folder) / EXTRAS_FILE
    if not path.is_file():
        return None
    st = ckpt_io.load(path).get("background")
    if st is None:
        return None
    p = st.get("param") if isinstance(st, dict) else None
    if (not isinstance(p, torch.Tensor) or p.dim() != 3 or p.shape[0] != 3 or p.shape[1] > 4096
            or p.shape[2] > 8192 or st.get("mode") not in ("color", "env")):
        raise InputError("extras file has a malformed background", path)
    return BackgroundModel.from_state(st, device)
