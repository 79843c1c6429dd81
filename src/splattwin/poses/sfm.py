"""Structure from motion with pycolmap on the CPU: SIFT extraction, matching, incremental mapping.

The result is in COLMAP's arbitrary (unscaled) world frame; `splattwin.poses.estimate` turns it into a
metric table frame.

Scaling to real photos:
- Features are extracted from images resized to `max_image_size` (longest side, default 1600 px; COLMAP
  maps keypoints back to full-size pixels) with at most `max_num_features` per image, on all cores but no
  more extraction threads than the memory budget allows (`extraction_threads`).
- The matcher follows the capture (`choose_matcher`): exhaustive for small sets (short videos too), beyond
  them sequential with loop closure for ordered frames (video), vocabulary-tree retrieval for unordered ones. Loop closure and
  retrieval use a visual vocabulary built from the capture's own descriptors (no download).
- One COLMAP camera per group of images that share a size and EXIF camera (make, model, focal length):
  a phone capture gets one shared camera, internet photos one per camera/size (`camera_groups`).
- Every pycolmap step runs in a child process (`colmap_process`): Ctrl-C stops it within a second, and
  progress shows live in a terminal and as plain lines in a redirected log.

Hard captures (`retry=True`): when images stay unregistered, cheaper-first retries follow (`retry_plan`):
relaxed mapping thresholds plus merging of sub-models that share images; the EXIF focal length held fixed;
one shared camera for same-size images when per-image cameras were asked for; guided matching; more
features on small images. The attempt registering the most images wins (the earlier one on a tie), and
each image that still fails gets a reason from the match graph (`explain_failures`).

Registration sanity check (`check_registration`, `splattwin.poses.sanity`): after every attempt (and every
merge) images registered with too few observations, or posed inconsistently with a tabletop capture (at or
below the table plane, looking up or away from the scene the others look at), are dropped from the model
(de-registered, then bundle adjustment again) and reported with the reason; only the images that pass
count as registered, so the retries go on while any is dropped. Each dropped image the best model lacks is
re-registered against that trusted model once, as soon as every image it lacks is such a dropped one (before
further retries, which would re-extract or re-match to no avail), else after the attempts
(`recover_dropped`: absolute pose from its
matches to the model's points, the homography its matches induce through the model's table plane, else
structure-less resectioning; refined, and kept only if it passes the check again, is no parallax-free
copy of another camera and, for numbered video frames walking around the scene, lies between its
neighbouring frames); the "recover" entry of the attempts says what came back and how.

The default thresholds suit sparse captures (8-20 views): a lower SIFT peak threshold and a looser ratio
test than COLMAP's (more matches per wide-baseline pair), fewer inliers for the initial pair and for
registering images, and frequent global bundle adjustment (cheap with few images).

Resume: the COLMAP databases, the attempts and the final model live in `work_dir`; a killed run re-uses
the features and matches already committed (COLMAP skips images/pairs it has), finished attempts
(attempts.json) and a finished model (sparse/done).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, invert_se3
from splattwin.errors import InputError
from splattwin.poses import colmap_process
from splattwin.poses.options import MATCHERS, check_sfm_limits
from splattwin.poses.progress import StageProgress

log = logging.getLogger(__name__)

_ADVICE = ("try: more overlap between views (each part of the table seen from >= 3 views, "
           "neighbouring views 15-30 degrees apart), more texture in the scene, known intrinsics "
           "(--intrinsics fx,fy,cx,cy), or known/robot poses (build --poses known / poses --method known, "
           "--robot-poses)")

# Relaxed retries map with this many random seeds (keeping the best) on captures of up to this many
# images: mapping then takes < 1 s per run, and on the cake photos (guided matches) single runs registered
# 6, 8, 8, 6, 6, 7 of 8 images with seeds 1-6.
MAPPING_SEEDS, MAPPING_SEEDS_MAX_IMAGES = 4, 100
LARGE_SIDE = 1400  # px: images at least this large (after the size bound) skip SIFT's upsampled octave
_MAX_IMAGE_ID = 2147483647  # COLMAP pair_id = id1 * this + id2 (id1 < id2)


@dataclass
class SfmOptions:
    """Knobs for `run_sfm`.

    intrinsics: (fx, fy, cx, cy) in pixels, known and kept fixed (all images must share a size); None =
      estimate: one camera per group of images with the same size and EXIF camera (see shared_intrinsics).
    camera_model: COLMAP model when intrinsics are estimated (SIMPLE_RADIAL, SIMPLE_PINHOLE, PINHOLE, OPENCV).
    shared_intrinsics: True = one camera per size/EXIF group; False = one camera per image.
    max_image_size: longest side (px) images are resized to for feature extraction (keypoints are in
      full-size pixels); <= 0: full size.
    max_num_features: SIFT features kept per image (the strongest).
    matcher: "auto" (`choose_matcher`), "exhaustive", "sequential" (+ loop closure) or "retrieval".
    ordered: the images are frames in capture order (video); None = unknown (treated as unordered).
    exhaustive_max_images: "auto" matches all pairs up to this many images.
    sequential_overlap: sequential matching pairs each frame with this many following frames.
    loop_closure: sequential matching also pairs frames that look alike (visual vocabulary).
    retrieval_neighbours: retrieval matching pairs each image with this many most similar ones.
    retry: retry hard captures (see the module docstring) while images are unregistered.
    check_registration: after each attempt, images whose poses fail the registration sanity check
      (`splattwin.poses.sanity`: too few observations; for a tabletop capture at or below the table plane,
      looking up while the others look down, or away from the scene) are dropped from the model, reported
      with the reason and count as unregistered (so the retries go on).
    min_observations: that check's minimum number of model points an image must observe.
    recover_dropped: re-register each image the check dropped (in any attempt) and the best model lacks,
      against that (trusted) model: absolute pose, table-plane homography, else structure-less
      resectioning, refined and kept only if it passes the check again (colmap_worker's recover step).
      Once per run: as soon as the dropped images are all the best model lacks, else after the attempts.
    min_registered: fewer registered images than this -> InputError. None = all images but at most 3
      missing, >= 3.
    num_threads: CPU threads for extraction, matching and mapping; 0 = all cores.
    max_memory_gib: memory budget that bounds the number of parallel extraction threads.
    """

    intrinsics: tuple[float, float, float, float] | None = None
    camera_model: str = "SIMPLE_RADIAL"
    shared_intrinsics: bool = True
    max_image_size: int = 1600
    max_num_features: int = 4096
    matcher: str = "auto"
    ordered: bool | None = None
    exhaustive_max_images: int = 50
    sequential_overlap: int = 10
    loop_closure: bool = True
    retrieval_neighbours: int = 30
    peak_threshold: float = 0.004      # COLMAP default 0.0067: more features from small, low-res views
    max_ratio: float = 0.85            # COLMAP default 0.8: a looser ratio test, geometric verification filters
    min_two_view_inliers: int = 12     # COLMAP default 15
    retry: bool = True
    check_registration: bool = True    # drop registered images whose poses fail `splattwin.poses.sanity`
    min_observations: int = 30         # the sanity check's minimum of model points an image observes
                                       # (COLMAP's default abs_pose_min_num_inliers; see poses.sanity)
    recover_dropped: bool = True      # re-register the images the check dropped against the trusted model
    min_registered: int | None = None
    num_threads: int = 0
    max_memory_gib: float = 2.0
    seed: int = 0

    def validate(self) -> None:
        if self.matcher not in MATCHERS:
            raise InputError(f"unknown matcher {self.matcher!r} ({', '.join(MATCHERS)})")
        check_sfm_limits(self.max_image_size, self.max_num_features, self.num_threads)
        if self.max_memory_gib <= 0:
            raise InputError(f"the SfM memory budget must be positive, got {self.max_memory_gib} GiB")
        if self.sequential_overlap < 1 or self.retrieval_neighbours < 1:
            raise InputError(f"sequential overlap and retrieval neighbours must be >= 1, got "
                             f"{self.sequential_overlap} and {self.retrieval_neighbours}")


@dataclass
class SfmResult:
    """SfM output in COLMAP's world frame (arbitrary scale, T_world_cam OpenCV convention).

    cameras: name -> Camera for each registered image. unregistered: names that did not register.
    failures: unregistered name -> why (from the match graph, or why the registration sanity check dropped it). points_xyz [N,3] float64, points_rgb [N,3]
    uint8, points_error [N] px, points_track_len [N]. timings: seconds per stage (extract, match, map,
    retries). attempts: one dict per attempt (name, what changed, registered, seconds). matcher: the
    matcher used. camera_groups: one dict per COLMAP camera group (size, EXIF, images). peak_rss_gib:
    the largest resident memory of a pycolmap step.
    """

    cameras: dict[str, Camera]
    unregistered: list[str]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_error: np.ndarray
    points_track_len: np.ndarray
    mean_reproj_error: float
    timings: dict[str, float] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    attempts: list[dict] = field(default_factory=list)
    matcher: str = ""
    camera_groups: list[dict] = field(default_factory=list)
    peak_rss_gib: float = 0.0
    resumed_timings: dict[str, float] = field(default_factory=dict)  # of the run that made a re-used model
    registration_check: dict = field(default_factory=dict)  # RegistrationCheck.to_dict() of the final model

    @property
    def num_registered(self) -> int:
        return len(self.cameras)

    @property
    def num_total(self) -> int:
        return len(self.cameras) + len(self.unregistered)

    def report(self) -> dict:
        """JSON-ready summary for poses_report.json."""
        return {"registered": self.num_registered, "total": self.num_total, "matcher": self.matcher,
                "mean_reproj_error": self.mean_reproj_error, "num_points": int(len(self.points_xyz)),
                "timings": self.timings, "attempts": self.attempts, "failures": self.failures,
                **({"resumed_from_timings": self.resumed_timings} if self.resumed_timings else {}),
                "camera_groups": self.camera_groups, "peak_rss_gib": self.peak_rss_gib,
                "registration_check": self.registration_check}


# -- choices (pure functions, unit-tested) -----------------------------------------------------------------
LOOP_PERIOD, LOOP_IMAGES = 10, 30   # sequential matching: every 10th frame is matched with its 30 look-alikes


def sequential_pairs(n: int, overlap: int, loop_closure: bool) -> int:
    """How many image pairs sequential matching of `n` frames matches, at most (the progress total): each
    frame with the next `overlap` ones, and with loop closure every `LOOP_PERIOD`-th frame with up to
    `LOOP_IMAGES` others that look alike (pairs already matched are matched once, so it may end below).
    The total counted n x overlap and no loop-closure pairs: a log said 639/600."""
    pairs = sum(min(overlap, n - 1 - i) for i in range(n))
    if loop_closure:
        pairs += math.ceil(n / LOOP_PERIOD) * min(LOOP_IMAGES, n - 1)
    return min(pairs, n * (n - 1) // 2)


def choose_matcher(num_images: int, matcher: str = "auto", ordered: bool | None = None,
                   exhaustive_max_images: int = 50) -> str:
    """The matcher for a capture (as `--matcher`'s help says): all pairs while that is affordable, up to
    `exhaustive_max_images`, video frames included (the most robust, and a short walk around the object
    closes its loop: sequential matching with its overlap could miss the pairs between the last and the
    first frames); beyond, frames in capture order (video) are matched sequentially (each with its next
    frames, plus loop closure) and unordered photos by the pairs a vocabulary-tree retrieval proposes."""
    if matcher not in MATCHERS:
        raise InputError(f"unknown matcher {matcher!r} ({', '.join(MATCHERS)})")
    if matcher != "auto":
        return matcher
    if num_images <= exhaustive_max_images:
        return "exhaustive"
    return "sequential" if ordered else "retrieval"


def extraction_threads(num_threads: int, max_side: int, budget_gib: float, cpu_count: int | None = None) -> int:
    """Parallel SIFT extraction threads: all cores (num_threads 0) but no more than fit in the budget.

    Per thread COLMAP's CPU SIFT holds the float scale space of the image it works on: measured ~0.4 GiB
    per thread for 1600x900 photos upsampled 2x (first octave -1), i.e. ~17 float32 copies of the
    3200x1800 pixels. `max_side` is the side SIFT works on (2x the image for octave -1); we assume 16:9
    and keep 0.35 GiB for the process itself.
    """
    want = num_threads if num_threads > 0 else (cpu_count or _cpu_count())
    side = max(int(max_side), 64)
    per_thread = 17 * 4 * side * (side * 9 / 16) / 2**30
    fit = int((budget_gib - 0.35) // max(per_thread, 1e-6))
    return max(1, min(want, fit))


def _cpu_count() -> int:
    """Cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def _all_threads(opts: SfmOptions) -> int:
    return opts.num_threads if opts.num_threads > 0 else _cpu_count()


@dataclass
class CameraGroup:
    """Images that share one COLMAP camera: same size and EXIF camera (make, model, focal length)."""

    names: list[str]
    width: int
    height: int
    exif: dict = field(default_factory=dict)
    per_image: bool = False
    camera_model: str | None = None     # known intrinsics: COLMAP model and its parameters, held fixed
    camera_params: list[float] | None = None

    def to_dict(self) -> dict:
        d = {"size": [self.width, self.height], "exif": self.exif, "images": len(self.names),
             "first": self.names[0], "per_image": self.per_image}
        if self.camera_params is not None:
            d["known"] = {"model": self.camera_model, "params": list(self.camera_params)}
        return d


def read_exif_camera(path: Path) -> dict:
    """EXIF make, model and focal length (mm, and 35 mm equivalent) from an image header; {} if none."""
    from PIL import Image

    out: dict = {}
    try:
        with Image.open(path) as im:
            ex = im.getexif()
            if not ex:
                return out
            for tag, key in ((271, "make"), (272, "model")):
                v = ex.get(tag)
                if isinstance(v, str) and v.strip():
                    out[key] = v.strip()[:64]
            sub = ex.get_ifd(0x8769)
            for tag, key in ((37386, "focal_mm"), (41989, "focal_35mm")):
                v = sub.get(tag)
                try:
                    f = float(v)
                except (TypeError, ValueError):
                    continue
                if math.isfinite(f) and 0 < f < 10_000:
                    out[key] = round(f, 3)
    except Exception:  # EXIF is a hint only: unreadable EXIF must not stop SfM
        return {}
    return out


def camera_groups(paths: list[Path], names: list[str], opts: SfmOptions) -> list[CameraGroup]:
    """Group images into COLMAP cameras (see CameraGroup); names in the given order inside each group,
    groups ordered by their first image. Fixed intrinsics need one image size."""
    from splattwin.capture.dataset import image_size

    info = []
    for p, n in zip(paths, names):
        w, h = image_size(p)
        info.append((n, w, h, read_exif_camera(p)))
    if opts.intrinsics is not None:
        sizes = {(w, h) for _, w, h, _ in info}
        if len(sizes) > 1:
            raise InputError(f"known intrinsics (--intrinsics) need one image size, but the images have "
                             f"{len(sizes)} sizes: {', '.join(f'{w}x{h}' for w, h in sorted(sizes))}", paths[0].parent)
    if opts.intrinsics is not None:
        w, h = info[0][1], info[0][2]
        return [CameraGroup([n for n, *_ in info], w, h, info[0][3], camera_model="PINHOLE",
                            camera_params=[float(v) for v in opts.intrinsics])]
    if not opts.shared_intrinsics:
        return [CameraGroup([n], w, h, ex, per_image=True) for n, w, h, ex in info]
    groups: dict[tuple, CameraGroup] = {}
    for n, w, h, ex in info:
        key = (w, h, ex.get("make"), ex.get("model"), ex.get("focal_mm"), ex.get("focal_35mm"))
        if key not in groups:
            groups[key] = CameraGroup([], w, h, ex)
        groups[key].names.append(n)
    return list(groups.values())


# -- retry plan ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Attempt:
    """One SfM attempt: which features, matching and mapping settings (see `retry_plan`)."""

    name: str
    why: str
    features: str = "base"      # "base" | "more"
    cameras: str = "base"       # "base" | "shared"
    matching: str = "base"      # "base" | "guided"
    mapping: str = "default"    # "default" | "relaxed" | "fixed_focal"
    merge: bool = False

    @property
    def db_key(self) -> str:
        return f"{self.features}_{self.cameras}_{self.matching}"


def retry_plan(groups: list[CameraGroup], opts: SfmOptions, small_images: bool, exif_focal: bool) -> list[Attempt]:
    """Attempts in order, cheapest first. The first is the default run; retries only follow while images
    stay unregistered. Mapping-only retries re-use the features and matches; guided matching re-matches
    the same features; more features re-extracts (only worthwhile on small images, where the size bound
    did not already give the feature budget)."""
    plan = [Attempt("default", "default settings")]
    if not opts.retry:
        return plan
    plan.append(Attempt("relaxed", "relaxed initialisation and registration thresholds, sub-models merged",
                        mapping="relaxed", merge=True))
    same_size = len({(g.width, g.height) for g in groups}) == 1
    if not opts.shared_intrinsics and same_size and len(groups) > 1 and opts.intrinsics is None:
        plan.append(Attempt("shared_intrinsics", "one camera shared by all images (same size)", cameras="shared",
                            mapping="relaxed", merge=True))
    if exif_focal and opts.intrinsics is None:
        plan.append(Attempt("exif_focal", "focal length fixed to the EXIF value", mapping="fixed_focal", merge=True))
    plan.append(Attempt("guided", "guided matching (epipolar-guided re-matching of the same features)",
                        matching="guided", mapping="relaxed", merge=True))
    if small_images:
        plan.append(Attempt("more_features", "more features (lower SIFT threshold) on the small images, "
                                             "guided matching", features="more", matching="guided",
                            mapping="relaxed", merge=True))
    return plan


def first_octave(min_side: int, features: str = "base") -> int:
    """SIFT's first octave: -1 (image upsampled 2x, COLMAP's default) unless every image is at least
    `LARGE_SIDE` px after the size bound. Then the upsampled octave's small-scale features would be the
    first ones dropped by the feature cap anyway (COLMAP keeps the largest scales): on the statue photos
    (1600 px) octave 0 cut extraction from 14.9 to 4.7 CPU s and its memory from 0.97 to 0.35 GB with the
    same 9/9 registered; at ~1000 px (british_museum) it lost two thirds of the points, so it is kept there."""
    return 0 if features == "base" and min_side >= LARGE_SIDE else -1


def _extraction_options(opts: SfmOptions, features: str, threads: int, min_side: int) -> dict:
    o = {"num_threads": threads, "max_image_size": opts.max_image_size if opts.max_image_size > 0 else -1,
         "sift.max_num_features": opts.max_num_features, "sift.peak_threshold": opts.peak_threshold,
         "sift.first_octave": first_octave(min_side, features)}
    if features == "more":
        o["sift.max_num_features"] = 2 * opts.max_num_features
        o["sift.peak_threshold"] = opts.peak_threshold / 2
    return o


def _matching_options(opts: SfmOptions, matching: str, threads: int) -> tuple[dict, dict]:
    m = {"num_threads": threads, "sift.max_ratio": opts.max_ratio, "guided_matching": matching == "guided"}
    v = {"min_num_inliers": opts.min_two_view_inliers, "ransac.random_seed": opts.seed}
    return m, v


def mapping_options(opts: SfmOptions, n: int, mode: str = "default", threads: int = 1) -> dict:
    """IncrementalPipelineOptions for `mode` "default", "relaxed" or "fixed_focal" (relaxed + focal
    lengths held at their prior) as dotted attributes."""
    o: dict = {"num_threads": threads, "random_seed": opts.seed, "min_model_size": min(3, n),
               "multiple_models": True, "extract_colors": True,
               # COLMAP 4's structure-less registration fallback took 15-30 s per failing image on the
               # cake photos (8 views) and registered nothing the relaxed retry does not
               "structure_less_registration_fallback": False,
               "mapper.init_min_num_inliers": 50, "mapper.abs_pose_min_num_inliers": 20,
               "mapper.init_min_tri_angle": 8.0, "mapper.random_seed": opts.seed,
               # Global BA after every image: at <= a few dozen views it costs little and keeps drift out.
               "ba_global_frames_ratio": 1.0 + 1.0 / max(n, 2), "ba_global_points_ratio": 1.0 + 1.0 / max(n, 2)}
    if n > 100:  # large captures: COLMAP's own schedule (global BA when the model grew by 10 %)
        o.pop("ba_global_frames_ratio")
        o.pop("ba_global_points_ratio")
    if mode in ("relaxed", "fixed_focal"):
        # Wide baselines and weak texture: fewer inliers and a smaller angle suffice to start, and images
        # with few 2D-3D inliers are still tried (cake: 3/8 -> 8/8 registered with guided matching).
        # Two-view tracks are triangulated too: more 2D-3D correspondences for the next image.
        o.update({"min_num_matches": 10, "mapper.init_min_num_inliers": 15, "mapper.abs_pose_min_num_inliers": 6,
                  "mapper.abs_pose_min_inlier_ratio": 0.1, "mapper.abs_pose_max_error": 16.0,
                  "mapper.init_min_tri_angle": 2.0, "mapper.max_reg_trials": 5,
                  "triangulation.ignore_two_view_tracks": False})
    if mode == "fixed_focal" or opts.intrinsics is not None:
        o.update({"ba_refine_focal_length": False, "mapper.abs_pose_refine_focal_length": False})
    if opts.intrinsics is not None:
        o.update({"ba_refine_principal_point": False, "ba_refine_extra_params": False,
                  "mapper.abs_pose_refine_extra_params": False})
    return o


def frame_order(names: list[str], opts: SfmOptions) -> list[str]:
    """The names in capture order when they are numbered frames (each ends in a number, as a video's
    extracted frames do: frame000069.jpg), sorted by that number; [] when they are not (or ordered=False),
    so order-based checks do not apply."""
    import re

    if opts.ordered is False:
        return []
    nums = {}
    for n in names:
        m = re.search(r"(\d+)\D*$", Path(n).name)
        if m is None:
            return []
        nums[n] = int(m.group(1))
    if len(set(nums.values())) != len(names):
        return []
    return sorted(names, key=lambda n: nums[n])


def explain_failures(names: list[str], registered: set[str], keypoints: dict[str, int],
                     verified: dict[tuple[str, str], int], min_inliers: int, sub_models: list[set[str]] | None = None,
                     min_features: int = 100) -> dict[str, str]:
    """Why each unregistered image failed, from its features and its verified matches (inlier counts per
    image pair). sub_models: image sets of the smaller sub-models (not merged into the main one)."""
    out: dict[str, str] = {}
    for n in names:
        if n in registered:
            continue
        k = keypoints.get(n, 0)
        if k < min_features:
            out[n] = f"only {k} features: textureless, blurred or over-exposed"
            continue
        links = {(b if a == n else a): c for (a, b), c in verified.items() if n in (a, b) and c >= min_inliers}
        if not links:
            out[n] = (f"no verified matches with any other image ({k} features): it does not overlap the others "
                      "or the viewpoint/lighting differs too much")
            continue
        to_reg = {m: c for m, c in links.items() if m in registered}
        sub = next((s for s in sub_models or [] if n in s), None)
        if sub is not None:
            out[n] = (f"registered only in a separate sub-model of {len(sub)} images that shares too few images "
                      "with the main one to be merged")
        elif not to_reg:
            others = sorted(links, key=lambda m: -links[m])[:3]
            out[n] = f"matches only other unregistered images ({', '.join(others)}): a separate group of views"
        else:
            best = max(to_reg, key=lambda m: to_reg[m])
            out[n] = (f"its pose could not be estimated from the registered images (best: {to_reg[best]} inlier "
                      f"matches with {best}): too few of them see points of the model")
    return out


# -- the run ---------------------------------------------------------------------------------------------
def image_layout(image_paths: list[Path]) -> tuple[Path, list[str]]:
    """Common image folder and the names relative to it (COLMAP identifies images by these names).
    Symbolic links are not followed: a link's own name is the image's name (`paths.unfollowed`)."""
    from splattwin.paths import unfollowed

    paths = [unfollowed(p) for p in image_paths]
    root = Path(os.path.commonpath([str(p.parent) for p in paths]))
    names = [p.relative_to(root).as_posix() for p in paths]
    if len(set(names)) != len(names):
        raise InputError("duplicate image paths in the dataset", root)
    return root, names


def _feature_mask_names(image_paths: list[Path], image_root: Path, masks: dict[Path, Path] | None) -> dict[str, Path]:
    """{image name (as COLMAP names it, `image_layout`): mask} for the images of `masks`."""
    if not masks:
        return {}
    from splattwin.paths import unfollowed

    out = {}
    for p in image_paths:
        m = masks.get(p)
        if m is not None:
            out[unfollowed(p).relative_to(image_root).as_posix()] = Path(m)
    return out


def _write_feature_masks(work: Path, mask_names: dict[str, Path], image_root: Path, names: list[str]) -> Path:
    """The masks where COLMAP looks for them: <work>/feature_masks/<image name>.png (0 = no features), and an
    all-keep mask for every other image of `names` (COLMAP extracts nothing from an image without one)."""
    from splattwin.limits import image_size

    root = work / "feature_masks"
    for name in names:
        dst = root / f"{name}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        if name in mask_names:
            with io.atomic_path(dst) as tmp:
                shutil.copyfile(mask_names[name], tmp)
        else:
            w, h = image_size(image_root / name)
            io.write_image(dst, np.full((h, w), 255, np.uint8))
    return root


def _config_key(opts: SfmOptions, names: list[str]) -> dict:
    d = asdict(opts)
    for k in ("min_registered", "num_threads", "max_memory_gib", "retry"):
        d.pop(k)  # do not change what a finished step computed
    d["images"] = names
    return d


class SfmRun:
    """State of one `run_sfm` call: folders, databases, progress, accumulated timings."""

    def __init__(self, work: Path, image_root: Path, names: list[str], opts: SfmOptions, progress: StageProgress,
                 groups: list[CameraGroup] | None = None, matcher: str | None = None, pairs_file: Path | None = None):
        self.work, self.image_root, self.names, self.opts = work, image_root, names, opts
        self.progress = progress
        self.threads = _all_threads(opts)
        self.timings: dict[str, float] = {}
        self.peak = 0
        self.groups = groups if groups is not None else camera_groups([image_root / n for n in names], names, opts)
        self.matcher = matcher or choose_matcher(len(names), opts.matcher, opts.ordered, opts.exhaustive_max_images)
        self.pairs_file = pairs_file
        self.max_side = max(max(g.width, g.height) for g in self.groups)
        self.dropped: dict[str, str] = {}  # name -> why the sanity check dropped it (any attempt)
        self.mask_root: Path | None = None  # COLMAP's mask_path: <mask_root>/<image name>.png (`run_sfm` masks)
        self.recovery: dict = {}  # the recover step's result (colmap_worker.step_recover)

    def _add(self, key: str, stats: colmap_process.StepStats) -> None:
        self.timings[key] = self.timings.get(key, 0.0) + stats.seconds
        self.timings["cpu"] = self.timings.get("cpu", 0.0) + stats.cpu_seconds
        self.peak = max(self.peak, stats.peak_rss_bytes)

    def db_path(self, a: Attempt) -> Path:
        return self.work / ("database.db" if a.db_key == "base_base_base" else f"database_{a.db_key}.db")

    def _done(self, db: Path, stage: str) -> bool:
        return (db.parent / f"{db.stem}.{stage}.done").is_file()

    def _mark(self, db: Path, stage: str, info: dict) -> None:
        io.write_json(db.parent / f"{db.stem}.{stage}.done", info)

    # -- stages -------------------------------------------------------------------------------------
    def extract(self, a: Attempt, label: str) -> Path:
        db = self.db_path(a)
        if self._done(db, "extract"):
            return db
        same_features = self.db_path(Attempt("src", "", features=a.features, cameras=a.cameras))
        if same_features != db and self._done(same_features, "extract"):
            # re-matching only (guided): copy the features, drop the matches
            _copy_features(same_features, db)
            self._mark(db, "extract", io.read_record(db.parent / f"{same_features.stem}.extract.done") or {})
            return db
        o = self.opts
        bound = o.max_image_size if o.max_image_size > 0 else 1 << 30
        side = min(self.max_side, bound)
        min_side = min(min(max(g.width, g.height), bound) for g in self.groups)
        octave = first_octave(min_side, a.features)
        # the upsampled octave (-1) holds 4x the pixels: budget for the size SIFT actually works on
        threads = extraction_threads(o.num_threads, side * (2 if octave < 0 else 1), o.max_memory_gib)
        groups = [CameraGroup(sum((g.names for g in self.groups), []), self.groups[0].width, self.groups[0].height)] \
            if a.cameras == "shared" else self.groups
        job_groups = []
        for g in groups:
            jg = {"names": g.names, "camera_model": o.camera_model, "per_image": g.per_image}
            if g.camera_params is not None:
                jg.update(camera_model=g.camera_model, camera_params=",".join(f"{v:.10g}" for v in g.camera_params),
                          prior_focal=True)
            job_groups.append(jg)
        job = {"step": "extract", "db": str(db), "image_root": str(self.image_root), "names": self.names,
               "groups": job_groups, "extraction": _extraction_options(o, a.features, threads, min_side)}
        if self.mask_root is not None:
            job["mask_root"] = str(self.mask_root)
        n = len(self.names)
        res, st = colmap_process.run_step(
            job, self.work, self.progress, f"{label}: SIFT features ({n} images, <= {side} px, {threads} threads)",
            total=n, poll_table="keypoints", cleanup=[])
        self._add("extract", st)
        self._mark(db, "extract", {"keypoints": res["keypoints"]})
        return db

    def match(self, db: Path, a: Attempt, label: str) -> None:
        if self._done(db, "match"):
            return
        o = self.opts
        n = len(self.names)
        m, v = _matching_options(o, a.matching, self.threads)
        job: dict = {"step": "match", "db": str(db), "kind": self.matcher, "matching": m, "verification": v}
        if self.matcher == "exhaustive":
            # small blocks: the database (and so the progress) advances every few pairs
            job["pairing"] = {"block_size": max(4, min(50, math.ceil(n / 3)))}
            total = n * (n - 1) // 2
        elif self.matcher == "sequential":
            job["pairing"] = {"overlap": o.sequential_overlap, "quadratic_overlap": False, "num_threads": self.threads}
            loop = bool(o.loop_closure and n > o.sequential_overlap + 1)  # else every pair is matched already
            if loop:
                job["loop_closure"] = {"path": str(self.work / "visual_index.bin"), "num_threads": self.threads}
                job["pairing"].update({"loop_detection_period": LOOP_PERIOD, "loop_detection_num_images": LOOP_IMAGES})
            total = sequential_pairs(n, o.sequential_overlap, loop)
        elif self.matcher == "pairs":
            job["pairs_file"] = str(self.pairs_file)
            total = sum(1 for line in Path(self.pairs_file).read_text().splitlines() if line.strip())
        else:  # retrieval
            total = n * min(o.retrieval_neighbours, n - 1)
            job = self._retrieval_job(db, job)
        res, st = colmap_process.run_step(
            job, self.work, self.progress, f"{label}: {self.matcher} matching"
            + (" (guided)" if a.matching == "guided" else ""), total=total,
            poll_table="two_view_geometries")
        self._add("match", st)
        self._mark(db, "match", res)

    def _retrieval_job(self, db: Path, job: dict) -> dict:
        # retrieval = match pairs proposed by a visual index of this capture: run as vocab-tree matching
        job = dict(job)
        job["kind"] = "vocabtree"
        job["pairing"] = {"num_images": self.opts.retrieval_neighbours, "num_threads": self.threads}
        job["loop_closure"] = {"path": str(self.work / "visual_index.bin"), "num_threads": self.threads}
        return job

    def map(self, db: Path, a: Attempt, label: str) -> list[Path]:
        out = self.work / "models" / a.name
        info = out.parent / f"{a.name}.json"
        if info.is_file() and out.is_dir():
            paths = _cached_models(info, "paths", self.work)
            if paths:
                return paths
        n = len(self.names)
        job = {"step": "map", "db": str(db), "image_root": str(self.image_root), "out": str(out),
               "num_images": n, "options": mapping_options(self.opts, n, a.mapping, self.threads)}
        if a.mapping != "default" and n <= MAPPING_SEEDS_MAX_IMAGES:
            job["seeds"] = [self.opts.seed + k for k in range(MAPPING_SEEDS)]
        # the worker counts the images each partial model registers, summed: the largest model may hold fewer
        res, st = colmap_process.run_step(job, self.work, self.progress, f"{label}: incremental mapping (images "
                                          "registered, all partial models)", total=n, cleanup=[out])
        self._add("map", st)
        paths = [Path(m["path"]) for m in res["models"]]
        if a.merge and len(paths) > 1:
            merged = self.merge(db, paths[0], paths[1:], out.parent / f"{a.name}_merged", label, a.mapping)
            if merged is not None:
                paths = [merged] + paths
        io.write_json(info, {"paths": [str(p) for p in paths]})
        return paths

    def drop(self, base: Path, names: list[str], out: Path, label: str, mapping: str = "default") -> Path:
        """The model in `base` without the images `names`, bundle-adjusted again (colmap_worker step_drop)
        with the intrinsics refined as `mapping`'s options allow."""
        info = out.parent / f"{out.name}.json"
        if info.is_file() and out.is_dir():
            return out
        job = {"step": "drop", "base": str(base), "out": str(out), "names": sorted(names),
               "options": mapping_options(self.opts, len(self.names), mapping, self.threads)}
        _, st = colmap_process.run_step(job, self.work, self.progress, f"{label}: dropping {len(names)} "
                                        "untrustworthy registration(s)", cleanup=[out])
        self._add("map", st)
        io.write_json(info, {"path": str(out), "dropped": sorted(names)})
        return out

    def recover(self, db: Path, base: Path, names: list[str], out: Path, label: str) -> dict:
        """Re-register `names` against the model `base` (colmap_worker's recover step); its result dict
        ({} if the step failed: recovery is a bonus, the trusted model stays)."""
        info = out.parent / f"{out.name}.json"
        rec = io.read_record(info)
        if isinstance(rec, dict):
            self.recovery = rec
            return self.recovery
        job = {"step": "recover", "db": str(db), "image_root": str(self.image_root), "out": str(out),
               "base": str(base), "names": list(names), "frame_order": frame_order(self.names, self.opts),
               "min_observations": self.opts.min_observations, "seed": self.opts.seed,
               "options": mapping_options(self.opts, len(self.names), "relaxed", self.threads)}
        try:
            res, st = colmap_process.run_step(job, self.work, self.progress, label, total=len(names),
                                              cleanup=[out])
        except colmap_process.StepError as e:
            log.warning("SfM: re-registering dropped images failed: %s", e.message)
            return {}
        self._add("map", st)
        for n, why in res.get("rejected", {}).items():
            log.info("SfM: %s not re-registered: %s", n, why)
        for n, how in res.get("recovered", {}).items():
            log.info("SfM: %s re-registered (%s, %d observations)", n, how["method"], how["observations"])
        io.write_json(info, res)
        self.recovery = res
        return res

    def merge(self, db: Path, base: Path, donors: list[Path], out: Path, label: str,
              mapping: str = "relaxed") -> Path | None:
        """The base model completed with the images the donor models registered (see colmap_worker's
        step_merge), with the mapping options of `mapping` (an attempt's own: "fixed_focal" keeps the
        focal lengths in the merge's bundle adjustment too); None if nothing could be added."""
        info = out.parent / f"{out.name}.json"
        rec = io.read_record(info)
        if isinstance(rec, dict):
            merged = _cached_models(info, "path", self.work)
            return merged[0] if rec.get("merged") and merged else None
        job = {"step": "merge", "db": str(db), "image_root": str(self.image_root), "out": str(out),
               "base": str(base), "donors": [str(p) for p in donors],
               "options": mapping_options(self.opts, len(self.names), mapping, self.threads)}
        try:
            res, st = colmap_process.run_step(job, self.work, self.progress, f"{label}: merging models",
                                              cleanup=[out])
        except colmap_process.StepError as e:  # merging is a bonus: keep what there is
            log.warning("SfM: merging models failed: %s", e.message)
            return None
        self._add("map", st)
        io.write_json(info, {"merged": bool(res.get("merged")), "path": str(out), "added": res.get("added", []),
                             "rejected": res.get("rejected", [])})
        if res.get("rejected"):
            log.info("SfM merge: rejected %s (too few or inconsistent observations)", ", ".join(res["rejected"]))
        return out if res.get("merged") else None


def run_sfm(image_paths: list[Path], work_dir: str | Path, opts: SfmOptions | None = None,
            progress: bool = True, masks: dict[Path, Path] | None = None) -> SfmResult:
    """Reconstruct camera poses and sparse points from images.

    Args:
        image_paths: images (any folders); names in the result are their paths relative to the common folder.
        work_dir: folder for the databases, attempts and the model (sparse/); re-used to resume.
        progress: live progress (bar on a terminal, plain lines in a redirected log).
        masks: {image path: mask} (0 = no features there: a photo's transparent pixels, `capture.images`),
            given to COLMAP's feature extraction (copied into work_dir/feature_masks/ as it names them).
    Returns: SfmResult in COLMAP's frame. Raises InputError if mapping fails or too few images register;
    KeyboardInterrupt (within about a second, the running step stopped and cleaned up) on Ctrl-C.
    """
    import pycolmap

    opts = opts or SfmOptions()
    opts.validate()
    if len(image_paths) < 2:
        raise InputError(f"structure from motion needs at least 2 images, got {len(image_paths)}; {_ADVICE}")
    for p in image_paths:
        if not Path(p).is_file():
            raise InputError("image not found", p)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    image_root, names = image_layout(image_paths)
    names = sorted(names)  # COLMAP ids follow this order: same images in any order -> same model (and resume)
    key = _config_key(opts, names)
    mask_names = _feature_mask_names(image_paths, image_root, masks)
    if mask_names:
        from splattwin.hashing import sha256_file

        key["feature_masks"] = {n: sha256_file(m) for n, m in sorted(mask_names.items())}
    key_path, model_dir = work / "sfm_config.json", work / "sparse"
    if key_path.is_file() and io.read_record(key_path) != json.loads(json.dumps(key)):
        log.info("SfM options or images changed: starting over in %s", work)
        clear_work(work)
    io.write_json(key_path, key)

    with StageProgress(progress) as bar:
        if (model_dir / "done").is_file():
            bar.update("SfM: re-using the finished model", 1, 1)
            meta = io.read_record(model_dir / "done")   # (an older version wrote no JSON there: {})
            meta = meta if isinstance(meta, dict) else {}
            rec = read_cached_model(model_dir)
            res = result_from_reconstruction(rec, names, {}, image_root)
            res.failures, res.attempts = meta.get("failures", {}), meta.get("attempts", [])
            res.matcher, res.camera_groups = meta.get("matcher", ""), meta.get("camera_groups", [])
            peak = meta.get("peak_rss_gib", 0.0)
            res.peak_rss_gib = float(peak) if isinstance(peak, (int, float)) and not isinstance(peak, bool) else 0.0
            res.resumed_timings = meta.get("timings", {})
            res.registration_check = meta.get("registration_check", {})
            _check_enough(res, opts, image_root)
            return res
        run = SfmRun(work, image_root, names, opts, bar)
        if mask_names:
            run.mask_root = _write_feature_masks(work, mask_names, image_root, names)
        outcome, attempt = _run_attempts(run, bar)
        rec, sub_models, db = outcome.rec, outcome.sub_models, outcome.db
        res = result_from_reconstruction(rec, names, run.timings, image_root)
        res.attempts = run_attempts_log(work)
        res.matcher = run.matcher
        res.camera_groups = [g.to_dict() for g in run.groups]
        res.peak_rss_gib = run.peak / 2**30
        kp, ver = _match_graph(db, names)
        res.failures = explain_failures(names, set(res.cameras), kp, ver, opts.min_two_view_inliers, sub_models)
        for n in res.unregistered:  # registered by some attempt, but its pose failed the sanity check
            if n in run.dropped:
                res.failures[n] = f"registered, but dropped by the registration sanity check: {run.dropped[n]}"
        for n, why in run.recovery.get("rejected", {}).items():
            if n in res.failures:
                res.failures[n] += f"; re-registering it against the final model failed ({why})"
        res.registration_check = outcome.check
        # final model: written beside, then renamed; `done` (with the report) marks it complete
        tmp = work / "sparse.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        rec.write(str(tmp))
        io.write_json(tmp / "done", {"attempt": attempt.name, "failures": res.failures, "attempts": res.attempts,
                                      "matcher": res.matcher, "camera_groups": res.camera_groups,
                                      "timings": res.timings, "peak_rss_gib": res.peak_rss_gib,
                                      "registration_check": res.registration_check})
        shutil.rmtree(model_dir, ignore_errors=True)
        os.replace(tmp, model_dir)
    _check_enough(res, opts, image_root)
    return res


def _copy_features(src: Path, dst: Path) -> None:
    """Copy a COLMAP database without its matches (same images, cameras and features), atomically."""
    import sqlite3

    colmap_process.recover_database(src)
    with io.atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
        con = sqlite3.connect(str(tmp))
        try:
            con.execute("DELETE FROM matches")
            con.execute("DELETE FROM two_view_geometries")
            con.commit()
        finally:
            con.close()


def clear_work(work: Path) -> None:
    """Empty the SfM work folder `work` for a fresh run, keeping only its `sfm_config.json`."""
    for q in work.iterdir():
        if q.name == "sfm_config.json":
            continue
        if q.is_dir():
            shutil.rmtree(q)
        else:
            q.unlink()


def run_attempts_log(work: Path) -> list[dict]:
    log_ = io.read_record(work / "attempts.json")
    return log_ if isinstance(log_, list) else []


# -- the work folder's own records -----------------------------------------------------------------
# An interrupted SfM resumes from OUT/sfm. That folder may be someone else's (a received poses or twin folder
# built into again): its records are read bounded, a malformed one counts as absent (the step runs again), the
# models they name must lie in the folder, and a finished model is checked as any COLMAP model before pycolmap.
def _cached_models(info: Path, key: str, work: Path) -> list[Path]:
    """The model folders a record names under `key` (a path or a list of paths) when every one is a folder inside
    `work` (symbolic links resolved); [] otherwise (the step runs again)."""
    from splattwin.paths import is_inside

    rec = io.read_record(info)
    got = rec.get(key) if isinstance(rec, dict) else None
    got = [got] if isinstance(got, str) else got
    if not isinstance(got, list) or not got or not all(isinstance(p, str) and p for p in got):
        return []
    paths = [Path(p) for p in got]
    if not all(p.is_dir() and is_inside(p, work) for p in paths):
        log.warning("SfM: %s names models outside %s or missing; running that step again", info, work)
        return []
    return paths


def read_cached_model(model_dir: Path):
    """The finished model of an earlier run, its counts checked (`capture.colmap.check_model`) before pycolmap
    reads it; InputError naming it when pycolmap cannot."""
    import pycolmap

    from splattwin.capture.colmap import check_model

    check_model(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # noqa: BLE001 - pycolmap raises ValueError/RuntimeError on corrupt files
        raise InputError(f"the finished SfM model of an earlier run cannot be read ({str(e).splitlines()[0][:200]}); "
                         f"remove {model_dir.parent} to run SfM again", model_dir) from None


@dataclass
class AttemptOutcome:
    """What one attempt produced: its largest model (None: nothing reconstructed), registered images,
    image sets of the other sub-models that hold images the largest lacks, its database, sub-model sizes."""

    rec: object | None
    registered: int
    sub_models: list[set[str]]
    db: Path | None
    models: list[int] = field(default_factory=list)
    path: Path | None = None                              # the largest model's folder
    paths: list[Path] = field(default_factory=list)       # all its models' folders
    dropped: dict[str, str] = field(default_factory=dict)  # name -> why the sanity check dropped it
    check: dict = field(default_factory=dict)              # the final RegistrationCheck.to_dict()
    recovery: dict = field(default_factory=dict)           # the recover step's result (recovered, rejected)


def run_plan(plan: list[Attempt], num_images: int, execute, say=lambda text: None,
             record=lambda attempt, outcome, seconds: None, complete=None,
             recover=None) -> tuple[AttemptOutcome, Attempt]:
    """Run attempts in order until one registers every image; returns the best (most registered, the
    earlier on a tie: stricter settings). execute(attempt, index) -> AttemptOutcome. complete(best,
    outcomes so far) -> AttemptOutcome | None: after a retry, the best model completed with images other
    attempts registered (merging across attempts). recover(best, its attempt) -> (AttemptOutcome, Attempt)
    | None: then, before the next retry, the best model with images re-registered by other means (None:
    not tried or nothing gained). InputError if no attempt reconstructed anything."""
    best: tuple[AttemptOutcome, Attempt] | None = None
    history: list[AttemptOutcome] = []
    for i, a in enumerate(plan):
        if i > 0:
            say(f"SfM: {best[0].registered if best else 0}/{num_images} images registered in the largest model; "
                f"retrying with {a.why}")
        t0 = time.perf_counter()
        out = execute(a, i)
        record(a, out, time.perf_counter() - t0)
        history.append(out)
        if out.rec is not None and (best is None or out.registered > best[0].registered):
            best = (out, a)
        if best is not None and best[0].registered < num_images and i > 0 and complete is not None:
            merged = complete(best[0], history)
            if merged is not None and merged.registered > best[0].registered:
                best = (merged, Attempt(f"{best[1].name}+merged", f"{best[1].why}, completed from other attempts",
                                        best[1].features, best[1].cameras, best[1].matching, best[1].mapping))
        if best is not None and best[0].registered < num_images and recover is not None:
            got = recover(*best)
            if got is not None and got[0].registered > best[0].registered:
                best = got
        if best is not None and best[0].registered >= num_images:
            break
    if best is None:
        raise InputError(f"structure from motion failed: no initial image pair could be reconstructed from "
                         f"{num_images} images (tried: {', '.join(a.name for a in plan)}); {_ADVICE}")
    return best


def _outcome(recs: list, paths: list[Path], db: Path) -> AttemptOutcome:
    """AttemptOutcome of the models `recs` (stored in `paths`) reconstructed from `db`."""
    if not recs:
        return AttemptOutcome(None, 0, [], db)
    k = max(range(len(recs)), key=lambda j: recs[j].num_reg_images())
    rec = recs[k]
    main = {rec.image(i).name for i in rec.reg_image_ids()}
    subs = [s for s in ({r.image(i).name for i in r.reg_image_ids()} for r in recs if r is not rec) if s - main]
    return AttemptOutcome(rec, int(rec.num_reg_images()), subs, db, [r.num_reg_images() for r in recs],
                          path=Path(paths[k]), paths=[Path(p) for p in paths])


def _run_attempts(run: SfmRun, bar: StageProgress) -> tuple[AttemptOutcome, Attempt]:
    """The retry plan for this capture, run until every image registers (see `run_plan`)."""
    import pycolmap

    n = len(run.names)
    # "small": the size bound did not shrink the images (much), so more features must come from a lower
    # SIFT threshold, not from more pixels
    limit = run.opts.max_image_size if run.opts.max_image_size > 0 else 1600
    small = run.max_side <= 0.75 * limit
    exif_focal = any("focal_mm" in g.exif or "focal_35mm" in g.exif for g in run.groups)
    plan = retry_plan(run.groups, run.opts, small_images=small, exif_focal=exif_focal)
    log_path = run.work / "attempts.json"
    done_log = run_attempts_log(run.work)

    def execute(a: Attempt, i: int) -> AttemptOutcome:
        label = "SfM" if i == 0 else f"SfM retry {i}/{len(plan) - 1} ({a.name})"
        if i > 0:
            log.info("SfM retry %d/%d: %s", i, len(plan) - 1, a.why)
        t0 = time.perf_counter()
        db = run.extract(a, label)
        run.match(db, a, label)
        paths = run.map(db, a, label)
        recs = [pycolmap.Reconstruction(str(p)) for p in paths]
        if i > 0:
            run.timings["retries"] = run.timings.get("retries", 0.0) + time.perf_counter() - t0
        if not recs:
            return AttemptOutcome(None, 0, [], db)
        return checked(_outcome(recs, paths, db), a.name, label, a.mapping)

    def complete(best: AttemptOutcome, history: list[AttemptOutcome]) -> AttemptOutcome | None:
        donors = [p for h in history for p in h.paths if p != best.path]
        if best.path is None or not donors:
            return None
        k = len(history)
        merged = run.merge(best.db, best.path, donors, run.work / "models" / f"completed_{k}", "SfM: completing")
        if merged is None:
            return None
        return checked(_outcome([pycolmap.Reconstruction(str(merged))], [merged], best.db), f"completed_{k}",
                       "SfM: completing")

    def checked(out: AttemptOutcome, tag: str, label: str, mapping: str = "relaxed") -> AttemptOutcome:
        return _checked(run, out, tag, label, mapping)

    def record(a: Attempt, out: AttemptOutcome, seconds: float) -> None:
        if not any(e.get("name") == a.name for e in done_log):
            done_log.append({"name": a.name, "why": a.why, "registered": out.registered, "models": out.models,
                             "seconds": round(seconds, 2), **({"dropped": sorted(out.dropped)} if out.dropped else {})})
            io.write_json(log_path, done_log)

    tried_on: list[str] = []  # the attempt whose model the early recovery ran against

    def recover(best: AttemptOutcome, attempt: Attempt) -> tuple[AttemptOutcome, Attempt] | None:
        # Early, once: when every image the best model lacks did register in some attempt but failed the
        # sanity check, re-registering those against the best model is what finally helps, and the
        # retries left (more features) would not: on the cake photos "more_features" (~1/3 of the SfM
        # time) ended with the same 6 images as "guided", and the recovery against guided's model then
        # brought 8/8 anyway.
        have = {best.rec.image(i).name for i in best.rec.reg_image_ids()}
        if tried_on or any(nm not in run.dropped for nm in run.names if nm not in have):
            return None
        tried_on.append(attempt.name)
        return _recovered(run, best, attempt, done_log, log_path)

    try:
        best, attempt = run_plan(plan, n, execute, say=bar.message, record=record, complete=complete,
                                 recover=recover)
    except InputError as e:
        raise InputError(e.problem, run.image_root) from e
    if not tried_on:
        return _recovered(run, best, attempt, done_log, log_path)
    if best.registered < n and attempt.name != tried_on[0] and not attempt.name.endswith("+recovered"):
        # a later retry beat the model the early recovery used: its own dropped images get their try too
        return _recovered(run, best, attempt, done_log, log_path, tag="recover_final")
    return best, attempt


def _recovered(run: SfmRun, best: AttemptOutcome, attempt: Attempt, done_log: list[dict],
               log_path: Path, tag: str = "recover") -> tuple[AttemptOutcome, Attempt]:
    """`best` with the images the sanity check dropped (in any attempt) that it lacks re-registered
    against it (colmap_worker's recover step), checked again; `best` itself when nothing was recovered.
    The step's result is logged as the attempt `tag` (attempts.json, poses_report.json), its model in
    models/recovered (models/recovered_<tag> for another tag)."""
    import dataclasses

    import pycolmap

    from splattwin.poses.sanity import SanityOptions, check_registration

    if not (run.opts.check_registration and run.opts.recover_dropped) or best.path is None or best.db is None:
        return best, attempt
    have = {best.rec.image(i).name for i in best.rec.reg_image_ids()}
    names = [n for n in run.names if n in run.dropped and n not in have]
    if not names:
        return best, attempt
    t0 = time.perf_counter()
    out = run.work / "models" / ("recovered" if tag == "recover" else f"recovered_{tag}")
    res = run.recover(best.db, best.path, names, out, "SfM: re-registering dropped images")
    entry = {"name": tag, "why": f"re-register {len(names)} dropped image(s) against the {attempt.name} "
             "model (absolute pose, table-plane homography, else structure-less), kept only if they pass the check",
             "tried": names, "recovered": res.get("recovered", {}), "rejected": res.get("rejected", {}),
             "registered": best.registered, "seconds": round(time.perf_counter() - t0, 2)}
    if res.get("recovered"):
        rec = pycolmap.Reconstruction(str(out))
        full = result_from_reconstruction(rec, [], {}, run.image_root)
        obs = {rec.image(i).name: int(rec.image(i).num_points3D) for i in rec.reg_image_ids()}
        chk = check_registration(full.cameras, obs, full.points_xyz,
                                 SanityOptions(min_observations=run.opts.min_observations), seed=run.opts.seed)
        if not chk.dropped:  # the worker checked the same; a disagreement keeps the trusted model
            check = chk.to_dict()
            check["dropped"] = {n: w for n, w in best.dropped.items() if n not in res["recovered"]}
            check["recovered"] = res["recovered"]
            best = dataclasses.replace(best, rec=rec, registered=int(rec.num_reg_images()), path=out,
                                       paths=[out] + best.paths, check=check, recovery=res,
                                       dropped=check["dropped"])
            attempt = Attempt(f"{attempt.name}+recovered", f"{attempt.why}, dropped images re-registered",
                              attempt.features, attempt.cameras, attempt.matching, attempt.mapping)
            for n in res["recovered"]:
                run.dropped.pop(n, None)
        else:
            entry["rejected_by_parent_check"] = chk.dropped
    entry["registered"] = best.registered
    if not any(e.get("name") == tag for e in done_log):
        done_log.append(entry)
        io.write_json(log_path, done_log)
    return best, attempt


def _checked(run: SfmRun, out: AttemptOutcome, tag: str, label: str, mapping: str = "default") -> AttemptOutcome:
    """`out` with the registrations the sanity check (`splattwin.poses.sanity`) does not trust removed:
    they are de-registered and the model is bundle-adjusted again (models/<tag>_checked<k>), repeated
    while the check still flags images (a drop moves the plane and the others' consensus a little)."""
    import dataclasses

    import pycolmap

    from splattwin.poses.sanity import SanityOptions, check_registration

    if not run.opts.check_registration or out.rec is None or out.path is None:
        return out
    rec, path, dropped = out.rec, out.path, {}
    sopts = SanityOptions(min_observations=run.opts.min_observations)
    for k in range(4):
        res = result_from_reconstruction(rec, [], {}, run.image_root)
        obs = {rec.image(i).name: int(rec.image(i).num_points3D) for i in rec.reg_image_ids()}
        chk = check_registration(res.cameras, obs, res.points_xyz, sopts, seed=run.opts.seed)
        if not chk.dropped or k == 3:
            break
        for n, why in sorted(chk.dropped.items()):
            log.warning("SfM (%s): %s registered but dropped: %s", tag, n, why)
        dropped.update(chk.dropped)
        run.dropped.update(chk.dropped)
        path = run.drop(path, list(chk.dropped), run.work / "models" / f"{tag}_checked{k}", label, mapping)
        rec = pycolmap.Reconstruction(str(path))
    check = chk.to_dict()
    check["dropped"] = dict(dropped)
    paths = [path] + [p for p in out.paths if p != out.path]  # the unchecked model is no merge donor
    return dataclasses.replace(out, rec=rec, registered=int(rec.num_reg_images()), path=path, paths=paths,
                               dropped=dropped, check=check)


def _match_graph(db: Path, names: list[str]) -> tuple[dict[str, int], dict[tuple[str, str], int]]:
    """Keypoints per image and verified inlier matches per image pair, read from a COLMAP database."""
    import sqlite3

    con = sqlite3.connect(str(db))
    try:
        id_name = dict(con.execute("SELECT image_id, name FROM images").fetchall())
        kp = {id_name[i]: int(r) for i, r in con.execute("SELECT image_id, rows FROM keypoints") if i in id_name}
        ver = {}
        for pid, rows in con.execute("SELECT pair_id, rows FROM two_view_geometries"):
            a, b = divmod(int(pid), _MAX_IMAGE_ID)
            if a in id_name and b in id_name:
                ver[(id_name[a], id_name[b])] = int(rows)
    finally:
        con.close()
    return {n: kp.get(n, 0) for n in names}, ver


def _camera_from_colmap(cam, T_cam_world: np.ndarray, name: str) -> Camera:
    """pycolmap.Camera + world->cam [4,4] -> splattwin Camera (OpenCV conventions agree with COLMAP)."""
    model, p = cam.model_name, np.asarray(cam.params, dtype=np.float64)
    dist = None
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]; cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist = np.array([p[3], 0.0, 0.0, 0.0])
    elif model == "RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist = np.array([p[3], p[4], 0.0, 0.0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]; dist = p[4:8].copy()
    else:
        raise InputError(f"camera model {model} is not supported (use SIMPLE_RADIAL, PINHOLE or OPENCV)")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return Camera(K=K, width=cam.width, height=cam.height, T_world_cam=invert_se3(T_cam_world), dist=dist, name=name)


_NAMED = 3   # unregistered images an error names (each one's reason is logged; a 30-image list filled 20 kB)


def _check_enough(res: SfmResult, opts: SfmOptions, image_root: Path) -> None:
    """Log why each unregistered image failed; InputError when fewer than --min-registered registered."""
    for name, why in res.failures.items():
        log.warning("SfM: %s not registered: %s", name, why)
    n = res.num_total
    need = opts.min_registered if opts.min_registered is not None else max(3, n - 3)
    need = min(need, n)
    if res.num_registered < need:
        missing = list(res.failures) or list(res.unregistered)
        if len(missing) <= _NAMED:
            why = "; ".join(f"{k}: {v}" for k, v in res.failures.items()) or ", ".join(missing)
        else:
            why = (f"{len(missing)} images ({', '.join(missing[:_NAMED])} and {len(missing) - _NAMED} more; "
                   f"why each failed: the warnings above)")
        raise InputError(
            f"structure from motion registered only {res.num_registered}/{n} images (need {need}); "
            f"not registered: {why}; {_ADVICE}; or lower --min-registered (build: --poses.min-registered)",
            image_root)


def result_from_reconstruction(rec, names: list[str], timings: dict[str, float], image_root: Path) -> SfmResult:
    """SfmResult of a pycolmap Reconstruction `rec` over the images `names` (relative to `image_root`):
    the registered images' cameras in COLMAP's world frame, the names it left unregistered, its 3D points
    (position, colour, reprojection error, track length) and `timings` (s)."""
    cameras: dict[str, Camera] = {}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        T_cam_world = np.eye(4)
        T_cam_world[:3, :] = im.cam_from_world().matrix()
        cameras[im.name] = _camera_from_colmap(rec.camera(im.camera_id), T_cam_world, im.name)
    unregistered = [n for n in names if n not in cameras]
    pts = rec.points3D
    ids = sorted(pts.keys())  # stable order: a resumed run must give the same frame
    xyz = np.array([pts[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([pts[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    err = np.array([pts[i].error for i in ids], dtype=np.float64)
    tl = np.array([pts[i].track.length() for i in ids], dtype=np.int64)
    return SfmResult(cameras=cameras, unregistered=unregistered, points_xyz=xyz, points_rgb=rgb, points_error=err,
                     points_track_len=tl, mean_reproj_error=float(rec.compute_mean_reprojection_error()),
                     timings=dict(timings))
