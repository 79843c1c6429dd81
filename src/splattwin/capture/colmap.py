"""COLMAP sparse models (text or binary) via pycolmap; writer in COLMAP's text format.

Layouts accepted by `read`: a sparse model folder itself (`cameras.bin|txt`, `images.*`, `points3D.*`),
or a project folder with `sparse/0/` (or `sparse/`) and `images/`. COLMAP's pose is `cam_from_world`
(OpenCV convention), which we invert to `T_world_cam`. Image names in the model must stay inside the
image folder (`splattwin.paths`).

A model is untrusted input, and pycolmap allocates whatever counts a binary file declares (a 40-byte
patch of images.bin made it reserve 15 GB): `check_model` walks the binary files first, checking every
count against the bytes actually left in the file and against `limits.MAX_ELEMENTS`, and every image's
rotation (a zero quaternion, which pycolmap silently turns into the identity), before pycolmap reads them.
That includes rigs.bin and frames.bin, which COLMAP >= 3.12 writes beside them and takes the poses from: a
frame's sensor count read past the end of a truncated frames.bin had pycolmap loop for billions of records.
"""

from __future__ import annotations

import logging
import math
import mmap
import struct
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, plausible
from splattwin.capture.dataset import Dataset, Frame, name_views_by_path
from splattwin.errors import InputError
from splattwin.limits import MAX_ELEMENTS, MAX_TEXT_BYTES, check_pixels
from splattwin.paths import confined
from splattwin.transforms import quat_wxyz_from_matrix

log = logging.getLogger(__name__)


def _is_model_dir(d: Path) -> bool:
    return any((d / f"cameras.{ext}").is_file() for ext in ("bin", "txt")) and \
        any((d / f"images.{ext}").is_file() for ext in ("bin", "txt"))


def find_sparse_dir(path: Path) -> Path | None:
    """The folder holding the COLMAP model files, or None."""
    for d in (path, path / "sparse" / "0", path / "sparse"):
        if d.is_dir() and _is_model_dir(d):
            return d
    return None


def camera_from_colmap(model: str, params: np.ndarray, width: int, height: int, name: str, where: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(K, dist) from a COLMAP camera model and its parameter vector."""
    p = [float(x) for x in params]
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = p; fx = fy = f; dist = None
    elif model == "PINHOLE":
        fx, fy, cx, cy = p; dist = None
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = p; fx = fy = f; dist = np.array([k, 0, 0, 0])
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p; fx = fy = f; dist = np.array([k1, k2, 0, 0])
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p; dist = np.array([k1, k2, p1, p2])
    elif model == "FULL_OPENCV" and not any(p[9:12]):
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = p[:9]; dist = np.array([k1, k2, p1, p2, k3])
    else:
        raise InputError(f"camera {name!r}: unsupported COLMAP camera model {model} (use PINHOLE/OPENCV, or undistort first)", where)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return K, dist


def _model_params() -> dict[int, int]:
    """COLMAP camera model id -> number of parameters (from pycolmap, so new models are known)."""
    import pycolmap

    out = {}
    for m in pycolmap.CameraModelId.__members__.values():
        if int(m.value) >= 0:
            out[int(m.value)] = len(pycolmap.Camera.create_from_model_id(1, m, 1.0, 1, 1).params)
    return out


class _Reader:
    """Bounds-checked little-endian reads over a memory map of one binary model file."""

    def __init__(self, buf, path: Path):
        self.buf, self.pos, self.path = buf, 0, path

    def left(self) -> int:
        return len(self.buf) - self.pos

    def take(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        if self.left() < n:
            raise InputError(f"truncated COLMAP model file: {what} at byte {self.pos} runs past its end", self.path)
        v = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return v

    def count(self, what: str, record_bytes: int, fmt: str = "<Q") -> int:
        """A count (uint64; `fmt` "<I": uint32) of records of at least `record_bytes` each: bounded by the
        bytes left."""
        (n,) = self.take(fmt, what)
        if n > MAX_ELEMENTS or n * record_bytes > self.left():
            raise InputError(f"{what} is {n}, but the file has only {self.left()} bytes left for them "
                             f"({record_bytes} or more bytes each; at most {int(MAX_ELEMENTS)}): a corrupt or "
                             f"crafted model", self.path)
        return n

    def skip(self, n_bytes: int, what: str) -> None:
        if self.left() < n_bytes:
            raise InputError(f"truncated COLMAP model file: {what} at byte {self.pos} runs past its end", self.path)
        self.pos += n_bytes

    def name(self, what: str) -> str:
        end = self.buf.find(b"\0", self.pos, min(len(self.buf), self.pos + 4096))
        if end < 0:
            raise InputError(f"{what}: no end of the name within 4096 bytes", self.path)
        raw = bytes(self.buf[self.pos:end])
        try:   # pycolmap's Image.name raised UnicodeDecodeError on any other bytes (exit 1)
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{what}: its name {raw[:100]!r} is not UTF-8 text", self.path) from None
        self.pos = end + 1
        return text


def _walk(path: Path, fn) -> None:
    if path.stat().st_size == 0:
        raise InputError("empty COLMAP model file", path)
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        r = _Reader(buf, path)
        fn(r)
        if r.left():
            raise InputError(f"{r.left()} bytes after the last record: not a COLMAP model file", path)


def _check_rotation(q, name: str, where: Path, what: str = "image") -> None:
    """InputError unless `q` (4 numbers) is a finite quaternion of a usable length. math.hypot: squaring a
    component of 1e308 raised OverflowError (exit 1), and a huge one made the pose matrix singular."""
    norm = math.hypot(*(float(x) for x in q))
    if not math.isfinite(norm) or not 1e-6 <= norm <= 1e6:
        raise InputError(f"{what} {name!r}: its quaternion {tuple(float(x) for x in q)} is not a rotation", where)


def check_model(sparse: Path) -> dict[int, str]:
    """InputError for a model file whose declared counts exceed what the file holds or `MAX_ELEMENTS`,
    a camera model pycolmap does not know, or an image whose rotation is no rotation (see the module
    docstring). Text files are bounded by size (their records are lines) and their quaternions checked.
    Returns the image names of an images.txt by image id (whole, spaces included; {} for images.bin)."""
    models = _model_params()
    names: dict[int, str] = {}

    def cameras(r: _Reader) -> None:
        for i in range(r.count("number of cameras", 24)):
            _cid, model = r.take("<Ii", f"camera {i}")[:2]
            if model not in models:
                raise InputError(f"camera {i}: unknown COLMAP camera model id {model}", r.path)
            r.skip(16 + 8 * models[model], f"camera {i}")

    def images(r: _Reader) -> None:
        for i in range(r.count("number of images", 69)):
            rec = r.take("<I4d3dI", f"image {i}")
            name = r.name(f"image {i}")
            _check_rotation(rec[1:5], name, r.path)
            r.skip(24 * r.count(f"number of 2D points of image {name!r}", 24), f"points of image {name!r}")

    def points(r: _Reader) -> None:
        for i in range(r.count("number of 3D points", 51)):
            r.skip(43, f"3D point {i}")
            r.skip(8 * r.count(f"track length of 3D point {i}", 8), f"track of 3D point {i}")

    def rigs(r: _Reader) -> None:   # COLMAP >= 3.12
        for i in range(r.count("number of rigs", 8)):
            r.skip(4, f"rig {i}")
            n = r.count(f"number of sensors of rig {i}", 8, "<I")
            if n:
                r.skip(8, f"reference sensor of rig {i}")
            for j in range(max(n - 1, 0)):
                r.skip(8, f"sensor {j} of rig {i}")
                (has_pose,) = r.take("<B", f"sensor {j} of rig {i}")
                if has_pose:
                    q = r.take("<4d3d", f"pose of sensor {j} of rig {i}")[:4]
                    _check_rotation(q, f"{i}/{j}", r.path, "rig sensor")

    def frames(r: _Reader) -> None:   # COLMAP >= 3.12: the poses pycolmap uses
        for i in range(r.count("number of frames", 68)):
            rec = r.take("<II4d3d", f"frame {i}")
            _check_rotation(rec[2:6], str(rec[0]), r.path, "frame")
            r.skip(16 * r.count(f"number of images of frame {rec[0]}", 16, "<I"), f"images of frame {rec[0]}")

    for stem, fn in (("rigs", rigs), ("cameras", cameras), ("frames", frames), ("images", images), ("points3D", points)):
        b, t = sparse / f"{stem}.bin", sparse / f"{stem}.txt"
        if b.is_file():
            _walk(b, fn)
        elif t.is_file():
            if t.stat().st_size > MAX_TEXT_BYTES:
                raise InputError(f"COLMAP model file of {t.stat().st_size} bytes (at most {int(MAX_TEXT_BYTES)})", t)
            if stem == "images":
                names = _check_text_rotations(t)
    return names


def _check_text_rotations(path: Path) -> dict[int, str]:
    """images.txt: each image line (`IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, the first non-empty,
    non-comment line) is followed by its points line (read as is, possibly empty), as COLMAP reads them.
    Returns {image id: NAME}, NAME being the rest of the line: COLMAP writes a name with spaces as it is
    (`f 4.jpg`), but reads (as pycolmap does) only up to the first space (`f`)."""
    from splattwin.limits import ascii_uint, read_text

    names: dict[int, str] = {}
    lines = iter(read_text(path, "COLMAP images.txt").splitlines())
    for ln in lines:
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        next(lines, None)   # its 2D points
        f = ln.split(maxsplit=9)
        if len(f) < 10:
            continue        # pycolmap names the bad line
        try:
            q = [float(x) for x in f[1:5]]
        except ValueError:
            continue
        name = f[9].rstrip()
        _check_rotation(q, name, path)
        image_id = ascii_uint(f[0])   # (int() of a 5000-digit id raised ValueError: exit 1, "a bug in splattwin")
        if image_id is not None:
            names[image_id] = name
    return names


def read(path: str | Path, image_dir: str | Path | None = None) -> Dataset:
    import pycolmap

    path = Path(path)
    sparse = find_sparse_dir(path)
    if sparse is None:
        raise InputError("no COLMAP model here (need cameras.bin|txt and images.bin|txt)", path)
    if image_dir is None:
        candidates = [path / "images", sparse.parent / "images", sparse.parent.parent / "images"]
        image_dir = next((c for c in candidates if c.is_dir()), path)
    image_dir = Path(image_dir)
    text_names = check_model(sparse)
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as e:  # pycolmap raises RuntimeError/ValueError on corrupt files
        raise InputError(f"unreadable COLMAP model: {e}", sparse) from e
    frames: list[Frame] = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        name = text_names.get(image_id, im.name)   # pycolmap cut a text model's `f 4.jpg` to `f`
        cam = rec.camera(im.camera_id)
        K, dist = camera_from_colmap(cam.model.name, np.asarray(cam.params), cam.width, cam.height, name, sparse)
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        T_cam_world = np.eye(4)
        T_cam_world[:3, :4] = np.asarray(cfw.matrix())
        if not np.all(np.isfinite(T_cam_world)):
            raise InputError(f"image {name!r}: pose is not finite", sparse)
        R = T_cam_world[:3, :3]
        with np.errstate(over="ignore", invalid="ignore"):   # a text model's frames.txt is not walked
            rigid = np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        if not rigid:
            raise InputError(f"image {name!r}: pose rotation is not a rotation matrix", sparse)
        img_path = confined(image_dir, name, sparse, f"image name of image {image_id}")
        check_pixels(cam.width, cam.height, sparse, f"camera of image {name!r}")
        if not img_path.is_file():
            log.warning("%s: image %s is missing; skipping it", sparse, img_path)
            continue
        try:
            camera = plausible(Camera(K=K, width=cam.width, height=cam.height, T_world_cam=np.linalg.inv(T_cam_world),
                                      dist=dist, name=Path(name).stem))
        except InputError as e:
            raise InputError(f"image {name!r}: {e.problem}", sparse) from e
        frames.append(Frame(image_path=img_path, camera=camera))
    if not frames:
        raise InputError("COLMAP model has no registered image with an existing file", sparse)
    name_views_by_path(frames)   # cam0/0000.jpg, cam1/0000.jpg: cam0_0000, cam1_0000
    pts = rec.points3D
    xyz = np.array([p.xyz for p in pts.values()], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts.values()], dtype=np.uint8).reshape(-1, 3)
    return Dataset(root=path, frames=frames, has_poses=True, points_xyz=xyz if len(xyz) else None,
                   points_rgb=rgb if len(rgb) else None, meta={"format": "colmap", "path": str(sparse)})


def write_text(dataset: Dataset, sparse_dir: str | Path) -> Path:
    """Write cameras.txt, images.txt, points3D.txt (one camera per distinct intrinsics).

    Image names are written relative to the common image folder (the first frame's parent).
    Points are written without tracks (COLMAP accepts empty tracks).
    """
    sparse_dir = Path(sparse_dir)
    image_root = dataset.frames[0].image_path.parent
    cam_lines, img_lines, cam_ids = [], [], {}
    for i, f in enumerate(dataset.frames, start=1):
        c = f.camera
        d = c.dist if c.dist is not None else None
        key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy, None if d is None else tuple(d))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            if d is None:
                cam_lines.append(f"{cam_ids[key]} PINHOLE {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx!r} {c.cy!r}")
            elif len(d) == 4 or d[4] == 0:
                cam_lines.append(f"{cam_ids[key]} OPENCV {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx!r} {c.cy!r} "
                                 + " ".join(repr(float(x)) for x in d[:4]))
            else:
                cam_lines.append(f"{cam_ids[key]} FULL_OPENCV {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx!r} {c.cy!r} "
                                 + " ".join(repr(float(x)) for x in d[:5]) + " 0 0 0")
        T = c.T_cam_world
        qw, qx, qy, qz = (float(v) for v in quat_wxyz_from_matrix(T[:3, :3]))  # COLMAP's order is wxyz, w >= 0
        tx, ty, tz = (float(v) for v in T[:3, 3])
        name = f.image_path.relative_to(image_root).as_posix() if f.image_path.is_relative_to(image_root) else f.image_path.name
        img_lines.append(f"{i} {qw!r} {qx!r} {qy!r} {qz!r} {tx!r} {ty!r} {tz!r} {cam_ids[key]} {name}\n")
    spaced = [ln.split(maxsplit=9)[9].rstrip("\n") for ln in img_lines if len(ln.split()) > 10]
    if spaced:
        many = len(spaced) > 1
        log.warning("%s: %d image name%s hold%s spaces (%s%s): splattwin reads them back whole, but COLMAP and "
                    "pycolmap read a text model's image names only up to the first space; rename the images for "
                    "those tools", sparse_dir, len(spaced), "s" if many else "", "" if many else "s",
                    ", ".join(spaced[:3]), ", ..." if len(spaced) > 3 else "")
    pts = []
    if dataset.points_xyz is not None:
        rgb = dataset.points_rgb if dataset.points_rgb is not None else np.full((len(dataset.points_xyz), 3), 128, np.uint8)
        for j, (p, col) in enumerate(zip(dataset.points_xyz, rgb), start=1):
            pts.append(f"{j} {float(p[0])!r} {float(p[1])!r} {float(p[2])!r} {int(col[0])} {int(col[1])} {int(col[2])} 0")
    io.write_text(sparse_dir / "cameras.txt", "# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cam_lines) + "\n")
    io.write_text(sparse_dir / "images.txt", "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D\n" + "".join(l + "\n" for l in img_lines))
    io.write_text(sparse_dir / "points3D.txt", "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(l + "\n" for l in pts))
    return sparse_dir
