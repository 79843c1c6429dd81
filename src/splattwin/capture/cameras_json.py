"""The 3DGS / InstantSplat `cameras.json` layout: read and write.

A JSON list of `{id, img_name, width, height, position [3], rotation [3][3], fx, fy}` where `position`
is the camera centre and `rotation` the camera-to-world rotation, OpenCV/COLMAP convention, principal
point at the image centre (as the reference 3DGS code writes it). Images are looked up by name (with
any image extension) in `images/` beside the file, or beside the file itself.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, plausible
from splattwin.capture.dataset import IMAGE_SUFFIXES, Dataset, Frame
from splattwin.errors import InputError

_REQUIRED = ("img_name", "width", "height", "position", "rotation", "fx", "fy")


def _find_image(root: Path, name, where: Path) -> Path | None:
    from splattwin.paths import confined

    for folder in (root / "images", root / "input", root):
        p = confined(folder, name, where, "img_name")
        if p.is_file():
            return p
        for ext in IMAGE_SUFFIXES:
            q = confined(folder, f"{name}{ext}", where, "img_name")
            if q.is_file():
                return q
    return None


def read(path: str | Path, image_dir: str | Path | None = None, require_images: bool = True) -> Dataset:
    """A 3DGS cameras.json. Every camera's image must be found (require_images False: a camera without
    its image is kept, its image path the one it would have under images/)."""
    path = Path(path)
    entries = io.read_json(path, missing="file does not exist")
    if not isinstance(entries, list) or not entries:
        raise InputError("expected a non-empty JSON list of cameras (3DGS cameras.json)", path)
    from splattwin.limits import MAX_VIEWS, check_count

    check_count(len(entries), path, "cameras", MAX_VIEWS, "SPLATTWIN_MAX_VIEWS")
    root = Path(image_dir) if image_dir is not None else path.parent
    frames = []
    if not all(isinstance(e, dict) for e in entries):
        raise InputError("every camera entry must be an object", path)
    from splattwin.limits import MAX_POSITION, check_pixels, number, numbers

    ids = [number(e.get("id", 0), path, f"camera entry {i}: id") for i, e in enumerate(entries)]
    entries = [e for _, e in sorted(zip(ids, entries), key=lambda ie: ie[0])]

    for i, e in enumerate(entries):
        missing = [k for k in _REQUIRED if k not in e]
        if missing:
            raise InputError(f"camera entry {i} lacks {', '.join(missing)}", path)
        if not isinstance(e["img_name"], str) or not e["img_name"]:
            raise InputError(f"camera entry {i}: img_name must be a non-empty string", path)
        what = f"camera {e['img_name']!r}:"
        rot = e["rotation"]
        if not (isinstance(rot, list) and len(rot) == 3 and all(isinstance(r, list) and len(r) == 3 for r in rot)):
            raise InputError(f"{what} rotation must be a 3x3 matrix (a list of 3 rows of 3 numbers)", path)
        T = np.eye(4)
        T[:3, :3] = numbers(rot, 9, path, f"{what} rotation").reshape(3, 3)
        T[:3, 3] = numbers(e["position"], 3, path, f"{what} position", -MAX_POSITION, MAX_POSITION)
        w, h = check_pixels(e["width"], e["height"], path, f"{what} width x height")
        K = np.array([[number(e["fx"], path, f"{what} fx"), 0, w / 2.0], [0, number(e["fy"], path, f"{what} fy"), h / 2.0],
                      [0, 0, 1.0]])
        img = _find_image(root, e["img_name"], path)
        if img is None and not require_images:
            from splattwin.paths import confined

            img = confined(root / "images", e["img_name"], path, "img_name")
        if img is None:
            raise InputError(f"image for camera {e['img_name']!r} not found under {root}", path)
        try:
            cam = plausible(Camera(K=K, width=w, height=h, T_world_cam=T, name=Path(e["img_name"]).stem))
        except InputError as err:
            raise InputError(f"camera {e['img_name']!r}: {err.problem}", path) from err
        frames.append(Frame(image_path=img, camera=cam))
    return Dataset(root=path.parent, frames=frames, has_poses=True, meta={"format": "cameras.json", "path": str(path)})


def write(dataset: Dataset, path: str | Path) -> Path:
    """Write the 3DGS layout. Cameras whose principal point is off-centre cannot be represented exactly
    in this format; they raise InputError rather than being silently shifted."""
    out = []
    for i, f in enumerate(dataset.frames):
        c = f.camera
        if c.dist is not None:   # every SfM result has k1: say how to get there, not only what is wrong
            raise InputError(f"camera {c.name!r} has lens distortion {np.round(c.dist, 5).tolist()}, and cameras.json "
                             f"stores only undistorted pinhole cameras: undistort the images first (e.g. "
                             f"`colmap image_undistorter --image_path IMAGES --input_path SPARSE --output_path UNDIST "
                             f"--output_type COLMAP`, then convert UNDIST), or convert to --format nerfstudio or "
                             f"colmap, which keep the distortion", path)
        if abs(c.cx - c.width / 2.0) > 1e-6 or abs(c.cy - c.height / 2.0) > 1e-6:
            raise InputError(f"camera {c.name!r}: cameras.json stores only centred, undistorted pinhole cameras "
                             f"(principal point {c.cx:g}, {c.cy:g} for a {c.width}x{c.height} image)", path)
        out.append({"id": i, "img_name": f.image_path.stem, "width": c.width, "height": c.height,
                    "position": c.T_world_cam[:3, 3].tolist(), "rotation": c.T_world_cam[:3, :3].tolist(),
                    "fy": c.fy, "fx": c.fx})
    return io.write_json(path, out)
