"""MP4 (H.264, yuv420p: plays in every browser, so the HTML report can embed it; the index first, "faststart",
so it plays while it downloads) through PyAV, which ships FFmpeg in its wheel. Written atomically: frames go
to a temporary file renamed on close.

Odd image sizes are padded by one black row/column (yuv420p needs even sizes); `read_mp4` crops back
when told the size.
"""

from __future__ import annotations

import os
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from splattwin.errors import InputError

MAX_FRAMES_READ = 200_000


class Mp4Writer:
    """Streaming writer: `with Mp4Writer(path, fps) as w: w.write(frame_uint8_HxWx3)`.

    crf: H.264 constant rate factor (0 lossless .. 51; 18 is visually lossless). The file appears at
    `path` only when the writer closes without an exception.
    """

    def __init__(self, path: str | Path, fps: float, crf: int = 18, codec: str = "libx264"):
        self.path = Path(path)
        self.fps = float(fps)
        if not 0 < self.fps <= 1000:
            raise ValueError(f"fps must be in (0, 1000], got {fps}")
        self.crf, self.codec = int(crf), codec
        self.frames = 0
        self._container = None
        self._stream = None
        self._tmp: Path | None = None
        self.size: tuple[int, int] | None = None   # (width, height) of the frames given

    def __enter__(self) -> "Mp4Writer":
        return self

    def _open(self, w: int, h: int) -> None:
        import av

        self.path.parent.mkdir(parents=True, exist_ok=True)
        from splattwin.io import temp_prefix

        # named as every temporary file of ours: a killed run's half video is removed by the next run
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(self.path.name), suffix=".mp4", dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        # the index (moov) before the frames: a player streaming the file over HTTP starts at once instead of
        # fetching its end first (FFmpeg's default writes the index last)
        self._container = av.open(str(self._tmp), mode="w", format="mp4", options={"movflags": "+faststart"})
        rate = Fraction(self.fps).limit_denominator(1001)
        s = self._container.add_stream(self.codec, rate=rate)
        s.width, s.height = w + (w % 2), h + (h % 2)
        s.pix_fmt = "yuv420p"
        s.options = {"crf": str(self.crf), "preset": "medium"} if "264" in self.codec else {}
        self._stream = s
        self.size = (w, h)

    def write(self, frame: np.ndarray) -> None:
        """Append one frame: uint8 [H,W,3] RGB (or float in [0,1])."""
        import av

        a = np.asarray(frame)
        if a.dtype != np.uint8:
            a = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"frames must be [H,W,3], got {a.shape}")
        h, w = a.shape[:2]
        if self._container is None:
            self._open(w, h)
        elif (w, h) != self.size:
            raise ValueError(f"frame size {w}x{h} differs from the first frame's {self.size[0]}x{self.size[1]}")
        if w % 2 or h % 2:
            a = np.pad(a, ((0, h % 2), (0, w % 2), (0, 0)))
        vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(a), format="rgb24")
        for pkt in self._stream.encode(vf):
            self._container.mux(pkt)
        self.frames += 1

    def close(self, ok: bool = True) -> Path | None:
        if self._container is None:
            if ok:
                raise ValueError(f"no frames written to {self.path}")
            return None
        try:
            if ok:
                for pkt in self._stream.encode():
                    self._container.mux(pkt)
            self._container.close()
            if ok:
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(self._tmp, 0o666 & ~umask)
                os.replace(self._tmp, self.path)
        finally:
            self._container = None
            if self._tmp is not None and self._tmp.exists():
                self._tmp.unlink()
        return self.path if ok else None

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(ok=exc_type is None)


def write_mp4(path: str | Path, frames, fps: float, crf: int = 18) -> Path:
    """Write an iterable of uint8 [H,W,3] frames as an MP4, atomically. Returns the path."""
    with Mp4Writer(path, fps, crf=crf) as w:
        for f in frames:
            w.write(f)
    return Path(path)


def probe_mp4(path: str | Path) -> dict:
    """{frames, width, height, fps, codec, pix_fmt} of a video file (InputError if unreadable)."""
    import av

    path = Path(path)
    if not path.is_file():
        raise InputError("video file not found", path)
    try:
        with av.open(str(path)) as c:
            s = c.streams.video[0]
            n = s.frames or sum(1 for _ in c.decode(video=0))
            return {"frames": int(n), "width": int(s.codec_context.width), "height": int(s.codec_context.height),
                    "fps": float(s.average_rate or s.guessed_rate or 0), "codec": s.codec_context.name,
                    "pix_fmt": str(s.codec_context.pix_fmt)}
    except (av.error.FFmpegError, IndexError) as e:
        raise InputError(f"not a readable video: {e}", path) from e


def read_mp4(path: str | Path, size: tuple[int, int] | None = None, max_frames: int = MAX_FRAMES_READ) -> np.ndarray:
    """All frames as uint8 [T,H,W,3] RGB; `size` (width, height) crops the even-size padding away."""
    import av

    path = Path(path)
    if not path.is_file():
        raise InputError("video file not found", path)
    out = []
    try:
        with av.open(str(path)) as c:
            for fr in c.decode(video=0):
                a = fr.to_ndarray(format="rgb24")
                if size is not None:
                    a = a[:size[1], :size[0]]
                out.append(a)
                if len(out) > max_frames:
                    raise InputError(f"video has more than {max_frames} frames", path)
    except av.error.FFmpegError as e:
        raise InputError(f"not a readable video: {e}", path) from e
    if not out:
        raise InputError("video has no frames", path)
    return np.stack(out)
