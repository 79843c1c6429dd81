"""semantics stage: 2D object masks (files or open-vocabulary prompts) lifted onto the Gaussians.

- `MaskSet` / `load_masks` (`masks`): per view and object label a bool mask + score, from PNG folders,
  label images, COCO RLE JSON (`rle`), the paper code's polygon JSON, or the embedded scene.
- `segment_images` / `OpenVocabSegmenter` (`segment`): Grounding DINO boxes + SAM / SAM 2 masks, or SAM 3.
- `fuse` / `naive_fusion` (`fusion`): visibility-aware fusion (paper section 3.2) and the baseline.
- metrics (`metrics`): 2D mIoU, 3D projection consistency, ghost index.
- `fuse_to_dir` (`lift`): files in, labels.npy + object PLYs + label maps out.
"""

from splattwin.semantics.fusion import FusionOptions, FusionResult, View, fuse, naive_fusion, splat_normals
from splattwin.semantics.masks import MaskSet, MaskWarning, load_masks, scene_masks

__all__ = ["FusionOptions", "FusionResult", "MaskSet", "MaskWarning", "View", "fuse", "load_masks", "naive_fusion",
           "scene_masks", "splat_normals"]
