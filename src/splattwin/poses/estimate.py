"""`estimate_poses(dataset, PoseOptions) -> PoseResult`: camera poses plus the frame they live in.

Pose sources (in `PoseOptions.method` "auto" order): robot poses + hand-eye (robot base frame; checked
against the photos by `splattwin.poses.hand_eye_check`: with "auto", poses that clearly do not fit them are
replaced by SfM aligned to the robot poses, recorded as stats["pose_fallback"]), poses already in the dataset
("known"; those of a TUM pose list or BOP scene scored against the photos too, with warnings only: stats
"pose_consistency", "intrinsics_check", "latency_check"; `--poses.time-offset-ms` re-matches a TUM list's
poses to the images at image time + offset), or structure from motion. With robot or known poses and depth images but no point cloud, the
depth's scale is checked against points triangulated with the poses held fixed (`_depth_fits_points`). The frame is then defined by the first
that applies:

1. SfM + robot poses: Umeyama Sim(3) from SfM centres to robot-derived centres → robot base frame.
2. ArUco marker of known size → marker frame (origin at its centre, z = its normal, metres).
3. RANSAC table plane + a known length → table frame (z up, table top z = 0), metric.
4. Robot poses alone → robot base frame; known dataset poses → kept as they are (assumed metric).
5. Otherwise RANSAC table plane without scale → table frame marked "unscaled" (robot stages refuse it).

Every result carries a `splattwin.poses.twin_frame.TwinFrame` naming the method and the 1-sigma relative scale
uncertainty.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame as DataFrame, load_image
from splattwin.equality import dataclass_eq
from splattwin.errors import InputError
from splattwin.paths import own_file
from splattwin.poses import align
from splattwin.poses.options import UP_AXES, PoseOptions
from splattwin.poses.table import KnownLength
from splattwin.poses.twin_frame import FRAME_FILE, TwinFrame, frame_beside

log = logging.getLogger(__name__)

REPORT_FILE = "poses_report.json"
DEPTH_PLY = "points3D_depth.ply"


@dataclass
class PoseResult:
    """Posed frames in the output frame.

    frames: registered frames with their cameras (T_world_cam in the output frame, metres if frame.scaled).
    unregistered: image names that got no pose. frame: the frame definition (source, scaled, uncertainty).
    points_xyz [N,3] / points_rgb [N,3] uint8: initial cloud: SfM (or the dataset's) points, joined by the
        back-projected depth (voxel-thinned, `poses.depth.merge_with_depth`) when the frame is metric and
        the depth agrees with them; the depth cloud alone without sparse points.
    depth_xyz / depth_rgb: back-projected depth cloud (RGB-D), if any.
    T_out_in: [4,4] similarity from the input frame (SfM model or dataset/robot frame) to the output frame.
    stats: registered, total, mean_reproj_error (px), method details, timings.
    """

    frames: list[DataFrame]
    unregistered: list[str]
    frame: TwinFrame
    points_xyz: np.ndarray | None = None
    points_rgb: np.ndarray | None = None
    depth_xyz: np.ndarray | None = None
    depth_rgb: np.ndarray | None = None
    T_out_in: np.ndarray = field(default_factory=lambda: np.eye(4))
    stats: dict = field(default_factory=dict)
    depth_scale: float | None = None  # metres per raw depth unit (see splattwin.capture.dataset)
    label_objects: dict | None = None  # name -> id of the label images' objects (capture.nerfstudio)

    __eq__ = dataclass_eq   # array-aware (points, T_out_in) (splattwin.equality)

    @property
    def cameras(self) -> list[Camera]:
        return [f.camera for f in self.frames]

    def to_dataset(self, root: str | Path | None = None) -> Dataset:
        """The posed frames as a Dataset. root: its folder; None: the folder that holds all the frames'
        images (never the current directory)."""
        if root is None:
            import os

            root = Path(os.path.commonpath([str(f.image_path.absolute()) for f in self.frames])) if self.frames else None
            if root is not None and any(root == f.image_path.absolute() for f in self.frames):
                root = root.parent  # one image: its folder
        if root is None:
            raise ValueError("PoseResult.to_dataset: no frames, so no folder to be the dataset's root; pass root=")
        return Dataset(root=Path(root), frames=list(self.frames), has_poses=True, points_xyz=self.points_xyz,
                       points_rgb=self.points_rgb, depth_scale=self.depth_scale, meta={"frame": dataclasses.asdict(self.frame),
                             **({"heldout": self.stats["heldout"]} if "heldout" in self.stats else {}),
                             **({"label_objects": self.label_objects} if self.label_objects else {})})

    @classmethod
    def load(cls, path: str | Path) -> PoseResult:
        """A PoseResult back from what `save` wrote: `path` is its folder or its transforms.json (with
        frame.json, poses_report.json and the point clouds beside it). The frames are read by
        `load_dataset` (paths confined to the folder); InputError names a missing or malformed file."""
        from splattwin.capture import nerfstudio
        from splattwin.poses.twin_frame import load_frame

        path = Path(path)
        tf = path / "transforms.json" if path.is_dir() else path
        out = tf.parent
        if not tf.is_file():
            raise InputError("no transforms.json here: not a folder written by PoseResult.save (or splattwin poses)", tf)
        ds = nerfstudio.read(tf)
        frame = load_frame(out / FRAME_FILE)
        rep = io.read_json(own_file(out, out / REPORT_FILE, REPORT_FILE), "no poses_report.json beside transforms.json") \
            if (out / REPORT_FILE).is_file() else {}
        if not isinstance(rep, dict):
            raise InputError("malformed poses report: expected a JSON object", out / REPORT_FILE)
        stats = {k: v for k, v in rep.items() if k not in ("frame", "T_out_in", "unregistered", "depth_ply", "bundled")}
        T = rep.get("T_out_in")
        if T is None:
            T_out_in = np.eye(4)
        else:
            try:
                T_out_in = np.asarray(T, dtype=np.float64)
            except (TypeError, ValueError):
                T_out_in = None
            if T_out_in is None or T_out_in.shape != (4, 4) or not np.all(np.isfinite(T_out_in)):
                raise InputError("malformed poses report: T_out_in must be a finite 4x4 matrix", out / REPORT_FILE)
        unreg = rep.get("unregistered", [])
        if not isinstance(unreg, list) or not all(isinstance(u, str) for u in unreg):
            raise InputError("malformed poses report: unregistered must be a list of image names", out / REPORT_FILE)
        d_xyz = d_rgb = None
        if isinstance(rep.get("depth_ply"), str) and (out / DEPTH_PLY).is_file():
            d_xyz, d_rgb = nerfstudio.read_points_ply(out / DEPTH_PLY)
        return cls(frames=ds.frames, unregistered=list(unreg), frame=frame, points_xyz=ds.points_xyz,
                   points_rgb=ds.points_rgb, depth_xyz=d_xyz, depth_rgb=d_rgb, T_out_in=T_out_in, stats=stats,
                   depth_scale=ds.depth_scale, label_objects=ds.meta.get("label_objects") or None)

    def save(self, out_dir: str | Path, bundle: bool = True) -> Path:
        """Write OUT/transforms.json (+ points3D.ply), OUT/frame.json, OUT/poses_report.json, OUT/cameras.png,
        and OUT/points3D_depth.ply (back-projected RGB-D cloud) when there is one.

        bundle=True (default): the frames' images, depth maps and masks are hard-linked (or copied) into
        OUT/images/, OUT/depth/, ... (`splattwin.capture.bundle`), so OUT is a self-contained nerfstudio
        dataset that can be moved, and transforms.json holds only paths inside OUT. bundle=False: its
        paths point at the input files where they are, relative to OUT; the files must then lie under OUT
        (e.g. OUT is the capture folder), else InputError before anything is written: `load_dataset`
        refuses a transforms.json whose paths lead outside its folder (`splattwin.paths`).
        Returns the transforms.json path.
        """
        from splattwin.capture import nerfstudio
        from splattwin.capture.bundle import bundle_frames, remove_unbundled

        out = Path(out_dir)
        if not bundle:
            outside = nerfstudio.outside_files(self.to_dataset(out), out)
            if outside:
                raise InputError(f"save(bundle=False): {len(outside)} input files lie outside {out} or are "
                                 f"symbolic links to files outside (e.g. {outside[0]}), and load_dataset refuses a transforms.json whose paths lead outside "
                                 f"its folder: save with bundle=True (the default: the files are linked into "
                                 f"{out}), or into a folder that holds them", out)
        out.mkdir(parents=True, exist_ok=True)
        earlier = _bundled_record(out)   # read before this run's report replaces it
        extra: dict = {}
        if self.depth_xyz is not None and len(self.depth_xyz):
            nerfstudio.write_points_ply(out / DEPTH_PLY, self.depth_xyz, self.depth_rgb)
            extra["depth_ply"] = DEPTH_PLY  # the RGB-D initialiser, beside the SfM points (ply_file_path)
        io.write_json(out / FRAME_FILE, dataclasses.asdict(self.frame))
        ds = self.to_dataset(out)
        inputs = [p for f in ds.frames for p in (f.image_path, f.depth_path, f.mask_path, f.label_path) if p]
        placed: list[str] = []
        if bundle:
            ds.frames = bundle_frames(ds.frames, out, placed=placed)
        # the files of views a rebuild no longer has (fewer frames, another capture) leave the folder
        remove_unbundled(out, earlier, placed, inputs)
        io.write_json(out / REPORT_FILE, {**self.stats, **extra, "frame": dataclasses.asdict(self.frame),
                                          "T_out_in": self.T_out_in, "unregistered": self.unregistered,
                                          "bundled": placed})
        try:
            plot_cameras(self, out / "cameras.png")
        except Exception as e:  # a picture must never fail the run
            log.warning("could not draw cameras.png: %s", e)
        # transforms.json last: its presence marks a finished output.
        return nerfstudio.write(ds, out / "transforms.json", ply_name="points3D.ply", confine=True)


# the flags that choose a pose source, in both commands' spelling (the same message serves `build` and `poses`)
KNOWN_FLAGS = "known poses (build: --poses known; splattwin poses: --known)"
POSE_SOURCES = "SfM (build: --poses sfm, or auto; splattwin poses: --sfm) or the robot's poses (--robot-poses POSES)"


def _no_poses(dataset: Dataset) -> str:
    what = "a video has" if dataset.meta.get("format") == "video" else "this dataset has"
    return f"{what} no camera poses; estimate them by {POSE_SOURCES}"


def _given(dataset: Dataset) -> Path:
    """The input the user named: the video, not the folder its frames were extracted into (`capture.video`)."""
    return Path(dataset.meta.get("video") or dataset.root)


def _as_given(e: InputError, dataset: Dataset) -> InputError:
    """`e` naming the video the user gave when it names the folder of the video's extracted frames."""
    if not dataset.meta.get("video") or e.path is None or e.path.resolve() != Path(dataset.root).resolve():
        return e
    return InputError(f"{e.problem} (its frames: {e.path})", _given(dataset))


def _bundled_record(out: Path) -> list:
    """The files the last `PoseResult.save` into `out` bundled there (poses_report.json "bundled"; an
    unreadable or older report: none, nothing is removed)."""
    from splattwin.limits import MAX_RECORD_BYTES

    try:
        rep = io.read_json(out / REPORT_FILE, "no poses report", MAX_RECORD_BYTES)
    except (InputError, OSError):
        return []
    names = rep.get("bundled") if isinstance(rep, dict) else None
    return names if isinstance(names, list) else []


# ------------------------------------------------------------------------------------------------
def _too_few_video_frames(dataset: Dataset) -> None:
    """InputError naming the video that gave SfM fewer than 2 frames, and why (the generic SfM message named
    no file and advised intrinsics and overlap)."""
    from splattwin.wording import plural

    n, decoded = len(dataset.frames), dataset.meta.get("frames_decoded")
    if decoded is not None and decoded < 2:
        why = f"the video has {plural(decoded, 'decodable frame')}"
    else:
        why = (f"of {decoded} decoded frames, the others differ too little from it (a camera that did not move; "
               f"--min-change 0 keeps near-duplicates)")
    raise InputError(f"gave {plural(n, 'frame')} ({why}); structure from motion needs >= 2",
                     dataset.meta.get("video") or dataset.root)


def estimate_poses(dataset: Dataset, options: PoseOptions | None = None) -> PoseResult:
    """Camera poses for `dataset` and the frame they are expressed in (see module docstring).

    `dataset` is left as it is: the hold-out split (`frame.split`, meta "heldout"/"split") is chosen on a
    copy, and comes back in the result's frames (`PoseResult.to_dataset()`)."""
    opts = _normalised(options or PoseOptions())
    if not isinstance(dataset, Dataset):
        raise InputError(f"estimate_poses needs a Dataset (splattwin.capture.load_dataset), got {type(dataset).__name__}")
    if not dataset.frames:
        raise InputError("dataset has no frames", dataset.root)
    given = dataset  # for the SfM fallback (a fresh run of this function)
    # the caller's frames and meta stay untouched (apply_holdout sets splits in place)
    dataset = dataclasses.replace(dataset, frames=[dataclasses.replace(f) for f in dataset.frames],
                                  meta=dict(dataset.meta))
    method = opts.method
    if method == "auto":
        method = "robot" if opts.robot_poses is not None else ("known" if dataset.has_poses else "sfm")
    if method not in ("sfm", "known", "robot"):
        raise InputError(f"unknown pose method {opts.method!r} (auto, sfm, known, robot)")
    if opts.up not in UP_AXES:
        raise InputError(f"--up {opts.up!r}: use auto, keep, or the world axis that points up (+z, -z, +y, -y, +x, -x)")
    if method == "known" and not dataset.has_poses:
        raise InputError(f"{KNOWN_FLAGS}: {_no_poses(dataset)}", _given(dataset))
    if method == "sfm" and len(dataset.frames) < 2 and dataset.meta.get("format") == "video":
        _too_few_video_frames(dataset)

    if opts.time_offset_ms:
        _apply_time_offset(dataset, float(opts.time_offset_ms))

    from splattwin.poses.holdout import HOLDOUT_KEY, apply_holdout

    heldout = apply_holdout(dataset, opts.holdout)  # capture order, before SfM (splattwin.poses.holdout)
    frames = list(dataset.frames)
    names = [_frame_key(f) for f in frames]
    robot = _robot_cameras(opts, frames, names, dataset) if opts.robot_poses is not None else None
    robot_T = robot.T_base_cam if robot is not None else None
    stats: dict = {"method": method, "total": len(frames), HOLDOUT_KEY: heldout.record()}
    pts_xyz = pts_rgb = None
    T_out_in = np.eye(4)
    frame: TwinFrame | None = None
    prior: TwinFrame | None = None
    in_cams: dict[str, Camera]

    if method == "sfm":
        from splattwin.poses.sfm import run_sfm

        sopts = _sfm_options(opts, intrinsics=_intrinsics_tuple(opts, frames), ordered=bool(dataset.meta.get("sequential")))
        import tempfile

        tmp = None if opts.work_dir is not None else tempfile.TemporaryDirectory(prefix="splattwin_sfm_")
        work = Path(opts.work_dir) if opts.work_dir is not None else Path(tmp.name)  # type: ignore[union-attr]
        try:
            sfm = run_sfm([f.image_path for f in frames], work, sopts, progress=opts.progress,
                          masks=_feature_masks(frames))
        except InputError as e:
            raise _as_given(e, dataset) from e
        finally:
            if tmp is not None:
                tmp.cleanup()
        key_of = _sfm_keys(frames)
        in_cams = {}
        for k, cam in sfm.cameras.items():
            n = key_of[k]
            in_cams[n] = dataclasses.replace(cam, name=frames[names.index(n)].camera.name or Path(k).stem)
        pts_xyz, pts_rgb = sfm.points_xyz, sfm.points_rgb
        stats.update(sfm.report())
        log.info("SfM registered %d/%d images, mean reprojection error %.3f px, %d points",
                 sfm.num_registered, sfm.num_total, sfm.mean_reproj_error, len(pts_xyz))
        input_scaled = False
    elif method == "robot":
        assert robot_T is not None
        in_cams = {n: _with_pose(f.camera, robot_T[n], opts) for f, n in zip(frames, names) if n in robot_T}
        stats.update(registered=len(in_cams))
        if opts.check_hand_eye:
            chk = _check_hand_eye(robot, opts, stats, cams=in_cams,
                                  images={n: f.image_path for f, n in zip(frames, names)})
            keys = [n for n in robot.T_base_ee if n in in_cams]
            _check_intrinsics(chk.measures, [in_cams[n].T_world_cam for n in keys], _intrinsics_source(dataset, opts),
                              stats)
            cons = stats["hand_eye_check"].get("pose_consistency") or {}
            if cons.get("verdict") == "bad" and opts.method == "auto":
                res = _sfm_fallback(given, opts, stats, cons)
                if res is not None:
                    return res
        frame = TwinFrame(source="robot", scaled=True, scale_uncertainty_rel=0.0,
                      description="robot base frame: T_base_cam = T_base_ee @ T_ee_cam (metres)")
        input_scaled = True
    else:
        in_cams = {n: _with_pose(f.camera, f.camera.T_world_cam, opts) for f, n in zip(frames, names)}
        pts_xyz, pts_rgb = dataset.points_xyz, dataset.points_rgb
        stats.update(registered=len(in_cams))
        if opts.check_hand_eye and dataset.meta.get("format") in KNOWN_POSE_CHECKED:
            _check_known_poses(dataset, opts, frames, names, in_cams, stats)
        elif opts.check_hand_eye and dataset.meta.get("format") == "nerfstudio" and not dataset.meta.get("sfm_derived"):
            _check_transforms_convention(dataset, frames, names, in_cams)
        meta_frame = dataset.meta.get("frame")
        prior = TwinFrame(**meta_frame) if isinstance(meta_frame, dict) else frame_beside(dataset.meta.get("path", dataset.root))  # chained runs
        if opts.scale != "auto":
            prior = None  # the user says what the lengths are: that overrides a frame.json beside the poses
        input_scaled = _input_scaled(dataset, prior, opts.scale)
        frame = prior or (TwinFrame(source="known_poses", scaled=True, scale_uncertainty_rel=None,
                                description="camera poses given with the dataset, metric"
                                            + (" (--scale metric)" if opts.scale == "metric" else ", assumed"))
                          if input_scaled else None)

    # -- frame definition ----------------------------------------------------------------------
    order = [n for n in names if n in in_cams]
    if method == "sfm" and robot_T is not None:
        if opts.check_hand_eye:
            _check_hand_eye(robot, opts, stats, cams=in_cams)
        tgt = np.array([robot_T[n][:3, 3] for n in order if n in robot_T])
        src = np.array([in_cams[n].center for n in order if n in robot_T])
        if len(src) < 3:
            raise InputError(f"only {len(src)} registered images have robot poses; need >= 3 to align SfM to the robot",
                             opts.robot_poses)
        try:
            fit = align.umeyama(src, tgt)
        except ValueError as e:
            raise InputError(f"cannot align SfM to the robot poses: {e}", opts.robot_poses) from e
        T_out_in = fit.S
        frame = TwinFrame(source="sfm+robot", scaled=True, scale_uncertainty_rel=fit.scale_uncertainty_rel,
                      description=f"robot base frame via Umeyama Sim(3) of {len(src)} SfM camera centres to robot "
                                  f"camera centres; residual RMS {fit.rms * 1000:.2f} mm")
        stats["umeyama"] = {"residual_rms_m": fit.rms, "residual_max_m": float(fit.residuals.max()),
                            "scale": fit.scale, "n": len(src)}
        log.info("SfM -> robot: residual RMS %.2f mm, max %.2f mm", fit.rms * 1000, fit.residuals.max() * 1000)
    elif opts.marker_size is not None:
        from splattwin.poses.marker import fit_marker

        cams = [in_cams[n] for n in order]
        imgs = [load_image(frames[names.index(n)].image_path) for n in order]
        mf = fit_marker(cams, imgs, opts.marker_size, opts.marker_dict, opts.marker_id, where=dataset.root,
                        pixel_sigma_floor=float(stats.get("mean_reproj_error", 0.0)))
        T_out_in = align.sim3_inverse(mf.S_sfm_marker)
        frame = TwinFrame(source="marker", scaled=True, scale_uncertainty_rel=mf.scale_uncertainty_rel,
                      description=f"ArUco {opts.marker_dict} id {opts.marker_id} ({opts.marker_size * 1000:.1f} mm) frame: "
                                  f"origin at its centre, z = its normal; seen in {len(mf.views)} views, "
                                  f"corner reprojection RMS {mf.reproj_rms:.2f} px")
        stats["marker"] = {"views": mf.views, "reproj_rms_px": mf.reproj_rms,
                           "side_lengths_m": (mf.side_lengths * 1.0).tolist()}
    elif opts.known_length is not None or not input_scaled:
        from splattwin.poses.table import scale_from_known_length, table_frame
        from splattwin.poses.up import table_plane_under_cameras

        if (pts_xyz is None or len(pts_xyz) < 20) and method != "sfm" and opts.triangulate:
            # known poses without points: triangulate them now (input frame), the table plane needs them
            tri = _triangulate(opts, [frames[names.index(n)].image_path for n in order], [in_cams[n] for n in order],
                               stats)
            if tri is not None:
                pts_xyz, pts_rgb = tri
        if pts_xyz is None or len(pts_xyz) < 20:
            raise InputError("the table frame needs sparse points (SfM or the dataset's point cloud); none available",
                             dataset.root)
        plane, table_evidence = table_plane_under_cameras(pts_xyz, [in_cams[n] for n in order], seed=opts.seed)
        T_tab_in = table_frame(plane, pts_xyz, in_cams[order[0]])
        stats["table_plane"] = {"inliers": int(plane.inliers.sum()), "rms": plane.rms, **table_evidence}
        depth_fit = None
        if (opts.known_length is None and method == "sfm" and opts.scale_from_depth
                and any(f.depth_path is not None for f in frames)):
            depth_fit = _depth_scale(frames, names, in_cams, pts_xyz, dataset, stats)
        if depth_fit is not None:
            S = np.diag([depth_fit.scale, depth_fit.scale, depth_fit.scale, 1.0])
            T_out_in = S @ T_tab_in
            frame = TwinFrame(source="table_plane+depth", scaled=True, scale_uncertainty_rel=depth_fit.uncertainty_rel,
                              description=f"table frame (RANSAC plane, z up, table top z = 0, origin near the table "
                                          f"centre); metric scale from the depth images: median of "
                                          f"{depth_fit.readings} sensor/SfM depth ratios over {depth_fit.views} views")
        elif opts.known_length is not None:
            tab_cams = {n: align.transform_camera(T_tab_in, c) for n, c in in_cams.items()}
            s, unc, note = scale_from_known_length(opts.known_length, tab_cams, plane.rms,
                                                   stats.get("mean_reproj_error", 0.5))
            S = np.diag([s, s, s, 1.0])
            T_out_in = S @ T_tab_in
            log.info("metric scale from %s = %g m: x %.6g (SfM unit -> m), uncertainty %.1f %%", note,
                     opts.known_length.value, s, 100.0 * unc if unc is not None else float("nan"))
            frame = TwinFrame(source="table_plane+known_length", scaled=True, scale_uncertainty_rel=unc,
                          description=f"table frame (RANSAC plane, z up, table top z = 0, origin near the table "
                                      f"centre); scale from {note} = {opts.known_length.value} m")
        else:
            T_out_in = T_tab_in
            frame = TwinFrame(source="unscaled", scaled=False, scale_uncertainty_rel=None,
                          description="table frame (RANSAC plane, z up, table top z = 0) in arbitrary SfM units: "
                                      "NOT metric. Give --marker-size, --known-length or --robot-poses for a metric twin")
            # said by the poses stage, which does not know whether a twin follows (`poses`, `build --until splats`)
            log.warning("no metric scale: the frame is marked 'unscaled' (lengths in SfM units; thresholds derived "
                        "from the cameras' distance to the scene); a twin built on these poses is unscaled too, and "
                        "robot planning refuses an unscaled twin (give --known-length, --marker-size or metric poses "
                        "for a metric one)")
        frame = dataclasses.replace(frame, up_check={"source": "table plane checked against the cameras' horizon",
                                                     **table_evidence})
    assert frame is not None
    if method == "known" and prior is None and input_scaled and opts.marker_size is None and opts.known_length is None:
        if ((pts_xyz is None or len(pts_xyz) == 0) and opts.triangulate and len(order) >= 2
                and not any(f.depth_path is not None for f in frames)):
            # known poses, no points, no depth: triangulate now (input frame), so the up check also has the
            # table plane and not only the cameras
            tri = _triangulate(opts, [frames[names.index(n)].image_path for n in order], [in_cams[n] for n in order],
                               stats)
            if tri is not None:
                pts_xyz, pts_rgb = tri
        frame, T_out_in = _check_up(frame, [in_cams[n] for n in order], pts_xyz, frames, dataset, opts, stats)
    elif opts.up not in ("auto", "keep"):
        log.warning("--up %s ignored: it applies to known poses in their own world, but this frame comes from %s",
                    opts.up, frame.source if prior is None else "an earlier poses run (frame.json)")
    T_twin_input = np.asarray(T_out_in, dtype=np.float64)
    if prior is not None and prior.T_twin_input is not None:  # chained runs: from the original input
        T_twin_input = T_twin_input @ np.asarray(prior.T_twin_input, dtype=np.float64)
    frame = dataclasses.replace(frame, T_twin_input=T_twin_input.tolist())

    out_cams = {n: align.transform_camera(T_out_in, c) for n, c in in_cams.items()}
    if frame.source == "sfm+robot" and opts.shared_intrinsics:
        # Images SfM could not register still have exact robot poses: pose them with the shared SfM camera
        # (only images of the reference camera's size: other sizes are other cameras).
        ref = in_cams[order[0]]
        size = {n: (f.camera.width, f.camera.height) for f, n in zip(frames, names)}
        filled = [n for n in names if n not in out_cams and n in robot_T and size[n] == (ref.width, ref.height)]
        for n in filled:
            out_cams[n] = Camera(K=ref.K, width=ref.width, height=ref.height, T_world_cam=robot_T[n], dist=ref.dist,
                                 name=frames[names.index(n)].camera.name)
        if filled:
            stats["posed_from_robot_only"] = filled
            log.info("%d image(s) not registered by SfM posed from their robot poses", len(filled))
    if pts_xyz is not None:
        pts_xyz = align.transform_points(T_out_in, pts_xyz)
    if not frame.scaled and pts_xyz is not None and len(pts_xyz):
        # the length every metric threshold of the later stages is expressed in (TwinFrame.nominal_metre)
        from splattwin.poses.table import nominal_metre

        nm = nominal_metre(list(out_cams.values()), pts_xyz, seed=opts.seed)
        frame = dataclasses.replace(frame, nominal_metre=None if nm is None else round(nm, 6))
        if nm is not None:
            stats["nominal_metre"] = round(nm, 6)
    out_frames = [dataclasses.replace(f, camera=out_cams[n]) for f, n in zip(frames, names) if n in out_cams]
    unregistered = [n for n in names if n not in out_cams]
    stats["registered"] = len(out_frames)
    stats["unregistered"] = unregistered

    # where the initial point cloud (that seeds the splats) comes from, for the logs (stats["points_source"])
    points_source = None
    if pts_xyz is not None and len(pts_xyz):
        points_source = ("SfM points" if method == "sfm" else "points triangulated from the known poses"
                         if "error" not in stats.get("triangulation", {"error": 1}) else "the capture's points")
    depth_xyz = depth_rgb = None
    if opts.depth_points and any(f.depth_path is not None for f in out_frames):
        if frame.scaled:
            from splattwin.poses.depth import backproject_frames

            # training views only: the cloud seeds the splats (colours and all), and a held-out view's
            # pixels must not reach the model it evaluates
            seed_frames = [f for f in out_frames if f.split != "heldout"] or out_frames
            depth_xyz, depth_rgb = backproject_frames(seed_frames, stride=opts.depth_stride,
                                                      depth_scale=dataset.depth_scale, seed=opts.seed)
            stats["depth_points"] = int(len(depth_xyz))
            stats["depth_points_views"] = len(seed_frames)
            if pts_xyz is None or len(pts_xyz) == 0:
                pts_xyz, pts_rgb = depth_xyz, depth_rgb
                points_source = "depth back-projection" if len(depth_xyz) else None
                if method != "sfm" and opts.triangulate and len(seed_frames) >= 2 and len(depth_xyz):
                    # robot or known poses: nothing else has measured the scene, so the depth's scale (and
                    # the poses' own) is checked against points triangulated with the poses held fixed
                    tri = _triangulate(opts, [f.image_path for f in seed_frames], [f.camera for f in seed_frames],
                                       stats, purpose="the depth-scale check")
                    if tri is not None and not _depth_fits_points(frame, out_frames, tri[0], dataset, stats,
                                                                  points="triangulated"):
                        pts_xyz, pts_rgb = tri
                        points_source = "points triangulated from the known poses (the depth disagreed with them)"
            elif len(depth_xyz) and _depth_fits_points(frame, out_frames, pts_xyz, dataset, stats):
                # SfM (or the dataset's) sparse points in a metric frame: the depth cloud joins them. Alone,
                # a few hundred SfM points on the objects' textured edges seeded the splats (the table
                # stopped at the objects' outer edges, an object vanished); the depth covers every surface
                from splattwin.poses.depth import merge_with_depth

                n_sparse = len(pts_xyz)
                pts_xyz, pts_rgb = merge_with_depth(pts_xyz, pts_rgb, depth_xyz, depth_rgb, seed=opts.seed)
                stats["initial_points"] = {"sparse": int(n_sparse), "depth": int(len(depth_xyz)),
                                           "merged": int(len(pts_xyz)), "voxel_m": 0.002}
                points_source = f"{points_source} + depth back-projection"
                log.info("initial point cloud: %d sparse points + %d back-projected depth points -> %d "
                         "(one per 2 mm voxel)", n_sparse, len(depth_xyz), len(pts_xyz))
        else:
            log.warning("depth images ignored for the point cloud: the frame is unscaled")
    if (pts_xyz is None or len(pts_xyz) == 0) and method != "sfm" and opts.triangulate and len(out_frames) >= 2:
        # known poses, no point cloud, no (metric) depth: points from the images with the poses held fixed
        tri = _triangulate(opts, [f.image_path for f in out_frames], [f.camera for f in out_frames], stats)
        if tri is not None:
            pts_xyz, pts_rgb = tri
            points_source = "points triangulated from the known poses"
    if points_source is not None and pts_xyz is not None and len(pts_xyz):
        stats["points_source"] = points_source
    _check_exposure(out_frames, pts_xyz, opts, stats)
    return PoseResult(frames=out_frames, unregistered=unregistered, frame=frame, points_xyz=pts_xyz,
                      points_rgb=pts_rgb, depth_xyz=depth_xyz, depth_rgb=depth_rgb, T_out_in=T_out_in,
                      stats=stats, depth_scale=dataset.depth_scale, label_objects=dataset.meta.get("label_objects"))


# ------------------------------------------------------------------------------------------------
def _feature_masks(frames: list[DataFrame]) -> dict[Path, Path]:
    """{image: loss mask} of the frames whose loss mask (a photo's transparent pixels, a nerfstudio mask_path)
    has the image's size: SfM extracts no features where it is 0, as COLMAP's mask_path (a reduced mask,
    nerfstudio's masks_2/, is left out: COLMAP refuses the image with it)."""
    from splattwin.capture.dataset import image_size

    return {f.image_path: f.mask_path for f in frames
            if f.mask_path is not None and image_size(f.mask_path) == (f.camera.width, f.camera.height)}


def _check_exposure(frames: list[DataFrame], pts_xyz: np.ndarray | None, opts: PoseOptions, stats: dict) -> None:
    """stats["exposure"]: per-image exposure / white-balance gains measured on the sparse points
    (`splattwin.poses.exposure`), logged (info: the splats stage warns when they differ beyond its threshold)."""
    from splattwin.poses import exposure

    rec = exposure.measure_exposure([f.camera for f in frames], [f.image_path for f in frames],
                                    [f.name for f in frames], pts_xyz, seed=opts.seed)
    stats["exposure"] = rec
    # the one warning is the splats stage's (`splat.appearance.decide`), which knows whether a correction is
    # trained; here the measurement only: a warning here too said the same thing twice in one build
    log.info("%s%s", exposure.describe(rec),
             "; the splats stage corrects it or warns (--splat.appearance)" if rec.get("varies") else "")


def _check_up(frame: TwinFrame, cams: list[Camera], pts_xyz: np.ndarray | None, frames: list[DataFrame],
              dataset: Dataset, opts: PoseOptions, stats: dict) -> tuple[TwinFrame, np.ndarray]:
    """Known poses: find up (cameras + table plane of the points or depth) and rotate the world to z up
    (`splattwin.poses.up`). Returns the frame (with `up_check`) and T_out_in."""
    if opts.up == "keep":
        return dataclasses.replace(frame, up_check={"input_up": "kept as given (--up keep)"}), np.eye(4)
    from splattwin.poses.up import check_up, depth_points

    pts = pts_xyz
    if (pts is None or len(pts) < 50) and opts.up == "auto":
        pts = depth_points(frames, dataset.depth_scale, seed=opts.seed)
    chk = check_up(cams, pts, opts.up, where=dataset.meta.get("path", dataset.root), seed=opts.seed)
    up_check, T_twin_input, what = chk.to_dict(), chk.T_twin_input, chk.describe()
    if chk.input_up == "tilted" and pts is not None and len(pts) >= 20:
        # A tilted world is no robot's or rig's frame (those are level: z up, or a quarter/half turn away)
        # but an arbitrary one, e.g. the first camera's: levelled alone, its table top stayed wherever that
        # origin put it (0.74 m below z = 0 in a camera-0 world) while the robot stands on z = 0. So it
        # gets the table frame, as an SfM capture does: table top z = 0, origin near the table centre.
        from splattwin.poses.table import table_frame
        from splattwin.poses.up import table_plane_under_cameras

        pts_level = align.transform_points(T_twin_input, pts)
        cams_level = [align.transform_camera(T_twin_input, c) for c in cams]
        plane, _ = table_plane_under_cameras(pts_level, cams_level, seed=opts.seed)
        T_twin_input = table_frame(plane, pts_level, cams_level[0]) @ T_twin_input
        up_check["moved_to_table_frame"] = True
        what += "; moved into the table frame (table top z = 0, origin near the table centre)"
    stats["up_check"] = up_check
    if chk.changed:
        log.warning("known poses: %s (recorded in frame.json)", what)
        frame = dataclasses.replace(frame, description=f"{frame.description}; {what}")
    else:
        log.info("known poses: %s", what)
    return dataclasses.replace(frame, up_check=up_check), T_twin_input


def _depth_scale(frames: list[DataFrame], names: list[str], in_cams: dict[str, Camera], pts_xyz: np.ndarray,
                 dataset: Dataset, stats: dict, max_views: int = 24):
    """SfM on an RGB-D capture: metres per SfM unit from up to `max_views` registered views' depth images
    (`splattwin.poses.depth_scale`), or None (logged, and recorded in stats) when they give none."""
    from splattwin.capture import load_depth
    from splattwin.poses.depth_scale import scale_from_depth

    views = [(f, in_cams[n]) for f, n in zip(frames, names) if n in in_cams and f.depth_path is not None]
    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    cams = [views[i][1] for i in pick]
    depths = [load_depth(views[i][0].depth_path, dataset.depth_scale, size=(c.width, c.height))
              for i, c in zip(pick, cams)]
    fit, note = scale_from_depth(cams, depths, pts_xyz)
    if fit is None:
        log.warning("no metric scale from the depth images: %s", note)
        stats["depth_scale"] = {"error": note}
        return None
    stats["depth_scale"] = fit.to_dict()
    log.info("metric scale from the depth images: x %.6g (SfM unit -> m), %s, uncertainty %.1f %%", fit.scale, note,
             100 * fit.uncertainty_rel)
    return fit


def _depth_fits_points(frame: TwinFrame, frames: list[DataFrame], pts_xyz: np.ndarray, dataset: Dataset,
                       stats: dict, max_views: int = 24, points: str = "sparse") -> bool:
    """Whether the back-projected depth may join the sparse points `pts_xyz` (output frame, metric): their
    scale agrees with the depth images (sensor depth / point depth within 5 %, or 3 x the frame's scale
    uncertainty). A frame scaled by these depth images agrees by construction; a marker, known length, robot
    or the dataset's own points are checked, so that depth in other units or from an unregistered sensor
    does not put a second, misplaced copy of the scene into the initial cloud. points: what `pts_xyz` are
    ("sparse": SfM's or the dataset's; "triangulated": from the images with robot or known poses held fixed,
    the only check of the depth's scale there)."""
    if frame.source == "table_plane+depth":
        return True
    from splattwin.capture import load_depth
    from splattwin.poses.depth_scale import scale_from_depth

    views = [f for f in frames if f.depth_path is not None]
    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    cams = [views[i].camera for i in pick]
    depths = [load_depth(views[i].depth_path, dataset.depth_scale, size=(c.width, c.height)) for i, c in zip(pick, cams)]
    fit, note = scale_from_depth(cams, depths, pts_xyz)
    tol = max(0.05, 3.0 * (frame.scale_uncertainty_rel or 0.0))
    if fit is None:
        ok = len(pts_xyz) < 50   # too few sparse points to check: they barely count beside the depth
        why = f"cannot check the depth against the {len(pts_xyz)} {points} points: {note}"
    else:
        ok = abs(fit.scale - 1.0) <= tol
        why = f"sensor depth / {points} point depth {fit.scale:.4g} (tolerance {tol:.0%})"
    rec = {"ok": bool(ok), "why": why, "points": points, "n_points": int(len(pts_xyz))}
    if fit is not None:
        rec["ratio"] = round(float(fit.scale), 5)
    stats["depth_fits_points"] = rec
    if not ok:
        ds = dataset.depth_scale
        if ds is None and views:
            from splattwin.capture.dataset import default_depth_scale

            ds = default_depth_scale(views[0].depth_path)
        hint = ""
        if fit is not None and ds:
            hint = (f"; a depth scale of {ds / fit.scale:.4g} m per depth unit instead of {ds:.4g} would make them "
                    f"agree")
        log.warning("depth images left out of the initial point cloud (the %d %s points only): %s; check the depth "
                    "scale (%s m per depth unit: BOP depth_scale, the intrinsics file's depth factor, nerfstudio "
                    "depth_unit_scale_factor)%s, that the depth is registered to the colour camera%s",
                    len(pts_xyz), points, why.rstrip("?."), "unknown" if ds is None else f"{ds:.4g}", hint,
                    ", and the camera poses" if points == "triangulated" else "")
    return ok


def _sfm_fallback(dataset: Dataset, opts: PoseOptions, stats: dict, cons: dict) -> PoseResult | None:
    """`--poses.method auto` with robot poses that clearly do not fit the photos (`hand_eye_check`
    pose_consistency "bad"): SfM aligned to the robot poses instead (the sfm+robot frame: the photos fix the
    relative poses, the robot only the metric frame). Its result, recording why (stats["pose_fallback"], the
    frame's description); None when SfM does not register the images (the robot poses are then kept)."""
    why = (f"robot poses + hand-eye off the photos' epipolar geometry by a median {cons['sampson_median_px']:.2f} px "
           f"({cons['sampson_median_mrad']:.1f} mrad > {cons['bad_mrad']:g})")
    try:
        res = estimate_poses(dataset, dataclasses.replace(opts, method="sfm"))
    except InputError as e:
        log.warning("SfM aligned to the robot poses failed (%s): keeping the robot poses as they are", e.problem)
        stats["pose_fallback"] = {"from": "robot", "tried": "sfm+robot", "used": False, "why": why,
                                  "error": e.problem}
        return None
    if res.frame.source != "sfm+robot":  # cannot happen with robot poses given; never silently another frame
        stats["pose_fallback"] = {"from": "robot", "tried": "sfm+robot", "used": False, "why": why,
                                  "error": f"frame {res.frame.source}"}
        return None
    res.stats["pose_fallback"] = {"from": "robot", "to": "sfm+robot", "used": True, "why": why,
                                  "robot_hand_eye_check": stats.get("hand_eye_check")}
    res.stats["method_requested"] = "auto"
    res.frame = dataclasses.replace(res.frame, description=f"{res.frame.description} (automatic fallback from robot "
                                                           f"poses alone: {why})")
    um = res.stats.get("umeyama", {})
    log.warning("poses: SfM aligned to the robot poses (frame sfm+robot) used instead of the robot poses alone: "
                "%d/%d images registered, Umeyama residual RMS %.1f mm", res.stats.get("registered", 0),
                res.stats.get("total", 0), 1000.0 * float(um.get("residual_rms_m", float("nan"))))
    return res


def _input_scaled(dataset: Dataset, prior: TwinFrame | None, scale: str) -> bool:
    """Whether known poses are metric or already in a defined frame (True), or need the table frame in
    their own units (False). `scale` metric/unscaled says which. auto: a frame.json beside the poses (a
    chained run) is their frame; SfM output is not metric: a COLMAP model, a transforms.json written by
    nerfstudio's COLMAP converters (`sfm_derived` in the dataset's meta), a 3DGS cameras.json (3DGS
    writes it from its COLMAP input); other poses (robot and capture-rig exports) are taken as metric."""
    if scale in ("metric", "unscaled"):
        return scale == "metric"
    if prior is not None:
        return True
    if dataset.meta.get("format") == "colmap":
        return False
    if dataset.meta.get("format") == "cameras.json":
        why = "a 3DGS cameras.json, which 3DGS writes from its COLMAP input"
    elif dataset.meta.get("sfm_derived"):
        why = f"it has {', '.join(dataset.meta['sfm_derived'])}, left by nerfstudio's COLMAP converters"
    else:
        return True
    log.warning("%s: the poses come from SfM (%s), so their lengths are not metres: they are put in a "
                "table frame marked 'unscaled', as is any twin built on them (give --known-length or "
                "--marker-size for a metric one, or --scale metric if they are metres)",
                dataset.meta.get("path", dataset.root), why)
    return False


def _frame_key(f: DataFrame) -> str:
    from splattwin.paths import unfollowed

    return str(unfollowed(f.image_path))  # a link's own path, matching the SfM names (sfm.image_layout)


def _sfm_keys(frames: list[DataFrame]) -> dict[str, str]:
    """SfM image name (relative to the common folder) -> our frame key."""
    from splattwin.poses.sfm import image_layout

    _, rel = image_layout([f.image_path for f in frames])
    return {r: _frame_key(f) for r, f in zip(rel, frames)}


def _triangulate(opts: PoseOptions, image_paths: list[Path], cameras: list[Camera], stats: dict,
                 purpose: str | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Sparse points from images with known cameras (poses held fixed), in the cameras' frame; None (and a
    warning) when nothing can be triangulated. purpose: what the points are for, when only a check (then
    a failure is logged as info, naming it)."""
    from splattwin.poses.triangulate import triangulate_known_poses

    work = Path(opts.work_dir) / "triangulation" if opts.work_dir is not None else None
    try:
        tri = triangulate_known_poses(image_paths, cameras, work, _sfm_options(opts), progress=opts.progress)
    except InputError as e:
        if purpose is not None:
            log.info("no points triangulated from the known poses for %s (%s): not checked", purpose, e.problem)
        else:
            log.warning("no points from the known poses (%s): training will start from fewer cues", e.problem)
        stats["triangulation"] = {"error": e.problem}
        return None
    stats["triangulation"] = tri.stats
    stats["num_points"] = int(len(tri.points_xyz))
    return tri.points_xyz, tri.points_rgb


def _sfm_options(opts: PoseOptions, intrinsics: tuple[float, float, float, float] | None = None,
                 ordered: bool | None = None):
    from splattwin.poses.sfm import SfmOptions

    return SfmOptions(intrinsics=intrinsics, camera_model=opts.camera_model, shared_intrinsics=opts.shared_intrinsics,
                      matcher=opts.matcher, ordered=ordered, min_registered=opts.min_registered,
                      max_image_size=opts.max_image_size, max_num_features=opts.max_num_features, retry=opts.retry,
                      check_registration=opts.check_registration,
                      num_threads=opts.num_threads, seed=opts.seed)


def _normalised(opts: PoseOptions) -> PoseOptions:
    """Options with their text forms parsed (known_length -> KnownLength, intrinsics -> (fx, fy, cx, cy))."""
    kl = opts.known_length
    if isinstance(kl, str):
        kl = KnownLength.parse(kl)
    if kl is not None:
        kl.validate()
    return dataclasses.replace(opts, known_length=kl, intrinsics=parse_intrinsics(opts.intrinsics))


def parse_intrinsics(value) -> str | tuple[float, float, float, float] | None:
    """None, "dataset", "fx,fy,cx,cy" (pixels) or a sequence of four numbers -> None, "dataset" or a tuple."""
    if value is None:
        return None
    if isinstance(value, str):
        if value.strip() == "dataset":
            return "dataset"
        try:
            value = [float(v) for v in value.split(",")]
        except ValueError as e:
            raise InputError(f"--intrinsics {value!r}: expected fx,fy,cx,cy in pixels or 'dataset'") from e
    vals = tuple(float(v) for v in value)
    # nan passed `<= 0` and reached COLMAP's feature extractor, which stopped the run (exit 1)
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
        raise InputError(f"--intrinsics {value!r}: expected four finite numbers fx,fy,cx,cy with positive focal lengths")
    return vals  # type: ignore[return-value]


def _intrinsics_tuple(opts: PoseOptions, frames: list[DataFrame]) -> tuple[float, float, float, float] | None:
    if opts.intrinsics is None:
        return None
    if opts.intrinsics == "dataset":
        c = frames[0].camera
        return (c.fx, c.fy, c.cx, c.cy)
    fx, fy, cx, cy = (float(v) for v in opts.intrinsics)
    return (fx, fy, cx, cy)


def _with_pose(cam: Camera, T_world_cam: np.ndarray, opts: PoseOptions) -> Camera:
    K = cam.K
    if isinstance(opts.intrinsics, tuple):
        fx, fy, cx, cy = opts.intrinsics
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return Camera(K=K, width=cam.width, height=cam.height, T_world_cam=T_world_cam, dist=cam.dist, name=cam.name)


@dataclass
class _RobotCameras:
    T_base_cam: dict[str, np.ndarray]   # frame key -> camera pose in the robot base frame
    T_base_ee: dict[str, np.ndarray]    # frame key -> flange pose
    T_ee_cam: np.ndarray
    hand_eye_file: Path                 # where the hand-eye came from (--hand-eye, or the pose file: inline)


def _check_hand_eye(robot: _RobotCameras, opts: PoseOptions, stats: dict, cams: dict[str, Camera],
                    images: dict[str, Path] | None = None):
    """The hand-eye against the camera motion seen in the photos (`images`: a few pairs matched) or in an SfM
    model (`cams` independent of the robot): InputError when its inverse fits clearly better
    (`splattwin.poses.hand_eye_check`); the verdict goes to stats["hand_eye_check"]."""
    from splattwin.poses import hand_eye_check as hec

    keys = [n for n in robot.T_base_ee if n in cams]
    T_ee = [robot.T_base_ee[n] for n in keys]
    if images is not None:
        chk = hec.check_with_images(keys, T_ee, robot.T_ee_cam, [images[n] for n in keys], [cams[n] for n in keys])
    else:
        chk = hec.check_with_rotations(keys, T_ee, robot.T_ee_cam, [cams[n].T_world_cam[:3, :3] for n in keys])
    for p in chk.pairs:  # image names, not the frame keys' full paths
        p["a"], p["b"] = Path(p["a"]).name, Path(p["b"]).name
    for p in (chk.consistency or {}).get("per_pair", []):
        p["a"], p["b"] = Path(p["a"]).name, Path(p["b"]).name
    stats["hand_eye_check"] = chk.to_dict()
    hec.report(chk, robot.hand_eye_file, inverted_error=lambda msg: InputError(msg, robot.hand_eye_file))
    cons = chk.consistency
    if cons is None:
        if images is not None:
            log.info("pose consistency not measured: fewer than %d image pairs matched", hec.MIN_PAIRS)
        return chk
    elif cons["verdict"] == "ok":
        log.info("pose consistency: median Sampson error %.2f px (%.2f mrad) of %d image pairs under the robot poses",
                 cons["sampson_median_px"], cons["sampson_median_mrad"], cons["pairs"])
    else:
        then = (None if cons["verdict"] == "warn" else
                "the robot poses are kept as given (--poses.method robot); remedy: --poses.method sfm with the same "
                "--robot-poses (SfM aligned to the robot poses)" if opts.method != "auto" else
                "--poses.method auto: trying SfM aligned to the robot poses instead (--poses.method robot keeps the "
                "robot poses)")
        log.warning("%s", hec.consistency_message(cons, robot.hand_eye_file, then))
    return chk


# known-pose captures whose poses are scored against the photos (robot-style captures: a TUM pose list, a BOP
# scene); other known poses (transforms.json, COLMAP) mostly come from SfM already
KNOWN_POSE_CHECKED = ("tum", "bop")


def _intrinsics_source(dataset: Dataset, opts: PoseOptions) -> str:
    """Where the cameras' intrinsics come from, for the intrinsics check's record and warning."""
    if isinstance(opts.intrinsics, tuple):
        return "--intrinsics " + ",".join(f"{v:g}" for v in opts.intrinsics)
    return str(dataset.meta.get("intrinsics_file") or dataset.meta.get("path") or dataset.root)


def _check_intrinsics(measures: list, T_world_cam: list[np.ndarray], where: str, stats: dict) -> None:
    """The focal length and principal point that best explain the matched pairs, the poses held fixed
    (`hand_eye_check.intrinsics_check`): stats["intrinsics_check"], and a warning naming `where` for each."""
    from splattwin.poses import hand_eye_check as hec

    ic = hec.intrinsics_check(measures, T_world_cam, where)
    if ic is None:
        return
    stats["intrinsics_check"] = ic
    if ic["verdict"] == "warn":
        log.warning("%s", hec.intrinsics_message(ic))
    elif ic["verdict"] == "undetermined":
        log.info("intrinsics check undetermined: the poses do not fit the photos at any focal length (their own "
                 "errors; see the pose consistency)")
    else:
        log.info("intrinsics check: focal length scale %.3f +- %.3f fits the photos best (%s)", ic["focal_scale"],
                 ic["focal_scale_sigma"], where)
    if ic["principal_point_verdict"] == "warn":
        log.warning("%s", hec.principal_point_message(ic))
    elif ic["principal_point_turn_as_good"]:
        dx, dy = ic["principal_point_offset_px"]
        log.info("intrinsics check: the principal point moved by (%+.1f, %+.1f) px or every camera turned by "
                 "(%+.2f, %+.2f) deg about its x, y axes (a hand-eye rotation error) fit the photos equally well: "
                 "principal point undetermined", dx, dy, *ic["principal_point_turn_deg"])


def _check_known_poses(dataset: Dataset, opts: PoseOptions, frames: list[DataFrame], names: list[str],
                       in_cams: dict[str, Camera], stats: dict) -> None:
    """Known poses of a robot-style capture (TUM pose list, BOP scene) against the photos: the pose consistency
    of near pairs (`hand_eye_check.check_poses_with_images`, stats["pose_consistency"]; a warning, the poses
    are kept), the focal length (`_check_intrinsics`) and, for poses matched to the images by timestamp, the
    time offset (`hand_eye_check.latency_check`, stats["latency_check"])."""
    from splattwin.capture.tum import POSE_TRACK, poses_at_offset
    from splattwin.poses import hand_eye_check as hec

    keys = [n for n in names if n in in_cams]
    paths = [frames[names.index(n)].image_path for n in keys]
    T = [in_cams[n].T_world_cam for n in keys]
    cons, measures = hec.check_poses_with_images(keys, T, paths, [in_cams[n] for n in keys])
    if cons is None:
        log.info("pose consistency not measured: fewer than %d image pairs matched", hec.MIN_PAIRS)
        return
    for p in cons["per_pair"]:
        p["a"], p["b"] = Path(p["a"]).name, Path(p["b"]).name
    stats["pose_consistency"] = cons
    where = dataset.meta.get("path", dataset.root)
    if cons["verdict"] == "ok":
        log.info("pose consistency: median Sampson error %.2f px (%.2f mrad) of %d image pairs under the known "
                 "poses", cons["sampson_median_px"], cons["sampson_median_mrad"], cons["pairs"])
    else:
        if dataset.meta.get("format") == "tum":
            _check_pose_list_convention(measures, T, cons, Path(where))
        elif dataset.meta.get("format") == "bop":
            _check_bop_convention(measures, T, cons, Path(where))
        log.warning("%s", hec.consistency_message(cons, where, "the poses are kept as given (--poses.method known); "
                                                              "remedy: --poses.method sfm", robot=False))
    _check_intrinsics(measures, T, _intrinsics_source(dataset, opts), stats)
    track = dataset.meta.get(POSE_TRACK)
    if track is None:
        return
    base = float(opts.time_offset_ms) / 1000.0
    # the pose list's own spacing may exceed the association's max_dt (30 Hz poses, 20 ms): the scan
    # interpolates across one pose period, as a shifted association would need
    gaps = np.diff(np.sort(track["t"]))
    reach = max(float(track["max_dt"]), 1.01 * float(np.median(gaps)) if len(gaps) else 0.0)
    used = sorted({k for i, j, _ in measures for k in (i, j)})  # only the matched views are re-interpolated

    def poses_at(dt: float) -> tuple[np.ndarray, np.ndarray]:
        T_all, ok_all = np.tile(np.eye(4), (len(paths), 1, 1)), np.zeros(len(paths), dtype=bool)
        T_all[used], ok_all[used] = poses_at_offset(track, [paths[k] for k in used], dt, reach)
        return T_all, ok_all

    lc = hec.latency_check(measures, poses_at, base)
    if lc is None:
        log.info("latency check not done: fewer than %d image pairs posed at every offset scanned", hec.MIN_PAIRS)
        return
    stats["latency_check"] = lc
    if lc["verdict"] == "warn":
        log.warning("%s", hec.latency_message(lc, track.get("pose_file")))
    elif lc["verdict"] == "undetermined":
        log.info("latency check undetermined: no time offset changes how well the poses fit the photos (the arm "
                 "still or at constant velocity between the matched views)")
    else:
        log.info("latency check: time offset %+.0f +- %.0f ms fits the photos best", lc["time_offset_ms"],
                 lc["time_offset_sigma_ms"])


def _better_reading(measures: list, readings: dict[str, list[np.ndarray]], cons: dict) -> tuple[str, dict] | None:
    """(name, consistency) of the reading of the poses ({name: T_world_cam per camera of `measures`}) that fits
    the matched pairs best, when it fits them ("ok") and at most a third of the error `cons` of the poses as
    read; else None."""
    from splattwin.poses import hand_eye_check as hec

    size = tuple(cons["matching_size"]) if cons.get("matching_size") else None
    best = None
    for kind, Ts in readings.items():
        rows = []
        for i, j, m in measures:
            T_ba = np.linalg.inv(Ts[j]) @ Ts[i]
            rows.append({"sampson_px": float(np.median(hec.sampson_px(m.xa, m.xb, T_ba[:3, :3], T_ba[:3, 3], m.f))),
                         "sampson_floor_px": m.floor_px, "focal_px": m.f})
        alt = hec.consistency(rows, size)
        if alt is not None and alt["verdict"] == "ok" and alt["sampson_median_px"] <= cons["sampson_median_px"] / 3 \
                and (best is None or alt["sampson_median_px"] < best[1]["sampson_median_px"]):
            best = (kind, alt)
    return best


def _check_bop_convention(measures: list, T_world_cam: list[np.ndarray], cons: dict, scene_camera: Path) -> None:
    """InputError naming scene_camera.json when its `cam_R_w2c` / `cam_t_w2c` fit the photos only read as the
    camera's pose in the world (camera-to-world written into the world-to-camera fields): read as given, such a
    scene went on with warnings blaming the intrinsics, a tilted world and the depth into a twin on wrong
    poses. `cons`, `measures`: as `_check_pose_list_convention`."""
    from splattwin.transforms import invert_pose

    best = _better_reading(measures, {"inverse": [invert_pose(T) for T in T_world_cam]}, cons)
    if best is None:
        return
    raise InputError(f"cam_R_w2c / cam_t_w2c look like camera-to-world poses: read as BOP's world-to-camera the "
                     f"poses miss the photos by a median {cons['sampson_median_px']:.2f} px (Sampson error of "
                     f"{cons['pairs']} image pairs), inverted by {best[1]['sampson_median_px']:.2f} px; write "
                     f"cam_R_w2c = R^T and cam_t_w2c = -R^T t (mm) of each camera-to-world pose (R, t)", scene_camera)


def _check_transforms_convention(dataset: Dataset, frames: list[DataFrame], names: list[str],
                                 in_cams: dict[str, Camera]) -> None:
    """InputError naming a hand-written transforms.json whose poses fit the photos only read in another
    convention: OpenCV camera axes (x right, y down, z forward: what robot and OpenCV code computes) where
    nerfstudio's `transform_matrix` is OpenGL's (y up, z backward), and/or world-to-camera. Read as written,
    such a file gave a twin on wrong poses without a word (the up check turned the flipped world "z up", 13
    points triangulated instead of 240). Only when the poses as read miss the photos; a transforms.json from
    nerfstudio's COLMAP converters (`sfm_derived`) is not checked."""
    from splattwin.poses import hand_eye_check as hec
    from splattwin.transforms import invert_pose

    keys = [n for n in names if n in in_cams]
    T = [in_cams[n].T_world_cam for n in keys]
    cons, measures = hec.check_poses_with_images(keys, T, [frames[names.index(n)].image_path for n in keys],
                                                 [in_cams[n] for n in keys])
    if cons is None or cons["verdict"] == "ok":
        return
    flip = np.diag([1.0, -1.0, -1.0, 1.0])   # OpenGL <-> OpenCV camera axes (its own inverse)
    readings = {"opencv": [Ti @ flip for Ti in T], "inverse": [invert_pose(Ti @ flip) @ flip for Ti in T],
                "both": [invert_pose(Ti @ flip) for Ti in T]}
    best = _better_reading(measures, readings, cons)
    if best is None:
        return
    kind, alt = best
    what = {"opencv": "OpenCV camera axes (x right, y down, z forward)",
            "inverse": "world-to-camera (the inverse of nerfstudio's camera-to-world)",
            "both": "world-to-camera in OpenCV camera axes (x right, y down, z forward)"}[kind]
    raise InputError(f"the transform_matrix poses look like {what}: read as nerfstudio's camera-to-world in OpenGL "
                     f"axes (x right, y up, z backward) they miss the photos by a median "
                     f"{cons['sampson_median_px']:.2f} px (Sampson error of {cons['pairs']} image pairs), read as "
                     f"{what} by "
                     f"{alt['sampson_median_px']:.2f} px; write camera-to-world OpenGL poses (from OpenCV axes: "
                     f"T_world_cam @ diag(1, -1, -1, 1))", Path(dataset.meta.get("path", dataset.root)))


def _check_pose_list_convention(measures: list, T_world_cam: list[np.ndarray], cons: dict, pose_file: Path) -> None:
    """InputError naming the pose list when its poses fit the photos only read another way: quaternions in
    `qw qx qy qz` order (EuRoC's, many ROS tools' and scripts') read as TUM's `qx qy qz qw`, or world-to-camera
    poses (T_cam_world, as COLMAP's images.txt and many SLAM exports store them) read as TUM's camera-to-world,
    or both. Either gives every camera another pose, which the checks after this one blamed on the hand-eye,
    timestamps, intrinsics or the table ("is the plane a wall?", --up), or which went on into a twin on wrong
    poses. `cons`: the pose consistency of the poses as read (not "ok"); `measures`: its matched pairs
    (`hand_eye_check.check_poses_with_images`)."""
    from splattwin.transforms import invert_pose, matrix_from_quat_wxyz, quat_wxyz_from_matrix

    def cycled(T: np.ndarray) -> np.ndarray:
        # read as (x, y, z, w) = the file's (qw, qx, qy, qz): the file's quaternion (w, x, y, z) is the one read,
        # cycled; any sign of q gives the same cycled rotation
        w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
        T2 = np.array(T, dtype=np.float64)
        T2[:3, :3] = matrix_from_quat_wxyz(np.array([x, y, z, w]))
        return T2

    readings = {"wxyz": [cycled(T) for T in T_world_cam], "inverse": [invert_pose(T) for T in T_world_cam]}
    readings["both"] = [invert_pose(T) for T in readings["wxyz"]]
    best = _better_reading(measures, readings, cons)
    if best is None:
        return
    kind, alt = best
    what = {"wxyz": "the quaternions look like w x y z order", "inverse": "the poses look like world-to-camera "
            "(T_cam_world)", "both": "the poses look like world-to-camera (T_cam_world) with quaternions in w x y z "
            "order"}[kind]
    read = {"wxyz": "read as `qw qx qy qz`", "inverse": "inverted", "both": "read as `qw qx qy qz` and inverted"}[kind]
    fix = {"wxyz": "write each line as `id tx ty tz qx qy qz qw` (e.g. awk '/^#/{print;next}"
                   "{print $1,$2,$3,$4,$6,$7,$8,$5}')",
           "inverse": "write each camera's pose in the world (camera-to-world, T_world_cam: the inverse of these)",
           "both": "write each camera's pose in the world (camera-to-world, T_world_cam: the inverse of these) as "
                   "`id tx ty tz qx qy qz qw`"}[kind]
    raise InputError(f"{what}: read as TUM's camera-to-world `tx ty tz qx qy qz qw` the poses miss the photos by a "
                     f"median {cons['sampson_median_px']:.2f} px (Sampson error of {cons['pairs']} image pairs), "
                     f"{read} by {alt['sampson_median_px']:.2f} px; {fix}", pose_file)


def _apply_time_offset(dataset: Dataset, offset_ms: float) -> None:
    """--poses.time-offset-ms: the frames' poses re-interpolated at their image time + offset (in place, on
    estimate_poses' copy); frames left without a pose are dropped with a warning."""
    from splattwin.capture.tum import POSE_TRACK, poses_at_offset

    if not np.isfinite(offset_ms) or abs(offset_ms) > 10_000.0:
        raise InputError(f"--poses.time-offset-ms {offset_ms!r}: expected a finite offset of at most 10000 ms")
    track = dataset.meta.get(POSE_TRACK)
    if track is None:
        raise InputError(f"--poses.time-offset-ms needs poses matched to the images by timestamp (a TUM pose list "
                         f"with image timestamps); these were matched by "
                         f"{dataset.meta.get('matched_by', 'name or id')} ({dataset.meta.get('format', 'dataset')})",
                         dataset.meta.get("path", dataset.root))
    T, ok = poses_at_offset(track, [f.image_path for f in dataset.frames], offset_ms / 1000.0)
    kept = [dataclasses.replace(f, camera=dataclasses.replace(f.camera, T_world_cam=T[k]))
            for k, f in enumerate(dataset.frames) if ok[k]]
    if not kept:
        raise InputError(f"--poses.time-offset-ms {offset_ms:g}: no image has a pose within {track['max_dt']} s of "
                         f"its timestamp + offset", track.get("pose_file"))
    if len(kept) < len(dataset.frames):
        log.warning("--poses.time-offset-ms %g: %d of %d images have no pose at their shifted time and are skipped",
                    offset_ms, len(dataset.frames) - len(kept), len(dataset.frames))
    dataset.frames = kept
    log.info("poses taken at image time %+g ms (--poses.time-offset-ms)", offset_ms)


def _robot_cameras(opts: PoseOptions, frames: list[DataFrame], names: list[str], dataset: Dataset) -> _RobotCameras:
    from splattwin.poses.robot import (RobotPose, camera_poses_in_base, load_hand_eye, load_robot_poses,
                                       match_to_images)

    poses, inline = load_robot_poses(opts.robot_poses)
    if opts.hand_eye is not None:
        T_ee_cam = load_hand_eye(opts.hand_eye)
        he_file = Path(opts.hand_eye)
    elif inline is not None:
        T_ee_cam = inline
        he_file = Path(opts.robot_poses)
    else:
        raise InputError("robot poses need a hand-eye transform T_ee_cam (--hand-eye FILE, or 'T_ee_cam' in the "
                         "pose file)", opts.robot_poses)
    if opts.intrinsics is None and dataset.meta.get("format") in ("images", "video"):
        log.warning("robot poses with intrinsics guessed from a field-of-view prior; pass --intrinsics for "
                    "accurate cameras")
    image_names = [Path(f.image_path).name for f in frames]
    by_name = match_to_images(poses, image_names, Path(opts.robot_poses))
    keys = list(by_name)
    try:
        T_base_cam = camera_poses_in_base([RobotPose(by_name[k], k) for k in keys], T_ee_cam)
    except InputError as e:   # the geometry check knows no file: name the pose file, as every other error here
        if e.path is not None:
            raise
        raise InputError(e.problem, opts.robot_poses) from None
    key = {k: names[image_names.index(k)] for k in keys}
    return _RobotCameras(T_base_cam={key[k]: T for k, T in zip(keys, T_base_cam)},
                         T_base_ee={key[k]: by_name[k] for k in keys}, T_ee_cam=T_ee_cam, hand_eye_file=he_file)


def view_box(C: np.ndarray, P: np.ndarray | None, q: float = 1.0, pad: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(lo [3], hi [3]) of the cameras.png view, in the frame's units: every camera centre C [N,3] and the
    points P [M,3] between their q and 100-q percentiles per axis, grown by `pad` of the largest side. SfM
    leaves a few stray points tens of scene sizes away (the cake's at -110 units, scene ~5): fitting them
    shrank cameras and scene to a dot in the middle of the picture."""
    pts = [np.asarray(C, float).reshape(-1, 3)]
    if P is not None and len(P):
        P = np.asarray(P, float)
        pts.append(np.percentile(P, [q, 100 - q], axis=0))
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    m = pad * max(float((hi - lo).max()), 1e-9)
    return lo - m, hi + m


def plot_cameras(result: PoseResult, path: str | Path) -> Path:
    """PNG: top view (x-y) and side view (x-z) of the points and camera centres with viewing directions."""
    from matplotlib.figure import Figure

    # a Figure of its own, not pyplot: the caller's backend and open figures stay as they are (a notebook's)
    fig = Figure(figsize=(10, 5))
    axes = fig.subplots(1, 2)
    C = np.array([c.center for c in result.cameras]).reshape(-1, 3)
    D = np.array([c.T_world_cam[:3, 2] for c in result.cameras]).reshape(-1, 3)
    span = float(np.ptp(C, axis=0).max()) if len(C) > 1 else 1.0
    lo, hi = view_box(C, result.points_xyz)
    for ax, (i, j), title in ((axes[0], (0, 1), "top view (x, y)"), (axes[1], (0, 2), "side view (x, z)")):
        if result.points_xyz is not None and len(result.points_xyz):
            P = result.points_xyz
            keep = np.random.default_rng(0).choice(len(P), min(len(P), 20000), replace=False)
            col = None if result.points_rgb is None else result.points_rgb[keep] / 255.0
            ax.scatter(P[keep, i], P[keep, j], s=1, c=col if col is not None else "grey")
        ax.scatter(C[:, i], C[:, j], c="red", s=12, label="cameras")
        ax.quiver(C[:, i], C[:, j], D[:, i], D[:, j], color="red", angles="xy", scale_units="xy", scale=8 / span)
        ax.set_title(title)
        # auto=True: limits that the equal aspect may grow (adjustable="datalim": nothing is cut); fixed ones
        # (the default) made matplotlib log "Ignoring fixed y limits ..." four times into every SfM build
        ax.set_xlim(lo[i], hi[i], auto=True)
        ax.set_ylim(lo[j], hi[j], auto=True)
        ax.set_aspect("equal", adjustable="datalim")
        unit = "m" if result.frame.scaled else "units"
        ax.set_xlabel(f"{'xyz'[i]} [{unit}]")
        ax.set_ylabel(f"{'xyz'[j]} [{unit}]")
    fig.suptitle(f"{len(result.frames)} cameras, frame: {result.frame.summary()}")
    fig.tight_layout()
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    return Path(path)
