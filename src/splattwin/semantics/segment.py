"""Open-vocabulary 2D masks from text prompts: Grounding DINO boxes + SAM masks (Hugging Face transformers).

Prompt: "blue box. yellow cube. toy hammer" -> one phrase per object (split on '.', lower-cased), in
order; object labels are 1..K in that order unless given. Per view:
1. Grounding DINO (`GroundingDinoForObjectDetection`) on the image resized to a working resolution
   (`working_size` = longest edge, px). Each query's per-phrase score is the max sigmoid logit over the
   phrase's tokens (phrases are delimited by the '.' tokens, as Grounding DINO's own phrase grounding);
   queries are assigned greedily to phrases by score, at most `max_per_object` boxes per phrase, kept
   when the score >= `box_threshold`. Boxes come back in original image pixels (xyxy).
2. SAM turns each box into a mask at the original image size: "sam" (`SamModel`, image embedding once
   per view, then all boxes in one prompt batch), "sam2" (`Sam2Model`, preprocessed by hand: its image
   processor needs torchvision), or "sam3" (`Sam3Model`, text-prompted: it segments the phrases
   directly and Grounding DINO is not used). Mask score = box score x predicted IoU.
Weights load only from the local Hugging Face cache (`local_files_only=True`); a missing model raises an
InputError that says how to download it; a folder or cached model of another kind (random weights) is an
InputError too. Models run in float32 on `device` (default: the CPU), with a progress bar over views.
Finished views are saved to `out_dir` as they complete, so a killed run resumes where it stopped.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from splattwin.errors import InputError
from splattwin.semantics.masks import MaskSet
# the options live in the light `splattwin.semantics.options` (re-exported here)
from splattwin.semantics.options import (DEFAULT_DETECTOR, DEFAULT_SEGMENTER, SEGMENTER_KINDS,  # noqa: F401
                                         SegmentOptions)

log = logging.getLogger(__name__)

_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def parse_prompt(prompt: str) -> list[str]:
    """'Blue box. yellow cube.toy hammer' -> ['blue box', 'yellow cube', 'toy hammer'] (InputError if empty)."""
    phrases = [" ".join(p.strip().lower().split()) for p in prompt.split(".")]
    phrases = [p for p in phrases if p]
    if not phrases:
        raise InputError(f"empty text prompt {prompt!r}: give phrases separated by '.', e.g. \"blue box. yellow cube\"")
    if len(set(phrases)) != len(phrases):
        raise InputError(f"prompt {prompt!r} repeats a phrase; each object needs its own phrase")
    return phrases


def prompt_object_names(prompt: str) -> dict[str, str]:
    """{phrase: object name} of a text prompt (`parse_prompt`); InputError for a name that is not allowed
    (reserved, not ASCII, clashing export ids): checked by the pre-flight before any work."""
    from splattwin.names import check_unique, object_name

    names = {p: object_name(p.replace(" ", "_"), "--prompt", "object name from the prompt phrase")
             for p in parse_prompt(prompt)}
    check_unique(names.values(), "--prompt")
    return names


def load_pretrained(cls, model_id: str, what: str, **kwargs):
    """`cls.from_pretrained(model_id, local_files_only=True, trust_remote_code=False)` with a clear InputError when
    absent or unreadable. trust_remote_code left unset (None) is not off: for a config with an unknown model_type
    and an `auto_map`, transformers asks on the terminal whether to run the model folder's own Python, so a
    received folder's code ran on a "y" (and a run without a terminal waited 15 s); False refuses it (ValueError)."""
    try:
        return cls.from_pretrained(model_id, local_files_only=True, trust_remote_code=False, **kwargs)
    except (OSError, ValueError, EnvironmentError, RuntimeError) as e:
        # RuntimeError: weights of other shapes than the config's (transformers raises, no InputError)
        why = f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else 'no message'}"
        if Path(model_id).is_dir():
            raise InputError(f"{what} folder {model_id!r} cannot be loaded ({why}); it needs the model's "
                             f"config.json and weights (model.safetensors) as saved by `save_pretrained`") from e
        if isinstance(e, RuntimeError):   # present, but not a checkpoint of this model's shapes
            raise InputError(f"{what} {model_id!r} cannot be loaded ({why}): not a checkpoint of this model") from e
        raise InputError(
            f"{what} {model_id!r} is not available offline ({type(e).__name__}). Download it once with "
            f"`huggingface-cli download {model_id}` (or `hf download {model_id}`) on a machine with network, "
            f"or pass a local folder holding config.json + weights; splattwin never downloads at run time") from e


# the role (`models.MODEL_TYPES`) of each model class: the model_type its config must declare
_ROLES = {"GroundingDinoForObjectDetection": "detector", "SamModel": "sam", "Sam2Model": "sam2", "Sam3Model": "sam3"}
# share of the parameters' elements a checkpoint may leave to random initialisation; a checkpoint of another
# model leaves all of them (transformers >= 5 only warns), a genuine one none
MAX_MISSING_SHARE = 0.01


def load_model(cls, model_id: str, what: str, device):
    """Model `cls` from `model_id` in float32, in eval mode, on torch `device`.

    InputError (naming the model) when its config is of another model type or when its weights leave more
    than MAX_MISSING_SHARE of the parameters missing or of another shape: transformers would otherwise
    initialise them at random with a warning, and the masks would be noise. float32 whatever the
    checkpoint's dtype: transformers >= 5 loads a half-precision checkpoint as such (dtype="auto"), and
    our float32 inputs would then fail in the first convolution."""
    import torch

    from splattwin.semantics.models import MODEL_TYPES

    want = MODEL_TYPES.get(_ROLES.get(cls.__name__, ""))
    if want is not None:
        from transformers import AutoConfig

        mt = load_pretrained(AutoConfig, model_id, f"{what} config").model_type
        if mt not in want:
            raise InputError(f"{what} {model_id!r} is a {mt!r} model (config.json model_type); expected "
                             f"{' or '.join(repr(w) for w in want)}")
    model, info = load_pretrained(cls, model_id, what, dtype=torch.float32, output_loading_info=True)
    missing = set(info.get("missing_keys", ())) | {k[0] if isinstance(k, tuple) else k
                                                   for k in info.get("mismatched_keys", ())}
    params = dict(model.named_parameters())
    n_missing = sum(params[k].numel() for k in missing if k in params)
    n_all = max(1, sum(p.numel() for p in params.values()))
    if n_missing > MAX_MISSING_SHARE * n_all:
        raise InputError(f"{what} {model_id!r}: its weights leave {n_missing / n_all:.0%} of the model's parameters "
                         f"missing or of another shape (e.g. {', '.join(sorted(missing)[:3])}): not a checkpoint of "
                         f"this model")
    if missing:
        log.warning("%s %s: %d weights missing from the checkpoint (%s)", what, model_id, len(missing),
                    ", ".join(sorted(missing)[:5]))
    return model.to(device).eval()


def torch_device(name: str):
    """torch.device `name` if tensors can be made on it here, else InputError naming it."""
    import torch

    try:
        dev = torch.device(name)
        torch.empty(1, device=dev)
    except (RuntimeError, AssertionError, ValueError) as e:   # unknown name, no CUDA build, no such GPU
        raise InputError(f"segmentation device {name!r} is not usable here ({str(e).splitlines()[0][:200]}); "
                         f"use --device cpu", "--device") from e
    return dev


def _model_type(model_id: str) -> str:
    from transformers import AutoConfig

    return load_pretrained(AutoConfig, model_id, "segmenter config").model_type


def phrase_token_spans(tokens: Sequence[str], n_phrases: int, max_tokens: int | None = None) -> list[list[int]]:
    """Token positions of each '.'-terminated phrase (special tokens skipped) -> n_phrases lists.

    `tokens`: the tokens the detector reads (already cut at its `max_tokens`); a phrase counts only when
    its closing '.' is among them, so a phrase cut by the limit is never scored on part of its words."""
    spans: list[list[int]] = []
    cur: list[int] = []
    for i, t in enumerate(tokens):
        if t in ("[CLS]", "[SEP]", "[PAD]", "<s>", "</s>", "<pad>"):
            continue
        if t == ".":
            if cur:
                spans.append(cur)
            cur = []
            continue
        cur.append(i)
    if len(spans) < n_phrases:
        limit = f" reads at most {max_tokens} tokens" if max_tokens else "'s tokenizer kept"
        raise InputError(f"text prompt too long: the detector{limit} and {len(spans)} of the {n_phrases} prompt "
                         f"phrases fit; use fewer or shorter phrases")
    return spans[:n_phrases]


def assign_queries(scores: np.ndarray, threshold: float, max_per_object: int = 1) -> list[tuple[int, int, float]]:
    """Greedy query -> phrase assignment. scores [Q,P] -> [(query, phrase, score)] best first.

    Each query is used once; each phrase gets at most max_per_object queries with score >= threshold.
    """
    Q, P = scores.shape
    order = np.argsort(-scores, axis=None)
    used_q: set[int] = set()
    per_p = np.zeros(P, dtype=int)
    out = []
    for flat in order:
        q, p = divmod(int(flat), P)
        s = float(scores[q, p])
        if s < threshold:
            break
        if q in used_q or per_p[p] >= max_per_object:
            continue
        used_q.add(q)
        per_p[p] += 1
        out.append((q, p, s))
    return out


class OpenVocabSegmenter:
    """Grounding DINO + SAM / SAM 2, or SAM 3 alone, loaded once; call on an image per view."""

    def __init__(self, options: SegmentOptions | None = None):
        import torch  # noqa: F401
        import transformers as tf

        self.opts = opts = options or SegmentOptions()
        kind = opts.segmenter_kind
        if kind not in SEGMENTER_KINDS:
            raise InputError(f"unknown segmenter kind {kind!r}; choose one of {', '.join(SEGMENTER_KINDS)}")
        if kind == "auto":
            mt = _model_type(opts.segmenter)
            kind = {"sam": "sam", "sam2": "sam2", "sam3": "sam3", "sam3_video": "sam3"}.get(mt)
            if kind is None:
                raise InputError(f"segmenter {opts.segmenter!r} has model_type {mt!r}; expected a SAM, SAM 2 or SAM 3 model")
        self.kind = kind
        self.device = dev = torch_device(opts.device)
        if kind == "sam3":
            if not hasattr(tf, "Sam3Model"):
                raise InputError(f"SAM 3 needs a transformers with Sam3Model (installed: {tf.__version__})")
            self.seg_model = load_model(tf.Sam3Model, opts.segmenter, "SAM 3 model", dev)
            # Sam3Processor's image processor needs torchvision: tokenizer only, images by hand (as SAM 2)
            self.seg_proc = load_pretrained(tf.AutoTokenizer, opts.segmenter, "SAM 3 tokenizer")
            return
        self.det_model = load_model(tf.GroundingDinoForObjectDetection, opts.detector, "Grounding DINO model", dev)
        self.det_proc = load_pretrained(tf.GroundingDinoProcessor, opts.detector, "Grounding DINO processor")
        if kind == "sam":
            self.seg_model = load_model(tf.SamModel, opts.segmenter, "SAM model", dev)
            self.seg_proc = load_pretrained(tf.SamProcessor, opts.segmenter, "SAM processor")
        else:
            self.seg_model = load_model(tf.Sam2Model, opts.segmenter, "SAM 2 model", dev)
            self.seg_proc = None  # Sam2ImageProcessor needs torchvision: preprocess by hand

    # -- detection -----------------------------------------------------------------------------
    def detect(self, image: np.ndarray, phrases: Sequence[str]) -> list[tuple[int, np.ndarray, float]]:
        """image uint8 [H,W,3] -> [(phrase index, box xyxy [4] original pixels, score)]."""
        import torch
        from PIL import Image

        H, W = image.shape[:2]
        s = min(1.0, self.opts.working_size / max(H, W))
        pil = Image.fromarray(image)
        if s < 1.0:
            pil = pil.resize((max(1, round(W * s)), max(1, round(H * s))), Image.BILINEAR)
        ip = self.det_proc.image_processor
        short = max(1, round(min(pil.size) * 1.0))
        ip.size = {"shortest_edge": short, "longest_edge": max(pil.size)}  # no upscaling to 800 px
        text = ". ".join(phrases) + "."
        inputs = self.det_proc(images=pil, text=text, return_tensors="pt")
        # the model reads only its first max_text_len tokens (it cuts input_ids there): spans past it are not scored
        n_text = int(self.det_model.config.max_text_len)
        tokens = self.det_proc.tokenizer.convert_ids_to_tokens(inputs["input_ids"][0].tolist())
        spans = phrase_token_spans(tokens[:n_text], len(phrases), n_text)
        with torch.no_grad():
            out = self.det_model(**inputs.to(self.device))
        prob = out.logits[0].float().sigmoid().cpu().numpy()  # [Q, max_text_len]
        scores = np.stack([prob[:, sp].max(axis=1) for sp in spans], axis=1)  # [Q,P]
        boxes = out.pred_boxes[0].cpu().numpy().astype(np.float64)  # cx, cy, w, h normalised
        xyxy = np.stack([boxes[:, 0] - boxes[:, 2] / 2, boxes[:, 1] - boxes[:, 3] / 2,
                         boxes[:, 0] + boxes[:, 2] / 2, boxes[:, 1] + boxes[:, 3] / 2], 1) * [W, H, W, H]
        xyxy = np.clip(xyxy, 0, [W, H, W, H])
        return [(p, xyxy[q], sc) for q, p, sc in assign_queries(scores, self.opts.box_threshold, self.opts.max_per_object)]

    # -- masks -----------------------------------------------------------------------------------
    def masks_from_boxes(self, image: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """boxes [B,4] xyxy pixels -> (masks [B,H,W] bool at image size, predicted IoU [B]).

        The low-resolution mask logits are brought to the image size one box at a time: a float mask of a
        large photo is 4 bytes a pixel (600 MB at the 150 MP limit), all boxes at once would be B times that."""
        import torch
        import torch.nn.functional as F
        from PIL import Image

        H, W = image.shape[:2]
        B = len(boxes)
        masks = np.zeros((B, H, W), dtype=bool)
        if B == 0:
            return masks, np.zeros(0)
        with torch.no_grad():
            if self.kind == "sam":
                inp = self.seg_proc(images=Image.fromarray(image), input_boxes=[[list(map(float, b)) for b in boxes]],
                                    return_tensors="pt")
                emb = self.seg_model.get_image_embeddings(inp["pixel_values"].to(self.device))
                out = self.seg_model(image_embeddings=emb, input_boxes=inp["input_boxes"].to(self.device),
                                     multimask_output=False)
                low = out.pred_masks.float().cpu()  # [1,B,1,h,w] over the padded square input
                for i in range(B):
                    masks[i] = self.seg_proc.post_process_masks(low[:, i:i + 1], inp["original_sizes"],
                                                                inp["reshaped_input_sizes"])[0][0, 0].numpy()
                return masks, out.iou_scores[0, :, 0].float().cpu().numpy()
            # SAM 2: square resize to the model's input size, ImageNet normalisation
            size = self.seg_model.config.prompt_encoder_config.image_size  # box coordinate frame = input size
            S = int(size[0] if isinstance(size, (list, tuple)) else size)
            x = np.asarray(Image.fromarray(image).resize((S, S), Image.BILINEAR), dtype=np.float32) / 255.0
            x = (x - _IMAGENET_MEAN) / _IMAGENET_STD
            pv = torch.from_numpy(x).permute(2, 0, 1)[None].to(self.device)
            b = torch.as_tensor(np.asarray(boxes, dtype=np.float32) * np.array([S / W, S / H, S / W, S / H], np.float32))
            out = self.seg_model(pixel_values=pv, input_boxes=b[None].to(self.device), multimask_output=False)
            logits = out.pred_masks[0, :, 0].float().cpu()  # [B,h,w] over the square input
            for i in range(B):
                masks[i] = (F.interpolate(logits[i][None, None], size=(H, W), mode="bilinear",
                                          align_corners=False)[0, 0] > 0).numpy()
            return masks, out.iou_scores[0, :, 0].float().cpu().numpy()

    def __call__(self, image: np.ndarray, phrases: Sequence[str]) -> dict[int, tuple[np.ndarray, float]]:
        """image uint8 [H,W,3] -> {phrase index: (mask bool [H,W], score)} for the phrases found."""
        if self.kind == "sam3":
            return self._sam3(image, phrases)
        dets = self.detect(image, phrases)
        masks, ious = self.masks_from_boxes(image, np.array([d[1] for d in dets]).reshape(-1, 4))
        found: dict[int, tuple[np.ndarray, float]] = {}
        for (p, _, s), m, iou in zip(dets, masks, ious):
            score = float(s * np.clip(iou, 0.0, 1.0))
            if p in found:  # several instances of one phrase: union
                found[p] = (found[p][0] | m, max(found[p][1], score))
            else:
                found[p] = (m, score)
        return found

    def _sam3(self, image: np.ndarray, phrases: Sequence[str]) -> dict[int, tuple[np.ndarray, float]]:
        """SAM 3 text prompts, one phrase at a time: best query (score = sigmoid(logit) x presence) kept
        when its score > box_threshold, its mask = sigmoid(mask logit) > 0.5 at the image size."""
        import torch
        import torch.nn.functional as F
        from PIL import Image

        H, W = image.shape[:2]
        size = self.seg_model.config.vision_config.image_size
        S = int(size[0] if isinstance(size, (list, tuple)) else size)
        x = np.asarray(Image.fromarray(image).resize((S, S), Image.BILINEAR), dtype=np.float32) / 255.0
        # Sam3ImageProcessor: mean = std = 0.5
        pv = torch.from_numpy((x - 0.5) / 0.5).permute(2, 0, 1)[None].to(self.device)
        found = {}
        with torch.no_grad():
            vision = self.seg_model.get_vision_features(pixel_values=pv)
            for p, phrase in enumerate(phrases):
                txt = self.seg_proc(phrase, padding="max_length", max_length=32, truncation=True, return_tensors="pt")
                out = self.seg_model(vision_embeds=vision, input_ids=txt["input_ids"].to(self.device),
                                     attention_mask=txt["attention_mask"].to(self.device))
                scores = out.pred_logits[0].float().sigmoid()
                if out.presence_logits is not None:
                    scores = scores * out.presence_logits[0].float().sigmoid()
                k = int(scores.argmax())
                score = float(scores[k])
                if score > self.opts.box_threshold:
                    m = F.interpolate(out.pred_masks[0, k][None, None].float().cpu(), size=(H, W), mode="bilinear",
                                      align_corners=False)[0, 0]
                    found[p] = (m.sigmoid().numpy() > 0.5, score)
        return found


SEGMENT_KEY = "segment_key.json"


def _segment_key(images: dict[str, Path], prompts: dict[int, str], options: SegmentOptions) -> dict:
    """What a saved view's masks depend on: {"run": digest of the prompt and options, "views": {view:
    sha256 of its photo}}."""
    import dataclasses
    import hashlib
    import json

    from splattwin.hashing import sha256_file

    run = {"prompts": {str(k): v for k, v in sorted(prompts.items())},
           "options": {k: str(v) for k, v in sorted(dataclasses.asdict(options).items())}}
    return {"run": hashlib.sha256(json.dumps(run, sort_keys=True).encode()).hexdigest(),
            "views": {v: sha256_file(p) for v, p in sorted(images.items())}}


def _read_segment_key(out_dir: Path) -> dict | None:
    """The saved key, or None (absent, unreadable or malformed: nothing is reused)."""
    from splattwin import io

    k = io.read_record(out_dir / SEGMENT_KEY)
    if not (isinstance(k, dict) and isinstance(k.get("run"), str) and isinstance(k.get("views"), dict)):
        return None
    return k


def segment_images(images: dict[str, Path], prompt: str, options: SegmentOptions | None = None,
                   labels: dict[str, int] | None = None, out_dir: str | Path | None = None,
                   progress: bool = True, segmenter: OpenVocabSegmenter | None = None,
                   resume: bool = True) -> MaskSet:
    """Run the open-vocabulary segmenter over views {view name: image path} -> MaskSet.

    labels: phrase -> object label (default 1..K in prompt order). out_dir: save after every view and,
    with resume, skip views already saved there whose photo (by content), prompt and segmentation
    options (models, thresholds, sizes) are the same (out_dir/segment_key.json). Objects found in no
    view raise InputError.
    """
    from splattwin.limits import read_image_array

    phrases = parse_prompt(prompt)
    labels = {p: i + 1 for i, p in enumerate(phrases)} if labels is None else {k.lower(): v for k, v in labels.items()}
    missing = [p for p in phrases if p not in labels]
    if missing:
        raise InputError(f"prompt phrases {missing} have no object label (known: {sorted(labels)})")
    names = prompt_object_names(prompt)
    ms = MaskSet(objects={labels[p]: names[p] for p in phrases},
                 prompts={labels[p]: p for p in phrases}, source=f"open-vocab:{prompt}")
    done: set[str] = set()
    key = _segment_key(images, ms.prompts, options or SegmentOptions())
    if out_dir is not None and resume and (Path(out_dir) / "masks.json").is_file():
        prev_key = _read_segment_key(Path(out_dir))
        if prev_key is not None and prev_key["run"] == key["run"]:
            prev = MaskSet.load(out_dir)
            if prev.prompts == ms.prompts:
                # a view is reused only when its photo is the one segmented (same name, same bytes)
                done = {v for v in prev.sizes if v in images and prev_key["views"].get(v) == key["views"][v]}
                for v in set(prev.views) | set(prev.sizes):
                    if v not in done:
                        prev.masks.pop(v, None), prev.scores.pop(v, None), prev.sizes.pop(v, None)
                ms = prev
                log.info("resuming: %d of %d views already segmented in %s", len(done), len(images), out_dir)
    if out_dir is not None:
        from splattwin import io

        Path(out_dir).mkdir(parents=True, exist_ok=True)
        io.write_json(Path(out_dir) / SEGMENT_KEY, key)
    todo = [v for v in sorted(images) if v not in done]
    seg = segmenter
    if todo and seg is None:
        seg = OpenVocabSegmenter(options)
    from splattwin.progress import Progress

    bar = Progress(len(todo), "segmenting views", unit="view", enabled=progress)
    for view in todo:
        # the photo's own 8-bit RGB (as `load_image` reads it, before its /255): 3 bytes a pixel, where the
        # float round trip held 28 (450 MB -> 4 GB at the 150 MP limit)
        img = read_image_array(images[view], mode="RGB", what="photo")
        ms.sizes[view] = img.shape[:2]
        for p, (mask, score) in seg(img, phrases).items():
            if mask.any():
                ms.add(view, labels[phrases[p]], mask, score)
        if out_dir is not None:
            ms.save(out_dir)
        bar.update(1)
    bar.close()
    for lab, name in ms.objects.items():
        if ms.n_views_with(lab) == 0:
            raise InputError(f"prompt phrase {ms.prompts[lab]!r} was found in no view (box threshold "
                             f"{(options or SegmentOptions()).box_threshold}); rephrase it or lower --box-threshold")
    return ms
