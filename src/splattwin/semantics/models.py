"""Which segmentation models a text prompt needs, and whether their weights are on this machine, without
loading them (`splattwin build --prompt` checks this before pose estimation and training).

`required_models(SegmentOptions)` -> [(role, hub id or folder)]: Grounding DINO (boxes from the phrases)
and SAM / SAM 2 (masks from the boxes); SAM 3 segments the phrases itself and needs no detector.
`missing_models(...)` names those whose config, weights or processor files (image-processor config,
tokenizer: what `segment.OpenVocabSegmenter` loads besides the model) are in neither a local folder nor
the local Hugging Face cache (`huggingface_hub.try_to_load_from_cache`: reads the cache folder, no
network), or whose config is of another model type than the role needs.
`missing_models_error(...)` is the InputError listing all of them with the command that fetches them.
"""

from __future__ import annotations

from pathlib import Path

from splattwin.errors import InputError
from splattwin.semantics.options import SegmentOptions

WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "pytorch_model.bin",
                "pytorch_model.bin.index.json")
# config.json model_type(s) of each role's models (facebook/sam3 ships a sam3_video config): what a
# checkpoint must declare to be loaded for that role (`segment.load_model`, `missing_models`)
MODEL_TYPES = {"detector": ("grounding-dino",), "sam": ("sam",), "sam2": ("sam2", "sam2_video"),
               "sam3": ("sam3", "sam3_video")}
_KINDS = {mt: kind for kind, mts in MODEL_TYPES.items() if kind != "detector" for mt in mts}
# files the processors read besides config + weights, per role (one of each group): a cache filled by
# `SamModel.from_pretrained` alone has the model but not these, and the run failed after training. SAM 2
# images are preprocessed by hand; SAM 3 needs only its tokenizer
PROCESSOR_FILES = {"detector": (("preprocessor_config.json", "processor_config.json"), ("tokenizer.json", "vocab.txt")),
                   "sam": (("preprocessor_config.json", "processor_config.json"),),
                   "sam2": (),
                   "sam3": (("tokenizer.json", "vocab.json"),)}


def _local_file(model: str, name: str) -> Path | None:
    """Path of `name` of model `model` (a folder, or a hub id in the local cache), or None."""
    p = Path(model)
    if p.is_dir():
        return p / name if (p / name).is_file() else None
    if p.exists() or model.count("/") != 1:
        return None
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - a dependency of transformers
        return None
    try:
        got = try_to_load_from_cache(model, name)
    except Exception:  # noqa: BLE001 - a malformed id: not available
        return None
    return Path(got) if isinstance(got, str) and Path(got).is_file() else None


def is_available(model: str, role: str | None = None) -> bool:
    """config.json and a weights file of `model` (folder or hub id) are on this machine, and with `role`
    (a PROCESSOR_FILES key) the processor files that role loads too."""
    return not missing_files(model, role)


def missing_files(model: str, role: str | None = None) -> list[str]:
    """The files (or 'a | b' alternatives) of `model` that are not on this machine; [] when it is usable."""
    groups = (("config.json",), WEIGHT_FILES) + PROCESSOR_FILES.get(role or "", ())
    return [" | ".join(g) for g in groups if not any(_local_file(model, f) for f in g)]


def _config_model_type(model: str) -> str | None:
    cfg = _local_file(model, "config.json")
    if cfg is None:
        return None
    from splattwin.errors import InputError
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    try:   # bounded before it is read (a model's config is KBs); deep nesting, bad JSON: unknown, not a traceback
        mt = read_json(cfg, max_bytes=MAX_RECORD_BYTES).get("model_type")
    except (InputError, OSError, AttributeError):
        return None
    return mt if isinstance(mt, str) else None


def segmenter_kind(options: SegmentOptions) -> str | None:
    """sam / sam2 / sam3 from the option, or from the segmenter's config.json when available (None:
    unknown, the config is not on this machine)."""
    if options.segmenter_kind != "auto":
        return options.segmenter_kind
    if _local_file(options.segmenter, "config.json") is None:
        low = options.segmenter.lower()
        return "sam3" if "sam3" in low else ("sam2" if "sam2" in low else ("sam" if "sam" in low else None))
    return _KINDS.get(_config_model_type(options.segmenter))


def required_models(options: SegmentOptions) -> list[tuple[str, str]]:
    """[(role, model)] the prompt needs: the detector unless the segmenter is SAM 3, and the segmenter."""
    kind = segmenter_kind(options)
    names = {"sam": "SAM segmenter", "sam2": "SAM 2 segmenter", "sam3": "SAM 3 segmenter"}
    out = [] if kind == "sam3" else [("Grounding DINO detector", options.detector)]
    return out + [(names.get(kind or "", "SAM segmenter"), options.segmenter)]


def _problems(options: SegmentOptions) -> list[tuple[str, str, str | None]]:
    """[(role, model, None or what is wrong)] for every model the prompt needs."""
    need = required_models(options)
    keys = ["detector"] * (len(need) - 1) + [segmenter_kind(options) or "sam"]   # the segmenter comes last
    out = []
    for (role, model), key in zip(need, keys):
        lacks = missing_files(model, key)
        mt = _config_model_type(model)
        if lacks:
            why = "MISSING" if "config.json" in lacks else f"MISSING {', '.join(lacks)}"
        elif key == "detector" and mt is not None and mt not in MODEL_TYPES["detector"]:
            why = f"a {mt!r} model, not Grounding DINO"   # transformers would load it with random weights
        elif key != "detector" and mt is not None and _KINDS.get(mt) != key:   # e.g. --segmenter-kind sam
            why = f"a {mt!r} model, not a {key} model"
        else:
            why = None
        out.append((role, model, why))
    return out


def missing_models(options: SegmentOptions) -> list[tuple[str, str]]:
    return [(role, m) for role, m, why in _problems(options) if why]


def missing_models_error(options: SegmentOptions) -> InputError | None:
    """None when every model the prompt needs is here; else an InputError naming all of them."""
    need = _problems(options)
    missing = [(r, m) for r, m, why in need if why]
    if not missing:
        return None
    listing = "; ".join(f"{r} {m!r} ({why or 'present'})" for r, m, why in need)
    cmds = " && ".join(f"hf download {m}" for _, m in missing if not Path(m).is_absolute())
    return InputError(
        f"--prompt needs these segmentation models on this machine: {listing}. splattwin never downloads at run "
        f"time: fetch them once on a machine with network ({cmds or 'copy the folders here'}; or "
        f"`huggingface-cli download ID`), then copy the Hugging Face cache (~/.cache/huggingface) or pass local "
        f"folders with --semantics.segment.detector / --semantics.segment.segmenter; or give 2D masks with --masks")
