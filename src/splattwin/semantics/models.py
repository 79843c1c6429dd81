"""Which segmentation models a text prompt needs, and whether their weights are on this machine, without
loading them (`splattwin build --prompt` checks this before pose estimation and training).

`required_models(SegmentOptions)` -> [(role, hub id or folder)]: Grounding DINO (boxes from the phrases)
and SAM / SAM 2 (masks from the boxes); SAM 3 segments the phrases itself and needs no detector.
`missing_models(...)` names those whose config and weights are in neither a local folder nor the local
Hugging Face cache (`huggingface_hub.try_to_load_from_cache`: reads the cache folder, no network).
`missing_models_error(...)` is the InputError listing all of them with the command that fetches them.
"""

from __future__ import annotations

import json
from pathlib import Path

from splattwin.errors import InputError
from splattwin.semantics.options import SegmentOptions

WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "pytorch_model.bin",
                "pytorch_model.bin.index.json")
_KINDS = {"sam": "sam", "sam2": "sam2", "sam2_video": "sam2", "sam3": "sam3", "sam3_video": "sam3"}


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


def is_available(model: str) -> bool:
    """config.json and a weights file of `model` (folder or hub id) are on this machine."""
    return _local_file(model, "config.json") is not None and any(_local_file(model, w) for w in WEIGHT_FILES)


def segmenter_kind(options: SegmentOptions) -> str | None:
    """sam / sam2 / sam3 from the option, or from the segmenter's config.json when available (None:
    unknown, the config is not on this machine)."""
    if options.segmenter_kind != "auto":
        return options.segmenter_kind
    cfg = _local_file(options.segmenter, "config.json")
    if cfg is None:
        low = options.segmenter.lower()
        return "sam3" if "sam3" in low else ("sam2" if "sam2" in low else ("sam" if "sam" in low else None))
    try:
        mt = json.loads(cfg.read_text(encoding="utf-8")[:1_000_000]).get("model_type")
    except (OSError, ValueError, AttributeError):
        return None
    return _KINDS.get(mt)


def required_models(options: SegmentOptions) -> list[tuple[str, str]]:
    """[(role, model)] the prompt needs: the detector unless the segmenter is SAM 3, and the segmenter."""
    kind = segmenter_kind(options)
    names = {"sam": "SAM segmenter", "sam2": "SAM 2 segmenter", "sam3": "SAM 3 segmenter"}
    out = [] if kind == "sam3" else [("Grounding DINO detector", options.detector)]
    return out + [(names.get(kind or "", "SAM segmenter"), options.segmenter)]


def missing_models(options: SegmentOptions) -> list[tuple[str, str]]:
    return [(role, m) for role, m in required_models(options) if not is_available(m)]


def missing_models_error(options: SegmentOptions) -> InputError | None:
    """None when every model the prompt needs is here; else an InputError naming all of them."""
    need = required_models(options)
    missing = [(r, m) for r, m in need if not is_available(m)]
    if not missing:
        return None
    listing = "; ".join(f"{r} {m!r} ({'MISSING' if (r, m) in missing else 'present'})" for r, m in need)
    cmds = " && ".join(f"hf download {m}" for _, m in missing if not Path(m).is_absolute())
    return InputError(
        f"--prompt needs these segmentation models on this machine: {listing}. splattwin never downloads at run "
        f"time: fetch them once on a machine with network ({cmds or 'copy the folders here'}; or "
        f"`huggingface-cli download ID`), then copy the Hugging Face cache (~/.cache/huggingface) or pass local "
        f"folders with --semantics.segment.detector / --semantics.segment.segmenter; or give 2D masks with --masks")
