"""Semantic metrics as the paper defines them (section 4.1.3 / 4.4).

- `miou`: 2D mean IoU of rendered label maps against ground-truth label images; IoU per (view, object)
  where the object is in the GT or the prediction, averaged per object over views, then over objects.
- `projection_consistency`: for the points labelled as an object, V_p = views where the point projects
  strictly inside the image, N_p = |V_p|, N_p^fg = views whose mask of that object contains the
  projection; share (in %) of labelled points with N_p > 0 and N_p^fg / N_p >= 0.8.
- `ghost_index`: "percentage increase in foreground points when relaxing the voting threshold,
  normalised by the total point count": 100 * (|FG(relaxed)| - |FG(kappa)|) / N_total with the
  relaxed threshold tau -> 0 (any positive weighted vote) and N_total all Gaussians that are visible
  in at least one view. It measures how much artefact mass sits just below the threshold.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from splattwin.semantics.fusion import FusionResult, View, consensus, visible_mask
from splattwin.semantics.masks import MaskSet
from splattwin.semantics.label_render import project_to_pixels


def iou_table(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray], label_ids: Sequence[int]) -> np.ndarray:
    """[V,L] IoU per view and object (nan where the object is in neither prediction nor GT)."""
    out = np.full((len(pred), len(label_ids)), np.nan)
    for i, (p, g) in enumerate(zip(pred, gt)):
        if p.shape != g.shape:
            raise ValueError(f"prediction {p.shape} and ground truth {g.shape} differ in size (view {i})")
        for k, lab in enumerate(label_ids):
            a, b = p == lab, g == lab
            union = np.logical_or(a, b).sum()
            if union:
                out[i, k] = np.logical_and(a, b).sum() / union
    return out


def miou(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray], label_ids: Sequence[int]) -> float:
    """Mean IoU over objects of the per-object mean IoU over views."""
    t = iou_table(pred, gt, label_ids)
    per_obj = np.nanmean(np.where(np.isnan(t), np.nan, t), axis=0) if np.isfinite(t).any() else np.array([0.0])
    return float(np.nanmean(per_obj))


def projection_consistency(means: np.ndarray, labels: np.ndarray, views: Sequence[View], masks: MaskSet,
                           threshold: float = 0.8, depths: Sequence[np.ndarray] | None = None,
                           depth_tol: float = 0.02, depth_tol_rel: float = 0.01) -> float:
    """Share (%) of labelled points whose in-image observations fall in their object's mask >= threshold.

    depths: optional rendered depth [H,W] per view; then only views where the point passes the fusion's
    visibility test count (a variant that does not penalise occlusion; the paper counts every in-image view).
    """
    lab_idx = np.flatnonzero(labels > 0)
    if lab_idx.size == 0:
        return 0.0
    pts = np.asarray(means, dtype=np.float64)[lab_idx]
    lab = labels[lab_idx]
    n = np.zeros(lab_idx.size, dtype=np.int32)
    n_fg = np.zeros(lab_idx.size, dtype=np.int32)
    for j, v in enumerate(views):
        pix, z = project_to_pixels(pts, v.camera)
        inside = pix >= 0 if depths is None else visible_mask(pix, z, depths[j], depth_tol, depth_tol_rel)
        n += inside
        for k in np.unique(lab):
            m = masks.get(v.name, int(k))
            sel = inside & (lab == k)
            if m is not None and sel.any():
                n_fg[sel] += m.reshape(-1)[pix[sel]]
    ok = n > 0
    if not ok.any():
        return 0.0
    return float(100.0 * np.mean(n_fg[ok] / n[ok] >= threshold))


def ghost_index(result: FusionResult, kappa: float | None = None) -> float:
    """Ghost index (%) of the consensus at `kappa` (default: the result's) from the final round's votes."""
    kappa = result.options.kappa if kappa is None else kappa
    fg = consensus(result.votes, result.n_visible, kappa, result.label_ids, result.options.min_views)[0] > 0
    relaxed = (result.votes > 0).any(axis=1) & (result.n_visible >= max(result.options.min_views, 1))
    total = max(int((result.n_visible > 0).sum()), 1)
    return float(100.0 * (relaxed.sum() - (fg & relaxed).sum()) / total)
