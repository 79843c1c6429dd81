"""Datasets: posed (or unposed) images with optional depth, masks and an initial point cloud.

`load_dataset(path)` detects the layout:
- a nerfstudio `transforms.json` (or a folder containing one),
- a COLMAP sparse model folder (`cameras.bin|txt`, `images.bin|txt`, `points3D.*`; or a folder with
  `sparse/0/` and `images/`),
- a 3DGS / InstantSplat `cameras.json` (or a folder containing one),
- a BOP scene folder (`scene_camera.json` + `rgb/` or `gray/`, optional `depth/`; `splattwin.capture.bop`),
- a TUM-style folder: a pose list (`groundtruth.txt`, `poses.txt`, ...) + an intrinsics file
  (`splattwin.capture.tum`),
- a plain image folder (no poses),
- a video file (frames extracted with PyAV into `frames_dir`, default a cache folder beside it).

Depth units are explicit per format (`Dataset.depth_scale`, metres per raw depth unit): nerfstudio's
`depth_unit_scale_factor`, BOP's per-scene `depth_scale` (raw x depth_scale = mm), TUM's 5000 units per
metre unless its intrinsics file says otherwise. `None` means the format's default: integer (16-bit PNG)
depth in millimetres, float depth (`.npy`) in metres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin.capture.camera import Camera
from splattwin.equality import dataclass_eq
from splattwin.errors import InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".bmp", ".tif", ".tiff", ".webp", ".heic", ".heif",
                  ".HEIC", ".HEIF")
_IMAGE_SUFFIXES_LOWER = frozenset(s.lower() for s in IMAGE_SUFFIXES)   # find_images: any case (.Jpg)


class _AnyCase(tuple):
    """Lower-case suffixes whose `in` ignores case: `path.suffix in VIDEO_SUFFIXES` (here and in the
    stages that test for a video) matches .Mp4 and .MKV, as image suffixes are matched."""

    def __contains__(self, suffix) -> bool:
        return isinstance(suffix, str) and tuple.__contains__(self, suffix.lower())


VIDEO_SUFFIXES = _AnyCase((".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"))


def is_video(path: str | Path) -> bool:
    """A video file by its suffix, in any case (.Mp4, .MKV: as image suffixes)."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


@dataclass
class Frame:
    """One view: an image file and its camera (identity pose when unknown)."""

    image_path: Path
    camera: Camera
    depth_path: Path | None = None
    mask_path: Path | None = None   # nerfstudio loss mask: 0 = ignore this pixel
    split: str = "train"  # "train" | "heldout"
    label_path: Path | None = None  # ground-truth instance label image (0 = background), for metrics

    @property
    def name(self) -> str:
        return self.camera.name or self.image_path.stem


@dataclass
class Dataset:
    """Frames plus an optional initial point cloud (world frame, metres when the poses are metric)."""

    root: Path
    frames: list[Frame]
    has_poses: bool
    points_xyz: np.ndarray | None = None  # [N,3] float64
    points_rgb: np.ndarray | None = None  # [N,3] uint8
    # metres per raw depth-file unit (16-bit PNG in mm: 1e-3; TUM: 1/5000); None: the default of the file
    # type (integer PNG in mm, float .npy in metres), see `load_depth`
    depth_scale: float | None = None
    meta: dict = field(default_factory=dict)

    __eq__ = dataclass_eq   # array-aware (points; frames via Camera's) (splattwin.equality)

    def __len__(self) -> int:
        return len(self.frames)

    def train(self) -> list[Frame]:
        return [f for f in self.frames if f.split == "train"]

    def heldout(self) -> list[Frame]:
        return [f for f in self.frames if f.split == "heldout"]

    @property
    def cameras(self) -> list[Camera]:
        return [f.camera for f in self.frames]

    def validate(self) -> None:
        """Check that files exist, that images and depth images match their cameras' sizes and are complete
        (reads image headers and ends only, `limits.check_image_complete`: a truncated photo stops here,
        before SfM), and that depth images are depth (`DEPTH_MODES`)."""
        from splattwin.limits import check_image_complete

        if not self.frames:
            raise InputError("dataset has no frames", self.root)
        for f in self.frames:
            w, h = image_size(f.image_path)
            check_image_complete(f.image_path)
            if (w, h) != (f.camera.width, f.camera.height):
                raise InputError(f"image is {w}x{h} but its camera says {f.camera.width}x{f.camera.height}", f.image_path)
            for extra in (f.depth_path, f.mask_path, f.label_path):
                if extra is not None and not extra.is_file():
                    raise InputError("file listed in the dataset does not exist", extra)
            if f.mask_path is not None:
                loss_mask_size(f.mask_path, (w, h))  # header only
            if f.depth_path is not None and f.depth_path.suffix.lower() != ".npy":
                depth_image_size(f.depth_path, (f.camera.width, f.camera.height))  # header only
                check_image_complete(f.depth_path, "depth image")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image header; InputError if missing, unreadable or beyond the pixel
    limit (`splattwin.limits`)."""
    from splattwin.limits import image_size as _size

    return _size(path)


def load_image(path: str | Path) -> np.ndarray:
    """RGB image as float32 HxWx3 in [0, 1] (alpha dropped, greyscale expanded). The header's size is
    checked (`splattwin.limits`) before the pixels are decoded."""
    from splattwin.limits import read_image_array

    return read_image_array(path, mode="RGB").astype(np.float32) / 255.0


def load_mask(path: str | Path) -> np.ndarray:
    """Mask or label image as uint8/uint16 HxW (first channel if it has several)."""
    from splattwin.limits import read_image_array

    m = read_image_array(path, what="mask")
    return m[..., 0] if m.ndim == 3 else m


# how much smaller than its photo a loss mask or a depth map may be: nerfstudio's masks_8/ at most; a phone's
# LiDAR depth (256x192) for its 4032x3024 photos is 1/15.75. A 1x1 map stretched over a photo says nothing.
MAX_REDUCTION = 16


def _mask_downscale(mask_size: tuple[int, int], image_size: tuple[int, int]) -> int | None:
    """The whole factor k >= 1 by which an image of `image_size` (w, h) was reduced to `mask_size`: each side
    w / k rounded either way (nerfstudio's downscaled masks_2/, masks_4/ ... folders); None when there is
    none."""
    (mw, mh), (w, h) = mask_size, image_size
    if mw < 1 or mh < 1 or mw > w or mh > h:
        return None
    k = max(1, round(w / mw))
    for kk in (k - 1, k, k + 1):
        if 1 <= kk <= MAX_REDUCTION and mw in (w // kk, -(-w // kk)) and mh in (h // kk, -(-h // kk)):
            return kk
    return None


def loss_mask_size(path: str | Path, image_size: tuple[int, int]) -> tuple[int, int]:
    """(width, height) of the loss mask at `path` from its header; InputError naming the mask when it is
    not of its image's size `image_size` (w, h) or that size divided by a whole factor."""
    from splattwin.limits import open_image

    with open_image(path, "loss mask") as im:
        size = tuple(im.size)
    if _mask_downscale(size, image_size) is None:
        raise InputError(f"loss mask is {size[0]}x{size[1]} but its image is {image_size[0]}x{image_size[1]}: a "
                         f"loss mask must have the image's size or the image's size divided by a whole number",
                         path)
    return size


def load_loss_mask(path: str | Path, image_size: tuple[int, int]) -> np.ndarray:
    """A nerfstudio loss mask (a frame's `mask_path`) as bool [h, w] at its image's size `image_size` (w, h):
    True where the pixel is trained on and evaluated, False (a 0 in the file) where it is ignored. As
    nerfstudio reads it: any non-zero value keeps the pixel (first channel of a colour image). A mask of the
    image's size divided by a whole factor (nerfstudio's masks_2/ ...) is enlarged by nearest pixel. The file
    is untrusted: its size is checked from the header before it is decoded (`loss_mask_size`)."""
    loss_mask_size(path, image_size)
    m = load_mask(path) != 0
    if (m.shape[1], m.shape[0]) != tuple(image_size):
        m = resize_nearest(m, image_size[0], image_size[1])
    return np.ascontiguousarray(m)


# PIL modes of depth images: 16-bit greyscale (PNG, TIFF; "I" is how PIL opens some 16-bit PNGs), 32-bit
# integer or float (TIFF). 8-bit, palette or colour images are not depth: read as millimetres they gave a
# plausible but wrong cloud (a 0..255 mm scene), so they are refused.
DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I", "F")
# metres per raw depth unit, every format (BOP depth_scale / 1000, TUM 1 / depth_factor, nerfstudio
# depth_unit_scale_factor): from a micrometre to 100 m. Values outside made every depth 0 or inf.
DEPTH_SCALE_RANGE = (1e-6, 1e2)


def _check_depth_image(im, path: Path, size: tuple[int, int] | None) -> None:
    if im.mode not in DEPTH_MODES:
        raise InputError(f"depth image must be single-channel 16-bit (or 32-bit integer or float), got PIL mode "
                         f"{im.mode!r} ({len(im.getbands())} channel(s)); 8-bit or colour images are not depth maps",
                         path)
    if size is not None:
        depth_needs_resize(tuple(im.size), tuple(size), path)


def depth_needs_resize(depth_wh: tuple[int, int], size: tuple[int, int], path: Path) -> bool:
    """Whether a depth map of `depth_wh` must be resized (nearest) to its camera's `size`: False when equal,
    True when smaller with the same aspect ratio within a pixel (a phone's 256x192 depth for 1024x768
    photos, which nerfstudio resizes too), else InputError: depth must be registered to the colour camera."""
    (dw, dh), (w, h) = depth_wh, size
    if (dw, dh) == (w, h):
        return False
    if (dw <= w and dh <= h and dw * MAX_REDUCTION >= w and dh * MAX_REDUCTION >= h
            and abs(dw * h / w - dh) <= 1 and abs(dh * w / h - dw) <= 1):
        return True
    raise InputError(f"depth map is {dw}x{dh} but its camera is {w}x{h}: depth must be registered to the colour "
                     f"camera, at its size or a smaller one of the same aspect ratio (at most {MAX_REDUCTION} times "
                     f"smaller)", path)


def depth_image_size(path: str | Path, size: tuple[int, int] | None = None) -> tuple[int, int]:
    """(width, height) of a depth image from its header, InputError naming it when it is not a depth image
    (DEPTH_MODES) or, with `size`, not of that size (its camera's)."""
    from splattwin.limits import open_image

    with open_image(path, "depth image") as im:
        _check_depth_image(im, Path(path), size)
        return im.size


def load_depth(path: str | Path, scale: float | None = None, size: tuple[int, int] | None = None) -> np.ndarray:
    """Depth map as float32 HxW metres (0 / non-finite = no measurement, as the sensors write it).

    path: `.npy` (numbers) or an image (16-bit PNG / TIFF). scale: metres per raw unit, explicit per
    format (`Dataset.depth_scale`: nerfstudio `depth_unit_scale_factor`, BOP `depth_scale` / 1000,
    TUM 1/5000); None = the file type's default: integer images in millimetres (nerfstudio's default
    1e-3), float arrays in metres. Integer depth with a scale of 1/k for a whole k (1/1000, 1/5000) is
    divided by k, so the metres are the correctly rounded float32 of raw / k.
    size: (width, height) of its camera: a smaller map of the same aspect is resized to it (nearest),
    another size is an InputError naming the depth file (`depth_needs_resize`).
    Images must be single-channel 16-bit, 32-bit integer or float (DEPTH_MODES).
    """
    from splattwin.limits import check_pixels, load_npy, open_image

    path = Path(path)
    if not path.is_file():
        raise InputError("depth file does not exist", path)
    if path.suffix == ".npy":
        d = load_npy(path, "depth array")
    else:
        with open_image(path, "depth image") as im:
            _check_depth_image(im, path, size)
            im.load()
            d = np.asarray(im)
    if d.ndim != 2:
        raise InputError(f"depth must be a 2-D array, got shape {d.shape}", path)
    check_pixels(d.shape[1], d.shape[0], path, "depth map")
    if size is not None and depth_needs_resize((d.shape[1], d.shape[0]), tuple(size), path):
        d = resize_nearest(d, *size)  # nearest: no depth invented across an edge
    if d.dtype.kind not in "fiub":
        raise InputError(f"depth must hold numbers, got dtype {d.dtype}", path)
    if scale is None:
        scale = 1e-3 if d.dtype.kind in "iub" else 1.0
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"depth scale must be a positive number of metres per unit, got {scale}", path)
    inv = 1.0 / scale
    if d.dtype.kind in "iub" and inv > 1.5 and abs(inv - round(inv)) < 1e-6 * inv:
        return (d.astype(np.float64) / round(inv)).astype(np.float32)
    return (d.astype(np.float64) * scale).astype(np.float32)


def default_depth_scale(path: str | Path) -> float:
    """The metres per raw unit `load_depth` assumes for this file without an explicit scale, from its header
    only: 1e-3 for integer depth (mm), 1.0 for float depth (m)."""
    from splattwin.limits import npy_header, open_image

    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            with open(path, "rb") as f:
                kind = npy_header(f)[1].kind
        except (ValueError, OSError, EOFError) as e:
            raise InputError(f"not a readable .npy depth array: {e}", path) from None
    else:
        with open_image(path, "depth image") as im:
            kind = "f" if im.mode == "F" else "i"
    return 1e-3 if kind in "iub" else 1.0


def resize_nearest(a: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H,W,...] array resized to [height,width,...] by nearest pixel centre: for depth and label maps,
    where averaging across an edge would invent values that are in neither neighbour."""
    v = np.minimum((np.arange(height) + 0.5) * a.shape[0] / height, a.shape[0] - 1).astype(int)
    u = np.minimum((np.arange(width) + 0.5) * a.shape[1] / width, a.shape[1] - 1).astype(int)
    return a[v[:, None], u[None, :]]


def find_images(folder: Path, inside: Path | None = None) -> list[Path]:
    """The image files of `folder` (suffix in IMAGE_SUFFIXES, any case), sorted by name (see `list_files`
    for `inside`)."""
    return list_files(folder, _IMAGE_SUFFIXES_LOWER, inside)


_HIDDEN_ANNOUNCED: set[Path] = set()


def list_files(folder: Path, suffixes, inside: Path | None = None) -> list[Path]:
    """The files of `folder` whose suffix is in `suffixes` (any case), sorted by name. Hidden files (a
    leading dot) are left out: macOS writes an AppleDouble `._IMG_0001.JPG` beside every photo copied to a
    FAT/exFAT drive or network share, which is no image and stopped the whole capture as unreadable.

    inside: the dataset folder every file must stay in, symbolic links resolved (InputError naming the
    link otherwise), as paths named in a dataset's files must (`splattwin.paths`): a received dataset
    cannot pull other files of this machine into the twin. None (a user's own photo folder): links to
    photos elsewhere are followed, by design."""
    from splattwin.paths import confined

    folder = Path(folder)
    lower = {x.lower() for x in suffixes}
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in lower and p.is_file())
    hidden = [p for p in files if p.name.startswith(".")]
    if hidden:
        files = [p for p in files if not p.name.startswith(".")]
        if folder not in _HIDDEN_ANNOUNCED:   # once per folder and run: every stage lists the capture
            _HIDDEN_ANNOUNCED.add(folder)
            log.info("%s: %d hidden file%s left out (%s%s)", folder, len(hidden), "s" if len(hidden) > 1 else "",
                     ", ".join(p.name for p in hidden[:3]), ", ..." if len(hidden) > 3 else "")
    if inside is not None:
        for p in files:
            confined(inside, p.relative_to(inside), p, f"{p.parent.name}/ file")
    return files


# what a command given a video would do with its camera poses (a video has none)
_POSES_FOR = {"train": "to train with", "eval": "to render the held-out views from",
              "fuse": "to project the 2D masks with"}


def refuse_video(path: str | Path, command: str) -> None:
    """InputError naming `path`, before any frame is extracted, when it is a video given to `command`
    (train, eval, fuse: they need camera poses, which a video has none of; segment: it needs the views'
    image files). Their frames would otherwise be extracted first, into `<stem>_frames/` beside the video,
    outside the command's --out, only for the command to fail on them."""
    if not is_video(path):
        return
    if command == "segment":
        raise InputError("segment needs the views' images, not a video; extract its frames first (`splattwin "
                         "capture frames VIDEO DIR`, then `splattwin segment DIR`), or let `splattwin build VIDEO "
                         "--prompt ...` segment the frames it extracts into the twin", path)
    raise InputError(f"a video has no camera poses {_POSES_FOR[command]}; estimate them first: `splattwin poses "
                     f"VIDEO POSES` then `splattwin {command}` on POSES, or `splattwin build VIDEO --out TWIN` "
                     f"(TWIN/poses is the posed dataset)", path)


def load_dataset(path: str | Path, max_frames: int | None = None, validate: bool = True,
                 frames_dir: str | Path | None = None, require_images: bool = True,
                 min_change: float | None = None, progress: bool = True) -> Dataset:
    """Load any supported dataset layout (see module docstring).

    frames_dir: where a video's extracted frames go (default `<stem>_frames/` beside the video; `build`
    puts them inside the twin folder so that nothing is written outside it), the loss masks of photos with
    transparent pixels, and the upright copies of an image folder's photos stored rotated (EXIF Orientation; `capture.orientation`: without frames_dir
    such a folder is refused).
    max_frames: at most this many frames, evenly spaced (a video: the sharpest of each of that many
    windows, default `VIDEO_MAX_FRAMES`); min_change: a video's near-duplicate threshold (`capture.video`).
    Photos with fully transparent pixels (alpha 0), in any layout, get loss masks in frames_dir/alpha_masks/
    (`capture.images.mask_transparent_pixels`; without frames_dir a warning names them).
    progress: the progress lines of a video's frame scoring (False: `--no-progress`).
    require_images: False keeps the cameras of a transforms.json / cameras.json whose images are missing
    (for work that needs only cameras; implies validate=False, which would read the images).
    Paths read from the dataset's files (image names, depth and mask paths) must stay inside the
    dataset's folder (`splattwin.paths`); names of views must be plain file names (`splattwin.names`).
    """
    from splattwin.capture import bop, cameras_json, colmap, images, nerfstudio, tum, video
    from splattwin.frame_options import check_max_frames

    check_max_frames(max_frames)   # before anything is read or extracted
    path = Path(path)
    if not path.exists():
        raise InputError("dataset path does not exist", path)
    if path.is_file():
        if path.name == bop.SCENE_CAMERA:
            ds = bop.read(path)
        elif path.name in tum.POSE_FILES:
            ds = tum.read(path)
        elif path.name.endswith(".json"):
            with open(path, "rb") as f:
                text_head = f.read(4096).decode("utf-8", errors="replace")
            ds = (cameras_json.read(path, require_images=require_images) if text_head.lstrip().startswith("[")
                  else nerfstudio.read(path, require_images=require_images))
        elif is_video(path):
            ds = video.read(path, max_frames=max_frames, out_dir=frames_dir, min_change=min_change,
                            progress=progress)
        else:
            raise InputError("not a dataset: expected transforms.json, cameras.json, a video, or a folder", path)
    elif (path / "transforms.json").is_file():
        ds = nerfstudio.read(path / "transforms.json", require_images=require_images)
    elif colmap.find_sparse_dir(path) is not None:
        ds = colmap.read(path)
    elif (path / "cameras.json").is_file():
        ds = cameras_json.read(path / "cameras.json", require_images=require_images)
    elif bop.is_scene(path):
        ds = bop.read(path)
    elif tum.is_capture(path) or (path / "rgb.txt").is_file():  # rgb.txt alone: say what is missing
        ds = tum.read(path)
    elif find_images(path) or (path / "images").is_dir():
        ds = images.read(path, out_dir=frames_dir)
    else:
        scenes = sorted(p.name for p in path.iterdir() if p.is_dir() and bop.is_scene(p))
        if scenes:
            raise InputError(f"this folder holds {len(scenes)} BOP scenes ({', '.join(scenes[:5])}"
                             f"{'...' if len(scenes) > 5 else ''}); give one scene folder", path)
        # a camera's own layout (RealSense / ROS exports: rgb/ + depth/ without a pose list; one folder per
        # camera): name the sub-folders that hold images rather than say there are none
        held = image_subfolders(path)
        hint = ""
        if held:
            photos = [n for n, _ in held if n.lower() in ("rgb", "color", "colour", "images", "photos", "frames")]
            # not depth/, masks/ ... (as capture.images.NOT_PHOTO_FOLDERS)
            photos += [n for n, _ in held if not n.lower().startswith(("depth", "mask", "label", "seg"))]
            example = (photos or [held[0][0]])[0]
            listed = ", ".join(f"{n}/ ({k} image{'s' if k > 1 else ''})" for n, k in held[:5])
            hint = (f"; its sub-folders hold images: {listed}{', ...' if len(held) > 5 else ''}. Give the folder of "
                    f"the photos (e.g. {path / example}), which structure from motion poses; sub-folders are "
                    f"not searched")
        raise InputError("no dataset found here (no transforms.json, COLMAP model, cameras.json, BOP scene, "
                         f"TUM pose list + intrinsics, or images){hint}", path)
    if max_frames is not None and len(ds.frames) > max_frames and not (path.is_file() and is_video(path)):
        idx = np.linspace(0, len(ds.frames) - 1, max_frames).round().astype(int)
        ds.frames = [ds.frames[i] for i in idx]
    # names first: they need no file, while validate() reads every image's header and end (~3 ms a frame), so a
    # transforms.json listing its 6 images 20 000 times took a minute to say that names repeat
    _check_frame_names(ds, path)
    if validate and require_images:
        ds.validate()
    if require_images:
        # every format alike (one place): a photo's fully transparent pixels become loss masks written under
        # frames_dir, ANDed with the frame's own mask_path (`capture.images.mask_transparent_pixels`)
        images.mask_transparent_pixels(ds.frames, None if frames_dir is None else Path(frames_dir))
    return ds


def image_subfolders(folder: Path) -> list[tuple[str, int]]:
    """(name, number of images) of the sub-folders of `folder` that hold images, sorted by name; hidden ones
    (.thumbnails, .git), links and folders that cannot be listed left out (for hints: they must not fail)."""
    out = []
    for p in sorted(Path(folder).iterdir()):
        if p.is_dir() and not p.is_symlink() and not p.name.startswith("."):
            try:
                n = len(find_images(p))
            except OSError:
                n = 0
            if n:
                out.append((p.name, n))
    return out


def name_views_by_path(frames: list[Frame]) -> None:
    """View names for images in sub-folders whose stems repeat (a COLMAP rig / multi-camera layout:
    `cam0/0000.jpg`, `cam1/0000.jpg`): when any two frames share an image stem, every frame is named by its
    image's path relative to the folder all the images share, '/' as '_' and without the suffix
    (`cam0_0000`); COLMAP's images/ and a transforms.json's file_path give the same names, as does the
    bundled copy (`capture.bundle` keeps that relative path). Unique stems stay the names (masks are keyed
    by them)."""
    import os

    stems = [f.image_path.stem for f in frames]
    if len(set(stems)) == len(stems):
        return
    common = Path(os.path.commonpath([str(Path(f.image_path).parent) for f in frames]))
    for f in frames:
        rel = Path(f.image_path).relative_to(common)
        f.camera.name = "_".join(rel.parent.parts + (rel.stem,))


def _check_frame_names(ds: Dataset, where: Path) -> None:
    """View names key masks and name output files (label maps, eval images): each must be a plain file
    name and unique within the dataset."""
    from splattwin.names import view_name

    seen: dict[str, Path] = {}
    for f in ds.frames:
        n = view_name(f.name, where, "view name (image file name)")
        if n in seen:
            raise InputError(f"two images have the view name {n!r} ({seen[n]} and {f.image_path}); view names "
                             f"(image file names without extension; when those repeat, the image paths below "
                             f"their common folder, cam0/0000.jpg as cam0_0000) must be unique", where)
        seen[n] = f.image_path
