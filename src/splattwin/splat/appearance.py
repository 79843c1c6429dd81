"""Per-image appearance: an affine colour correction of each training image, learnt with the splats.

Photos of one capture differ in exposure and white balance (auto-exposure, a cloud, a phone's tone
mapping). Without a correction the Gaussians absorb these differences as view-dependent colour (SH) or
floaters, which hurts new views. Each training view i gets

    c' = A_i c + b_i          c: the rendered RGB of a pixel, [3]; A_i [3,3], b_i [3]

applied to the rendered image before the loss ("affine"), or the diagonal special case A_i = diag(g_i)
("gain": per-channel gain and bias, 6 numbers per view). The splats keep one canonical colour. Each A_i
starts at diag(g_i), the per-channel gains the poses stage's exposure check measured for photo i relative
to the median photo (`initial_gains`; 1 where none was measured), so the canonical colour is the median
photo's look and each correction reproduces its own photo's exposure from the first step (at the default
learning rate the gains move only ~0.025 in 500 steps: started at 1 they could not reach gains of 0.7..1.3);
a penalty `reg * (||A_i - A0_i||_F^2 + ||b_i||^2)` keeps them near that start (an affine ambiguity would
otherwise be free). Held-out views
have no learnt correction: they are rendered with the identity (`plain` metrics), and can be scored
with the "fit on the left half, score on the right half" protocol of NeRF-W / Mip-NeRF 360's
appearance evaluation (`heldout_corrected_psnr`): a closed-form (ridge) fit of the same affine model on
the left half of the held-out image, PSNR on the right half only.

Which mode a run gets (`decide`): "off" (the default), "gain" or "affine" as asked; "auto" is "off" unless
the poses stage's exposure check (`splattwin.poses.exposure`, "exposure" in the poses_report.json beside the
dataset's transforms.json) says the photos' gains differ beyond its threshold, then `AUTO_MODE`. "off" on such
a capture trains without a correction and warns, naming the images and suggesting the correction. train.json records the
decision ("appearance": requested, mode, decision auto | suggested | explicit | none) and, when a correction
is trained, where it started (init measured | identity, init_views, init_why) and the learnt corrections'
common gain and bias (gauge: how far the canonical colour's level drifted, `AppearanceModel.gauge`).

Why our own: it is 20 lines of torch; gsplat's appearance module is a per-image embedding + MLP on SH
(a different, heavier model) and needs CUDA.

Optimisers: one Adam per view, like `pose_refine.PoseCorrection` (a step renders one view; a shared Adam's
momentum would keep moving the views not rendered), and `step(idx)` updates only those views.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

APPEARANCE_MODES = ("off", "gain", "affine", "auto")
# "auto" (opt-in): the mode trained when the poses stage's exposure check found the photos' gains differ. Not the
# default, because the figures do not agree across seeds (bench/exposure.py, embedded scene as a 24-view robot
# capture, 320x240, 500 steps; held-out PSNR / right halves after a colour fit on the left / against the unperturbed
# photos). Corrections started at the measured gains (`initial_gains`), off -> auto: per-view gain 0.7..1.3 x white
# balance 0.9..1.1, seed 0: 21.75 / 24.90 / 25.26 -> 23.21 / 26.62 / 26.29; seed 1: 19.80 / 27.11 / 25.78 -> 20.28 /
# 27.64 / 25.25; milder (0.9..1.1 x 0.97..1.03, 13-14 %), seed 0: 25.93 / 26.75 / 26.59 -> 26.07 / 27.78 / 27.48;
# seed 1: 24.73 / 26.38 / 26.05 -> 25.33 / 26.81 / 26.06. Seed 1's loss against the unperturbed photos is the
# canonical colour's overall level (4-7 % dark; one per-channel gain over the held-out views: 25.58 off -> 26.13
# auto), which no photo statistic can see: seed 1's 21 training photos average 0.95-0.97 of the unperturbed exposure
# (the median photo 0.96-0.98; seed 0: 0.97-1.00 and 1.04-1.09), and every correction's bias drifts up together
# (`AppearanceModel.gauge`, train.json "gauge": mean bias +0.007..+0.012, common gain +0.5-0.8 %) taking the
# canonical colour a further 3-5 % dark. Tried (Nov 2026, exposure-anchor, not kept): starts divided by their
# geometric mean over the training views (the mean exposure, not the median photo's) and the common gain and bias
# projected back to the start's after every step (canonical level then within 1-2 % of the photos' mean): 0.7..1.3
# seed 0 21.96 / 26.62 / 27.28, seed 1 20.16 / 27.67 / 25.79 (+0.99 / +0.54 against the unperturbed photos),
# 0.9..1.1 seed 0 26.16 / 27.37 / 27.48, seed 1 24.69 / 26.00 / 25.87 (0.00 / -0.19; plain -1.25 on 0.7..1.3 seed 0,
# where the held-out photos are 1.1-1.2 bright); the start alone 21.36 / 26.82 / 27.18, 20.51 / 27.72 / 25.01, 25.43
# / 27.52 / 27.26, 25.53 / 27.71 / 26.43; the hold alone (median start) 24.02 / 26.80 / 25.38, 19.99 / 27.39 / 26.15
# (0.7..1.3; docs/BENCHMARKS.md "Exposure"). At 3 held-out views a 0.4 % change of the start moved the right halves
# 0.9 dB (0.9..1.1 seed 1): single cells are noise at that size. Started at 1 instead (before), the learnt gains
# stayed within +-0.025 of 1 (the applied ones reach +-0.3): 26.01 (seed 0) and 25.06 (seed 1) against the
# unperturbed photos; a 10x learning rate (1e-2) let them move but the canonical colour drifted (25.25 / 22.35). On
# the unperturbed capture a forced gain costs 0.3-0.8 dB (27.55 -> 27.24 seed 0 started at 1, 26.41 -> 25.65 seed 1
# at the measured ~1 gains); the measured start beats the start at 1 on 0.7..1.3 (both seeds), 0.9..1.1 seed 0 reads
# 27.78 / 27.48 vs 27.53 / 27.71 (right halves / against the unperturbed photos); auto stays off there.
# british_museum (81 % spread, 1500 steps, started at 1): off 11.76 dB / right halves 13.19, gain 11.77 / 12.84. The
# default ("off") warns on such photos instead ("suggested").
AUTO_MODE = "gain"


class AppearanceModel:
    """Learnable colour corrections of V training views; `mode` "gain" or "affine" (see module doc)."""

    def __init__(self, n_views: int, mode: str = "affine", lr: float = 1e-3, reg: float = 0.01,
                 device: str | torch.device = "cpu", init_gains: np.ndarray | None = None):
        """init_gains: [n_views, 3] per-channel gains each view's correction starts at (A = diag(gains):
        model colour -> that photo's colour; `initial_gains`), and the regulariser's centre; None: identity."""
        if mode not in ("gain", "affine"):
            raise ValueError(f"appearance mode must be 'gain' or 'affine', got {mode!r}")
        self.mode, self.reg = mode, float(reg)
        n_lin = 3 if mode == "gain" else 9
        # per view: the deviation from identity of A (3 or 9 numbers) and the bias (3): zero = identity
        prior = torch.zeros(n_views, n_lin + 3)
        if init_gains is not None:
            g = torch.as_tensor(np.asarray(init_gains, np.float32))
            if tuple(g.shape) != (n_views, 3) or not torch.isfinite(g).all() or (g <= 0).any():
                raise ValueError(f"init_gains must be [{n_views}, 3] positive, got {tuple(g.shape)}")
            diag = [0, 1, 2] if mode == "gain" else [0, 4, 8]   # A's diagonal within the parameters
            prior[:, diag] = g - 1.0
        self.prior = prior.to(device)
        self.params = [torch.nn.Parameter(prior[i].clone().to(device)) for i in range(n_views)]
        self.optimizers = [torch.optim.Adam([p], lr=lr) for p in self.params]

    def __len__(self) -> int:
        return len(self.params)

    def matrix_bias(self, idx: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(A [3,3], b [3]) of view idx (differentiable)."""
        p = self.params[idx]
        eye = torch.eye(3, dtype=p.dtype, device=p.device)
        A = eye + (torch.diag(p[:3]) if self.mode == "gain" else p[:9].reshape(3, 3))
        return A, p[-3:]

    def apply(self, img: torch.Tensor, idx: int) -> torch.Tensor:
        """Corrected image [H,W,3] = A img + b of training view idx (img [H,W,3])."""
        A, b = self.matrix_bias(idx)
        return img @ A.T + b

    def regularizer(self, idx: int) -> torch.Tensor:
        """reg * (||A - A0||_F^2 + ||b||^2) of view idx (scalar); A0: its initial (measured) gains, else I."""
        return self.reg * ((self.params[idx] - self.prior[idx]) ** 2).sum()

    def step(self, idx: list[int]) -> None:
        for i in idx:
            self.optimizers[i].step()
            self.optimizers[i].zero_grad(set_to_none=True)

    def as_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """All corrections as numpy: A [V,3,3], b [V,3]."""
        with torch.no_grad():
            mb = [self.matrix_bias(i) for i in range(len(self))]
        return (np.stack([m.detach().cpu().numpy() for m, _ in mb]) if mb else np.zeros((0, 3, 3)),
                np.stack([b.detach().cpu().numpy() for _, b in mb]) if mb else np.zeros((0, 3)))

    def gauge(self) -> dict:
        """The corrections' common part, per channel (r, g, b): "gain", the geometric mean over the views of A's
        diagonal, "gain_start", the same of where they started, and "bias", the views' mean b. A colour transform
        shared by the canonical colour and every correction is free ((c, A_i, b_i) ~ (S c + d, A_i S^-1,
        b_i - A_i S^-1 d)); only the penalty towards the start holds it, so a common part that moved from the
        start's is the canonical colour's level drifting the other way (gain 2 % above gain_start, or bias
        +0.01: the photos read brighter than the splats' own colour, which went dark)."""
        A, b = self.as_arrays()
        d0 = 1.0 + self.prior[:, [0, 1, 2] if self.mode == "gain" else [0, 4, 8]].detach().cpu().numpy()
        gm = lambda d: [round(float(v), 4) for v in np.exp(np.log(np.clip(d, 1e-6, None)).mean(axis=0))]  # noqa: E731
        return {"gain": gm(np.diagonal(A, axis1=1, axis2=2)), "gain_start": gm(d0),
                "bias": [round(float(v), 4) for v in b.mean(axis=0)]}

    def state_dict(self) -> dict:
        return {"mode": self.mode, "params": torch.stack([p.detach().cpu() for p in self.params]),
                "prior": self.prior.detach().cpu(), "optimizers": [o.state_dict() for o in self.optimizers]}

    def load_state_dict(self, sd: dict) -> None:
        if sd["mode"] != self.mode or tuple(sd["params"].shape) != (len(self), self.params[0].numel()):
            raise ValueError(f"appearance state is {sd['mode']!r} {tuple(sd['params'].shape)}, this run "
                             f"{self.mode!r} ({len(self)}, {self.params[0].numel()})")
        with torch.no_grad():
            for p, v in zip(self.params, sd["params"]):
                p.copy_(v.to(p.device, p.dtype))
            prior = sd.get("prior")   # the run's own centre (absent in checkpoints from before the init)
            if prior is not None:
                if (not isinstance(prior, torch.Tensor) or tuple(prior.shape) != tuple(self.prior.shape)
                        or not bool(torch.isfinite(prior).all())):
                    raise ValueError(f"appearance state's prior is not a finite {tuple(self.prior.shape)} tensor")
                self.prior = prior.to(self.prior.device, self.prior.dtype)
        for o, s in zip(self.optimizers, sd["optimizers"]):
            o.load_state_dict(s)


def fit_affine(render: np.ndarray, target: np.ndarray, mode: str = "affine", ridge: float = 1e-3
               ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares colour correction (A [3,3], b [3]) with A render + b ~= target over the pixels of
    render/target [..., 3], ridge-regularised towards the identity (weight `ridge` per pixel)."""
    x = np.asarray(render, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    n = len(x)
    if mode == "gain":
        A, b = np.eye(3), np.zeros(3)
        for c in range(3):
            X = np.stack([x[:, c], np.ones(n)], 1)
            M = X.T @ X + ridge * n * np.eye(2)
            g, o = np.linalg.solve(M, X.T @ y[:, c] + ridge * n * np.array([1.0, 0.0]))
            A[c, c], b[c] = g, o
        return A, b
    if mode != "affine":
        raise ValueError(f"fit_affine mode must be 'gain' or 'affine', got {mode!r}")
    X = np.concatenate([x, np.ones((n, 1))], 1)  # [n,4]
    prior = np.concatenate([np.eye(3), np.zeros((1, 3))], 0)  # [4,3]: identity, zero bias
    M = X.T @ X + ridge * n * np.eye(4)
    W = np.linalg.solve(M, X.T @ y + ridge * n * prior)  # [4,3]: y = X W
    return W[:3].T, W[3]


def heldout_corrected_psnr(render: np.ndarray, gt: np.ndarray, mode: str = "affine",
                           mask: np.ndarray | None = None) -> dict:
    """The appearance protocol on one held-out view (render, gt [H,W,3] in [0,1]): a correction fitted
    on the left half of the image, PSNR of the right half before ('psnr_right_plain') and after
    ('psnr_right_corrected') applying it. mask: [H,W] bool, the pixels that count (a loss mask's kept
    pixels): the fit and both PSNRs use only those (NaN when the right half has none; no correction when
    the left half has none)."""
    from splattwin.splat import metrics

    w = render.shape[1] // 2
    if mask is None:
        A, b = fit_affine(render[:, :w], gt[:, :w], mode)
    else:
        left = mask[:, :w]
        A, b = fit_affine(render[:, :w][left], gt[:, :w][left], mode) if left.any() else (np.eye(3), np.zeros(3))
    right, right_gt = render[:, w:], gt[:, w:]
    corr = np.clip(right @ A.T + b, 0.0, 1.0).astype(np.float32)
    if mask is None:
        return {"psnr_right_plain": metrics.psnr(right, right_gt),
                "psnr_right_corrected": metrics.psnr(corr, right_gt)}
    keep = mask[:, w:]
    return {"psnr_right_plain": metrics.masked_psnr(right, right_gt, keep),
            "psnr_right_corrected": metrics.masked_psnr(corr, right_gt, keep)}


def exposure_record(dataset) -> tuple[dict | None, Path | None]:
    """The poses stage's exposure check of a posed dataset (the poses_report.json beside its transforms.json,
    `init.poses_report_path`, "exposure"), and the file read; (None, path or None) when there is none or it
    is unreadable or malformed (logged: the check is a hint, training goes on without it)."""
    from splattwin.errors import InputError
    from splattwin.limits import MAX_RECORD_BYTES, read_json
    from splattwin.splat.init import poses_report_path

    path = poses_report_path(dataset)
    if not path.is_file():
        return None, None
    try:
        rep = read_json(path, "poses report", MAX_RECORD_BYTES)
    except InputError as e:
        log.warning("exposure check not read: %s", e)
        return None, path
    rec = rep.get("exposure") if isinstance(rep, dict) else None
    if rec is None:
        return None, path
    ok = (isinstance(rec, dict) and (isinstance(rec.get("error"), str) or (
        isinstance(rec.get("varies"), bool) and isinstance(rec.get("spread_pct"), (int, float))
        and isinstance(rec.get("images_off"), list) and all(isinstance(n, str) for n in rec["images_off"]))))
    if not ok:
        log.warning("exposure check not read: %s: malformed \"exposure\" record (expected varies, spread_pct, "
                    "images_off)", path)
        return None, path
    return rec, path


GAIN_RANGE = (0.05, 20.0)   # measured gains outside are not trusted as a start (a broken record): 1 instead


def initial_gains(exposure: dict | None, names: list[str], source: str | Path | None = None
                  ) -> tuple[np.ndarray, dict]:
    """Each training view's starting per-channel gain from the poses stage's exposure check.

    exposure: the record (`exposure_record`) or None; names: the training views' names (`Frame.name`, the
    record's keys). The record's `rgb_gain` of image i is colour_i / colour_median-image per channel (8-bit
    encoding); the correction maps the model's colour to photo i's (c' = A_i c), and the model is meant to
    learn the median image's colours, so A_i starts at diag(rgb_gain_i) (a photo twice as bright: x2).
    Returns (gains [V,3], {"init": "measured" | "identity", "init_views": views started from a measurement,
    "init_why": why not, when some or all start at 1}); views without a usable gain start at 1 (logged)."""
    g = np.ones((len(names), 3))
    where = f" ({source})" if source else ""
    images = exposure.get("images") if isinstance(exposure, dict) and not exposure.get("error") else None
    if not isinstance(images, dict):
        why = ("no exposure check read" if exposure is None else f"exposure check not measured: {exposure['error']}"
               if isinstance(exposure, dict) and exposure.get("error") else "exposure record has no \"images\"")
        log.info("appearance: corrections start at gain 1 (%s%s)", why, where)
        return g, {"init": "identity", "init_views": 0, "init_why": why}
    missing: list[str] = []
    for i, n in enumerate(names):
        r = images.get(n)
        v = r.get("rgb_gain") if isinstance(r, dict) else None
        ok = (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                           for x in v)
              and all(np.isfinite(x) and GAIN_RANGE[0] <= x <= GAIN_RANGE[1] for x in v))
        if ok:
            g[i] = v
        else:
            missing.append(n)
    used = len(names) - len(missing)
    rec: dict = {"init": "measured" if used else "identity", "init_views": used}
    if missing:
        named = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        rec["init_why"] = f"no usable measured gain for {len(missing)} of {len(names)} views ({named}): gain 1"
        log.info("appearance: %s%s", rec["init_why"], where)
    if used:
        log.info("appearance: %d of %d corrections start at the measured gains (%.2f..%.2f)%s", used, len(names),
                 float(g.min()), float(g.max()), where)
    return g, rec


def decide(requested: str, exposure: dict | None, source: str | Path | None = None) -> dict:
    """The appearance mode a run trains with, and why (train.json's "appearance" record).

    requested: TrainConfig.appearance ("off", "gain", "affine" or "auto"); exposure: the poses stage's
    exposure record (`exposure_record`) or None. decision: "auto" (auto turned the correction on: the
    photos' gains differ), "suggested" ("off" on such photos: a warning), "explicit" (a mode
    asked for), "none" (auto, and nothing measured or no difference: off)."""
    if requested not in APPEARANCE_MODES:
        raise ValueError(f"appearance mode must be one of {APPEARANCE_MODES}, got {requested!r}")
    varies = bool(exposure and not exposure.get("error") and exposure.get("varies"))
    rec: dict = {"requested": requested, "source": None if source is None else str(source)}
    if exposure is None:
        rec["exposure"] = "not measured (no poses report with an exposure check beside the dataset)"
    elif exposure.get("error"):
        rec["exposure"] = f"not measured ({exposure['error']})"
    else:
        rec.update(spread_pct=exposure["spread_pct"], threshold_pct=exposure.get("threshold_pct"),
                   images_off=list(exposure["images_off"]))
    off = list(exposure.get("images_off") or []) if varies else []
    named = ", ".join(off[:8]) + (f" and {len(off) - 8} more" if len(off) > 8 else "")
    where = "" if source is None else f", {source}"
    if requested == "auto" and varies:
        rec.update(mode=AUTO_MODE, decision="auto")
        log.warning("appearance: the photos differ in exposure / white balance by up to %.1f %% (%s; the poses "
                    "stage's exposure check%s): training with a per-image colour correction (--splat.appearance "
                    "%s; --splat.appearance off to train without)", exposure["spread_pct"], named, where, AUTO_MODE)
    elif requested == "auto":
        rec.update(mode="off", decision="none")
    elif requested == "off" and varies:
        rec.update(mode="off", decision="suggested")
        log.warning("appearance: the photos differ in exposure / white balance by up to %.1f %% (%s; the poses "
                    "stage's exposure check%s) and are trained without a per-image colour correction; "
                    "--splat.appearance %s (or auto) learns one", exposure["spread_pct"], named, where, AUTO_MODE)
    else:
        rec.update(mode=requested, decision="explicit")
    return rec
