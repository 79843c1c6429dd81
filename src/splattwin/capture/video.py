"""Frames from a video file (PyAV): evenly spaced windows, the sharpest new view of each.

The clip is split into `max_frames` equal windows of consecutive frames; in each window the frame with
the highest variance of the Laplacian (a standard focus measure, computed on a downscaled grey image)
is kept. This avoids the motion-blurred frames a hand-held or robot scan is full of.

Near-duplicates are skipped: a frame is kept only if it differs from the last few kept frames by at least
`min_change` (mean absolute difference of 64-px grey thumbnails, in grey levels of 0..255) and is no
motion-blurred copy of one of them (`select_frames`); a window without such a frame gives none. A camera
that pauses, even with blurred frames while it settles, thus yields its sharpest frame once: copies held out
beside their twin in training inflated the held-out PSNR (68-82 dB to their neighbours) and cost SfM
pairs. Measured on H.264 (crf 23) clips of the real photos: a still camera differs by <= 0.16, a pan
of one pixel (of 512 or 1440) by >= 1.2; the default 1.0 lies between.

Frames stored rotated (a phone's display matrix, PyAV's `frame.rotation`) are turned upright before
they are scored and written, as a player shows them (and as EXIF-rotated photos are, `orientation`).

The frames are cached in the output folder with a record, `frames.json` (the video's size/mtime and
the settings, and the frame files it wrote); a changed video or setting re-extracts, removing the
previous extraction's frames first, and only the frames the record lists are read.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.dataset import Dataset
from splattwin.errors import InputError
from splattwin.frame_options import MIN_CHANGE, VIDEO_MAX_FRAMES, check_max_frames, check_min_change
from splattwin.limits import check_pixels

log = logging.getLogger(__name__)

THUMB_SIDE = 64
# thumbnails the scoring pass keeps at most (~40 KB of memory each with small frames, measured: 330 MB); a longer
# video is scored on every 2nd, 4th, ... frame (`extract_frames`)
MAX_SCORED = 8192
# bumped when the extraction changes what it writes (2: frames upright, near-duplicates skipped, 3: and blurred
# copies of a kept view): an older record's frames are extracted again
METHOD = 3
# a frame is compared with this many of the last kept frames, not the last alone (a camera back at a view
# after a jolt elsewhere)
NEARBY = 3
BLUR_SIGMA = 1.5   # thumbnail pixels: the low-pass under which a motion-blurred copy matches its sharp view
BLUR_CHANGE = 2.0  # low-passed, a blurred copy differs by less than this many times min_change
BLUR_RATIO = 0.5   # a copy with less than this fraction of the sharper one's focus measure is a blurred copy
_FRAME_RE = re.compile(r"^frame_\d{5}\.png$")   # the only files this module writes (and removes)


def sharpness(rgb: np.ndarray, max_side: int = 320) -> float:
    """Variance of the Laplacian of the grey image (higher = sharper). rgb: HxWx3 uint8."""
    import cv2

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    s = max_side / max(grey.shape)
    if s < 1:
        grey = cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def thumbnail(rgb: np.ndarray, side: int = THUMB_SIDE) -> np.ndarray:
    """Grey uint8 thumbnail, longest side `side` (area-averaged: codec noise averages out, motion stays)."""
    import cv2

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    s = side / max(grey.shape)
    return cv2.resize(grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else grey


def change(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two thumbnails (grey levels); inf when their shapes differ."""
    if a.shape != b.shape:
        return float("inf")
    return float(np.mean(np.abs(a.astype(np.float32) - b.astype(np.float32))))


def open_video(path: Path):
    """An open PyAV container with at least one video stream (the caller closes it); InputError naming the
    file when it is missing, unreadable or has no video stream."""
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
    cc = container.streams.video[0].codec_context
    if cc.width and cc.height:   # declared frame size, checked before a frame is decoded (0: not declared)
        try:
            check_pixels(cc.width, cc.height, path, "video frame")
        except InputError:
            container.close()
            raise
    return container


def _check_frame_count(n: int, path: Path, container=None) -> None:
    """InputError naming the video when it has more than `limits.MAX_VIDEO_FRAMES` frames: `n` is the count its
    header declares (with `container`, closed first; 0 = not declared) or the frames decoded so far. A bound on
    the time the scoring pass decodes for (a still scene compresses to ~20 bytes a frame: a few MB can hold
    hours); its memory is bounded by `MAX_SCORED` whatever the length."""
    from splattwin import limits

    limit = limits.MAX_VIDEO_FRAMES
    if not n or n <= limit:
        return
    if container is not None:
        container.close()
    count = f"{n} frames (its header says)" if container is not None else f"more than {limit} frames"
    raise InputError(f"video has {count}; a capture may have at most {limit} (every frame is decoded to score "
                     f"it; set SPLATTWIN_MAX_VIDEO_FRAMES to allow more): cut the clip to the part that films the "
                     f"scene, or lower its frame rate", path)


def quarter_turns(rotation) -> int:
    """np.rot90's k that shows a frame upright, from PyAV's `frame.rotation` (degrees counter-clockwise
    of the display matrix, as ffmpeg's autorotate reads it: -90 = turn 90 degrees clockwise). Checked on a
    phone-style MP4 (tkhd matrix): np.rot90(frame, rotation // 90) equals the photo it was made from."""
    r = float(rotation or 0)
    k = round(r / 90.0)
    if abs(r - 90 * k) > 1:   # not a quarter turn: no phone writes it; shown as stored
        log.warning("video display rotation %.1f degrees is not a multiple of 90; frames kept as stored", r)
        return 0
    return k % 4


def _upright(frame, path: Path | None = None) -> tuple[np.ndarray, int]:
    """The frame as upright RGB uint8 [h, w, 3] and the quarter turns applied. Its size is checked (MAX_IMAGE_PIXELS,
    as a photo's) before the RGB copy: a stream whose frames are larger than its header says is no exception."""
    check_pixels(frame.width, frame.height, path, "video frame")
    k = quarter_turns(getattr(frame, "rotation", 0))
    rgb = frame.to_ndarray(format="rgb24")
    return (np.ascontiguousarray(np.rot90(rgb, k)) if k else rgb), k


def select_frames(scores: np.ndarray, max_frames: int, thumbs: list[np.ndarray] | None = None,
                  min_change: float = MIN_CHANGE) -> list[int]:
    """Indices of the sharpest frame in each of `max_frames` equal windows over `len(scores)` frames.

    thumbs (one per frame, `thumbnail`): each window gives its sharpest frame that is a new view, or none.
    A frame is not a new view beside one of the last `NEARBY` kept frames when it differs from it by less
    than `min_change` (`change`: a copy), or when it is a blurred copy of it (`_blur_relation`). A frame
    whose only kept neighbour is a blurred copy of it takes that frame's place. So a camera that pauses,
    with motion-blurred frames while it settles, gives the pause's sharpest frame once (the last kept frame
    alone was compared: a blurred frame passed as new, and the next sharp copy passed against it). Without
    thumbs (or min_change 0) every window gives its sharpest frame."""
    n = len(scores)
    if n == 0:
        return []
    scores = np.asarray(scores, dtype=np.float64)
    k = min(max_frames, n)
    edges = np.linspace(0, n, k + 1).round().astype(int)
    keep: list[int] = []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        order = a + np.argsort(-scores[a:b], kind="stable")
        if thumbs is None or min_change <= 0 or not keep:
            keep.append(int(order[0]))
            continue
        for i in (int(j) for j in order):
            near = keep[-NEARBY:]
            if any(change(thumbs[i], thumbs[j]) < min_change
                   or _blur_relation(thumbs[i], thumbs[j], scores[i], scores[j], min_change) == "blurred"
                   for j in near):
                continue   # a copy, or a blurred copy, of a kept view: the window's next candidate
            if _blur_relation(thumbs[i], thumbs[keep[-1]], scores[i], scores[keep[-1]], min_change) == "sharper":
                keep[-1] = i   # the kept frame was a blurred copy of this one
            else:
                keep.append(i)
            break
    return keep


def _blur_relation(a: np.ndarray, b: np.ndarray, score_a: float, score_b: float,
                   min_change: float) -> str | None:
    """"blurred" when thumbnail `a` shows b's view blurred, "sharper" when the other way round, else None.

    The same view: low-passed (`BLUR_SIGMA`), which a motion blur barely changes, the thumbnails differ by
    less than `BLUR_CHANGE` x `min_change`; blurred: its focus measure (`sharpness`) below `BLUR_RATIO` of
    the other's. Measured on 9 real photos (cake, statue, british_museum at 682 px wide), horizontal blur
    of 15 / 31 px: 1.4-5.2 / 4.5-13.6 grey levels on the thumbnails, 0.17-0.61 / 0.49-2.2 low-passed,
    focus 0.17-0.34 / 0.09-0.24 of the sharp frame's; a pan of 1 / 2 px: 0.35-0.81 / 0.70-1.6 low-passed,
    focus unchanged (sharp frames of a still camera vary by < 10 %)."""
    import cv2

    if a.shape != b.shape:
        return None
    lo_a, lo_b = (cv2.GaussianBlur(t.astype(np.float32), (0, 0), BLUR_SIGMA) for t in (a, b))
    if change(lo_a, lo_b) >= BLUR_CHANGE * min_change:
        return None
    if score_a < BLUR_RATIO * score_b:
        return "blurred"
    if score_b < BLUR_RATIO * score_a:
        return "sharper"
    return None


def _read_record(index: Path) -> dict | None:
    """The folder's frames.json, or None when it is not one (bounded: the folder may be someone else's)."""
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    try:
        rec = read_json(index, "no frames record", MAX_RECORD_BYTES)
    except (InputError, OSError):
        return None
    return rec if isinstance(rec, dict) else None


def _listed(rec: dict | None) -> list[str]:
    """The frame files a record lists, this module's names only (the record lives in a user's folder)."""
    names = rec.get("frames") if rec else None
    if not isinstance(names, list):
        return []
    return [n for n in names if isinstance(n, str) and _FRAME_RE.match(n)]


def extract_frames(path: str | Path, out_dir: str | Path, max_frames: int = VIDEO_MAX_FRAMES,
                   min_change: float = MIN_CHANGE, progress: bool = True) -> list[Path]:
    """Write the selected frames as PNG into `out_dir` (frame_00000.png, ...) and their record
    `frames.json`; cached by video size/mtime and the settings. Returns the frames of this extraction
    only: a previous extraction's frames are removed when it is redone. progress: the scoring pass's
    progress bar / lines (`--no-progress`: none)."""
    from splattwin.progress import Progress

    path, out_dir = Path(path), Path(out_dir)
    check_max_frames(max_frames)
    check_min_change(min_change)
    stamp = {"video": str(path.resolve()), "size": path.stat().st_size if path.is_file() else None,
             "mtime": path.stat().st_mtime if path.is_file() else None, "max_frames": max_frames,
             "min_change": float(min_change), "method": METHOD}
    index = out_dir / "frames.json"
    old = _read_record(index) if index.is_file() else None
    if old is not None and old.get("stamp") == stamp:
        names = _listed(old)
        if names and len(names) == len(old.get("frames", [])) and all(
                (out_dir / n).is_file() and not (out_dir / n).is_symlink() for n in names):
            return [out_dir / n for n in names]
    # Pass 1: sharpness and a thumbnail of every frame (cheap, downscaled), of at most MAX_VIDEO_FRAMES frames
    container = open_video(path)
    _check_frame_count(container.streams.video[0].frames, path, container)
    # Frames scored: every `stride`-th; past MAX_SCORED of them every other one is dropped and the stride doubles,
    # so a long video keeps at most MAX_SCORED thumbnails (a 200 000-frame clip held 3.4 GB of them and failed).
    scores, thumbs, source, turns, stride, decoded = [], [], [], 0, 1, 0
    with Progress(container.streams.video[0].frames or None, f"scoring {path.name}", unit="frame",
                  enabled=progress) as prog:
        try:
            for i, frame in enumerate(container.decode(video=0)):
                decoded = i + 1
                _check_frame_count(decoded, path)   # the header's count may be missing (0) or wrong
                if i % stride == 0:
                    rgb, k = _upright(frame, path)
                    turns = turns or k
                    scores.append(sharpness(rgb))
                    thumbs.append(thumbnail(rgb))
                    source.append(i)
                    if len(source) > MAX_SCORED:
                        scores, thumbs, source, stride = scores[::2], thumbs[::2], source[::2], 2 * stride
                prog.update(1)
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 — PyAV decode errors have many types
            raise InputError(f"video decoding failed after {decoded} frames: {e}", path) from e
        finally:
            container.close()
    if stride > 1:
        log.info("%s: %d frames, every %d-th scored (at most %d are compared)", path.name, decoded, stride,
                 MAX_SCORED)
    if not scores:
        raise InputError("video has no decodable frames", path)
    if turns:
        log.info("%s is stored rotated (display matrix): frames turned upright, %s", path.name,
                 {1: "90 degrees counter-clockwise", 2: "180 degrees", 3: "90 degrees clockwise"}[turns])
    keep = [source[j] for j in select_frames(np.asarray(scores), max_frames, thumbs, min_change)]
    skipped = min(max_frames, len(scores)) - len(keep)
    if skipped:
        log.info("%s: %d window(s) gave no new view (every frame a copy of a kept one, within %g grey levels, "
                 "or a blurred copy: camera still)", path.name, skipped, min_change)
    del thumbs
    # The previous extraction's frames go first (a shorter or other video would leave them beside the new
    # ones); the record lists what is about to be written before it is, so a killed run leaves no file
    # that a later run would not know to remove.
    names = [f"frame_{i:05d}.png" for i in range(len(keep))]
    io.remove_files(out_dir, sorted(set(_listed(old)) - set(names)))
    for n in names:   # a folder in the way of a frame is not ours to remove (a link is replaced, not followed)
        p = out_dir / n
        if p.is_dir() and not p.is_symlink():
            raise InputError(f"{n} in the frames folder is a folder, not a frame; remove it or choose another "
                             f"folder", out_dir)
    io.write_json(index, {"stamp": None, "frames": names})
    container = open_video(path)
    want = {idx: name for idx, name in zip(keep, names)}
    written = 0
    try:
        for i, frame in enumerate(container.decode(video=0)):
            if i in want:
                io.write_image(out_dir / want[i], _upright(frame, path)[0])
                written += 1
            if written == len(keep):
                break
    finally:
        container.close()
    if written != len(keep):
        raise InputError(f"video decoded differently the second time ({written} of {len(keep)} frames)", path)
    io.write_json(index, {"stamp": stamp, "frames": names, "source_indices": keep,
                          "turned_ccw_deg": 90 * turns, "frames_decoded": decoded, "scored_every": stride})
    log.info("extracted %d of %d frames from %s into %s", len(names), decoded, path, out_dir)
    return [out_dir / n for n in names]


def read(path: str | Path, max_frames: int | None = None, out_dir: str | Path | None = None,
         min_change: float | None = None, progress: bool = True) -> Dataset:
    """A video as an unposed image dataset: the frames of this extraction (`extract_frames`, into
    `out_dir`, default `<stem>_frames/` beside the video). max_frames / min_change None: the defaults
    (`VIDEO_MAX_FRAMES`, `MIN_CHANGE`)."""
    from splattwin.capture import images

    path = Path(path)
    out = Path(out_dir) if out_dir is not None else path.parent / f"{path.stem}_frames"
    files = extract_frames(path, out, max_frames=VIDEO_MAX_FRAMES if max_frames is None else max_frames,
                           min_change=MIN_CHANGE if min_change is None else min_change, progress=progress)
    ds = images.read_files(files, root=out)
    decoded = (_read_record(out / "frames.json") or {}).get("frames_decoded")
    ds.meta.update({"format": "video", "video": str(path), "sequential": True,
                    "frames_decoded": decoded if isinstance(decoded, int) else None})
    return ds
