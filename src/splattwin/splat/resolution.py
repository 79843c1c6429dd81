"""The image size training (and, by default, evaluation) runs at.

`TrainConfig.resolution` follows 3DGS's `-r`: 1, 2, 4, 8 divide the image size; a larger value is a
target width in pixels; -1 downsizes only images wider than 1600 px. 0 ("auto", the default) depends on
where training runs: on the CPU every image whose longest side exceeds `TrainConfig.cpu_max_side`
(640 px by default) is scaled down to it (a 12-megapixel photo trained at full size would take days on
our CPU rasterizer, and sparse captures gain little from it); with CUDA the images are used at full size.
The embedded scene (320 x 240) is below the cap and is trained unchanged.

`Resolution` is the rule resolved for one device; `scale(width, height)` is the factor applied to an
image of that size. train.json records the rule (`record`) so that evaluation renders the held-out views
at the same size (`splattwin.splat.eval`; `--eval-full-resolution` for the full image size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from splattwin.errors import InputError

AUTO = 0
MIN_SIDE = 16
# Largest target width or side cap: JPEG's own limit on an image side. (A received train.json's target
# width of 100000 px made evaluation allocate 23 GB; the view sizes are also checked against
# splattwin.limits.MAX_IMAGE_PIXELS.)
MAX_SIDE = 65535


@dataclass(frozen=True)
class Resolution:
    """resolution: as TrainConfig.resolution but never AUTO; max_side: cap on the longest image side in
    px (None: no cap). how: one line for the log and the report. max_scale: cap on the factor (None: none;
    evaluation from a training record uses 1.0, since a held-out photo upsampled holds nothing more and a
    forged target width would size every view up to the pixel limit)."""

    resolution: int = 1
    max_side: int | None = None
    how: str = "full size"
    max_scale: float | None = None

    def scale(self, width: int, height: int) -> float:
        """Factor (<= 1 unless a target width asks for more) applied to a width x height image."""
        r = self.resolution
        if r in (1, 2, 4, 8):
            s = 1.0 / r
        elif r == -1:
            s = min(1.0, 1600.0 / width)
        elif MIN_SIDE <= r <= MAX_SIDE:
            s = r / width
        else:
            raise InputError(f"--resolution must be 0 (auto), 1, 2, 4, 8, a target width of {MIN_SIDE} to "
                             f"{MAX_SIDE} pixels, or -1; got {r}")
        if self.max_side is not None:
            s = min(s, self.max_side / max(width, height))
        if self.max_scale is not None:
            s = min(s, self.max_scale)
        return s

    def size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) in px at this resolution (as `Camera.scaled` rounds)."""
        s = self.scale(width, height)
        return max(1, int(round(width * s))), max(1, int(round(height * s)))

    def record(self) -> dict:
        return {"resolution": self.resolution, "max_side": self.max_side, "how": self.how}

    @classmethod
    def from_record(cls, rec: dict | None) -> "Resolution | None":
        """The rule train.json recorded (None when absent or malformed: older training folders)."""
        if not isinstance(rec, dict) or not isinstance(rec.get("resolution"), int):
            return None
        ms = rec.get("max_side")
        ms = ms if isinstance(ms, int) and ms >= MIN_SIDE else None
        return cls(rec["resolution"], ms, str(rec.get("how", ""))[:200])


FULL = Resolution(1, None, "full size")


def resolve(resolution: int, cpu_max_side: int, device: str) -> Resolution:
    """The rule for TrainConfig.resolution / cpu_max_side on `device` ("cpu" or "cuda")."""
    if resolution != AUTO:
        Resolution(resolution).scale(100, 100)  # InputError for an invalid value
        return Resolution(resolution, None, f"--resolution {resolution}")
    if device == "cuda":
        return Resolution(1, None, "auto: full size (CUDA)")
    if cpu_max_side < MIN_SIDE:
        raise InputError(f"--cpu-max-side must be at least {MIN_SIDE} px, got {cpu_max_side}")
    return Resolution(1, int(cpu_max_side), f"auto: longest side at most {cpu_max_side} px on the CPU "
                                            "(--resolution 1: full size)")


def describe_sizes(sizes: list[tuple[int, int]]) -> str:
    """'640x427' or '640x427, 480x640 (2 sizes)' for a list of (width, height)."""
    uniq = sorted(set(sizes), key=lambda s: (-s[0] * s[1], s))
    text = ", ".join(f"{w}x{h}" for w, h in uniq[:4]) + (", ..." if len(uniq) > 4 else "")
    return text + (f" ({len(uniq)} sizes)" if len(uniq) > 1 else "")


# -- the default Gaussian budget for a training size ----------------------------------------------------
BASE_PIXELS, BASE_INIT_POINTS, BASE_MAX_GAUSSIANS = 320 * 240, 24_000, 28_000
# the cap never goes below this: small images (320x240) gain from room to densify beyond the 24k initial
# Gaussians (+0.2 dB held-out on the embedded scene), while the sqrt law's larger caps at photo sizes cost
# real captures (statue at 360x640: 13.1 dB held-out with 69k vs 14.4 dB with 48k). See TrainConfig.
MIN_MAX_GAUSSIANS = 40_000


def capacity(n_pixels: float) -> tuple[int, int]:
    """Default (init_points, max_gaussians) for training images of n_pixels (mean): 24k / 28k at 320x240,
    scaled with sqrt(n_pixels / (320 x 240)) above (2x at 640x480), the cap at least MIN_MAX_GAUSSIANS (40k:
    the cap is 40k up to ~460x345, 48k at 360x640, 56k at 640x480)."""
    s = max(1.0, math.sqrt(n_pixels / BASE_PIXELS))
    return int(round(BASE_INIT_POINTS * s, -3)), max(MIN_MAX_GAUSSIANS, int(round(BASE_MAX_GAUSSIANS * s, -3)))
