"""SAM 3 (text-prompted) segmentation through the real transformers code path with a tiny random-weight model.

The model is built from a small config and saved to a temp folder with a locally built CLIP tokenizer (no
downloads, no torchvision): the test checks the plumbing (shapes, thresholds, phrase -> label bookkeeping),
not segmentation quality.
"""

from __future__ import annotations

import numpy as np
import pytest

tf = pytest.importorskip("transformers")
if not hasattr(tf, "Sam3Model"):
    pytest.skip("transformers has no Sam3Model", allow_module_level=True)

from splattwin import io  # noqa: E402
from splattwin.semantics.segment import OpenVocabSegmenter, SegmentOptions, segment_images  # noqa: E402

WORDS = ["blue", "box", "yellow", "cube", "toy", "hammer"]
S, PATCH = 56, 14  # model input size (px) and ViT patch: a 4x4 token grid


@pytest.fixture(scope="module")
def tiny_sam3(tmp_path_factory):
    import torch
    from transformers import (CLIPTextConfig, CLIPTokenizer, Sam3Config, Sam3DETRDecoderConfig, Sam3DETREncoderConfig,
                              Sam3GeometryEncoderConfig, Sam3MaskDecoderConfig, Sam3Model, Sam3VisionConfig,
                              Sam3ViTConfig)

    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("hf") / "sam3"
    chars = sorted(set("".join(WORDS)))
    vocab = ["<|startoftext|>", "<|endoftext|>"] + chars + [c + "</w>" for c in chars] + [w + "</w>" for w in WORDS]
    tok = CLIPTokenizer(vocab={t: i for i, t in enumerate(vocab)}, merges=[])
    g = S // PATCH
    vit = Sam3ViTConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2, image_size=S,
                        patch_size=PATCH, window_size=2, global_attn_indexes=[1], pretrain_image_size=S)
    cfg = Sam3Config(
        vision_config=Sam3VisionConfig(backbone_config=vit, fpn_hidden_size=32,
                                       backbone_feature_sizes=[[4 * g, 4 * g], [2 * g, 2 * g], [g, g]]),
        text_config=CLIPTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=64, projection_dim=32,
                                   num_hidden_layers=1, num_attention_heads=2, max_position_embeddings=32,
                                   bos_token_id=0, eos_token_id=1, pad_token_id=1),
        geometry_encoder_config=Sam3GeometryEncoderConfig(hidden_size=32, num_layers=1, num_attention_heads=2,
                                                          intermediate_size=64),
        detr_encoder_config=Sam3DETREncoderConfig(hidden_size=32, num_layers=1, num_attention_heads=2,
                                                  intermediate_size=64),
        detr_decoder_config=Sam3DETRDecoderConfig(hidden_size=32, num_layers=1, num_queries=8, num_attention_heads=2,
                                                  intermediate_size=64),
        mask_decoder_config=Sam3MaskDecoderConfig(hidden_size=32, num_attention_heads=2))
    Sam3Model(cfg).save_pretrained(d)
    tok.save_pretrained(d)
    return d


def test_sam3_phrases_to_masks(tiny_sam3):
    img = np.random.default_rng(0).integers(0, 255, (60, 90, 3), dtype=np.uint8)
    seg = OpenVocabSegmenter(SegmentOptions(segmenter=str(tiny_sam3), box_threshold=0.0))
    assert seg.kind == "sam3"                                  # picked from the config's model_type
    found = seg(img, ["blue box", "yellow cube"])
    assert set(found) == {0, 1}                                # threshold 0: every phrase gets its best query
    for mask, score in found.values():
        assert isinstance(mask, np.ndarray) and mask.dtype == bool and mask.shape == (60, 90)
        assert isinstance(score, float) and 0.0 <= score <= 1.0

    strict = OpenVocabSegmenter(SegmentOptions(segmenter=str(tiny_sam3), segmenter_kind="sam3", box_threshold=1.01))
    assert strict(img, ["blue box", "yellow cube"]) == {}      # no score can pass a threshold above 1

    # the threshold sits between the two phrases' scores: only the better one is kept
    lo, hi = sorted(s for _, s in found.values())
    if hi > lo:
        seg.opts.box_threshold = (lo + hi) / 2
        mid = seg(img, ["blue box", "yellow cube"])
        assert len(mid) == 1 and next(iter(mid.values()))[1] == pytest.approx(hi)


def test_sam3_segment_images_labels(tiny_sam3, tmp_path):
    rng = np.random.default_rng(1)
    images = {v: io.write_image(tmp_path / "images" / f"{v}.png", rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
              for v in ("train_000", "train_001")}
    opts = SegmentOptions(segmenter=str(tiny_sam3), segmenter_kind="sam3", box_threshold=0.0)
    seg = OpenVocabSegmenter(opts)

    calls = []

    class Spy:  # the real segmenter, recording the phrases it is asked for
        def __call__(self, image, phrases):
            calls.append(list(phrases))
            return seg(image, phrases)

    labels = {"Blue box": 3, "yellow cube": 5}                 # scene labels, not prompt order; keys case-folded
    ms = segment_images(images, "blue box. Yellow cube", opts, labels=labels, out_dir=tmp_path / "masks",
                        progress=False, segmenter=Spy())
    assert calls == [["blue box", "yellow cube"]] * 2
    assert ms.objects == {3: "blue_box", 5: "yellow_cube"}
    assert ms.prompts == {3: "blue box", 5: "yellow cube"}
    assert set(ms.sizes) == set(images) and all(hw == (48, 64) for hw in ms.sizes.values())
    for v in images:
        for lab in ms.masks.get(v, {}):
            assert lab in (3, 5)
            assert ms.get(v, lab).shape == (48, 64) and ms.get(v, lab).dtype == bool
            assert 0.0 <= ms.scores[v][lab] <= 1.0
    assert (tmp_path / "masks" / "masks.json").is_file()
    assert all(ms.n_views_with(lab) >= 1 for lab in (3, 5))   # each phrase's mask reached the MaskSet
