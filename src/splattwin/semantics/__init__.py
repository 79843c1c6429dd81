"""semantics stage: 2D object masks (files or open-vocabulary prompts) lifted onto the Gaussians.

- `MaskSet` / `load_masks` (`masks`): per view and object label a bool mask + score, from PNG folders,
  label images, COCO RLE JSON (`rle`), the paper code's polygon JSON, or the embedded scene.
- `segment_images` / `OpenVocabSegmenter` (`segment`): Grounding DINO boxes + SAM / SAM 2 masks, or SAM 3.
- `fuse` / `naive_fusion` (`fusion`): visibility-aware fusion (paper section 3.2) and the baseline.
- metrics (`metrics`): 2D mIoU, 3D projection consistency, ghost index.
- `fuse_to_dir` (`lift`): files in, labels.npy + object PLYs + label maps out (lengths scaled to the
  frame); `prompt_labels`: a generated scene's ids for prompted masks.
- options (`options`): `SemanticsOptions`, `FusionOptions`, `SegmentOptions`.

Imports are lazy (`splattwin.semantics.options` is read by `splattwin --help`).
"""

from __future__ import annotations

from splattwin._lazy import lazy_exports

_EXPORTS = {"FusionOptions": "options", "SegmentOptions": "options", "SemanticsOptions": "options",
            "FusionResult": "fusion", "View": "fusion", "fuse": "fusion", "naive_fusion": "fusion",
            "splat_normals": "fusion", "MaskSet": "masks", "MaskWarning": "masks", "load_masks": "masks",
            "scene_masks": "masks", "segment_images": "segment", "OpenVocabSegmenter": "segment",
            "fuse_to_dir": "lift", "prompt_labels": "lift", "label_objects": "lift"}

__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
