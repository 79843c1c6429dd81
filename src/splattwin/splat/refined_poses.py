"""The camera poses a splat was trained with, when they were refined (`TrainConfig.refine_poses`), and
their use by the later stages.

With pose refinement the splats are fitted to the *corrected* training cameras, so anything projecting the
splats into the training views (semantic fusion of the 2D masks, the twin's silhouette coverage, the
moved objects' refinement) must use those corrected cameras, not the capture's. The held-out views share
the capture's pose errors but were never refined: the splat stage fits each to its image with the splats
fixed (`eval --align-poses`, the BARF / nerfstudio / InstantSplat evaluation protocol) and stores the
result beside the training poses.

One file, written by the splat stage into its own folder and absent when the poses were not refined (a
stale one is removed, so a twin built without refinement reads exactly the capture's poses):

    splat/refined_poses.json = {"convention": "T_world_cam, OpenCV",
                                "poses": {training view: [4x4]},            (refined jointly, by the trainer)
                                "heldout": {"poses": {held-out view: [4x4]}, "how": ...}}   (the splat stage)

The capture's own poses/transforms.json is kept as it is. `apply` puts the file's poses on a loaded
dataset's frames (by view name); the pipeline hands the file to the semantics and twin stages.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from splattwin.errors import InputError, short_repr

log = logging.getLogger(__name__)

FILE = "refined_poses.json"
CONVENTION = "T_world_cam, OpenCV"
HELDOUT_HOW = ("aligned to each held-out image with the splats fixed (test-time pose fit, as `eval --align-poses`): "
               "the held-out cameras share the capture's pose errors but were not refined with the training ones")


def path_in(splat_dir: str | Path) -> Path | None:
    """The refined-poses file of a training folder, or None when its poses were not refined."""
    p = Path(splat_dir) / FILE
    return p if p.is_file() else None


def read(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """{"train": {name: T_world_cam}, "heldout": {name: T_world_cam}} from a refined-poses file."""
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    path = Path(path)
    d = read_json(path, "refined poses", MAX_RECORD_BYTES)
    if not isinstance(d, dict) or not isinstance(d.get("poses"), dict):
        raise InputError("malformed refined poses: expected an object with 'poses'", path)
    held = d.get("heldout") or {}
    held = held.get("poses") if isinstance(held, dict) else None
    out: dict[str, dict[str, np.ndarray]] = {}
    for key, poses in (("train", d["poses"]), ("heldout", held or {})):
        if not isinstance(poses, dict):
            raise InputError(f"malformed refined poses: {key} poses must be an object", path)
        out[key] = {}
        for name, T in poses.items():
            out[key][str(name)] = _pose(T, f"refined pose of view {short_repr(name)}", path)
    return out


def _pose(value, what: str, path: Path) -> np.ndarray:
    """T_world_cam [4,4] from a file: 16 numbers (not text or booleans, which np.asarray turned into 1.0),
    a rotation (orthonormal, right-handed) and a position within MAX_POSITION, as the capture's poses."""
    from splattwin.limits import MAX_POSITION, numbers
    from splattwin.transforms import pose_from_file_value

    M = pose_from_file_value(numbers(value, 16, path, what).reshape(4, 4), what, path, rigid=True)
    if np.max(np.abs(M[:3, 3])) > MAX_POSITION:
        raise InputError(f"{what}: position more than {MAX_POSITION:g} from the origin", path)
    return M


def write(out_dir: str | Path, train: dict[str, list], heldout: dict[str, np.ndarray] | None = None) -> Path:
    """Write (or rewrite with the held-out views' aligned poses) OUT/refined_poses.json."""
    from splattwin.io import write_json

    d: dict = {"convention": CONVENTION, "poses": train}
    if heldout:
        d["heldout"] = {"poses": {k: np.asarray(v, dtype=np.float64).tolist() for k, v in heldout.items()},
                        "how": HELDOUT_HOW}
    return write_json(Path(out_dir) / FILE, d)


def add_heldout(out_dir: str | Path, heldout: dict[str, np.ndarray]) -> Path | None:
    """Add the held-out views' aligned poses (T_world_cam) to OUT/refined_poses.json (None if there is none)."""
    p = path_in(out_dir)
    if p is None:
        return None
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    d = read_json(p, "refined poses", MAX_RECORD_BYTES)
    return write(out_dir, d["poses"], heldout)


def apply(dataset, path: str | Path | None):
    """The dataset with its frames' poses replaced by the file's (training views: refined; held-out views:
    aligned), as a copy; the dataset itself when path is None. Frames the file does not name keep their
    pose (a warning names how many training views that is: the file belongs to another capture)."""
    if path is None:
        return dataset
    poses = read(path)
    by_name = {**poses["heldout"], **poses["train"]}
    frames, used, missing = [], {"train": 0, "heldout": 0}, 0
    for f in dataset.frames:
        T = by_name.get(f.name)
        if T is None:
            missing += f.split == "train"
            frames.append(f)
            continue
        used["train" if f.name in poses["train"] else "heldout"] += 1
        frames.append(dataclasses.replace(f, camera=dataclasses.replace(f.camera, T_world_cam=T.copy())))
    if missing:
        log.warning("%d training view(s) have no refined pose in %s: their capture poses are used", missing, path)
    log.info("using the refined poses of %s (%d training views refined, %d held-out views aligned)", path,
             used["train"], used["heldout"])
    meta = dict(dataset.meta)
    meta["refined_poses"] = {"file": str(path), "train": used["train"], "heldout": used["heldout"]}
    return dataclasses.replace(dataset, frames=frames, meta=meta)


def describe(dataset) -> str:
    """How a dataset's poses came ("as captured", or the refined-poses record `apply` left)."""
    r = dataset.meta.get("refined_poses")
    if not r:
        return "as captured"
    return (f"refined with the splats ({r['train']} training views refined jointly, {r['heldout']} held-out "
            f"views aligned with the splats fixed; {Path(r['file']).name})")
