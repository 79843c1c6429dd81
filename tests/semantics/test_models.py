"""`splattwin.semantics.models`: the pre-flight check that the prompt's models are on this machine."""

from __future__ import annotations

import json
from pathlib import Path

from splattwin.semantics import models
from splattwin.semantics.options import SegmentOptions


def _folder(root: Path, model_type: str, *files: str) -> Path:
    root.mkdir(parents=True)
    (root / "config.json").write_text(json.dumps({"model_type": model_type}))
    (root / "model.safetensors").write_bytes(b"\0" * 8)
    for f in files:
        (root / f).write_text("{}")
    return root


def test_processor_files_are_part_of_a_model(tmp_path):
    """A cache filled by `SamModel.from_pretrained` alone holds config + weights but not the processor's
    files: the pre-flight passed and segmentation failed after pose estimation and training. The files
    each role loads are now checked and named."""
    det = _folder(tmp_path / "dino", "grounding-dino", "preprocessor_config.json")        # no tokenizer
    sam = _folder(tmp_path / "sam", "sam")                                                # no image processor
    e = models.missing_models_error(SegmentOptions(detector=str(det), segmenter=str(sam)))
    assert e is not None
    assert "(MISSING tokenizer.json | vocab.txt)" in e.problem
    assert "(MISSING preprocessor_config.json | processor_config.json)" in e.problem
    assert not models.is_available(str(sam), "sam") and models.is_available(str(sam))
    (det / "vocab.txt").write_text("[PAD]\n")
    (sam / "processor_config.json").write_text("{}")                  # transformers 5's save_pretrained name
    assert models.missing_models_error(SegmentOptions(detector=str(det), segmenter=str(sam))) is None
    # SAM 2 images are preprocessed by hand: config + weights suffice; SAM 3 needs its tokenizer
    sam2 = _folder(tmp_path / "sam2", "sam2")
    assert models.missing_models_error(SegmentOptions(detector=str(det), segmenter=str(sam2))) is None
    sam3 = _folder(tmp_path / "sam3", "sam3")
    assert "(MISSING tokenizer.json | vocab.json)" in models.missing_models_error(
        SegmentOptions(segmenter=str(sam3))).problem


def test_detector_of_another_model_type_is_named(tmp_path):
    """A SAM folder given as the detector (or a Grounding DINO one as a forced-kind segmenter) loads with
    random weights (transformers only warns): named at the pre-flight, before any work."""
    sam = _folder(tmp_path / "sam", "sam", "preprocessor_config.json", "tokenizer.json")
    e = models.missing_models_error(SegmentOptions(detector=str(sam), segmenter=str(sam)))
    assert e is not None and "(a 'sam' model, not Grounding DINO)" in e.problem
    dino = _folder(tmp_path / "dino", "grounding-dino", "preprocessor_config.json", "tokenizer.json")
    e = models.missing_models_error(SegmentOptions(detector=str(dino), segmenter=str(dino), segmenter_kind="sam"))
    assert e is not None and "(a 'grounding-dino' model, not a sam model)" in e.problem and "(present)" in e.problem
