"""Options of the semantics stage: open-vocabulary segmentation (`SegmentOptions`), the visibility-aware
fusion (`FusionOptions`), and the stage as the pipeline runs it (`SemanticsOptions`: where the 2D masks
come from, the renderers, both of the above). The single source of their defaults and help (see
`splattwin.options`). Light: no numpy, torch or transformers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from splattwin.options import option

DEFAULT_DETECTOR = "IDEA-Research/grounding-dino-tiny"
DEFAULT_SEGMENTER = "facebook/sam-vit-base"
SEGMENTER_KINDS = ("auto", "sam", "sam2", "sam3")
RENDERERS = ("auto", "splat", "points")


@dataclass
class SegmentOptions:
    """Open-vocabulary segmentation settings (`splattwin.semantics.segment`). Sizes in pixels, thresholds
    in [0,1]."""

    detector: str = option(DEFAULT_DETECTOR, "Grounding DINO hub id or local folder")
    segmenter: str = option(DEFAULT_SEGMENTER, "SAM / SAM 2 / SAM 3 hub id or local folder (e.g. "
                            "facebook/sam2.1-hiera-tiny, facebook/sam3)")
    segmenter_kind: str = option("auto", "segmenter family (auto: from the model config's model_type)",
                                 choices=SEGMENTER_KINDS)
    box_threshold: float = option(0.30, "minimum phrase score of a box (0-1)")
    working_size: int = option(640, "longest image edge fed to the detector", unit="px")
    max_per_object: int = option(1, "boxes kept per phrase (twin objects are single instances)")
    device: str = option("cpu", "torch device of the models")


@dataclass
class FusionOptions:
    """Parameters of `splattwin.semantics.fusion.fuse` (units: metres)."""

    kappa: float = option(1.5, "consensus strictness: tau = N / kappa", build_alias="kappa")
    iters: int = option(3, "refinement rounds (1 = single pass, no re-rendering)")
    depth_tol: float = option(0.02, "visibility: |z - rendered depth| <= depth_tol + depth_tol_rel * depth",
                              unit="m")
    depth_tol_rel: float = option(0.01, "relative part of the visibility depth tolerance")
    eps: float = option(0.02, "DBSCAN eps on depth", unit="m")
    min_samples: int = option(10, "DBSCAN min_samples (the point itself included, like scikit-learn)")
    gate_sigma: float | None = option(None, "soft-gate length scale (none: eps)", unit="m")
    min_views: int = option(1, "a Gaussian needs at least this many visible views to be labelled by consensus")
    min_cos: float = option(0.25, "flat splats seen more edge-on than this |cos| do not count as visible")
    knn_k: int = option(16, "neighbours of the KNN boundary smoothing")
    knn_threshold: float = option(0.6, "neighbour majority share needed to flip a label")
    knn_confidence: float = option(0.8, "only labels with a confidence below this may flip")
    floater_share: float = option(0.5, "share of in-mask observations gated out in front that marks a floater")
    converge_share: float = option(0.001, "stop refining when a smaller share of the labels changes")


@dataclass
class SemanticsOptions:
    """The semantics stage: 2D masks from files (`masks`), from text prompts (`prompt`, segmented with
    `segment`), or, for the embedded scene, its simulated segmenter; lifted onto the Gaussians with `fusion`."""

    masks: Path | None = option(None, "2D masks instead of a prompt: PNG folders, label images, COCO RLE JSON, "
                                "polygon JSON, BOP mask_visib, per-instance files", path=True, build_alias="masks")
    prompt: str | None = option(None, 'open-vocabulary objects, e.g. "blue box. yellow cube. toy hammer"',
                                build_alias="prompt")
    segment: SegmentOptions = option(factory=SegmentOptions, help="open-vocabulary segmentation (with a prompt)")
    fusion: FusionOptions = option(factory=FusionOptions, help="visibility-aware fusion")
    renderer: str = option("auto", "depth for the visibility test: centre z-buffer (points) or the rasterizer "
                           "(splat); auto: splat when the rasterizer is usable", choices=RENDERERS)
    maps_renderer: str = option("auto", "label maps: rasterized one-hot labels (splat; auto when available) or "
                                "centre z-buffer (points)", choices=RENDERERS)
    maps: bool = option(True, "render label maps of every view")
    naive: bool = option(False, "the naive voting baseline instead of the visibility-aware fusion (for comparison)")
