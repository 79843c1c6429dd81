"""Trained splats reused when only the twin frame changed: a build given its metric scale afterwards.

A build without scale (SfM: the table frame in SfM units) followed by the same build with `--known-length`
(or another change of the table frame alone) gives the same photos, the same SfM and the same training
options; only the world frame differs, by one similarity S = [[s R, t], [0, 1]]. Moving a trained 3DGS by S
(`splattwin.splat.transform.transform_gaussians`: positions s R p + t, rotations R q, log-scales + log s,
opacities and colours as they were, SH rotated) and its cameras with it renders the very same images, so
the splats stage moves the trained splats into the new frame instead of training again (6.6 min on the
real cake, and a different result).

After each run the stage records what the splats were trained on, OUT/trained_on.json: the training
options, the held-out views, each view's name, image size, intrinsics, pose (T_world_cam) and the digest of
its image, mask and depth files, and the digest of point_cloud.ply. The next run reuses the splats only when
all of it matches but the poses, the poses differ by one similarity (every camera within 1e-6 of the scene's
size and 1e-6 rad), and point_cloud.ply is the file recorded (not rewritten by a `splattwin train` by hand).
Not with pose refinement (its refined poses would have to move too), a depth loss (depth is measured in
metres, the old frame's units were not) or a learnt environment map under a rotation; these train again.

The checkpoints are removed (they hold the old frame's parameters and optimiser state; a later run with
other options trains from scratch anyway); train.json records the move ("rescaled"); the held-out
evaluation runs again in the new frame (the same figures).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin.capture import Dataset
from splattwin.errors import InputError
from splattwin.hashing import sha256_file
from splattwin.splat.config import TrainConfig

log = logging.getLogger(__name__)

RECORD = "trained_on.json"
POSE_TOL = 1e-6   # relative to the scene's size (camera centres), and radians for the orientations


@dataclass
class Rescaled:
    """The splats moved into the new frame: T_new_old [4,4] (similarity), scale s, Gaussians kept."""

    T_new_old: np.ndarray
    scale: float
    gaussians: int
    train_s: float | None


def _file_digest(path: Path | None) -> str | None:
    return None if path is None else sha256_file(path)


def _view_record(frame) -> dict:
    c = frame.camera
    return {"name": frame.name, "width": int(c.width), "height": int(c.height),
            "K": np.asarray(c.K, np.float64).round(9).tolist(),
            "dist": None if c.dist is None else np.asarray(c.dist, np.float64).round(12).tolist(),
            "files": [_file_digest(p) for p in (frame.image_path, frame.mask_path, frame.depth_path)],
            "T_world_cam": np.asarray(c.T_world_cam, np.float64).tolist()}


def _run_options(cfg: TrainConfig | dict) -> dict:
    from splattwin.splat.trainer import run_options

    if isinstance(cfg, TrainConfig):
        return run_options(cfg)
    # an option the record does not hold is newer than it: that run had its default (as trainer.check_resumable)
    base = run_options(TrainConfig())
    return {**base, **{k: v for k, v in cfg.items()}}


def record(out_dir: Path, ds: Dataset, cfg: TrainConfig) -> Path:
    """Write OUT/trained_on.json for the splats just written to OUT/point_cloud.ply (module docstring)."""
    from splattwin.io import write_json

    return write_json(Path(out_dir) / RECORD, obj={
        "run_options": _run_options(cfg), "heldout": sorted(f.name for f in ds.heldout()),
        "views": [_view_record(f) for f in ds.train()],
        "ply_sha256": _file_digest(Path(out_dir) / "point_cloud.ply")})


def _read_record(out_dir: Path) -> dict | None:
    from splattwin.limits import read_json

    p = Path(out_dir) / RECORD
    if not p.is_file() or not (Path(out_dir) / "point_cloud.ply").is_file():
        return None
    try:
        rec = read_json(p)
    except InputError as e:
        log.info("%s: not read (%s): training again", p, e)
        return None
    return rec if isinstance(rec, dict) else None


def similarity_between(old: list[np.ndarray], new: list[np.ndarray]) -> np.ndarray | None:
    """The similarity S [4,4] with new_i = S-moved old_i for every camera-to-world pose (centres
    s R C + t, orientations R R_old), or None when no one similarity maps them within POSE_TOL (relative
    to the cameras' spread; fewer than 3 non-collinear centres: None)."""
    from splattwin.poses.align import umeyama

    C_old = np.array([T[:3, 3] for T in old])
    C_new = np.array([T[:3, 3] for T in new])
    try:
        fit = umeyama(C_old, C_new)
    except ValueError:
        return None
    s = fit.scale
    R = fit.S[:3, :3] / s
    spread = float(np.sqrt(np.mean(np.sum((C_new - C_new.mean(0)) ** 2, axis=1))))
    if not spread > 0 or fit.residuals.max() > POSE_TOL * spread:
        return None
    for To, Tn in zip(old, new):
        if np.abs(R @ To[:3, :3] - Tn[:3, :3]).max() > POSE_TOL:
            return None
    return fit.S


def _why_not(rec: dict, ds: Dataset, cfg: TrainConfig) -> str | None:
    """Why the recorded splats cannot be moved into `ds`'s frame (None: they can, pending the poses)."""
    if _run_options(rec.get("run_options") or {}) != _run_options(cfg):
        return "the training options changed"
    if rec.get("heldout") != sorted(f.name for f in ds.heldout()):
        return "the held-out views changed"
    views = rec.get("views")
    train = ds.train()
    if not isinstance(views, list) or len(views) != len(train):
        return "the training views changed"
    for v, f in zip(views, train):
        now = _view_record(f)
        if not isinstance(v, dict) or any(v.get(k) != now[k]
                                          for k in ("name", "width", "height", "K", "dist", "files")):
            return f"the training view {f.name} changed (image, mask, depth or intrinsics)"
    if cfg.refine_poses:
        return "pose refinement is on (--splat.refine-poses)"
    if cfg.depth_lambda > 0 and any(f.depth_path is not None for f in train):
        return "the depth loss is on (--splat.depth-lambda)"
    return None


def try_rescale(ds: Dataset, out_dir: str | Path, cfg: TrainConfig, frame_note: str = "") -> Rescaled | None:
    """Move OUT's trained splats into `ds`'s frame when only the frame changed since they were trained
    (module docstring); None (nothing changed on disk) when they cannot be, or when the frame is the same
    (training then resumes or starts as usual). frame_note: the new frame's units for the log ("metres")."""
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.transform import transform_gaussians

    out_dir = Path(out_dir)
    rec = _read_record(out_dir)
    if rec is None:
        return None
    if rec.get("ply_sha256") != _file_digest(out_dir / "point_cloud.ply"):
        log.info("%s was rewritten since the splats stage trained it: training again", out_dir / "point_cloud.ply")
        return None
    why = _why_not(rec, ds, cfg)
    if why is not None:
        log.info("the trained splats are not reused: %s", why)
        return None
    try:
        old = [np.asarray(v["T_world_cam"], np.float64).reshape(4, 4) for v in rec["views"]]
    except (KeyError, TypeError, ValueError):
        return None
    S = similarity_between(old, [np.asarray(f.camera.T_world_cam, np.float64) for f in ds.train()])
    if S is None:
        log.info("the trained splats are not reused: the cameras moved by more than a change of frame")
        return None
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R = S[:3, :3] / s
    if np.allclose(S, np.eye(4), atol=1e-12):
        return None   # the same frame: nothing to move (a finished checkpoint is resumed with no step left)
    if cfg.background_mode == "env" and np.abs(R - np.eye(3)).max() > POSE_TOL:
        log.info("the trained splats are not reused: the frame rotated and the environment map is looked up by "
                 "world direction")
        return None
    moved = transform_gaussians(Gaussians.load_ply(out_dir / "point_cloud.ply"), S)
    _move(out_dir, moved, S, s)
    n = len(moved)
    rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    moved = (f" (and moved into the new table frame: {rot:.2f} deg, {np.linalg.norm(S[:3, 3]):.4g} shift)"
             if rot > 1e-6 or np.linalg.norm(S[:3, 3]) > 1e-9 else "")
    if frame_note:   # a metric frame now: the usual case, scale given after an unscaled build
        log.info("scale given: the trained splats are rescaled by %.4g into %s, not retrained%s", s, frame_note, moved)
    else:
        log.info("the twin frame changed: the trained splats are rescaled by %.4g into it, not retrained%s", s, moved)
    train = _train_record(out_dir)
    return Rescaled(T_new_old=S, scale=s, gaussians=n, train_s=train.get("wall_s"))


def _train_record(out_dir: Path) -> dict:
    from splattwin.limits import read_json

    try:
        d = read_json(out_dir / "train.json")
    except InputError:
        return {}
    return d if isinstance(d, dict) else {}


def _move(out_dir: Path, g, S: np.ndarray, s: float) -> None:
    """Write the moved splats, drop the old frame's checkpoints and evaluation, note the move in train.json."""
    from splattwin.io import write_json
    from splattwin.splat.eval import remove_evaluation
    from splattwin.splat.trainer import checkpoint_files

    g.save_ply(out_dir / "point_cloud.ply")
    stale = checkpoint_files(out_dir)
    for p in stale:
        p.unlink()
    if stale:
        log.info("removed %d checkpoint(s) of the old frame in %s: the splats were moved, not the optimiser's "
                 "state (a later run with other training options trains from scratch)", len(stale),
                 out_dir / "checkpoints")
    remove_evaluation(out_dir / "eval")
    train = _train_record(out_dir)
    if train:
        moves = list(train.get("rescaled") or [])
        moves.append({"scale": s, "T_new_old": np.asarray(S).tolist(),
                      "note": "splats trained in an earlier frame, moved by this similarity, not retrained"})
        train["rescaled"] = moves
        if isinstance(train.get("scene_scale"), (int, float)):
            train["scene_scale"] = float(train["scene_scale"]) * s
        write_json(out_dir / "train.json", obj=json.loads(json.dumps(train)))
