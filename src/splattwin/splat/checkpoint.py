"""Training checkpoints as tensors plus plain data: one safetensors file, never a pickle.

A checkpoint in OUT/checkpoints/ may come from someone else (a received twin folder, a shared run);
`torch.load` of a pickle runs any code it contains. This format holds only tensors (safetensors, a
JSON header and raw little-endian arrays) and one JSON document of plain data in the safetensors
metadata, so loading it can never run code.

Layout of `ckpt_XXXXXX.safetensors`:
    tensors:   "t0", "t1", ... every tensor of the state (on the CPU, contiguous)
    metadata:  {"format": "splattwin-checkpoint", "version": "1", "state": JSON}
    JSON:      the state with each tensor replaced by {"__tensor__": "tK"}; dicts whose keys are not all
               strings (optimizer states use int keys) as {"__dict__": [[key, value], ...]}; tuples as
               {"__tuple__": [...]}.

Files written by `save` are atomic (`splattwin.io.atomic_path`). `load` turns any unreadable, foreign
or inconsistent file into an InputError naming it. Checkpoints of earlier versions (`ckpt_*.pt`,
pickles) are never loaded.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from splattwin.errors import InputError
from splattwin.io import atomic_path

FORMAT = "splattwin-checkpoint"
VERSION = "1"
SUFFIX = ".safetensors"
LEGACY_SUFFIX = ".pt"


def _encode(obj: Any, tensors: dict[str, torch.Tensor]) -> Any:
    if isinstance(obj, torch.Tensor):
        key = f"t{len(tensors)}"
        tensors[key] = obj.detach().to("cpu").contiguous().clone()
        return {"__tensor__": key}
    if isinstance(obj, np.ndarray):
        return _encode(torch.from_numpy(np.ascontiguousarray(obj)), tensors)
    if isinstance(obj, dict):
        if all(isinstance(k, str) for k in obj) and not ({"__tensor__", "__dict__", "__tuple__", "__float__"} & set(obj)):
            return {k: _encode(v, tensors) for k, v in obj.items()}
        return {"__dict__": [[_encode(k, tensors), _encode(v, tensors)] for k, v in obj.items()]}
    if isinstance(obj, tuple):
        return {"__tuple__": [_encode(v, tensors) for v in obj]}
    if isinstance(obj, list):
        return [_encode(v, tensors) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return {"__float__": repr(obj)}
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return _encode(obj.item(), tensors)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise TypeError(f"checkpoint state holds a {type(obj).__name__}; only tensors and plain data are stored")


def _decode(obj: Any, tensors: dict[str, torch.Tensor], where: Path) -> Any:
    if isinstance(obj, list):
        return [_decode(v, tensors, where) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if set(obj) == {"__tensor__"}:
        key = obj["__tensor__"]
        if not isinstance(key, str) or key not in tensors:
            raise InputError(f"checkpoint refers to a missing tensor {key!r}", where)
        return tensors[key]
    if set(obj) == {"__dict__"}:
        items = obj["__dict__"]
        if not isinstance(items, list) or not all(isinstance(kv, list) and len(kv) == 2 for kv in items):
            raise InputError("checkpoint state is malformed (__dict__)", where)
        out = {}
        for k, v in items:
            k = _decode(k, tensors, where)
            if not isinstance(k, (str, int, float, bool)) and k is not None:
                raise InputError("checkpoint state is malformed (dict key)", where)
            out[k] = _decode(v, tensors, where)
        return out
    if set(obj) == {"__tuple__"}:
        if not isinstance(obj["__tuple__"], list):
            raise InputError("checkpoint state is malformed (__tuple__)", where)
        return tuple(_decode(v, tensors, where) for v in obj["__tuple__"])
    if set(obj) == {"__float__"}:
        if obj["__float__"] not in ("nan", "inf", "-inf"):
            raise InputError("checkpoint state is malformed (__float__)", where)
        return float(obj["__float__"])
    return {k: _decode(v, tensors, where) for k, v in obj.items()}


def save(path: str | Path, state: dict) -> Path:
    """Write `state` (nested dicts/lists/tuples of tensors and plain data) atomically to `path`."""
    from safetensors.torch import save_file

    tensors: dict[str, torch.Tensor] = {}
    doc = _encode(state, tensors)
    meta = {"format": FORMAT, "version": VERSION, "state": json.dumps(doc, allow_nan=False)}
    path = Path(path)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)
    return path


def load(path: str | Path) -> dict:
    """The state saved by `save`; InputError naming the file when it is not such a checkpoint."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise InputError("not a splattwin checkpoint (no splattwin-checkpoint metadata)", path)
            if meta.get("version") != VERSION:
                raise InputError(f"checkpoint format version {meta.get('version')!r} is not supported "
                                 f"(expected {VERSION}); start a new run", path)
            tensors = {k: f.get_tensor(k) for k in f.keys()}
        doc = json.loads(meta["state"])
    except InputError:
        raise
    except (SafetensorError, OSError, ValueError, KeyError, RecursionError) as e:
        raise InputError(f"unreadable checkpoint ({type(e).__name__}: {str(e)[:200]})", path) from None
    state = _decode(doc, tensors, path)
    if not isinstance(state, dict):
        raise InputError("checkpoint state is not a mapping", path)
    return state
