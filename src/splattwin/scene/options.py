"""Options of the embedded tabletop scene: what to render (`SceneOptions`) and how the simulated
open-vocabulary segmenter errs (`MaskNoise`). Both are plain dataclasses recorded verbatim in scene.json.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

from splattwin.errors import InputError


@dataclass(frozen=True)
class MaskNoise:
    """Error model of the simulated open-vocabulary segmenter (one mask per view and object).

    Each (view, object) pair draws its own events from a generator seeded by (seed, view index, label),
    so masks do not change when other views are added. Probabilities are per (view, object) pair.

    Attributes:
        p_miss: probability the object is not detected at all (empty mask).
        p_partial: probability only part of the object is segmented: the pixels on one side of a random
            straight cut are kept, a fraction drawn uniformly from `partial_keep`.
        partial_keep: (min, max) fraction of the object's visible pixels kept by a partial detection.
        p_bleed: probability the mask bleeds across the object's boundary.
        bleed_px: (min, max) bleed distance in pixels (dilation radius).
        bleed_behind_only: bleeding spreads only onto surfaces *behind* the object (deeper than the
            object's nearby depth + `bleed_depth_margin`), as a box-prompted segmenter does; occluders in
            front are not swallowed.
        bleed_depth_margin: metres.
        p_blob: probability of one spurious blob elsewhere in the image (false positive).
        blob_radius_px: (min, max) blob radius in pixels at 320 px image width (scaled with width).
        boundary_jitter_px: standard deviation in pixels of the smooth random boundary wobble every
            detected mask gets (real masks never follow the silhouette exactly).
        min_visible_px: objects with fewer visible pixels than this are never detected (too small).
    """

    p_miss: float = 0.06
    p_partial: float = 0.08
    partial_keep: tuple[float, float] = (0.45, 0.8)
    p_bleed: float = 0.35
    bleed_px: tuple[int, int] = (2, 5)
    bleed_behind_only: bool = True
    bleed_depth_margin: float = 0.01
    p_blob: float = 0.12
    blob_radius_px: tuple[float, float] = (4.0, 10.0)
    boundary_jitter_px: float = 0.7
    min_visible_px: int = 12

    def validate(self) -> None:
        for name in ("p_miss", "p_partial", "p_bleed", "p_blob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"mask noise {name} must be a probability in [0, 1], got {v}")
        for name in ("partial_keep", "bleed_px", "blob_radius_px"):
            lo, hi = getattr(self, name)
            if lo < 0 or hi < lo:
                raise InputError(f"mask noise {name} must be a (min, max) range with 0 <= min <= max, got {(lo, hi)}")
        if self.partial_keep[1] > 1.0:
            raise InputError(f"mask noise partial_keep must lie in [0, 1], got {self.partial_keep}")
        if self.boundary_jitter_px < 0 or self.bleed_depth_margin < 0 or self.min_visible_px < 0:
            raise InputError("mask noise boundary_jitter_px, bleed_depth_margin and min_visible_px must be >= 0")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> MaskNoise:
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names})

    @classmethod
    def clean(cls) -> MaskNoise:
        """A perfect segmenter (noisy masks == GT masks, up to objects below `min_visible_px`)."""
        return cls(p_miss=0.0, p_partial=0.0, p_bleed=0.0, p_blob=0.0, boundary_jitter_px=0.0, min_visible_px=0)


@dataclass(frozen=True)
class SceneOptions:
    """What the generator renders.

    Attributes:
        seed: seeds the layout, the camera jitter, the textures and the mask noise.
        width, height: image size in pixels.
        views: number of training views; heldout: number of held-out views interleaved between them.
        marker: print an ArUco marker (DICT_4X4_50, id `marker_id`) of side `marker_size` metres on the table.
        fov_x: horizontal field of view, radians.
        supersample: rays per pixel side for the RGB image (a box filter over the pixel, as a sensor integrates
            light over its area); GT depth/labels use pixel centres. 5 by default: the wood grain and the 2 mm
            speckle are above the pixel rate on the far table, and with 2x2 samples the held-out views
            carry moire that no other view predicts (heldout_004 at 320x240: SSIM 0.955 against a 12x12
            reference, 0.998 at 5x5; a splat trained on 2x2 images scored held-out SSIM 0.921, on 5x5
            images 0.953).
        shadows: cast shadows from the directional light.
        noise: the simulated segmenter's error model.
    """

    seed: int = 0
    width: int = 320
    height: int = 240
    views: int = 15
    heldout: int = 5
    marker: bool = False
    marker_id: int = 0
    marker_size: float = 0.08
    fov_x: float = math.radians(70.0)
    supersample: int = 5
    shadows: bool = True
    noise: MaskNoise = field(default_factory=MaskNoise)

    def validate(self) -> None:
        if not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"scene option seed must be a non-negative integer, got {self.seed!r}")
        if self.width < 16 or self.height < 16:
            raise InputError(f"scene option width/height must be at least 16 pixels, got {self.width}x{self.height}")
        if self.width > 8192 or self.height > 8192:
            raise InputError(f"scene option width/height must be at most 8192 pixels, got {self.width}x{self.height}")
        if self.views < 1:
            raise InputError(f"scene option views must be at least 1, got {self.views}")
        if self.heldout < 0:
            raise InputError(f"scene option heldout must be >= 0, got {self.heldout}")
        if self.heldout > 0 and self.views < 2:
            raise InputError("held-out views are interleaved between training views: need views >= 2")
        if self.views + self.heldout > 500:
            raise InputError(f"scene option views + heldout must be at most 500, got {self.views + self.heldout}")
        if not 0 <= self.marker_id < 50:
            raise InputError(f"scene option marker_id must be in [0, 50) for DICT_4X4_50, got {self.marker_id}")
        if not 0.02 <= self.marker_size <= 0.15:
            raise InputError(f"scene option marker_size must be in [0.02, 0.15] m, got {self.marker_size}")
        if not math.radians(10) <= self.fov_x <= math.radians(150):
            raise InputError(f"scene option fov_x must be in [10, 150] degrees, got {math.degrees(self.fov_x):.1f}")
        if not 1 <= self.supersample <= 8:
            raise InputError(f"scene option supersample must be in [1, 8], got {self.supersample}")
        self.noise.validate()

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["noise"] = self.noise.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SceneOptions:
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if isinstance(kw.get("noise"), dict):
            kw["noise"] = MaskNoise.from_dict(kw["noise"])
        return cls(**kw)
