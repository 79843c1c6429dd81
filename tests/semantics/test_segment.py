"""Open-vocabulary segmentation through the real transformers code path with tiny random-weight models.

The models are built from small configs and saved to a temp folder (no downloads): the test checks the
plumbing (shapes, box -> mask, phrase -> label bookkeeping, resume, errors), not segmentation quality.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("transformers")

from splattwin import io  # noqa: E402
from splattwin.errors import InputError  # noqa: E402
from splattwin.semantics.segment import (OpenVocabSegmenter, SegmentOptions, assign_queries, parse_prompt,  # noqa: E402
                                         phrase_token_spans, segment_images)

WORDS = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", "blue", "box", "yellow", "cube", "toy", "hammer"]


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    import torch
    from transformers import (BertConfig, BertTokenizer, GroundingDinoConfig, GroundingDinoForObjectDetection,
                              GroundingDinoImageProcessorPil, GroundingDinoProcessor, SamConfig,
                              SamImageProcessorPil, SamMaskDecoderConfig, SamModel, SamProcessor,
                              SamPromptEncoderConfig, SamVisionConfig, SwinConfig)

    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("hf")
    tok = BertTokenizer(vocab={w: i for i, w in enumerate(WORDS)}, do_lower_case=True)
    cfg = GroundingDinoConfig(
        backbone_config=SwinConfig(embed_dim=8, depths=[1, 1, 1, 1], num_heads=[1, 1, 1, 1], window_size=4,
                                   image_size=64, out_features=["stage2", "stage3", "stage4"]),
        text_config=BertConfig(vocab_size=len(WORDS), hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                               intermediate_size=32, max_position_embeddings=64),
        d_model=32, encoder_layers=1, decoder_layers=2, encoder_ffn_dim=32, decoder_ffn_dim=32,
        encoder_attention_heads=2, decoder_attention_heads=2, num_queries=12, num_feature_levels=3,
        encoder_n_points=2, decoder_n_points=2, max_text_len=32)
    GroundingDinoForObjectDetection(cfg).save_pretrained(d / "gdino")
    GroundingDinoProcessor(image_processor=GroundingDinoImageProcessorPil(), tokenizer=tok).save_pretrained(d / "gdino")
    scfg = SamConfig(
        vision_config=SamVisionConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=2, mlp_dim=32,
                                      output_channels=16, image_size=64, patch_size=16, global_attn_indexes=[0],
                                      window_size=0, num_pos_feats=8),
        prompt_encoder_config=SamPromptEncoderConfig(hidden_size=16, image_size=64, patch_size=16, mask_input_channels=4),
        mask_decoder_config=SamMaskDecoderConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2,
                                                 mlp_dim=32, iou_head_hidden_dim=16))
    SamModel(scfg).save_pretrained(d / "sam")
    from transformers import (Sam2Config, Sam2HieraDetConfig, Sam2MaskDecoderConfig, Sam2Model,
                              Sam2PromptEncoderConfig, Sam2VisionConfig)

    bb = Sam2HieraDetConfig(hidden_size=8, image_size=[128, 128], embed_dim_per_stage=[8, 16, 32, 64],
                            num_attention_heads_per_stage=[1, 1, 1, 1], blocks_per_stage=[1, 1, 2, 1],
                            window_size_per_stage=[4, 4, 4, 4], global_attention_blocks=[3],
                            window_positional_embedding_background_size=[2, 2])
    s2 = Sam2Config(vision_config=Sam2VisionConfig(backbone_config=bb, backbone_channel_list=[64, 32, 16, 8],
                                                   backbone_feature_sizes=[[32, 32], [16, 16], [8, 8]], fpn_hidden_size=32),
                    prompt_encoder_config=Sam2PromptEncoderConfig(hidden_size=32, image_size=128, patch_size=16,
                                                                  mask_input_channels=4),
                    mask_decoder_config=Sam2MaskDecoderConfig(hidden_size=32, mlp_dim=64, num_attention_heads=2,
                                                              iou_head_hidden_dim=32))
    Sam2Model(s2).save_pretrained(d / "sam2")
    SamProcessor(image_processor=SamImageProcessorPil(size={"longest_edge": 64},
                                                      pad_size={"height": 64, "width": 64})).save_pretrained(d / "sam")
    return d


def test_parse_prompt():
    assert parse_prompt("Blue box. yellow  cube.toy hammer") == ["blue box", "yellow cube", "toy hammer"]
    with pytest.raises(InputError):
        parse_prompt(" . ")
    with pytest.raises(InputError):
        parse_prompt("box. box")


def test_phrase_spans_and_assignment():
    toks = ["[CLS]", "blue", "box", ".", "yellow", "cube", ".", "[SEP]"]
    assert phrase_token_spans(toks, 2) == [[1, 2], [4, 5]]
    s = np.array([[0.9, 0.8], [0.85, 0.2], [0.1, 0.7]])
    got = assign_queries(s, threshold=0.5)
    # query 0 takes phrase 0 (best overall); phrase 1 then goes to query 2 (query 0 is used)
    assert [(q, p) for q, p, _ in got] == [(0, 0), (2, 1)]
    assert assign_queries(s, threshold=0.95) == []


def test_end_to_end_tiny_models(tiny_models, tmp_path):
    rng = np.random.default_rng(0)
    images = {}
    for v in ("train_000", "train_001"):
        images[v] = io.write_image(tmp_path / "images" / f"{v}.png", rng.integers(0, 255, (72, 96, 3), dtype=np.uint8))
    opts = SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam"),
                          box_threshold=0.0, working_size=64)
    seg = OpenVocabSegmenter(opts)
    assert seg.kind == "sam"
    img = rng.integers(0, 255, (72, 96, 3), dtype=np.uint8)
    dets = seg.detect(img, ["blue box", "yellow cube"])
    assert sorted(p for p, _, _ in dets) == [0, 1]           # one box per phrase at threshold 0
    for _, box, _ in dets:
        assert box.shape == (4,) and 0 <= box[0] <= box[2] <= 96 and 0 <= box[1] <= box[3] <= 72
    masks, ious = seg.masks_from_boxes(img, np.array([[10, 10, 50, 40], [40, 20, 90, 70]], float))
    assert masks.shape == (2, 72, 96) and masks.dtype == bool and ious.shape == (2,)

    labels = {"blue box": 3, "yellow cube": 5}                # scene labels, not prompt order
    out = tmp_path / "masks"
    ms = segment_images(images, "blue box. yellow cube", opts, labels=labels, out_dir=out, progress=False, segmenter=seg)
    assert ms.objects == {3: "blue_box", 5: "yellow_cube"}
    assert ms.prompts == {3: "blue box", 5: "yellow cube"}
    assert set(ms.sizes) == set(images) and all(hw == (72, 96) for hw in ms.sizes.values())
    for v in images:
        for lab in ms.masks.get(v, {}):
            assert ms.get(v, lab).shape == (72, 96) and 0.0 <= ms.scores[v][lab] <= 1.0
    assert (out / "masks.json").is_file()

    class Boom:  # resume: every view is already done, the segmenter must not run again
        def __call__(self, *a):
            raise AssertionError("segmenter called on a finished view")

    again = segment_images(images, "blue box. yellow cube", opts, labels=labels, out_dir=out, progress=False,
                           segmenter=Boom())
    for v in images:
        for lab in ms.masks.get(v, {}):
            assert np.array_equal(again.get(v, lab), ms.get(v, lab))

    square = np.zeros((72, 96), bool)
    square[5:9, 5:9] = True

    class Count:  # the views segmented anew; finds a 4x4 square for every phrase
        def __init__(self):
            self.views = 0

        def __call__(self, img, phrases):
            self.views += 1
            return {i: (square, 0.9) for i in range(len(phrases))}

    # a view is reused only for the same photo and options: the mask files were kept when the options
    # (model, threshold) or a photo changed, and `build --from semantics` still reused them
    for kw, n in ((dict(options=replace(opts, box_threshold=0.5)), 2), (dict(resume=False), 2)):
        c = Count()
        segment_images(images, "blue box. yellow cube", kw.get("options", opts), labels=labels, out_dir=out,
                       progress=False, segmenter=c, resume=kw.get("resume", True))
        assert c.views == n
        ms = segment_images(images, "blue box. yellow cube", opts, labels=labels, out_dir=out, progress=False,
                            segmenter=seg)   # back to the first options: segmented again, then kept
    io.write_image(images["train_001"], rng.integers(0, 255, (72, 96, 3), dtype=np.uint8))
    c = Count()
    again = segment_images(images, "blue box. yellow cube", opts, labels=labels, out_dir=out, progress=False,
                           segmenter=c)
    assert c.views == 1 and all(np.array_equal(again.get("train_001", lab), square) for lab in (3, 5))
    for lab in ms.masks.get("train_000", {}):
        assert np.array_equal(again.get("train_000", lab), ms.get("train_000", lab))


def test_sam2_path_tiny_model(tiny_models):
    opts = SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam2"),
                          box_threshold=0.0, working_size=64)
    seg = OpenVocabSegmenter(opts)
    assert seg.kind == "sam2"                                  # picked from the config's model_type
    img = np.random.default_rng(1).integers(0, 255, (60, 90, 3), dtype=np.uint8)
    masks, ious = seg.masks_from_boxes(img, np.array([[5, 5, 40, 30], [30, 20, 85, 55], [0, 0, 90, 60]], float))
    assert masks.shape == (3, 60, 90) and masks.dtype == bool and ious.shape == (3,)
    found = seg(img, ["toy hammer", "blue box"])
    assert set(found) == {0, 1} and all(m.shape == (60, 90) for m, _ in found.values())


def test_missing_weights_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "empty_cache"))
    with pytest.raises(InputError, match="huggingface-cli download"):
        OpenVocabSegmenter(SegmentOptions(detector="IDEA-Research/grounding-dino-tiny",
                                          segmenter="facebook/sam-vit-base", segmenter_kind="sam"))


def test_cli_prompt_maps_phrases_to_scene_labels(tiny_models, scene_small, tmp_path):
    """`splattwin segment DATASET --prompt ...` end to end with the tiny models on the embedded scene."""
    import json

    from splattwin.cli import main
    from splattwin.semantics.masks import MaskSet

    out = tmp_path / "masks"
    rc = main(["segment", str(scene_small), "--prompt", "Blue box. yellow cube", "--detector", str(tiny_models / "gdino"),
               "--segmenter", str(tiny_models / "sam"), "--box-threshold", "0", "--working-size", "64",
               "--split", "heldout", "--out", str(out)])
    assert rc == 0
    ms = MaskSet.load(out)
    scene = {o["name"]: o["label"] for o in json.loads((scene_small / "scene.json").read_text())["objects"]}
    assert ms.objects == {scene["blue_box"]: "blue_box", scene["yellow_cube"]: "yellow_cube"}
    assert sorted(ms.sizes) == ["heldout_000", "heldout_001", "heldout_002"]
    assert all(hw == (120, 160) for hw in ms.sizes.values())
