"""Structure from motion with pycolmap on the CPU: SIFT extraction, matching, incremental mapping.

The result is in COLMAP's arbitrary (unscaled) world frame; `splattwin.poses.estimate` turns it into a
metric table frame. Options are tuned for sparse captures (8–20 views, measured on the embedded scene):
a lower SIFT peak threshold and looser ratio test with guided matching (more verified matches per
wide-baseline pair), lower inlier thresholds for the initial pair and for registering further images, a
smaller minimum model size, and frequent global bundle adjustment (cheap with few images).

Resume: the COLMAP database and the model live in `work_dir`; a killed run re-uses the features and
matches already in the database (COLMAP skips images/pairs it has) and a finished model is re-loaded.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, invert_se3
from splattwin.errors import InputError

log = logging.getLogger(__name__)

_ADVICE = ("try: more overlap between views (each part of the table seen from >= 3 views, "
           "neighbouring views 15-30 degrees apart), more texture in the scene, known intrinsics "
           "(--intrinsics fx,fy,cx,cy), or known/robot poses (--known, --robot-poses)")


@dataclass
class SfmOptions:
    """Knobs for `run_sfm`.

    intrinsics: (fx, fy, cx, cy) in pixels, known and kept fixed; None = estimate one shared camera.
    camera_model: COLMAP model when intrinsics are estimated (SIMPLE_RADIAL, SIMPLE_PINHOLE, PINHOLE, OPENCV).
    shared_intrinsics: one camera for all images (True) or one per image.
    matcher: "auto" (exhaustive for <= 50 images, else sequential), "exhaustive" or "sequential".
    min_registered: fewer registered images than this -> InputError. None = all images but at most 3 missing, >= 3.
    """

    intrinsics: tuple[float, float, float, float] | None = None
    camera_model: str = "SIMPLE_RADIAL"
    shared_intrinsics: bool = True
    matcher: str = "auto"
    sequential_overlap: int = 10
    max_num_features: int = 8192
    peak_threshold: float = 0.004      # COLMAP default 0.0067: more features from small, low-res views
    max_ratio: float = 0.85            # COLMAP default 0.8: a looser ratio test, geometric verification filters
    min_two_view_inliers: int = 12     # COLMAP default 15
    min_registered: int | None = None
    num_threads: int = 2
    seed: int = 0


@dataclass
class SfmResult:
    """SfM output in COLMAP's world frame (arbitrary scale, T_world_cam OpenCV convention).

    cameras: name -> Camera for each registered image. unregistered: names that did not register.
    points_xyz [N,3] float64, points_rgb [N,3] uint8, points_error [N] px, points_track_len [N].
    timings: seconds per stage (extract, match, map).
    """

    cameras: dict[str, Camera]
    unregistered: list[str]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    points_error: np.ndarray
    points_track_len: np.ndarray
    mean_reproj_error: float
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def num_registered(self) -> int:
        return len(self.cameras)

    @property
    def num_total(self) -> int:
        return len(self.cameras) + len(self.unregistered)


def _quiet_colmap() -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2  # glog: errors only; stages report through our progress bar


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


def _image_layout(image_paths: list[Path]) -> tuple[Path, list[str]]:
    """Common image folder and the names relative to it (COLMAP identifies images by these names)."""
    paths = [Path(p).resolve() for p in image_paths]
    root = Path(os.path.commonpath([str(p.parent) for p in paths]))
    names = [p.relative_to(root).as_posix() for p in paths]
    if len(set(names)) != len(names):
        raise InputError("duplicate image paths in the dataset", root)
    return root, names


def _config_key(opts: SfmOptions, names: list[str]) -> dict:
    d = asdict(opts)
    d.pop("min_registered")  # does not change the reconstruction
    d["images"] = names
    return d


def run_sfm(image_paths: list[Path], work_dir: str | Path, opts: SfmOptions | None = None,
            progress: bool = True) -> SfmResult:
    """Reconstruct camera poses and sparse points from images.

    Args:
        image_paths: images (any folders); names in the result are the file stems' relative paths.
        work_dir: folder for database.db and the model (sparse/); re-used to resume.
    Returns: SfmResult in COLMAP's frame. Raises InputError if mapping fails or too few images register.
    """
    import pycolmap

    opts = opts or SfmOptions()
    _quiet_colmap()
    if len(image_paths) < 2:
        raise InputError(f"structure from motion needs at least 2 images, got {len(image_paths)}; {_ADVICE}")
    for p in image_paths:
        if not Path(p).is_file():
            raise InputError("image not found", p)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    image_root, names = _image_layout(image_paths)
    names = sorted(names)  # COLMAP ids follow this order: same images in any order -> same model (and resume)
    key = _config_key(opts, names)
    key_path, db, model_dir = work / "sfm_config.json", work / "database.db", work / "sparse"
    if key_path.is_file() and json.loads(key_path.read_text()) != json.loads(json.dumps(key)):
        log.info("SfM options or images changed: starting over in %s", work)
        for q in (db, model_dir):
            if q.is_dir():
                shutil.rmtree(q)
            elif q.exists():
                q.unlink()
    io.write_json(key_path, key)

    timings: dict[str, float] = {}
    with _stage_progress(progress) as bar:
        if (model_dir / "done").is_file():
            rec = pycolmap.Reconstruction(str(model_dir))
            bar("SfM: re-using finished model", 1, 1)
        else:
            # -- extract -----------------------------------------------------------------------
            t0 = time.perf_counter()
            bar("SfM 1/3: SIFT features", 0, 1)
            reader = pycolmap.ImageReaderOptions()
            if opts.intrinsics is not None:
                reader.camera_model = "PINHOLE"
                reader.camera_params = ",".join(f"{v:.10g}" for v in opts.intrinsics)
            else:
                reader.camera_model = opts.camera_model
            # One extraction thread: with more, image ids follow thread completion order and the whole
            # reconstruction changes from run to run (measured: equally fast at 320x240 on 2 cores).
            ext = pycolmap.FeatureExtractionOptions(num_threads=1)
            ext.sift.max_num_features = opts.max_num_features
            ext.sift.peak_threshold = opts.peak_threshold
            mode = pycolmap.CameraMode.SINGLE if (opts.shared_intrinsics or opts.intrinsics is not None) \
                else pycolmap.CameraMode.PER_IMAGE
            pycolmap.extract_features(str(db), str(image_root), image_names=names, camera_mode=mode,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
            timings["extract"] = time.perf_counter() - t0
            # -- match -------------------------------------------------------------------------
            t0 = time.perf_counter()
            matcher = opts.matcher if opts.matcher != "auto" else ("exhaustive" if len(names) <= 50 else "sequential")
            bar(f"SfM 2/3: {matcher} matching", 0, 1)
            mopts = pycolmap.FeatureMatchingOptions(num_threads=opts.num_threads)
            mopts.guided_matching = True  # more inliers per pair: 9/11 instead of 2/11 views on a 160x120 scene
            mopts.sift.max_ratio = opts.max_ratio
            verify = pycolmap.TwoViewGeometryOptions()
            verify.min_num_inliers = opts.min_two_view_inliers
            verify.ransac.random_seed = opts.seed
            if matcher == "exhaustive":
                pycolmap.match_exhaustive(str(db), matching_options=mopts, verification_options=verify,
                                          device=pycolmap.Device.cpu)
            elif matcher == "sequential":
                pair = pycolmap.SequentialPairingOptions(overlap=opts.sequential_overlap, loop_detection=False)
                pycolmap.match_sequential(str(db), matching_options=mopts, pairing_options=pair,
                                          verification_options=verify, device=pycolmap.Device.cpu)
            else:
                raise InputError(f"unknown matcher {opts.matcher!r} (auto, exhaustive, sequential)")
            timings["match"] = time.perf_counter() - t0
            # -- map ---------------------------------------------------------------------------
            t0 = time.perf_counter()
            done = [0]

            def _next() -> None:
                done[0] += 1
                bar("SfM 3/3: incremental mapping", min(done[0] + 1, len(names)), len(names))

            bar("SfM 3/3: incremental mapping", 0, len(names))
            if model_dir.exists():
                shutil.rmtree(model_dir)
            model_dir.mkdir(parents=True)
            recs = pycolmap.incremental_mapping(str(db), str(image_root), str(model_dir / "tmp"),
                                                options=_mapping_options(opts, len(names)),
                                                initial_image_pair_callback=_next, next_image_callback=_next)
            timings["map"] = time.perf_counter() - t0
            if not recs:
                raise InputError(f"structure from motion failed: no initial image pair could be reconstructed "
                                 f"from {len(names)} images; {_ADVICE}", image_root)
            rec = max(recs.values(), key=lambda r: r.num_reg_images())
            rec.write(str(model_dir))
            shutil.rmtree(model_dir / "tmp", ignore_errors=True)
            (model_dir / "done").write_text("ok\n")
    return _result_from_reconstruction(rec, names, opts, timings, image_root)


def _mapping_options(opts: SfmOptions, n: int):
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = opts.num_threads
    o.random_seed = opts.seed
    o.min_model_size = min(3, n)
    o.multiple_models = True
    o.extract_colors = True
    o.mapper.init_min_num_inliers = 50
    o.mapper.abs_pose_min_num_inliers = 20
    o.mapper.init_min_tri_angle = 8.0
    o.mapper.random_seed = opts.seed
    # Global BA after every image: at <= a few dozen views it costs little and keeps drift out.
    o.ba_global_frames_ratio = 1.0 + 1.0 / max(n, 2)
    o.ba_global_points_ratio = 1.0 + 1.0 / max(n, 2)
    if opts.intrinsics is not None:
        o.ba_refine_focal_length = False
        o.ba_refine_principal_point = False
        o.ba_refine_extra_params = False
        o.mapper.abs_pose_refine_focal_length = False
        o.mapper.abs_pose_refine_extra_params = False
    return o


def _result_from_reconstruction(rec, names: list[str], opts: SfmOptions, timings: dict[str, float],
                                image_root: Path) -> SfmResult:
    cameras: dict[str, Camera] = {}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        T_cam_world = np.eye(4)
        T_cam_world[:3, :] = im.cam_from_world().matrix()
        cameras[im.name] = _camera_from_colmap(rec.camera(im.camera_id), T_cam_world, im.name)
    unregistered = [n for n in names if n not in cameras]
    need = opts.min_registered if opts.min_registered is not None else max(3, len(names) - 3)
    need = min(need, len(names))
    if len(cameras) < need:
        raise InputError(
            f"structure from motion registered only {len(cameras)}/{len(names)} images (need {need}); "
            f"not registered: {', '.join(unregistered)}; {_ADVICE}; or lower --min-registered", image_root)
    if unregistered:
        log.warning("SfM: %d/%d images did not register and get no pose: %s", len(unregistered), len(names),
                    ", ".join(unregistered))
    pts = rec.points3D
    ids = sorted(pts.keys())  # stable order: a resumed run must give the same frame
    xyz = np.array([pts[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([pts[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    err = np.array([pts[i].error for i in ids], dtype=np.float64)
    tl = np.array([pts[i].track.length() for i in ids], dtype=np.int64)
    return SfmResult(cameras=cameras, unregistered=unregistered, points_xyz=xyz, points_rgb=rgb, points_error=err,
                     points_track_len=tl, mean_reproj_error=float(rec.compute_mean_reprojection_error()),
                     timings=timings)


class _stage_progress:
    """Rich progress bar with one line per SfM stage (description + count + elapsed)."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.progress = None
        self.task = None

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), transient=False)
            self.progress.__enter__()
            self.task = self.progress.add_task("SfM", total=1)
        return self

    def __call__(self, desc: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress.update(self.task, description=desc, completed=done, total=total)

    def __exit__(self, *exc):
        if self.progress is not None:
            self.progress.__exit__(*exc)
        return False
