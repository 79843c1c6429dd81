"""How many frames a capture gives (`--max-frames`) and which of a video's frames are near-duplicates
(`--min-change`): one small option dataclass, shared without importing a stage (light: no numpy) by
`capture frames` and the poses options (`poses`/`build`, which inherit it), with the defaults that
`splattwin.capture.video` extracts with."""

from __future__ import annotations

from dataclasses import dataclass

from splattwin.errors import InputError
from splattwin.options import option

# frames taken from a video when --max-frames is not given (the sharpest of each of that many windows)
VIDEO_MAX_FRAMES = 30
# grey levels (0..255), mean |difference| of 64-px grey thumbnails below which a frame is a near-duplicate
# of a recently kept one (capture.video: a still camera measured <= 0.16, a one-pixel pan >= 1.2); 0 keeps them
MIN_CHANGE = 1.0


@dataclass
class FrameOptions:
    """max_frames None: `VIDEO_MAX_FRAMES` for a video, every frame of any other capture."""

    max_frames: int | None = option(None, f"use at most N frames of the capture, evenly spaced (a video: the sharpest "
                                    f"frame of each of N equal windows; default {VIDEO_MAX_FRAMES} for a video, every "
                                    f"frame otherwise)", build_alias="max-frames")
    min_change: float = option(MIN_CHANGE, "video: skip a frame that differs from one of the last 3 kept ones by less "
                               "than this (mean absolute difference of 64-px grey thumbnails, grey levels 0-255), "
                               "or is a motion-blurred copy of one; 0 keeps near-duplicates and blurred copies",
                               build_alias="min-change")

    def check(self) -> None:
        """InputError for values no extraction can use, before any work (0 was silently taken as the default,
        a negative count failed inside numpy)."""
        check_max_frames(self.max_frames)
        check_min_change(self.min_change)


def check_max_frames(n) -> None:
    """InputError unless `n` is None (the default) or a whole number >= 1."""
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise InputError(f"--max-frames must be >= 1, got {n}")


def check_min_change(x) -> None:
    """InputError unless `x` is a finite number >= 0 (grey levels)."""
    import math

    if isinstance(x, bool) or not isinstance(x, (int, float)) or not (x >= 0 and math.isfinite(x)):
        raise InputError(f"--min-change must be a number >= 0, got {x}")
