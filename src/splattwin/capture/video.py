"""Frames from a video file (PyAV): evenly spaced windows, the sharpest frame of each.

The clip is split into `max_frames` equal windows of consecutive frames; in each window the frame with
the highest variance of the Laplacian (a standard focus measure, computed on a downscaled grey image)
is kept. This avoids the motion-blurred frames a hand-held or robot scan is full of.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.dataset import Dataset
from splattwin.errors import InputError

log = logging.getLogger(__name__)


def sharpness(rgb: np.ndarray, max_side: int = 320) -> float:
    """Variance of the Laplacian of the grey image (higher = sharper). rgb: HxWx3 uint8."""
    import cv2

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    s = max_side / max(grey.shape)
    if s < 1:
        grey = cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _open(path: Path):
    import av

    if not path.is_file():
        raise InputError("video file does not exist", path)
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as e:  # type: ignore[attr-defined]
        raise InputError(f"unreadable video ({e})", path) from e
    if not container.streams.video:
        container.close()
        raise InputError("file has no video stream", path)
    return container


def select_frames(scores: np.ndarray, max_frames: int) -> list[int]:
    """Indices of the sharpest frame in each of `max_frames` equal windows over `len(scores)` frames."""
    n = len(scores)
    if n == 0:
        return []
    k = min(max_frames, n)
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def extract_frames(path: str | Path, out_dir: str | Path, max_frames: int = 30) -> list[Path]:
    """Write the selected frames as PNG into `out_dir` (frame_00000.png, ...); cached by video size/mtime."""
    from splattwin.progress import Progress

    path, out_dir = Path(path), Path(out_dir)
    if max_frames < 1:
        raise InputError(f"--max-frames must be >= 1, got {max_frames}")
    stamp = {"video": str(path.resolve()), "size": path.stat().st_size if path.is_file() else None,
             "mtime": path.stat().st_mtime if path.is_file() else None, "max_frames": max_frames}
    index = out_dir / "frames.json"
    if index.is_file():
        from splattwin.paths import confined

        try:
            cached = json.loads(index.read_text())
            if cached.get("stamp") == stamp:
                paths = [confined(out_dir, n, index, "frame file") for n in cached["frames"]]
                if all(p.is_file() for p in paths):
                    return paths
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError):
            pass
    # Pass 1: sharpness of every frame (cheap, downscaled).
    container = _open(path)
    scores = []
    with Progress(container.streams.video[0].frames or None, f"scoring {path.name}", unit="frame") as prog:
        try:
            for frame in container.decode(video=0):
                scores.append(sharpness(frame.to_ndarray(format="rgb24")))
                prog.update(1)
        except Exception as e:  # noqa: BLE001 — PyAV decode errors have many types
            raise InputError(f"video decoding failed after {len(scores)} frames: {e}", path) from e
        finally:
            container.close()
    if not scores:
        raise InputError("video has no decodable frames", path)
    keep = select_frames(np.asarray(scores), max_frames)
    # Pass 2: write the chosen frames.
    container = _open(path)
    names, want = [], set(keep)
    try:
        for i, frame in enumerate(container.decode(video=0)):
            if i in want:
                name = f"frame_{len(names):05d}.png"
                io.write_image(out_dir / name, frame.to_ndarray(format="rgb24"))
                names.append(name)
            if len(names) == len(keep):
                break
    finally:
        container.close()
    io.write_json(index, {"stamp": stamp, "frames": names, "source_indices": keep})
    log.info("extracted %d of %d frames from %s into %s", len(names), len(scores), path, out_dir)
    return [out_dir / n for n in names]


def read(path: str | Path, max_frames: int | None = None, out_dir: str | Path | None = None) -> Dataset:
    """A video as an unposed image dataset (frames cached in `<stem>_frames/` beside the video)."""
    from splattwin.capture import images

    path = Path(path)
    out = Path(out_dir) if out_dir is not None else path.parent / f"{path.stem}_frames"
    extract_frames(path, out, max_frames=max_frames or 30)
    ds = images.read(out)
    ds.meta.update({"format": "video", "video": str(path), "sequential": True})
    return ds
