"""Options of the poses stage (`estimate_poses`, `splattwin poses`, `build --poses.*`): one plain dataclass,
the single source of their defaults and help (see `splattwin.options`). Light: no numpy, no capture."""

from __future__ import annotations

import math

from dataclasses import dataclass
from pathlib import Path

from splattwin.heldout import HELDOUT_EVERY_DEFAULT, HELDOUT_MIN_VIEWS  # noqa: F401 (re-exported)
from splattwin.errors import InputError
from splattwin.options import flag_spellings, option
from splattwin.frame_options import FrameOptions

METHODS = ("auto", "known", "sfm", "robot")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")
# known poses: which input world axis points up ("auto": detect, see splattwin.poses.up; "keep": no check)
UP_AXES = ("auto", "keep", "+z", "-z", "+y", "-y", "+x", "-x")
# known poses: are their lengths metres ("auto": see splattwin.poses.estimate._input_scaled)
SCALES = ("auto", "metric", "unscaled")


# lengths a user gives for scale (--known-length, --marker-size), metres: 0.1 mm to 10 km. Outside, a typo or
# garbage (1e-300 passed "positive" and failed deep in SfM's scaling with a message about something else)
LENGTH_RANGE_M = (1e-4, 1e4)


def check_length_m(value: float | None, what: str) -> None:
    """InputError when a positive length given for scale lies outside `LENGTH_RANGE_M`."""
    lo, hi = LENGTH_RANGE_M
    if value is not None and math.isfinite(value) and value > 0 and not lo <= value <= hi:
        raise InputError(f"{what} {value:g} m is outside {lo:g} to {hi:g} m: a length in metres (0.08 for an 8 cm "
                         f"marker)")


@dataclass
class HoldoutOptions:
    """Which views are held out of training for the held-out PSNR/SSIM (`splattwin.poses.holdout`).

    Give at most one of the three. None given: a capture with a split of its own (a transforms.json with
    train/test file lists or per-frame splits, the embedded scene) keeps it; otherwise every 8th view,
    starting with the first, is held out when there are >= 6 views (the Mip-NeRF 360 / 3DGS
    convention), none below 6. Views are counted in the capture's order (image folders: sorted by file
    name; video: time order; known-pose captures: their file's order), before pose estimation, so the
    split does not depend on which images SfM registers. The split is recorded in transforms.json
    ("heldout"), eval/metrics.json and the report.
    """

    heldout_every: int | None = option(None, "hold out every K-th view, starting with the first (0: none; default: "
                                       "8 with >= 6 views, unless the capture has its own split)",
                                       aliases=("heldout-every",), build_alias="heldout-every")
    heldout: int | None = option(None, "hold out N views spread evenly over the capture, starting with the first "
                                 "(0: none)", aliases=("heldout",), build_alias="heldout")
    heldout_views: str | None = option(None, "hold out exactly these views: a comma list of view indices (0-based, "
                                       "capture order) and/or image names, e.g. '0,12,img_0031'",
                                       aliases=("heldout-views",), build_alias="heldout-views")


@dataclass
class PoseOptions(FrameOptions):
    """Options of `estimate_poses`.

    max_frames / min_change (`FrameOptions`, inherited): how many frames the capture gives (a video: which).
    method "auto": robot poses when given, else the dataset's poses, else structure from motion.
    intrinsics: None = estimate (SfM) / take the dataset's; "dataset" = the dataset's K, kept fixed;
      "fx,fy,cx,cy" (or a tuple of four floats from Python) = known, kept fixed.
    known_length: metric scale for the table-plane frame, as `splattwin.poses.table.KnownLength.parse`
      reads it (Python callers may pass a `KnownLength`).
    max_image_size / max_num_features / retry / check_registration / num_threads: see
      `splattwin.poses.sfm.SfmOptions`.
    triangulate: points for known/robot poses without a point cloud or depth (`splattwin.poses.triangulate`).
    up: which way is up in a known-pose world (`splattwin.poses.up`); recorded in frame.json.
    holdout: which views are held out of training (`HoldoutOptions`); recorded in transforms.json.
    """

    method: str = option("auto", "pose source: robot poses, the dataset's (known), or structure from motion",
                         choices=METHODS, build_alias="poses")
    robot_poses: Path | None = option(None, "JSON/YAML list of end-effector poses T_base_ee per image (4x4, or "
                                      "position + quat_xyzw/quat_wxyz); alone: exact cameras in the robot base "
                                      "frame; with SfM: SfM aligned to them (Umeyama)", path=True,
                                      build_alias="robot-poses")
    hand_eye: Path | None = option(None, "hand-eye calibration T_ee_cam (JSON/YAML); may also be inline in "
                                   "robot_poses", path=True, build_alias="hand-eye")
    marker_size: float | None = option(None, "ArUco marker side: marker frame + metric scale", unit="m",
                                       build_alias="marker-size")
    marker_dict: str = option("DICT_4X4_50", "ArUco dictionary")
    marker_id: int = option(0, "ArUco marker id")
    known_length: str | None = option(None, "metric scale for the table frame: camera_height=M (mean camera "
                                      "height above the table), camera_height@IMAGE=M, or baseline@IMG_A,IMG_B=M "
                                      "(distance between two camera centres)", build_alias="known-length")
    intrinsics: str | tuple[float, float, float, float] | None = option(
        None, "known pinhole intrinsics 'fx,fy,cx,cy' in pixels (kept fixed), or 'dataset' to use the dataset's",
        build_alias="intrinsics")
    camera_model: str = option("SIMPLE_RADIAL", "camera model when SfM estimates the intrinsics", choices=CAMERA_MODELS)
    shared_intrinsics: bool = option(True, "one camera for all images (--no-shared-intrinsics: one per image)")
    matcher: str = option("auto", "feature matching (auto: exhaustive for <= 50 images; beyond, sequential + loop "
                          "closure for video frames, vocabulary-tree retrieval for unordered photos)",
                          choices=MATCHERS)
    min_registered: int | None = option(None, "fail unless SfM registers at least this many images (none: all but "
                                        "3, at least 3)")
    max_image_size: int = option(1600, "SfM extracts features from images resized to this longest side (0: full "
                                 "size)", unit="px")
    max_num_features: int = option(4096, "SIFT features per image (the strongest)", aliases=("max-features",))
    retry: bool = option(True, "retry SfM automatically (other settings) while images fail to register")
    check_registration: bool = option(True, "after SfM, drop images registered from too few observations or posed "
                                      "inconsistently with a tabletop capture (at/below the table plane, looking up "
                                      "or away from the scene); they are reported and count as unregistered")
    check_hand_eye: bool = option(True, "robot poses: check the hand-eye against the camera motion in the photos "
                                  "(a few image pairs) or the SfM model, and stop when its inverse (T_cam_ee given "
                                  "for T_ee_cam) fits clearly better; score how well the robot poses fit the photos "
                                  "(Sampson error) and, with method auto, use SfM aligned to the robot poses when "
                                  "they clearly do not. Robot poses and TUM/BOP known poses: also estimate the focal "
                                  "length and (TUM, matched by timestamp) the image-to-pose time offset that best "
                                  "fit the photos, warning when they differ from those given")
    time_offset_ms: float = option(0.0, "poses matched to images by timestamp (TUM pose lists): take each image's "
                                   "pose at its timestamp + this offset (camera latency or clock offset; the "
                                   "poses check's latency_check estimates it)", unit="ms",
                                   build_alias="time-offset-ms")
    num_threads: int = option(0, "CPU threads for SfM (0: all cores)", aliases=("threads",), hashed=False)
    depth_points: bool = option(True, "back-project depth images (RGB-D) into the initial point cloud when the "
                                "frame is metric")
    triangulate: bool = option(True, "known/robot poses without a point cloud: triangulate sparse points from the "
                               "images with the poses held fixed")
    scale_from_depth: bool = option(True, "SfM on an RGB-D capture: metric scale from the depth images (median of "
                                    "sensor depth / SfM depth at the SfM points; unused when they disagree)")
    depth_stride: int = option(4, "pixel stride of the depth back-projection")
    scale: str = option("auto", "known poses: are their lengths metres? auto: yes, except SfM output (a COLMAP "
                        "model, or a transforms.json from nerfstudio's COLMAP converters, marked by applied_transform "
                        "or colmap_im_id) unless a frame.json beside it says so; metric / unscaled: say which "
                        "(unscaled: the table frame in the poses' own units, as after SfM)",
                        choices=SCALES, build_alias="scale")
    up: str = option("auto", "known poses: the world axis that points up (--up=-z, --up=+y, ...); auto finds it "
                     "from the cameras and the table plane and rotates z-down/y-up worlds to z up (recorded in "
                     "frame.json), stopping when unclear; keep = use the poses as they are",
                     choices=UP_AXES, build_alias="up")
    seed: int = option(0, "seed of the SfM and RANSAC steps")
    holdout: HoldoutOptions = option(factory=HoldoutOptions, help="held-out views (evaluation)")
    work_dir: Path | None = option(None, "SfM scratch folder (database, model), re-used to resume (default: "
                                   "OUT/sfm; the pipeline: TWIN/poses/sfm)", runtime=True)
    progress: bool = option(True, "progress bars", runtime=True)

    def check(self) -> None:
        """InputError for values no run can use, before any work (`splattwin poses`, and `build` before its
        pre-flight): the frames' (`FrameOptions.check`), SfM's limits, --min-registered and --marker-size;
        each message names the flag in both commands' spelling."""
        super().check()
        check_sfm_limits(self.max_image_size, self.max_num_features, self.num_threads)
        if self.min_registered is not None and self.min_registered < 2:
            raise InputError(f"{_flag('min_registered')} must be >= 2, got {self.min_registered}")
        # inf passed `> 0`: the marker frame would have scaled the twin by it
        if self.marker_size is not None and not (math.isfinite(self.marker_size) and self.marker_size > 0):
            raise InputError(f"{_flag('marker_size')} must be a positive number of metres, got {self.marker_size}")
        check_length_m(self.marker_size, _flag("marker_size"))
        if self.robot_poses is not None:
            self._check_robot_files()

    def _check_robot_files(self) -> None:
        """The robot pose file and the hand-eye read and checked now: a pose file without a hand-eye (no
        --hand-eye, none inline) was refused only after a video's frames had been extracted."""
        from splattwin.poses.robot import load_hand_eye, load_robot_poses

        if not Path(self.robot_poses).is_file():
            raise InputError("no such robot pose file", self.robot_poses)
        _, inline = load_robot_poses(self.robot_poses)
        if self.hand_eye is not None:
            if not Path(self.hand_eye).is_file():
                raise InputError("no such hand-eye file", self.hand_eye)
            load_hand_eye(self.hand_eye)
        elif inline is None:
            raise InputError("robot poses need a hand-eye transform T_ee_cam (--hand-eye FILE, or 'T_ee_cam' in the "
                             "pose file)", self.robot_poses)


def _flag(name: str) -> str:
    """PoseOptions' `name` as `splattwin poses` and `build` spell it ('--max-image-size (build: --poses.max-image-size)')."""
    return flag_spellings(PoseOptions, name, "poses")


def check_sfm_limits(max_image_size: int, max_num_features: int, num_threads: int) -> None:
    """InputError for SfM feature and thread settings no run can use (`PoseOptions.check`, and
    `poses.sfm.SfmOptions.validate` for Python callers), naming the flags in both commands' spelling."""
    if 0 < max_image_size < 64:
        raise InputError(f"{_flag('max_image_size')} must be >= 64 px (or 0 for full size), got {max_image_size}")
    if max_num_features < 64:
        raise InputError(f"{_flag('max_num_features')} must be >= 64, got {max_num_features}")
    if num_threads < 0:
        raise InputError(f"{_flag('num_threads')} must be >= 0 (0 = all cores), got {num_threads}")
