"""Options of the embedded tabletop scene: what to render (`SceneOptions`), how the simulated
open-vocabulary segmenter errs (`MaskNoise`), and the robot-style capture `scene generate --robot-capture`
writes instead (`RobotCaptureOptions`, see `splattwin.scene.robot_capture`). Plain dataclasses recorded
verbatim in scene.json.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from splattwin.errors import InputError
from splattwin.options import option


@dataclass(frozen=True)
class MaskNoise:
    """Error model of the simulated open-vocabulary segmenter (one mask per view and object).

    Each (view, object) pair draws its own events from a generator seeded by (seed, view index, label),
    so masks do not change when other views are added. Probabilities are per (view, object) pair. A
    partial detection keeps the pixels on one side of a random straight cut. Bleeding spreads only onto
    surfaces *behind* the object (deeper than its nearby depth + `bleed_depth_margin`) when
    `bleed_behind_only`, as a box-prompted segmenter does; occluders in front are not swallowed.
    """

    p_miss: float = option(0.06, "probability the object is not detected at all (empty mask)")
    p_partial: float = option(0.08, "probability only part of the object is segmented")
    partial_keep: tuple[float, float] = option((0.45, 0.8), "(min, max) fraction of the visible pixels a partial "
                                                "detection keeps")
    p_bleed: float = option(0.35, "probability the mask bleeds across the object's boundary")
    bleed_px: tuple[int, int] = option((2, 5), "(min, max) bleed distance (dilation radius)", unit="px")
    bleed_behind_only: bool = option(True, "bleeding spreads only onto surfaces behind the object")
    bleed_depth_margin: float = option(0.01, "depth margin of 'behind' for bleeding", unit="m")
    p_blob: float = option(0.12, "probability of one spurious blob elsewhere in the image (false positive)")
    blob_radius_px: tuple[float, float] = option((4.0, 10.0), "(min, max) blob radius at 320 px image width "
                                                 "(scaled with the width)", unit="px")
    boundary_jitter_px: float = option(0.7, "standard deviation of the smooth random boundary wobble every "
                                       "detected mask gets", unit="px")
    min_visible_px: int = option(12, "objects with fewer visible pixels are never detected", unit="px")

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

    supersample: rays per pixel side for the RGB image (a box filter over the pixel, as a sensor integrates
    light over its area); GT depth/labels use pixel centres. 5 by default: the wood grain and the 2 mm
    speckle are above the pixel rate on the far table, and with 2x2 samples the held-out views carry
    moire that no other view predicts (heldout_004 at 320x240: SSIM 0.955 against a 12x12 reference,
    0.998 at 5x5; a splat trained on 2x2 images scored held-out SSIM 0.921, on 5x5 images 0.953).
    """

    seed: int = option(0, "layout / texture / camera jitter / mask noise seed")
    width: int = option(320, "image width", unit="px", build_alias="width")
    height: int = option(240, "image height", unit="px", build_alias="height")
    views: int = option(15, "training views", build_alias="views")
    heldout: int = option(5, "held-out views interleaved with the training views (demo: --scene.heldout; --heldout "
                          "there is the poses stage's hold-out, which re-splits the views)")
    marker: bool = option(False, "print an ArUco marker (DICT_4X4_50, id marker_id) on the table")
    marker_id: int = option(0, "ArUco marker id (DICT_4X4_50)")
    marker_size: float = option(0.08, "marker side", unit="m")
    fov_x: float = option(math.radians(70.0), "horizontal field of view", unit="rad", flag="fov", degrees=True)
    supersample: int = option(5, "rays per pixel side, box-filtered (anti-aliasing; 1-8)")
    shadows: bool = option(True, "cast shadows from the directional light")
    noise: MaskNoise = option(factory=MaskNoise, help="the simulated segmenter's error model")

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


@dataclass(frozen=True)
class DepthNoise:
    """D435-like error model of the robot capture's depth maps (`splattwin.scene.depth_noise`).

    Applied to the ray-cast z-depth before it is written as 16-bit millimetres; every lost reading is 0
    in the PNG, as a RealSense writes it. Each view draws from a generator seeded by (scene seed, view
    index), so a capture is reproducible. Pixel sizes are at the D435's 640 px colour width and scale
    with the image width.

    - Axial noise: RMS error sigma(z) = rms_1m * z^2 (z in m), Gaussian, spatially correlated over
      `noise_corr_px` (stereo block matching). Intel's model (white paper "Tuning depth cameras for best
      performance"): RMS = z^2 * subpixel / (f * B); D435 f ~ 424 px at 848 px (90 deg HFOV), B = 50 mm,
      subpixel 0.08 (well-textured best case) to ~0.2: 3.8-9.4 mm at 1 m. The D4xx data sheet's bound is
      2 % at 2 m, i.e. ~1 % at 1 m: rms_1m = 0.01 m (4.9 mm at the capture's 0.7 m, 1.6 mm at 0.4 m).
    - Edge fattening: within `fattening_px` of a depth discontinuity the nearer surface spreads onto the
      farther one (the matching window straddles the edge).
    - Occlusion shadows: background the right imager (`baseline` to the camera's +x) cannot see is lost,
      a band on the left of near objects as wide as their disparity step f * B * (1/z_near - 1/z_far).
    - Edge holes: ragged dropouts within `edge_hole_px` of a discontinuity (a step over `edge_jump`
      between neighbours, or next to no return), about `edge_hole_prob` of that band.
    - Blobs: `blob_fraction` of the pixels lost in smooth random blobs of ~`blob_radius_px` (specular,
      dark or textureless patches).

    On the robot capture at 320x240 (cameras 0.65-0.8 m from the table centre) the defaults give a median
    |D - D_true| of 3.7 mm (mean 5.0 mm) and lose 4.6 % of the pixels that see a surface (bench/depth.py).
    """

    enabled: bool = option(True, "apply the D435-like error model (off: perfect ray-cast depth)")
    rms_1m: float = option(0.01, "axial RMS depth error at 1 m; grows with the depth squared", unit="m")
    noise_corr_px: float = option(1.0, "spatial correlation of the axial noise (Gaussian sigma) at 640 px width",
                                  unit="px")
    fattening_px: float = option(2.0, "the nearer surface spreads this far across a depth edge, at 640 px width",
                                 unit="px")
    baseline: float = option(0.05, "stereo baseline (right imager at the camera's +x): occlusion-shadow holes "
                             "(0: none)", unit="m")
    edge_jump: float = option(0.02, "a depth step larger than this between neighbouring pixels is an edge",
                              unit="m")
    edge_hole_px: float = option(3.0, "edge holes lie within this distance of an edge, at 640 px width", unit="px")
    edge_hole_prob: float = option(0.5, "fraction of the edge band lost (ragged: a smooth random field)")
    blob_fraction: float = option(0.01, "fraction of the pixels lost in random blobs")
    blob_radius_px: float = option(8.0, "typical blob radius at 640 px width", unit="px")

    def validate(self) -> None:
        for name in ("rms_1m", "noise_corr_px", "fattening_px", "baseline", "edge_jump", "edge_hole_px",
                     "blob_radius_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"depth noise {name} must be a finite number >= 0, got {v}")
        if self.rms_1m > 0.2 or self.baseline > 1.0:
            raise InputError(f"depth noise rms_1m must be <= 0.2 m and baseline <= 1 m, got {self.rms_1m}, "
                             f"{self.baseline}")
        for name in ("edge_hole_prob", "blob_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"depth noise {name} must be a fraction in [0, 1], got {v}")
        if self.blob_fraction > 0.5:
            raise InputError(f"depth noise blob_fraction must be at most 0.5, got {self.blob_fraction}")

    @classmethod
    def perfect(cls) -> DepthNoise:
        """Ray-cast depth as it is (mm rounding only)."""
        return cls(enabled=False)


WORLDS = ("z-down", "z-up")
FORMATS = ("bop", "tum")


@dataclass(frozen=True)
class RobotCaptureOptions:
    """What the robot-style capture looks like (`splattwin.scene.robot_capture.write_robot_capture`).

    views, width, height: frames and image size (D435 intrinsics scaled to it; 4:3 expected); on `scene
    generate` they come from the scene's --views, --width, --height. world: "z-down" (the scene's world
    rotated 180 degrees about x) or "z-up" (the scene's own world). format: "bop" or "tum". depth_noise:
    the D435-like error model of the depth maps (`DepthNoise`; `DepthNoise.perfect()` for ray-cast depth).
    """

    views: int = option(16, "frames", cli=False)
    width: int = option(640, "image width", unit="px", cli=False)
    height: int = option(480, "image height", unit="px", cli=False)
    format: str = option("bop", "given on `scene generate`: write a robot-style RGB-D capture instead of the scene "
                         "(D435-like camera, 16-bit depth in mm, per-instance masks, known poses), as a BOP scene or "
                         "a TUM pose list", choices=FORMATS, aliases=("robot-capture",))
    world: str = option("z-down", "world of the capture's poses (z-down: the scene's world rotated 180 deg about x)",
                        choices=WORLDS, aliases=("robot-world",))
    distance: tuple[float, float] = option((0.65, 0.80), "(min, max) camera distance from the look-at point", unit="m")
    elevation: tuple[float, float] = option((50.0, 70.0), "(min, max) camera elevation above the table", unit="deg")
    roll_deg: float = option(20.0, "largest wrist roll about the optical axis", unit="deg")
    depth_noise: DepthNoise = option(factory=DepthNoise, help="D435-like depth errors: axial noise ~z^2, holes "
                                     "at edges, occlusion shadows and blobs, edge fattening (default on; "
                                     "--no-robot-capture.depth_noise.enabled: perfect depth)")

    def validate(self) -> None:
        if not 3 <= self.views <= 500:
            raise InputError(f"robot capture views must be in [3, 500], got {self.views}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise InputError(f"robot capture size must be 16..4096 pixels, got {self.width}x{self.height}")
        if self.world not in WORLDS:
            raise InputError(f"robot capture world must be one of {', '.join(WORLDS)}, got {self.world!r}")
        if self.format not in FORMATS:
            raise InputError(f"robot capture format must be one of {', '.join(FORMATS)}, got {self.format!r}")
        self.depth_noise.validate()

    @classmethod
    def from_dict(cls, d: dict) -> RobotCaptureOptions:
        """The options as scene.json's `robot_capture` entry records them (other keys ignored; a record
        written before `depth_noise` existed had perfect depth)."""
        names = {f.name for f in fields(cls)}
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names}
        dn = kw.get("depth_noise")
        if isinstance(dn, dict):
            dn_names = {f.name for f in fields(DepthNoise)}
            kw["depth_noise"] = DepthNoise(**{k: v for k, v in dn.items() if k in dn_names})
        elif "depth_noise" not in kw:
            kw["depth_noise"] = DepthNoise.perfect()
        return cls(**kw)
