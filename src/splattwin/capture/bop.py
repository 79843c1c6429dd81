"""BOP scenes (the BOP benchmark's "scenewise" layout, bop_toolkit's format): read and write.

A scene folder holds (`{im:06d}` = image id, `{k:06d}` = index of an annotated instance in the image's
`scene_gt.json` list):

    scene_camera.json  {"<im>": {"cam_K": [9], "depth_scale": s, "cam_R_w2c": [9], "cam_t_w2c": [3]}}
    scene_gt.json      {"<im>": [{"obj_id": int, "cam_R_m2c": [9], "cam_t_m2c": [3]}, ...]}
    rgb/ or gray/      {im:06d}.png | .jpg | .tif
    depth/             {im:06d}.png, 16-bit; raw x depth_scale = millimetres
    mask/, mask_visib/ {im:06d}_{k:06d}.png: the instance's whole silhouette / its visible part

Units and frames: BOP translations are millimetres (we convert to metres); matrices are row-major;
`cam_K` puts pixel centres at integer coordinates (bop_toolkit, OpenCV), ours at +0.5 (COLMAP), so the
principal point read is cx + 0.5, cy + 0.5 (and written back as cx - 0.5, cy - 0.5);
`cam_R_w2c`, `cam_t_w2c` map world points into the camera (x_cam = R x_world + t), `cam_R_m2c`,
`cam_t_m2c` model points into the camera; cameras are OpenCV (x right, y down, z forward).

Poses: when every image of `scene_camera.json` has `cam_R_w2c`/`cam_t_w2c` the dataset is posed in the
scene's world frame (metres); when none has, it is an image set (SfM estimates the poses); a mix is an
InputError. Depth: `Dataset.depth_scale` = depth_scale / 1000 metres per raw unit; BOP allows it per
image, we need one value per scene (InputError naming `scene_camera.json` otherwise).

Object names (`object_names`): `obj_id` -> name from an optional `object_names.json` (`{"1": "mug"}`) in
the scene folder or up to two folders above it (the split folder, the dataset root), else a `"name"`
entry of the dataset root's `models*/models_info.json`, else `obj_000001`. Names are checked by
`splattwin.names`. Masks are read by `splattwin.semantics.masks.load_bop_masks`.

All files are untrusted: ids must be whole numbers, every value is type-checked (InputError naming the
file and the image id), JSON sizes and image headers are bounded (`splattwin.limits`); file names are
built from integer ids, never taken from the files.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, invert_se3, plausible
from splattwin.capture.dataset import DEPTH_SCALE_RANGE, IMAGE_SUFFIXES, Dataset, Frame, image_size, list_files
from splattwin.errors import InputError
from splattwin.limits import MAX_POSITION, MAX_VIEWS, ascii_uint, check_count, number, numbers

log = logging.getLogger(__name__)
_ANNOUNCED: set[str] = set()   # scenes whose notes (no poses, amodal masks) were logged in this process

SCENE_CAMERA = "scene_camera.json"
SCENE_GT = "scene_gt.json"
NAMES_FILE = "object_names.json"
IMAGE_DIRS = ("rgb", "gray")
MASK_DIRS = ("mask_visib", "mask")
MM = 1e-3  # metres per millimetre
PIXEL_CENTRE_SHIFT = 0.5  # cam_K's pixel centres are at integers (bop_toolkit), ours at +0.5


@dataclass
class GtInstance:
    """One annotated object instance in one image: BOP `obj_id`, its index in the image's list, and
    T_cam_obj [4,4] (model frame -> camera, metres)."""

    obj_id: int
    index: int
    T_cam_obj: np.ndarray


def is_scene(path: Path) -> bool:
    """A BOP scene folder: `scene_camera.json` beside `rgb/` or `gray/`."""
    return (path / SCENE_CAMERA).is_file() and any((path / d).is_dir() for d in IMAGE_DIRS)


def _image_id(key, where: Path, what: str = "image id") -> int:
    i = ascii_uint(key, 9)
    if i is None:
        raise InputError(f"{what} {str(key)[:40]!r} must be a whole number (a key like \"0\" or \"12\")", where)
    return i


def _unique_ids(keys, where: Path, what: str) -> dict[int, str]:
    """id -> key of a file's image-id keys; InputError when two keys name one id ("0" and "00")."""
    out: dict[int, str] = {}
    for k in keys:
        i = _image_id(k, where)
        if i in out:
            raise InputError(f"{what} has two entries for image {i} ({out[i]!r} and {k!r})", where)
        out[i] = k
    return out


def _rigid(R9, t3, where: Path, what: str) -> np.ndarray:
    """[4,4] from a row-major rotation [9] and a translation [3] in mm (-> metres); checked rotation."""
    R = numbers(R9, 9, where, f"{what} rotation").reshape(3, 3)
    t = numbers(t3, 3, where, f"{what} translation (mm)", -MAX_POSITION / MM, MAX_POSITION / MM) * MM
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise InputError(f"{what} rotation is not a proper rotation matrix", where)
    # re-orthonormalise the rounded matrix BOP files store (6-8 digits)
    U, _, Vt = np.linalg.svd(R)
    T = np.eye(4)
    T[:3, :3] = U @ Vt
    T[:3, 3] = t
    return T


def _read_dict(path: Path, what: str) -> dict:
    data = io.read_json(path, missing=f"no {what} here")
    if not isinstance(data, dict):
        raise InputError(f"malformed {what}: expected an object keyed by image id", path)
    check_count(len(data), path, "images", MAX_VIEWS, "SPLATTWIN_MAX_VIEWS")
    return data


def _index_images(scene: Path) -> tuple[Path, dict[str, Path]]:
    for d in IMAGE_DIRS:
        files = _listing(scene, d, IMAGE_SUFFIXES)
        if files:
            return scene / d, files
    raise InputError("BOP scene has no images in rgb/ or gray/", scene)


def _listing(scene: Path, sub: str, suffixes) -> dict[str, Path]:
    """stem -> file of scene/sub, confined to the scene (a link out of it is refused: `list_files`)."""
    folder = scene / sub
    return {p.stem: p for p in list_files(folder, suffixes, inside=scene)} if folder.is_dir() else {}


def read(path: str | Path) -> Dataset:
    """A BOP scene folder (or its scene_camera.json) -> Dataset (see module docstring)."""
    path = Path(path)
    scene = path.parent if path.is_file() else path
    cam_file = scene / SCENE_CAMERA
    meta = _read_dict(cam_file, SCENE_CAMERA)
    image_dir, images = _index_images(scene)
    depth_files = _listing(scene, "depth", (".png", ".tif", ".tiff"))
    entries = sorted(((i, meta[k]) for i, k in _unique_ids(meta, cam_file, SCENE_CAMERA).items()),
                     key=lambda kv: kv[0])
    for im_id, e in entries:  # before the pose check, which would call a non-object "an image without pose"
        if not isinstance(e, dict):
            raise InputError(f"image {im_id}: entry must be an object with cam_K, got {type(e).__name__}", cam_file)
    posed = [isinstance(v, dict) and "cam_R_w2c" in v and "cam_t_w2c" in v for _, v in entries]
    some = [isinstance(v, dict) and ("cam_R_w2c" in v or "cam_t_w2c" in v) for _, v in entries]
    if any(some) and not all(posed):
        missing = [i for (i, _), p in zip(entries, posed) if not p][:5]
        raise InputError(f"some images have camera poses (cam_R_w2c, cam_t_w2c) and some do not (e.g. image "
                         f"{missing}); give poses for all images or for none", cam_file)
    has_poses = bool(entries) and all(posed)
    frames: list[Frame] = []
    scales: dict[float, list[int]] = {}
    skipped = []
    for im_id, e in entries:
        where = f"image {im_id}"
        if "cam_K" not in e:
            raise InputError(f"{where}: no cam_K", cam_file)
        K = numbers(e["cam_K"], 9, cam_file, f"{where} cam_K").reshape(3, 3)
        K[:2, 2] += PIXEL_CENTRE_SHIFT  # integer pixel centres (BOP) -> ours
        stem = f"{im_id:06d}"
        img = images.get(stem)
        if img is None:
            skipped.append(stem)
            continue
        w, h = image_size(img)
        T = np.eye(4)
        if has_poses:
            T = invert_se3(_rigid(e["cam_R_w2c"], e["cam_t_w2c"], cam_file, f"{where} cam_R_w2c/cam_t_w2c"))
        depth = depth_files.get(stem)
        if depth is not None:
            # BOP's depth_scale is millimetres per raw unit
            lo, hi = (x / MM for x in DEPTH_SCALE_RANGE)
            s = number(e.get("depth_scale", 1.0), cam_file, f"{where}: depth_scale (mm per raw depth unit)", lo, hi)
            scales.setdefault(s, []).append(im_id)
        try:
            cam = plausible(Camera(K=K, width=w, height=h, T_world_cam=T, name=stem))
        except InputError as err:
            raise InputError(f"{where}: {err.problem}", cam_file) from err
        frames.append(Frame(image_path=img, camera=cam, depth_path=depth))
    if skipped:
        log.warning("%s: %d image id(s) have no image file in %s (e.g. %s); skipped", cam_file, len(skipped),
                    image_dir, ", ".join(skipped[:3]))
    if not frames:
        raise InputError(f"no image of {SCENE_CAMERA} has a file in {image_dir.name}/", cam_file)
    if len(scales) > 1:
        desc = ", ".join(f"{s} (images {ids[:3]}...)" for s, ids in scales.items())
        raise InputError(f"depth_scale differs between images ({desc}); one depth unit per scene is supported: "
                         f"convert the depth images to one scale", cam_file)
    depth_scale = next(iter(scales)) * MM if scales else None
    said = str(cam_file) in _ANNOUNCED   # once per scene and run: pre-flight and every stage read it
    _ANNOUNCED.add(str(cam_file))
    if not said and not (scene / "mask_visib").is_dir() and (scene / "mask").is_dir():
        # fusion labels what each pixel shows: an amodal mask labels the occluder as the occluded object
        log.warning("%s: only mask/ (amodal: whole silhouettes, occluded parts included) and no mask_visib/; label "
                    "fusion expects visible-part masks, so occluders may take the occluded object's label", scene)
    if not has_poses and not said:
        log.info("%s: no camera poses (cam_R_w2c/cam_t_w2c); poses will be estimated", cam_file)
    files = [cam_file] + [scene / SCENE_GT] * (scene / SCENE_GT).is_file()
    return Dataset(root=scene, frames=frames, has_poses=has_poses, depth_scale=depth_scale,
                   meta={"format": "bop", "path": str(cam_file), "files": [str(f) for f in files],
                         "depth_units": None if depth_scale is None else f"{depth_scale} m per unit"})


def read_scene_gt(path: str | Path) -> dict[int, list[GtInstance]]:
    """`scene_gt.json` (the file or its scene folder) -> image id -> annotated instances, in file order."""
    path = Path(path)
    if path.is_dir():
        path = path / SCENE_GT
    data = _read_dict(path, SCENE_GT)
    out: dict[int, list[GtInstance]] = {}
    for im_id, key in _unique_ids(data, path, SCENE_GT).items():
        lst = data[key]
        if not isinstance(lst, list):
            raise InputError(f"image {im_id}: expected a list of annotated instances", path)
        check_count(len(lst), path, f"instances of image {im_id}", limit=100_000)
        insts = []
        for k, g in enumerate(lst):
            what = f"image {im_id} instance {k}"
            if not isinstance(g, dict) or "obj_id" not in g:
                raise InputError(f"{what}: expected an object with obj_id", path)
            oid = g["obj_id"]
            if isinstance(oid, bool) or not isinstance(oid, int) or not 0 < oid < 10**6:
                raise InputError(f"{what}: obj_id must be a positive whole number below 10^6, got {oid!r}", path)
            T = np.eye(4)
            if "cam_R_m2c" in g or "cam_t_m2c" in g:
                T = _rigid(g.get("cam_R_m2c"), g.get("cam_t_m2c"), path, f"{what} cam_R_m2c/cam_t_m2c")
            insts.append(GtInstance(obj_id=oid, index=k, T_cam_obj=T))
        out[im_id] = insts
    return out


def names_source(scene: str | Path) -> Path | None:
    """The file that names a scene's objects (object_names.json beside, above or two above the scene,
    else the dataset's models*/models_info.json), or None: the file to blame when names collide."""
    scene = Path(scene)
    for folder in (scene, scene.parent, scene.parent.parent):
        if (folder / NAMES_FILE).is_file():
            return folder / NAMES_FILE
    return next(iter(sorted(scene.parent.parent.glob("models*/models_info.json"))), None)


def object_names(scene: str | Path, obj_ids: list[int] | None = None) -> dict[int, str]:
    """obj_id -> object name for a scene folder (see module docstring). With `obj_ids`, every one of
    them gets a name (the default `obj_XXXXXX` where no file names it). InputError naming the names
    file when two obj_ids get one name (their masks would merge into one object)."""
    from splattwin.names import check_unique, name_from_label

    names: dict[int, str] = {}
    f = names_source(scene)
    if f is not None and f.name == NAMES_FILE:
        data = io.read_json(f)
        if not isinstance(data, dict):
            raise InputError('expected an object {"<obj_id>": "name", ...}', f)
        for k, v in data.items():
            names[_image_id(str(k), f, "obj_id")] = name_from_label(v, f, f"name of obj_id {k}")
    elif f is not None:
        data = io.read_json(f)
        if isinstance(data, dict):
            for k, v in data.items():
                if isinstance(v, dict) and isinstance(v.get("name"), str):
                    names.setdefault(_image_id(str(k), f, "obj_id"), name_from_label(v["name"], f, f"name of obj_id {k}"))
    if f is not None:
        check_unique(names.values(), f)
    for oid in obj_ids or []:
        names.setdefault(oid, f"obj_{oid:06d}")
    return names


# -- writing ----------------------------------------------------------------------------------------
def _mm(T: np.ndarray) -> tuple[list, list]:
    return [float(x) for x in T[:3, :3].reshape(-1)], [float(x) / MM for x in T[:3, 3]]


def write_scene_camera(path: str | Path, cameras: list[Camera], depth_scale: float | None = 1.0,
                       with_poses: bool = True) -> Path:
    """`scene_camera.json` for cameras in image-id order (id = list index). depth_scale: BOP's (raw x it
    = mm). Poses (world -> camera, mm) when `with_poses`."""
    out = {}
    for i, c in enumerate(cameras):
        K = c.K.copy()
        K[:2, 2] -= PIXEL_CENTRE_SHIFT  # ours -> BOP's integer pixel centres
        e: dict = {"cam_K": [float(x) for x in K.reshape(-1)]}
        if depth_scale is not None:
            e["depth_scale"] = float(depth_scale)
        if with_poses:
            e["cam_R_w2c"], e["cam_t_w2c"] = _mm(c.T_cam_world)
        out[str(i)] = e
    return io.write_json(path, out)


def write_scene_gt(path: str | Path, instances: list[list[tuple[int, np.ndarray]]]) -> Path:
    """`scene_gt.json` from, per image (id = list index), [(obj_id, T_cam_obj [4,4] metres), ...]."""
    out = {}
    for i, lst in enumerate(instances):
        out[str(i)] = []
        for oid, T in lst:
            R, t = _mm(np.asarray(T, dtype=np.float64))
            out[str(i)].append({"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": int(oid)})
    return io.write_json(path, out)


def image_name(im_id: int, suffix: str = ".png") -> str:
    return f"{im_id:06d}{suffix}"


def mask_name(im_id: int, index: int) -> str:
    return f"{im_id:06d}_{index:06d}.png"
