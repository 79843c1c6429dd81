"""The poses stage as the pipeline runs it: `run(PosesInputs, PoseOptions) -> PosesResult`.

Reads the capture (any layout `splattwin.capture.load_dataset` reads; a video's frames are extracted into
`inputs.frames_dir`) and the robot pose files; writes OUT/transforms.json (+ the capture's images, depth,
masks, labels bundled into OUT), OUT/frame.json, OUT/poses_report.json, OUT/cameras.png, OUT/sfm/.
`input_files` names what it reads, for the pipeline's content-hashed stage keys.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from splattwin.poses.options import PoseOptions


@dataclass
class PosesInputs:
    capture: Path                   # dataset: image folder, video, transforms.json, COLMAP, cameras.json, BOP, TUM
    out_dir: Path                   # the stage's folder (TWIN/poses)
    frames_dir: Path | None = None  # where a video input's frames are extracted


@dataclass
class PosesResult:
    transforms: Path   # posed nerfstudio dataset (self-contained: the capture's files bundled beside it)
    frame: Path        # frame.json: the twin frame's source, scale, uncertainty
    registered: int | None
    total: int | None


def _load(inputs: PosesInputs, options: PoseOptions, validate: bool = True):
    from splattwin.capture import load_dataset

    return load_dataset(inputs.capture, validate=validate, frames_dir=inputs.frames_dir,
                        max_frames=options.max_frames, min_change=options.min_change, progress=options.progress)


def run(inputs: PosesInputs, options: PoseOptions, *, progress: bool = True) -> PosesResult:
    from splattwin.poses.estimate import estimate_poses
    from splattwin.poses.twin_frame import FRAME_FILE

    opts = replace(options, progress=progress, work_dir=options.work_dir or inputs.out_dir / "sfm")
    result = estimate_poses(_load(inputs, opts), opts)
    path = result.save(inputs.out_dir)
    return PosesResult(transforms=path, frame=inputs.out_dir / FRAME_FILE, registered=result.stats.get("registered"),
                       total=result.stats.get("total"))


def input_files(inputs: PosesInputs, options: PoseOptions) -> dict:
    """What the stage reads from outside the twin, hashed by content for its key: the capture's metadata,
    images, depth, masks and points, its frame.json prior, and the robot pose files."""
    import numpy as np

    from splattwin.capture.dataset import VIDEO_SUFFIXES

    src = Path(inputs.capture)
    out: dict = {"robot_poses": options.robot_poses, "hand_eye": options.hand_eye}
    if not src.exists() or (src.is_file() and src.suffix in VIDEO_SUFFIXES):
        out["capture"] = src
        return out
    ds = _load(inputs, options, validate=False)
    files = []
    meta_path = ds.meta.get("path")
    if meta_path and ds.meta.get("format") in ("nerfstudio", "cameras.json", "colmap"):
        files.append(Path(meta_path))
        files.append((Path(meta_path).parent if Path(meta_path).is_file() else Path(meta_path)) / "frame.json")
    files += [Path(p) for p in ds.meta.get("files", [])]  # pose lists, intrinsics, BOP json (bop, tum)
    for f in ds.frames:
        files += [f.image_path, f.depth_path, f.mask_path, f.label_path]
    out["capture"] = files
    if ds.points_xyz is not None:
        rgb = b"" if ds.points_rgb is None else np.ascontiguousarray(ds.points_rgb).tobytes()
        out["points"] = np.ascontiguousarray(ds.points_xyz).tobytes() + rgb
    return out
