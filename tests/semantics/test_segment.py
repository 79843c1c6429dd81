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


# -- the real models' output conventions, checked with chosen outputs (no real weights) -------------------

def _fake_detector(seg, logits_by_query, boxes_cxcywh, seen):
    """Replace the detector's forward: query q's logit is `logits_by_query[q]` on the tokens of the phrase
    it names (else -10), its box `boxes_cxcywh[q]` (normalised centre x, y, width, height, as the real
    model's pred_boxes); `seen` gets the inputs."""
    import torch
    from transformers.models.grounding_dino.modeling_grounding_dino import GroundingDinoObjectDetectionOutput

    cfg = seg.det_model.config

    def forward(input_ids=None, pixel_values=None, **kw):
        seen.update(input_ids=input_ids, pixel_values=pixel_values)
        tokens = seg.det_proc.tokenizer.convert_ids_to_tokens(input_ids[0].tolist())
        logits = torch.full((1, cfg.num_queries, cfg.max_text_len), -10.0)
        logits[:, :, len(tokens):] = float("-inf")   # the real model: -inf past the text
        spans = phrase_token_spans(tokens, 2)
        for q, (p, v) in logits_by_query.items():
            logits[0, q, spans[p]] = v
        boxes = torch.full((1, cfg.num_queries, 4), 0.5)
        for q, b in boxes_cxcywh.items():
            boxes[0, q] = torch.tensor(b)
        return GroundingDinoObjectDetectionOutput(logits=logits, pred_boxes=boxes)

    seg.det_model.forward = forward


def test_detect_output_conventions(tiny_models):
    """Grounding DINO's pred_boxes are cx, cy, w, h normalised to the image: they come back as xyxy pixels
    of the ORIGINAL (non-square, larger than the working size) image, each with its phrase and score."""
    opts = SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam"),
                          box_threshold=0.3, working_size=64)
    seg = OpenVocabSegmenter(opts)
    seen = {}
    # query 3 -> phrase 1 (score sigmoid(2)), query 7 -> phrase 0 (sigmoid(1)), query 5 below the threshold
    _fake_detector(seg, {3: (1, 2.0), 7: (0, 1.0), 5: (0, -2.0)},
                   {3: (0.25, 0.5, 0.2, 0.4), 7: (0.7, 0.2, 0.4, 0.2), 5: (0.5, 0.5, 0.1, 0.1)}, seen)
    img = np.zeros((300, 500, 3), np.uint8)                 # H=300, W=500
    dets = seg.detect(img, ["blue box", "yellow cube"])
    assert [p for p, _, _ in dets] == [1, 0]
    np.testing.assert_allclose(dets[0][1], [75, 90, 175, 210], atol=1e-4)   # 0.15..0.35 x 500, 0.3..0.7 x 300
    np.testing.assert_allclose(dets[1][1], [250, 30, 450, 90], atol=1e-4)
    np.testing.assert_allclose([s for _, _, s in dets], [1 / (1 + np.exp(-2)), 1 / (1 + np.exp(-1))], rtol=1e-6)
    # the prompt as the model card writes it (lower case, each phrase ended by '.'), the image at the
    # working size (longest edge 64, aspect kept), not the processor's default 800 px
    assert seg.det_proc.tokenizer.decode(seen["input_ids"][0], skip_special_tokens=True) == "blue box. yellow cube."
    assert tuple(seen["pixel_values"].shape[-2:]) in ((38, 64), (39, 64))


def test_sam_output_conventions(tiny_models):
    """SAM: boxes go in as [image][box][x0 y0 x1 y1] in the processor's resized frame (longest edge 64 here:
    x 2/3), the low-res mask covers the PADDED square input (64 x 64, the image in its top-left 48 x 64)
    and comes back cropped and resized to the original 72 x 96 image; single-mask output, its IoU."""
    import torch
    from transformers.models.sam.modeling_sam import SamImageSegmentationOutput

    seg = OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam")))
    seen = {}

    def forward(image_embeddings=None, input_boxes=None, multimask_output=True, **kw):
        seen.update(input_boxes=input_boxes, multimask=multimask_output)
        B, n = input_boxes.shape[1], 3 if multimask_output else 1
        low = torch.full((1, B, n, 16, 16), -5.0)
        low[0, 0, :, 0:6, 8:16] = 5.0        # padded input rows 0-24, cols 32-64 -> image rows 0-36, cols 48-96
        low[0, 1, :, 8:12, 0:4] = 5.0        # rows 32-48 (the padding starts at 48), cols 0-16
        iou = torch.tensor([[[0.8, 0.1, 0.1][:n], [0.6, 0.1, 0.1][:n]]])
        return SamImageSegmentationOutput(iou_scores=iou, pred_masks=low)

    seg.seg_model.forward = forward
    img = np.zeros((72, 96, 3), np.uint8)
    masks, ious = seg.masks_from_boxes(img, np.array([[12, 6, 60, 42], [0, 48, 24, 72]], float))
    np.testing.assert_allclose(seen["input_boxes"][0].numpy(), [[8, 4, 40, 28], [0, 32, 16, 48]], atol=1e-4)
    assert seen["multimask"] is False and masks.shape == (2, 72, 96)
    np.testing.assert_allclose(ious, [0.8, 0.6], rtol=1e-6)
    assert masks[0, :34, 50:].all() and not masks[0, 38:].any() and not masks[0, :, :46].any()
    assert masks[1, 50:70, :22].all() and not masks[1, :46].any() and not masks[1, :, 26:].any()


def test_device_option_is_used(tiny_models):
    """`--device` places the models (it was ignored: everything ran on the CPU whatever was asked); a device
    that cannot be used here is a clear error naming it, not a silent CPU run."""
    opts = SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam"))
    with pytest.raises(InputError, match="device 'cuda:99' is not usable"):
        OpenVocabSegmenter(replace(opts, device="cuda:99"))
    with pytest.raises(InputError, match="device 'gpu' is not usable"):
        OpenVocabSegmenter(replace(opts, device="gpu"))
    seg = OpenVocabSegmenter(opts)
    assert str(seg.device) == "cpu"
    for m in (seg.det_model, seg.seg_model):
        assert {p.device.type for p in m.parameters()} == {"cpu"} and not m.training


def test_half_precision_checkpoint_runs_in_float32(tiny_models, tmp_path):
    """transformers >= 5 loads a checkpoint in its stored dtype (dtype="auto"): a bfloat16 SAM failed in its
    first convolution ("Input type (float) and bias type (c10::BFloat16)"). Loaded as float32 it runs and
    gives the float32 model's masks."""
    import shutil

    import torch
    from transformers import SamModel

    SamModel.from_pretrained(tiny_models / "sam").to(torch.bfloat16).save_pretrained(tmp_path / "sam16")
    shutil.copy(tiny_models / "sam" / "processor_config.json", tmp_path / "sam16")
    opts = SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tmp_path / "sam16"))
    seg = OpenVocabSegmenter(opts)
    assert {p.dtype for p in seg.seg_model.parameters()} == {torch.float32}
    img = np.random.default_rng(3).integers(0, 255, (72, 96, 3), dtype=np.uint8)
    masks, ious = seg.masks_from_boxes(img, np.array([[10, 10, 50, 40]], float))
    assert masks.shape == (1, 72, 96) and np.isfinite(ious).all()


def test_checkpoint_of_another_model_is_refused(tiny_models, tmp_path):
    """transformers >= 5 only warns when a folder holds another model (or misses weights) and initialises the
    missing weights at random: a SAM folder given as the detector, or a Grounding DINO folder forced as the
    SAM segmenter, loaded and gave noise. Now an InputError names the model and what is wrong."""
    from safetensors.torch import load_file, save_file

    with pytest.raises(InputError, match=r"Grounding DINO model .*sam.* is a 'sam' model"):
        OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "sam"), segmenter=str(tiny_models / "sam")))
    with pytest.raises(InputError, match=r"SAM model .*gdino.* is a 'grounding-dino' model"):
        OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "gdino"),
                                          segmenter_kind="sam"))
    # a SAM checkpoint without its vision encoder's weights: most of the model would be random
    import shutil

    shutil.copytree(tiny_models / "sam", tmp_path / "part")
    sd = load_file(tmp_path / "part" / "model.safetensors")
    save_file({k: v for k, v in sd.items() if not k.startswith("vision_encoder.")},
              tmp_path / "part" / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(InputError, match=r"SAM model .*part.*parameters missing"):
        OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tmp_path / "part")))


def test_local_folder_without_weights_names_the_folder(tiny_models, tmp_path):
    """A local folder that cannot be loaded is named as a folder (the message said `hf download /its/path`)."""
    import shutil

    shutil.copytree(tiny_models / "sam", tmp_path / "noweights")
    (tmp_path / "noweights" / "model.safetensors").unlink()
    with pytest.raises(InputError, match=r"SAM model folder .*noweights.* cannot be loaded") as e:
        OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tmp_path / "noweights")))
    assert "download" not in str(e.value)


def test_prompt_longer_than_the_detector_reads(tiny_models):
    """Grounding DINO cuts input_ids at max_text_len (256 for the real model, 32 here) and scores only
    those: a longer prompt raised IndexError (spans past the logits); now an InputError, and a phrase cut
    by the limit is never scored on part of its words."""
    assert phrase_token_spans(["[CLS]", "blue", "box", ".", "yellow"], 1) == [[1, 2]]
    with pytest.raises(InputError, match="reads at most 5 tokens and 1 of the 2"):
        phrase_token_spans(["[CLS]", "blue", "box", ".", "yellow"], 2, 5)
    seg = OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam"),
                                            box_threshold=0.0, working_size=64))
    img = np.zeros((40, 60, 3), np.uint8)
    words = ["blue", "box", "yellow", "cube", "toy", "hammer"]
    phrases = [f"{a} {b} {c}" for a in words for b in words[:2] for c in words[2:4]][:12]   # 12 x 4 tokens > 32
    with pytest.raises(InputError, match="prompt too long: the detector reads at most 32 tokens and 7 of the 12"):
        seg.detect(img, phrases)
    assert len(seg.detect(img, phrases[:7])) == 7


def test_masks_upsampled_one_box_at_a_time(tiny_models, monkeypatch):
    """A float mask at photo size is 4 bytes a pixel (600 MB at the 150 MP limit): the boxes' masks were all
    upsampled together (B times that). Now never more than one full-size float mask at a time, same masks."""
    import torch.nn.functional as F

    img = np.random.default_rng(4).integers(0, 255, (60, 90, 3), dtype=np.uint8)
    boxes = np.array([[5, 5, 40, 30], [30, 20, 85, 55], [0, 0, 90, 60]], float)
    full = []
    interpolate = F.interpolate

    def spy(x, size=None, **kw):
        if isinstance(size, (tuple, list)) and tuple(int(v) for v in size) == (60, 90):
            full.append(x.shape[0] * x.shape[1])       # masks brought to the image size in this call
        return interpolate(x, size=size, **kw)

    for kind in ("sam", "sam2"):
        seg = OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / kind)))
        ref, _ = seg.masks_from_boxes(img, boxes)
        full.clear()
        monkeypatch.setattr(F, "interpolate", spy)
        masks, _ = seg.masks_from_boxes(img, boxes)
        monkeypatch.setattr(F, "interpolate", interpolate)
        assert full == [1, 1, 1], kind
        assert np.array_equal(masks, ref)


def test_segment_images_reads_photos_as_bytes(tmp_path):
    """segment_images read each photo as float32 and back (clip, x255: ~28 bytes a pixel at its peak, 4 GB
    for a photo at the 150 MP limit); the segmenter gets the same uint8 pixels from a 3-byte-a-pixel read."""
    import tracemalloc

    rng = np.random.default_rng(5)
    photo = rng.integers(0, 255, (1200, 1600, 3), dtype=np.uint8)
    images = {"v0": io.write_image(tmp_path / "v0.png", photo)}
    got = {}

    class Keep:
        def __call__(self, img, phrases):
            got["img"] = img
            m = np.zeros(img.shape[:2], bool)
            m[:10, :10] = True
            return {0: (m, 0.9)}

    tracemalloc.start()
    segment_images(images, "blue box", progress=False, segmenter=Keep())
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert got["img"].dtype == np.uint8 and np.array_equal(got["img"], photo)
    assert peak < 4 * photo.size, f"peak {peak / 1e6:.0f} MB for a {photo.size / 1e6:.1f} MB photo"


def test_sam2_output_conventions(tiny_models):
    """SAM 2 (preprocessed by hand): boxes in the square input frame (x S/W, y S/H, as Sam2Processor's
    _normalize_coordinates), the low-res mask covers the whole square input (no padding) and is resized
    straight to the original 60 x 90 image (Sam2ImageProcessor.post_process_masks); single mask, its IoU."""
    import torch
    from transformers.models.sam2.modeling_sam2 import Sam2ImageSegmentationOutput

    seg = OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tiny_models / "sam2")))
    seen = {}

    def forward(pixel_values=None, input_boxes=None, multimask_output=True, **kw):
        seen.update(pixel_values=pixel_values, input_boxes=input_boxes, multimask=multimask_output)
        B, n = input_boxes.shape[1], 3 if multimask_output else 1
        low = torch.full((1, B, n, 32, 32), -5.0)
        low[0, 0, :, 16:32, 0:8] = 5.0       # bottom half, left quarter of the square -> rows 30-60, cols 0-22.5
        iou = torch.tensor([[[0.7, 0.1, 0.1][:n]]])
        return Sam2ImageSegmentationOutput(iou_scores=iou, pred_masks=low)

    seg.seg_model.forward = forward
    masks, ious = seg.masks_from_boxes(np.zeros((60, 90, 3), np.uint8), np.array([[9, 30, 45, 60]], float))
    assert tuple(seen["pixel_values"].shape) == (1, 3, 128, 128) and seen["multimask"] is False
    np.testing.assert_allclose(seen["input_boxes"][0].numpy(), [[12.8, 64, 64, 128]], atol=1e-4)   # x 128/90, y 128/60
    np.testing.assert_allclose(ious, [0.7], rtol=1e-6)
    assert masks[0, 32:, :21].all() and not masks[0, :28].any() and not masks[0, :, 25:].any()


def test_weights_of_other_shapes_are_an_input_error(tiny_models, tmp_path):
    """A folder whose weights do not fit its config raised transformers' bare RuntimeError
    ("You set `ignore_mismatched_sizes` to `False`..."); now an InputError naming the folder."""
    import json
    import shutil

    shutil.copytree(tiny_models / "sam", tmp_path / "odd")
    cfg = json.loads((tmp_path / "odd" / "config.json").read_text())
    cfg["mask_decoder_config"]["iou_head_hidden_dim"] = 8          # the weights hold 16
    (tmp_path / "odd" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(InputError, match=r"SAM model folder .*odd.* cannot be loaded \(RuntimeError"):
        OpenVocabSegmenter(SegmentOptions(detector=str(tiny_models / "gdino"), segmenter=str(tmp_path / "odd")))
