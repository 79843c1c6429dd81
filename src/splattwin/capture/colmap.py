"""COLMAP sparse models (text or binary) via pycolmap; writer in COLMAP's text format.

Layouts accepted by `read`: a sparse model folder itself (`cameras.bin|txt`, `images.*`, `points3D.*`),
or a project folder with `sparse/0/` (or `sparse/`) and `images/`. COLMAP's pose is `cam_from_world`
(OpenCV convention), which we invert to `T_world_cam`. Image names in the model must stay inside the
image folder (`splattwin.paths`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera
from splattwin.capture.dataset import Dataset, Frame
from splattwin.errors import InputError
from splattwin.limits import check_pixels
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
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as e:  # pycolmap raises RuntimeError/ValueError on corrupt files
        raise InputError(f"unreadable COLMAP model: {e}", sparse) from e
    frames: list[Frame] = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        cam = rec.camera(im.camera_id)
        K, dist = camera_from_colmap(cam.model.name, np.asarray(cam.params), cam.width, cam.height, im.name, sparse)
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        T_cam_world = np.eye(4)
        T_cam_world[:3, :4] = np.asarray(cfw.matrix())
        if not np.all(np.isfinite(T_cam_world)):
            raise InputError(f"image {im.name!r}: pose is not finite", sparse)
        img_path = confined(image_dir, im.name, sparse, f"image name of image {image_id}")
        check_pixels(cam.width, cam.height, sparse, f"camera of image {im.name!r}")
        if not img_path.is_file():
            log.warning("%s: image %s is missing; skipping it", sparse, img_path)
            continue
        try:
            camera = Camera(K=K, width=cam.width, height=cam.height, T_world_cam=np.linalg.inv(T_cam_world), dist=dist,
                            name=Path(im.name).stem)
        except InputError as e:
            raise InputError(f"image {im.name!r}: {e.problem}", sparse) from e
        frames.append(Frame(image_path=img_path, camera=camera))
    if not frames:
        raise InputError("COLMAP model has no registered image with an existing file", sparse)
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
    pts = []
    if dataset.points_xyz is not None:
        rgb = dataset.points_rgb if dataset.points_rgb is not None else np.full((len(dataset.points_xyz), 3), 128, np.uint8)
        for j, (p, col) in enumerate(zip(dataset.points_xyz, rgb), start=1):
            pts.append(f"{j} {float(p[0])!r} {float(p[1])!r} {float(p[2])!r} {int(col[0])} {int(col[1])} {int(col[2])} 0")
    io.write_text(sparse_dir / "cameras.txt", "# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cam_lines) + "\n")
    io.write_text(sparse_dir / "images.txt", "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D\n" + "".join(l + "\n" for l in img_lines))
    io.write_text(sparse_dir / "points3D.txt", "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(l + "\n" for l in pts))
    return sparse_dir
