"""Options of the playback package's build step: the object-focused refinement of the splats
(`splattwin.playback.refine`, `build --refine.*`). Light: read by `splattwin --help`."""

from __future__ import annotations

from dataclasses import dataclass

from splattwin.options import option


@dataclass
class RefineOptions:
    """Object-focused refinement of the splats after the twin is built (`splattwin.playback.refine`): the moved
    objects' Gaussians trained again on the training photos, the rest of the scene frozen, densified on
    their own budget."""

    iters: int = option(0, "steps of the object refinement (one training view each; 0: off)")
    grad_threshold: float = option(1e-4, "densification threshold of the objects' view-space gradient (NDC; "
                                   "the splat stage's is 2e-4)")
    max_factor: float = option(4.0, "an object may grow to this many times its Gaussians")
    split_scale: float = option(0.0015, "selected Gaussians larger than this split, smaller ones are cloned",
                                unit="m")
    refine_every: int = option(50, "steps between densification rounds")
    refine_stop: float = option(0.6, "densify during this share of the run")
    means_lr: float = option(1.6e-4, "Adam LR of the means (times the scene scale; decays 100x over the run)")
    dc_only: bool = option(False, "train and keep the objects' SH degree 0 only (moved objects are drawn "
                           "with it)")
    ssim_lambda: float = option(0.2, "weight of D-SSIM in the photometric loss")
    mask_lambda: float = option(0.01, "weight of a silhouette loss: each object's rendered coverage against its "
                                "2D masks (the semantics stage's), where a view has one (0: off)")
    mask_min_iou: float = option(0.7, "a mask joins the silhouette loss only if its IoU with the object as the "
                                 "twin renders it before refinement is at least this (detector errors stay out)")
    seed: int = option(0, "seed of the view order and the split samples")
