"""nerfstudio `transforms.json`: read and write.

Supports global or per-frame intrinsics (fl_x, fl_y, cx, cy, w, h), camera models PINHOLE and OPENCV
(k1 k2 p1 p2 [k3]), `depth_file_path`, `mask_path` (nerfstudio's loss mask), our `label_path` (ground-truth
instance labels, ignored by nerfstudio), `ply_file_path`, and the split lists
`train_filenames` / `val_filenames` / `test_filenames` (val and test become our "heldout" split); a
per-frame `"split"` key is also honoured. Poses are OpenGL camera-to-world (`transform_matrix`); we
convert to OpenCV on read and back on write. Frames whose image is missing are skipped with a warning.

The file is untrusted: every path in it (`file_path`, `depth_file_path`, `mask_path`, `label_path`,
`ply_file_path`) must be relative and stay inside the file's folder (`splattwin.paths`), every value
must have the right type (a frame that is not an object, a `file_path` that is not a string, text in a
matrix: InputError naming the file and the frame), and image sizes are bounded (`splattwin.limits`).
`write` names the dataset's files relative to the output file's folder; with confine=True it refuses
(InputError) files outside that folder, which `read` would refuse, and otherwise warns about them.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, opencv_from_opengl, opengl_from_opencv, plausible
from splattwin.capture.dataset import DEPTH_SCALE_RANGE, Dataset, Frame, name_views_by_path
from splattwin.errors import InputError
from splattwin.limits import MAX_VIEWS, check_count, check_pixels, number
from splattwin.names import check_unique, object_name
from splattwin.paths import confined, is_inside, own_file, unfollowed
from splattwin.transforms import pose_from_file_value

log = logging.getLogger(__name__)

SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")
_INTR_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")
MM_LOOKING_METRES = 20.0   # median float .npy depth (read as metres) beyond which `read` suspects millimetres


def _intrinsics(src: dict, fallback: dict, where: Path, frame_name: str) -> tuple[np.ndarray, int, int, np.ndarray | None]:
    def get(key: str):
        return src.get(key, fallback.get(key))

    fl_x, fl_y = get("fl_x"), get("fl_y")
    w, h = get("w"), get("h")
    missing = [k for k, v in (("fl_x or camera_angle_x", fl_x if fl_x is not None else get("camera_angle_x")),
                              ("w", w), ("h", h)) if v is None]
    if missing:
        raise InputError(f"frame {frame_name!r}: missing intrinsics {', '.join(missing)}", where)
    what = f"frame {frame_name!r}: intrinsics"
    w_i, h_i = check_pixels(w, h, where, f"{what} w x h")
    if fl_x is None:  # Blender/NeRF-synthetic style: horizontal field of view, radians
        angle = number(get("camera_angle_x"), where, f"{what} camera_angle_x (radians)")
        if not 0 < angle < math.pi:
            raise InputError(f"{what} camera_angle_x must be a field of view in radians, between 0 and pi, got "
                             f"{angle:g}", where)
        fl_x = 0.5 * w_i / math.tan(0.5 * angle)
    fl_x = number(fl_x, where, f"{what} fl_x")
    fl_y = fl_x if fl_y is None else number(fl_y, where, f"{what} fl_y")
    cx = w_i / 2.0 if get("cx") is None else number(get("cx"), where, f"{what} cx")
    cy = h_i / 2.0 if get("cy") is None else number(get("cy"), where, f"{what} cy")
    K = np.array([[fl_x, 0.0, cx], [0.0, fl_y, cy], [0.0, 0.0, 1.0]])
    dist = np.array([0.0 if get(k) is None else number(get(k), where, f"{what} {k}") for k in _DIST_KEYS])
    return K, w_i, h_i, (dist if np.any(dist) else None)


def read(path: str | Path, require_images: bool = True) -> Dataset:
    """A nerfstudio transforms.json. Frames whose image is missing are skipped (a warning each), unless
    require_images is False: then they are kept for their cameras (e.g. the geometry stage's carving,
    which never reads a pixel)."""
    path = Path(path)
    if (path.parent / "poses_report.json").exists():   # a poses folder splattwin wrote, not a user's capture
        own_file(path.parent, path, "transforms.json")
    meta = io.read_json(path, missing="file does not exist")
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise InputError("not a nerfstudio transforms.json (no 'frames' list)", path)
    model = meta.get("camera_model", "OPENCV")
    if model not in SUPPORTED_MODELS:
        raise InputError(f"unsupported camera_model {model!r} (supported: {', '.join(SUPPORTED_MODELS)})", path)
    root = path.parent
    check_count(len(meta["frames"]), path, "frames", MAX_VIEWS, "SPLATTWIN_MAX_VIEWS")
    heldout_names = set()
    for key in ("test_filenames", "val_filenames"):
        names = meta.get(key, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise InputError(f"{key} must be a list of file names", path)
        heldout_names |= set(names)
    frames: list[Frame] = []
    for i, fr in enumerate(meta["frames"]):
        if not isinstance(fr, dict):
            raise InputError(f"frame {i} must be an object with file_path and transform_matrix, got "
                             f"{type(fr).__name__}", path)
        if "file_path" not in fr:
            raise InputError(f"frame {i} has no file_path", path)
        rel = fr["file_path"]
        if not isinstance(rel, str) or not rel:
            raise InputError(f"frame {i}: file_path must be a non-empty string, got {rel!r}", path)
        img = confined(root, rel, path, f"frame {i} file_path")
        if not img.suffix and not img.exists():  # NeRF-synthetic omits the extension
            img = confined(root, rel + ".png", path, f"frame {i} file_path")
        if require_images and not img.is_file():
            log.warning("%s: frame %d image %s is missing; skipping it", path, i, img)
            continue
        fr_model = fr.get("camera_model", model)
        if fr_model not in SUPPORTED_MODELS:
            raise InputError(f"frame {rel!r}: unsupported camera_model {fr_model!r}", path)
        K, w, h, dist = _intrinsics(fr, meta, path, rel)
        T_gl = pose_from_file_value(fr.get("transform_matrix"), f"frame {rel!r}: transform_matrix", path)
        if np.max(np.abs(T_gl[3] - [0.0, 0.0, 0.0, 1.0])) > 1e-6:  # a projective row would be silently dropped
            raise InputError(f"frame {rel!r}: transform_matrix must end with the row 0 0 0 1, got "
                             f"{[float(x) for x in T_gl[3]]}", path)
        split = fr.get("split")
        if split is None:
            split = "heldout" if (rel in heldout_names or img.name in heldout_names) else "train"
        elif split in ("test", "val", "heldout"):
            split = "heldout"
        else:
            split = "train"
        try:
            cam = plausible(Camera(K=K, width=w, height=h, T_world_cam=opencv_from_opengl(T_gl), dist=dist,
                                   name=Path(rel).stem))
        except InputError as e:
            raise InputError(f"frame {rel!r}: {e.problem}", path) from e
        extra = {k: confined(root, fr[k], path, f"frame {rel!r} {k}") if fr.get(k) else None
                 for k in ("depth_file_path", "mask_path", "label_path")}
        frames.append(Frame(
            image_path=img,
            camera=cam,
            depth_path=extra["depth_file_path"],
            mask_path=extra["mask_path"],
            label_path=extra["label_path"],
            split=split,
        ))
    if not frames:
        raise InputError("no frame has an existing image" if require_images else "no frames", path)
    name_views_by_path(frames)   # images/cam0/0000.jpg, images/cam1/0000.jpg: cam0_0000, cam1_0000
    xyz = rgb = None
    if meta.get("ply_file_path"):
        ply = confined(root, meta["ply_file_path"], path, "ply_file_path")
        if ply.is_file():
            xyz, rgb = read_points_ply(ply)
            if len(xyz) == 0:
                log.warning("%s: ply_file_path %s holds no points; no initial point cloud", path, ply)
                xyz = rgb = None
        else:
            log.warning("%s: ply_file_path %s is missing; no initial point cloud", path, ply)
    depth_scale = None  # absent: nerfstudio's default (16-bit PNG in mm), our .npy in metres
    if meta.get("depth_unit_scale_factor") is not None:
        # metres per raw depth unit
        depth_scale = number(meta["depth_unit_scale_factor"], path, "depth_unit_scale_factor", *DEPTH_SCALE_RANGE)
    else:
        _warn_mm_npy(frames, path)
    ds_meta: dict = {"format": "nerfstudio", "path": str(path)}
    # a split of its own (file lists or per-frame splits): kept unless a hold-out option is given
    if any(k in meta for k in ("train_filenames", "val_filenames", "test_filenames")) or any(
            isinstance(fr, dict) and "split" in fr for fr in meta["frames"]):
        ds_meta["split"] = True
    rec = meta.get("heldout")
    if isinstance(rec, dict):  # the rule that made the split (splattwin.poses.holdout), for the report
        ds_meta["heldout"] = {k: (rec[k][:200] if isinstance(rec[k], str) else rec[k]) for k in ("source", "rule", "every")
                              if isinstance(rec.get(k), (str, int)) and not isinstance(rec.get(k), bool)}
    names = _label_objects(meta, path)
    if names:
        ds_meta["label_objects"] = names
    sfm_marks = [k for k in ("applied_transform", "applied_scale") if k in meta]
    if any(isinstance(fr, dict) and "colmap_im_id" in fr for fr in meta["frames"]):
        sfm_marks.append("colmap_im_id")
    if sfm_marks:
        # nerfstudio's COLMAP converters (ns-process-data) leave these: the poses are SfM output, so their
        # lengths are in arbitrary SfM units, not metres (splattwin.poses.estimate)
        ds_meta["sfm_derived"] = sfm_marks
    return Dataset(root=root, frames=frames, has_poses=True, points_xyz=xyz, points_rgb=rgb,
                   depth_scale=depth_scale, meta=ds_meta)


def _label_objects(meta: dict, path: Path) -> dict[str, int]:
    """name -> id of the objects in the frames' ground-truth label images (`label_path`): the file's
    "label_objects" (a generated scene and the poses stage write it). Lets the metrics match fused objects
    to the ground truth by name, whatever ids the masks gave them. {} when unknown."""
    src, where = meta.get("label_objects"), path
    if src is None:
        return {}
    if not isinstance(src, dict) or not all(isinstance(n, str) and isinstance(k, int) and not isinstance(k, bool)
                                            and k <= 65535 for n, k in src.items()):
        raise InputError("label_objects must map object names to integer label ids (at most 65535: label images "
                         "are 16-bit)", where)
    out = {n: k for n, k in src.items() if k > 0}
    # they become the fused objects' names (`semantics.lift.label_objects`): checked where they enter, as the
    # names of every other source are ('a/b', '..', '' and names equal ignoring case were taken as they were)
    for n in out:
        object_name(n, where, "label_objects name")
    check_unique(out, where, "label_objects name")
    by_id: dict[int, str] = {}
    for n, k in out.items():
        if k in by_id:
            raise InputError(f"label_objects gives label id {k} to both {by_id[k]!r} and {n!r}", where)
        by_id[k] = n
    return out


def outside_files(dataset: Dataset, root: str | Path) -> list[Path]:
    """The dataset's files (images, depth maps, masks, label images) that `read` would refuse from a
    transforms.json in `root`: the path written for each (`_rel`) joined onto `root` and tested as the
    reader tests it (`paths.is_inside`: '..' and symbolic links resolved). So a file elsewhere (a '..'
    path) and a link under `root` to a file elsewhere (a capture folder of links) are both named."""
    root = Path(root)
    return [p for f in dataset.frames for p in (f.image_path, f.depth_path, f.mask_path, f.label_path)
            if p is not None and not is_inside(root / _rel(p, root), root)]


def write(dataset: Dataset, path: str | Path, ply_name: str = "sparse_pc.ply", confine: bool = False) -> Path:
    """Write `dataset` as `path` (a transforms.json). File paths are written relative to its folder.

    Shared intrinsics go top-level, differing ones per frame. Points (if any) go to `ply_name`.
    Files outside the folder get '..' paths, which nerfstudio reads but `read` (and so `load_dataset`)
    refuses: confine=True raises InputError for them instead (before writing anything), else a warning
    says so. `splattwin.capture.bundle.bundle_frames` brings the files into the folder first.
    """
    path = Path(path)
    root = path.parent
    outside = outside_files(dataset, root)
    if outside:
        problem = (f"{len(outside)} of the dataset's files lie outside {root} (e.g. {outside[0]}); a transforms.json "
                   f"there would name them with '..' paths or through symbolic links leading out of it, which "
                   f"splattwin's readers refuse (paths in a dataset file must stay in its folder)")
        if confine:
            raise InputError(f"{problem}: bundle the files into the folder (splattwin.capture.bundle.bundle_frames, "
                             f"PoseResult.save(bundle=True)) or write into a folder that holds them", path)
        log.warning("%s: %s; nerfstudio reads them", path, problem)
    cams = [f.camera for f in dataset.frames]
    first = cams[0]

    def intr(c: Camera) -> dict:
        d = {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}
        if c.dist is not None:
            d.update({k: float(v) for k, v in zip(_DIST_KEYS, c.dist)})
        return d

    shared = all(intr(c) == intr(first) for c in cams)
    meta: dict = {"camera_model": "OPENCV" if any(c.dist is not None for c in cams) else "PINHOLE"}
    if shared:
        meta.update(intr(first))
    frames = []
    for f in dataset.frames:
        d = {"file_path": _rel(f.image_path, root), "transform_matrix": opengl_from_opencv(f.camera.T_world_cam).tolist()}
        if not shared:
            d.update(intr(f.camera))
        if f.depth_path is not None:
            d["depth_file_path"] = _rel(f.depth_path, root)
        if f.mask_path is not None:
            d["mask_path"] = _rel(f.mask_path, root)
        if f.label_path is not None:
            d["label_path"] = _rel(f.label_path, root)
        d["split"] = f.split
        frames.append(d)
    meta["frames"] = frames
    meta["train_filenames"] = [fr["file_path"] for fr in frames if fr["split"] == "train"]
    meta["test_filenames"] = [fr["file_path"] for fr in frames if fr["split"] == "heldout"]
    # nerfstudio's parser refuses a file with split lists but none for "val", the split ns-train evaluates
    meta["val_filenames"] = list(meta["test_filenames"])
    if dataset.meta.get("label_objects"):  # the names of the label images' ids travel with them
        meta["label_objects"] = dict(dataset.meta["label_objects"])
    rec = dataset.meta.get("heldout")
    if isinstance(rec, dict):  # how the split was chosen (splattwin.poses.holdout)
        meta["heldout"] = {**{k: rec[k] for k in ("source", "rule", "every") if k in rec},
                           "views": [f.name for f in dataset.frames if f.split == "heldout"]}
    factor = _depth_factor(dataset)
    if factor is not None:
        meta["depth_unit_scale_factor"] = factor
    if dataset.points_xyz is not None:
        write_points_ply(root / ply_name, dataset.points_xyz, dataset.points_rgb)
        meta["ply_file_path"] = ply_name
    return io.write_json(path, meta)


def _depth_factor(dataset: Dataset) -> float | None:
    """depth_unit_scale_factor for the written file: the dataset's explicit units (BOP, TUM, ...), else the
    default of its depth files' type (float .npy: 1.0, metres; 16-bit: 0.001, mm), always written:
    nerfstudio multiplies every depth file, .npy included, by the factor and assumes 0.001 when absent,
    so our metre .npy read without it came out 1000x too near. None: no depth, or files of both kinds
    (one factor cannot say both; splattwin's own reading of the file needs none)."""
    if dataset.depth_scale is not None:
        return dataset.depth_scale
    from splattwin.capture.dataset import default_depth_scale

    scales = {default_depth_scale(f.depth_path) for f in dataset.frames
              if f.depth_path is not None and f.depth_path.is_file()}
    if len(scales) > 1:
        log.warning("depth files are both integer (mm) and float (m): transforms.json gets no "
                    "depth_unit_scale_factor, which nerfstudio then reads as 0.001 for all of them")
        return None
    return scales.pop() if scales else None


def _warn_mm_npy(frames: list[Frame], path: Path) -> None:
    """Without depth_unit_scale_factor we read float .npy depth as metres (what splattwin wrote before it
    wrote the factor), nerfstudio as millimetres. A tabletop is not 20 m away: a first depth array whose
    median is beyond that is most likely in mm, and is named."""
    from splattwin.limits import load_npy

    fr = next((f for f in frames if f.depth_path is not None and f.depth_path.suffix.lower() == ".npy"
               and f.depth_path.is_file()), None)
    if fr is None:
        return
    first = fr.depth_path
    try:
        # no larger than its camera's image of float64 (a depth map is that or smaller): this runs on every
        # read of the dataset, `capture info` included, and must not load whatever a header claims
        d = load_npy(first, "depth array", max_bytes=8 * fr.camera.width * fr.camera.height)
    except InputError:
        return   # named when the depth is read
    if d.dtype.kind != "f":
        return
    valid = d[np.isfinite(d) & (d > 0)]
    if valid.size and float(np.median(valid)) > MM_LOOKING_METRES:
        log.warning("%s: no depth_unit_scale_factor, so float .npy depth is read in metres, but %s has a median of "
                    "%.0f: millimetres? (nerfstudio would read it so). Add \"depth_unit_scale_factor\": 0.001 to the "
                    "file if it is in mm, 1.0 to silence this", path, first.name, float(np.median(valid)))


def _rel(p: Path, root: Path) -> str:
    # the link's own place, not its target: a bundled image is `images/x.jpg` even if it is a link
    return Path(os.path.relpath(unfollowed(p), root.resolve())).as_posix()


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Point cloud (xyz [N,3] float64, rgb [N,3] uint8 or None) from a PLY via Open3D-free trimesh."""
    import trimesh

    from splattwin.limits import check_ply_header

    check_ply_header(path, "point cloud PLY")
    try:
        pc = trimesh.load(path, process=False)
    except Exception as e:  # trimesh raises many types on malformed files
        raise InputError(f"unreadable point cloud PLY: {e}", path) from e
    try:
        xyz = np.asarray(getattr(pc, "vertices", np.zeros((0, 3))), dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("point cloud PLY must hold xyz vertices", path) from None
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.all(np.isfinite(xyz)):
        raise InputError("point cloud PLY must hold finite xyz vertices", path)
    colors = getattr(pc, "colors", None)
    rgb = None
    if colors is not None and len(colors) == len(xyz):
        rgb = np.asarray(colors)[:, :3].astype(np.uint8)
    return xyz, rgb


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> Path:
    import trimesh

    colors = None if rgb is None else np.hstack([np.asarray(rgb, np.uint8), np.full((len(rgb), 1), 255, np.uint8)])
    pc = trimesh.PointCloud(np.asarray(xyz, dtype=np.float64), colors=colors)
    with io.atomic_path(path) as tmp:
        pc.export(tmp, file_type="ply")
    return Path(path)
