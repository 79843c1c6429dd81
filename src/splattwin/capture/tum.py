"""TUM-style captures: a pose list + an intrinsics file (+ optional depth): read and write.

A folder holding
- a pose list `groundtruth.txt` | `poses.txt` | `trajectory.txt` | `camera_poses.txt` | `poses.tum` |
  `trajectory.tum`: one pose per line, `id_or_timestamp tx ty tz qx qy qz qw` (spaces or commas, `#`
  comments): T_world_cam, camera-to-world, metres, quaternion xyzw (scalar last, the TUM RGB-D
  benchmark's convention), OpenCV camera frame (x right, y down, z forward: the TUM optical frame);
- an intrinsics file `intrinsics.{yaml,yml,json}` | `camera.{yaml,yml,json}` | `calibration.{yaml,yml,json}`:
  `fx fy cx cy width height` (also `w`/`h`, a 3x3 `K`, nested under `camera:`/`intrinsics:`), optional
  distortion `k1 k2 p1 p2 [k3]` or `distortion: [...]`, and the depth unit: `depth_factor` (units per
  metre, TUM / ORB-SLAM `DepthMapFactor`, 5000 for TUM RGB-D) or `depth_scale` (metres per unit, the
  RealSense SDK's, 0.001 for millimetres). Also read: ORB-SLAM2/3 settings (`Camera.fx`, `Camera1.fx`,
  `RGBD.DepthMapFactor`, `Stereo.`-prefixed keys; `Camera.type` must be PinHole), OpenCV FileStorage files
  (`%YAML:1.0` first line, `!!opencv-matrix` entries such as `camera_matrix`, `distortion_coefficients`),
  ROS `camera_info` YAML (camera_calibration's `image_width`, `image_height`, `camera_matrix: {rows, cols,
  data}`, `distortion_coefficients`, `distortion_model: plumb_bob`; or a CameraInfo message's `width`,
  `height`, `k` / `K`, `d` / `D`);
- images: listed in `rgb.txt` (`timestamp path`, TUM RGB-D) or the files of `rgb/` (else `images/`);
- depth (optional): listed in `depth.txt` or the files of `depth/`: 16-bit images, or float images
  (32-bit TIFF, `.npy`) in metres.

Pixel convention: these files (OpenCV, ROS, ORB-SLAM, TUM's tools) put pixel centres at integer
coordinates; splattwin's `Camera` puts them at +0.5 (COLMAP). The principal point read is therefore
cx + 0.5, cy + 0.5, and `write_intrinsics` writes cx - 0.5, cy - 0.5.

Matching poses to images: by id when the first column names the images (`000012` or `12` for
`000012.png`, or the file name); otherwise by time: each image's pose is interpolated (SLERP of the
rotation, linear in the position, as TUM's evaluation tools do) between the two poses that bracket its
timestamp when both are within `max_dt` (default 0.02 s, as TUM's `associate.py`), else the nearest pose
within `max_dt`; images without one are skipped with a warning. Matched by time, the pose list and the image
times are kept in the Dataset's meta (`POSE_TRACK`): `--poses.time-offset-ms` re-matches the images at their
timestamp + an offset (`poses_at_offset`), and the poses stage's latency check scans that offset. Image timestamps come from `rgb.txt`,
else from the file names (`1305031102.175304.png`); whole numbers of 18 or more digits are nanoseconds
(ROS / EuRoC exports: `1403636579763555584`). Depth images are matched to images by nearest timestamp.

Depth units are explicit: the intrinsics file's `depth_factor` / `depth_scale`; without them float depth
is metres, and integer depth is 5000 per metre for the TUM RGB-D layout (`depth.txt` present, with a
warning) and an InputError otherwise (a wrong guess would scale the whole twin).

Everything read is untrusted: text and JSON/YAML sizes are bounded (`splattwin.limits`), paths from
`rgb.txt` / `depth.txt` stay inside the folder (`splattwin.paths`), numbers are checked (finite, unit
quaternions); errors name the file and the line.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.capture.camera import Camera, plausible
from splattwin.capture.dataset import (DEPTH_SCALE_RANGE, Dataset, Frame, default_depth_scale, find_images,
                                       image_size, list_files)
from splattwin.errors import InputError
from splattwin.limits import MAX_POSITION, ascii_uint, check_count, check_pixels, loads_yaml, number, numbers, read_text
from splattwin.paths import confined

log = logging.getLogger(__name__)

POSE_FILES = ("groundtruth.txt", "poses.txt", "trajectory.txt", "camera_poses.txt", "poses.tum", "trajectory.tum")
INTRINSICS_FILES = tuple(f"{s}.{e}" for s in ("intrinsics", "camera", "calibration") for e in ("yaml", "yml", "json"))
TUM_DEPTH_FACTOR = 5000.0  # TUM RGB-D: 5000 depth units per metre
MAX_DT = 0.02              # seconds: TUM associate.py's default max_difference
NS_DIGITS = 18             # a whole-number timestamp this long is nanoseconds (seconds since 1970: 10 digits)
_PREFIXES = ("", "Camera.", "Camera1.", "RGBD.", "Stereo.")  # ORB-SLAM2/3 settings' key prefixes
# OpenCV/ROS/ORB-SLAM pixel centres are at integer coordinates, ours (COLMAP) at +0.5
PIXEL_CENTRE_SHIFT = 0.5
_SPLIT = re.compile(r"[\s,]+")


@dataclass
class Intrinsics:
    """Pinhole intrinsics of a capture (pixels), optional OpenCV distortion and depth unit (metres per
    raw depth unit, None when the file does not say)."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray | None = None
    depth_scale: float | None = None


def find_pose_file(folder: Path) -> Path | None:
    return next((folder / n for n in POSE_FILES if (folder / n).is_file()), None)


def find_intrinsics_file(folder: Path) -> Path | None:
    return next((folder / n for n in INTRINSICS_FILES if (folder / n).is_file()), None)


def is_capture(folder: Path) -> bool:
    """A folder with a pose list and an intrinsics file."""
    return find_pose_file(folder) is not None and find_intrinsics_file(folder) is not None


# -- text lists -----------------------------------------------------------------------------------
def _lines(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-empty, non-comment lines of a bounded text file."""
    text = read_text(path, what)
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, [t for t in _SPLIT.split(s) if t]))
    check_count(len(out), path, f"lines of the {what}")
    return out


def read_pose_list(path: str | Path) -> list[tuple[str, np.ndarray]]:
    """`id_or_timestamp tx ty tz qx qy qz qw` lines -> [(id, T_world_cam [4,4])] in file order."""
    from splattwin.transforms import pose_from_pos_quat_wxyz, quat_wxyz_from_xyzw

    path = Path(path)
    rows = _lines(path, "pose list")
    if not rows:
        raise InputError("pose list holds no pose (expected lines 'id tx ty tz qx qy qz qw')", path)
    keys, vals = [], []
    seen: dict[str, int] = {}  # id -> line: a set, not keys.count (quadratic on a long trajectory)
    for ln, tok in rows:
        if len(tok) != 8:
            raise InputError(f"line {ln}: expected 8 fields 'id_or_timestamp tx ty tz qx qy qz qw', got {len(tok)}", path)
        try:
            v = np.array([float(t) for t in tok[1:]])
        except ValueError:
            raise InputError(f"line {ln}: tx ty tz qx qy qz qw must be numbers, got {' '.join(tok[1:])!r}", path) from None
        if not np.all(np.isfinite(v)):
            raise InputError(f"line {ln}: pose holds a non-finite number", path)
        if np.max(np.abs(v[:3])) > MAX_POSITION:
            raise InputError(f"line {ln}: translation {' '.join(tok[1:4])} is more than {MAX_POSITION:g} m from the "
                             f"origin (wrong units?)", path)
        n = np.linalg.norm(v[3:])
        if abs(n - 1.0) > 1e-2:
            raise InputError(f"line {ln}: quaternion qx qy qz qw has norm {n:.4f}, not 1 (is the order "
                             f"'tx ty tz qx qy qz qw'?)", path)
        if tok[0] in seen:
            raise InputError(f"line {ln}: id/timestamp {tok[0]!r} appears twice (first on line {seen[tok[0]]})", path)
        seen[tok[0]] = ln
        keys.append(tok[0])
        vals.append(v)
    V = np.array(vals)
    T = pose_from_pos_quat_wxyz(V[:, :3], quat_wxyz_from_xyzw(V[:, 3:] / np.linalg.norm(V[:, 3:], axis=1, keepdims=True)))
    return list(zip(keys, T))


def write_pose_list(path: str | Path, poses: list[tuple[str, np.ndarray]], header: str = "") -> Path:
    """Write `id tx ty tz qx qy qz qw` lines (T_world_cam, metres, quaternion xyzw)."""
    from splattwin.transforms import pos_quat_wxyz_from_pose, quat_xyzw_from_wxyz

    lines = [f"# {h}" for h in header.splitlines()] + ["# id_or_timestamp tx ty tz qx qy qz qw"]
    for key, T in poses:
        p, q = pos_quat_wxyz_from_pose(np.asarray(T, dtype=np.float64))
        vals = list(p) + list(quat_xyzw_from_wxyz(q))
        lines.append(" ".join([str(key)] + [repr(float(x)) for x in vals]))
    return io.write_text(path, "\n".join(lines) + "\n")


def _file_list(path: Path, root: Path, what: str) -> list[tuple[float, Path]]:
    """`timestamp path` lines (TUM rgb.txt / depth.txt) -> [(t, file)], paths confined to `root`."""
    out = []
    for ln, tok in _lines(path, what):
        if len(tok) < 2:
            raise InputError(f"line {ln}: expected 'timestamp path'", path)
        t = _as_time(tok[0])
        if t is None:
            raise InputError(f"line {ln}: timestamp {tok[0]!r} is not a finite number (seconds, or whole "
                             f"nanoseconds)", path)
        out.append((t, confined(root, tok[1], path, f"line {ln} path")))
    return out


# -- intrinsics -----------------------------------------------------------------------------------
def _load_mapping(path: Path) -> dict:
    if path.suffix == ".json":
        data = io.read_json(path)
    else:
        text = read_text(path, "intrinsics file", max_bytes=1 << 20)
        if text.startswith("%YAML"):  # OpenCV FileStorage header (`%YAML:1.0`): not YAML 1.1, comment it out
            text = "#" + text  # (a comment, not removed: error messages keep the file's line numbers)
        data = loads_yaml(text, path, opencv=True)
    if not isinstance(data, dict):
        raise InputError("intrinsics file must hold a mapping (fx, fy, cx, cy, width, height)", path)
    flat = dict(data)
    for k in ("camera", "intrinsics", "Camera", "color"):
        if isinstance(data.get(k), dict):
            flat.update(data[k])
    return flat


def _matrix_data(v, path: Path, what: str):
    """An OpenCV `!!opencv-matrix` / ROS `{rows, cols, data}` mapping -> its data list (other values as they are)."""
    if isinstance(v, dict) and "data" in v:
        data = v["data"]
        if not isinstance(data, list):
            raise InputError(f"{what}: 'data' must be a list of numbers", path)
        rows, cols = v.get("rows"), v.get("cols")
        if isinstance(rows, int) and isinstance(cols, int) and rows * cols != len(data):
            raise InputError(f"{what}: {rows}x{cols} matrix with {len(data)} numbers", path)
        return data
    return v


def _get(d: dict, names: tuple[str, ...]):
    for n in names:
        for prefix in _PREFIXES:
            if prefix + n in d:
                return d[prefix + n]
    return None


def read_intrinsics(path: str | Path) -> Intrinsics:
    """Intrinsics file (YAML/JSON, see module docstring) -> Intrinsics; InputError naming the file."""
    path = Path(path)
    d = _load_mapping(path)
    ctype = d.get("Camera.type", d.get("Camera1.type"))
    if isinstance(ctype, str) and ctype.strip().lower() != "pinhole":
        # ORB-SLAM3's KannalaBrandt8 (fisheye) k1..k4 are not OpenCV's k1 k2 p1 p2
        raise InputError(f"camera type {ctype!r}: only a PinHole camera (OpenCV radial-tangential distortion) "
                         f"is read; undistort the images first", path)
    model = d.get("distortion_model")
    if model is not None and str(model).strip().lower() not in ("plumb_bob", "radtan", "radial-tangential"):
        # ROS camera_info: equidistant (fisheye) or rational_polynomial coefficients mean something else
        raise InputError(f"distortion_model {str(model)[:40]!r}: only plumb_bob (OpenCV k1 k2 p1 p2 k3) is read; "
                         f"undistort the images first", path)
    K = None
    rawK = next((d[k] for k in ("K", "k", "camera_matrix") if d.get(k) is not None), None)
    if rawK is not None:
        K = numbers(_matrix_data(rawK, path, "camera matrix K"), 9, path, "K (3x3)").reshape(3, 3)
    else:
        vals = {n: _get(d, (n,)) for n in ("fx", "fy", "cx", "cy")}
        missing = [n for n, v in vals.items() if v is None]
        if missing:
            raise InputError(f"intrinsics file lacks {', '.join(missing)} (needs fx fy cx cy width height)", path)
        fx, fy, cx, cy = (number(vals[n], path, n) for n in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    K = K.copy()
    K[:2, 2] += PIXEL_CENTRE_SHIFT  # integer pixel centres (OpenCV) -> ours (+0.5)
    w, h = _get(d, ("width", "w", "image_width")), _get(d, ("height", "h", "image_height"))
    if w is None or h is None:
        raise InputError("intrinsics file lacks width/height (image size in pixels)", path)
    w, h = check_pixels(w, h, path, "width x height")
    dist = None
    raw = _get(d, ("distortion", "dist", "distortion_coeffs", "distortion_coefficients", "D", "d"))
    raw = _matrix_data(raw, path, "distortion")
    if raw is not None:
        if not isinstance(raw, (list, tuple)) or len(raw) not in (4, 5):
            raise InputError(f"distortion must be 4 or 5 finite numbers k1 k2 p1 p2 [k3], got {str(raw)[:60]}", path)
        dist = numbers(raw, len(raw), path, "distortion k1 k2 p1 p2 [k3]")
    elif any(_get(d, (k,)) is not None for k in ("k1", "k2", "p1", "p2", "k3")):
        dist = np.array([number(0.0 if _get(d, (k,)) is None else _get(d, (k,)), path, k)
                         for k in ("k1", "k2", "p1", "p2", "k3")])
    if dist is not None:
        if dist.size == 5 and dist[4] == 0:
            dist = dist[:4]
    depth_scale = None
    factor = _get(d, ("depth_factor", "DepthMapFactor", "depth_units_per_metre", "depth_units_per_meter"))
    scale = _get(d, ("depth_scale", "depth_unit_scale_factor"))
    if factor is not None and scale is not None:
        raise InputError("give the depth unit once: depth_factor (units per metre) or depth_scale (metres per unit)", path)
    lo, hi = DEPTH_SCALE_RANGE  # metres per raw unit
    if factor is not None:
        depth_scale = 1.0 / number(factor, path, "depth_factor (depth units per metre)", 1.0 / hi, 1.0 / lo)
    elif scale is not None:
        s = number(scale, path, "depth_scale")
        if not 0 < s <= 1:
            raise InputError(f"depth_scale is metres per depth unit (0.001 for millimetres), got {s}; for units "
                             f"per metre (TUM: 5000) write depth_factor", path)
        depth_scale = number(s, path, "depth_scale (metres per depth unit)", lo, hi)
    try:
        plausible(Camera(K=K, width=w, height=h, dist=dist))
    except InputError as e:
        raise InputError(e.problem, path) from e
    return Intrinsics(K=K, width=w, height=h, dist=dist if dist is not None and np.any(dist) else None,
                      depth_scale=depth_scale)


def write_intrinsics(path: str | Path, camera: Camera, depth_factor: float | None = None) -> Path:
    """YAML intrinsics file (fx fy cx cy width height, distortion, depth_factor in units per metre)."""
    import yaml

    # integer pixel centres in the file (OpenCV/TUM), ours at +0.5: see PIXEL_CENTRE_SHIFT
    d: dict = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx - PIXEL_CENTRE_SHIFT,
               "cy": camera.cy - PIXEL_CENTRE_SHIFT, "width": camera.width, "height": camera.height}
    if camera.dist is not None:
        d["distortion"] = [float(x) for x in camera.dist]
    if depth_factor is not None:
        d["depth_factor"] = float(depth_factor)
    return io.write_text(path, yaml.safe_dump(d, sort_keys=False))


# -- matching -------------------------------------------------------------------------------------
def _as_int(s: str) -> int | None:
    return ascii_uint(s, 18)


def _as_time(s: str) -> float | None:
    """Seconds from a timestamp string; a whole number of NS_DIGITS or more digits is nanoseconds."""
    if len(s) >= NS_DIGITS and s.isascii() and s.isdigit():
        # nanoseconds since the epoch have 19 digits; a longer number is no timestamp (and int() of thousands
        # of digits raises, a float of it overflows)
        return int(s) * 1e-9 if len(s) <= NS_DIGITS + 3 else None
    try:
        t = float(s)
    except ValueError:
        return None
    return t if np.isfinite(t) else None


def _match_by_id(keys: list[str], names: list[tuple[str, str]]) -> dict[int, int]:
    """image index -> pose index where a pose id names the image (stem, file name, or equal integers)."""
    by_key: dict = {}
    for j, k in enumerate(keys):
        by_key[k] = j
        if _as_int(k) is not None:
            by_key[("int", _as_int(k))] = j
    out = {}
    for i, (stem, fname) in enumerate(names):
        j = by_key.get(stem, by_key.get(fname))
        if j is None and _as_int(stem) is not None:
            j = by_key.get(("int", _as_int(stem)))
        if j is not None:
            out[i] = j
    return out


def nearest(t_query: np.ndarray, t_ref: np.ndarray, max_dt: float) -> np.ndarray:
    """For each query time, the index of the nearest reference time within max_dt, else -1."""
    order = np.argsort(t_ref)
    ts = t_ref[order]
    pos = np.clip(np.searchsorted(ts, t_query), 1, max(len(ts) - 1, 1))
    lo = np.clip(pos - 1, 0, len(ts) - 1)
    hi = np.clip(pos, 0, len(ts) - 1)
    pick = np.where(np.abs(ts[lo] - t_query) <= np.abs(ts[hi] - t_query), lo, hi)
    ok = np.abs(ts[pick] - t_query) <= max_dt
    return np.where(ok, order[pick], -1)


def interpolate(t_query: np.ndarray, t_ref: np.ndarray, T_ref: np.ndarray,
                max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses at the query times: SLERP + linear position between the two reference poses that bracket each
    query when both are within max_dt of it, else the nearest within max_dt. Returns (T [N,4,4], ok [N]).
    (Nearest alone is off by up to v * half the pose period: 2.5 mm at 0.5 m/s and 100 Hz mocap.)"""
    from scipy.spatial.transform import Rotation, Slerp

    order = np.argsort(t_ref)
    ts, Ts = t_ref[order], T_ref[order]
    near = nearest(t_query, ts, max_dt)
    out = np.array([Ts[j] if j >= 0 else np.eye(4) for j in near])
    hi = np.searchsorted(ts, t_query, side="left")
    for i, (t, h) in enumerate(zip(t_query, hi)):
        if h == 0 or h >= len(ts) or ts[h] == t:
            continue  # outside the trajectory, or an exact match (nearest already took it)
        lo = h - 1
        if t - ts[lo] > max_dt or ts[h] - t > max_dt:
            continue
        a = (t - ts[lo]) / (ts[h] - ts[lo])
        rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Ts[lo][:3, :3], Ts[h][:3, :3]])))([a])
        T = np.eye(4)
        T[:3, :3] = rot.as_matrix()[0]
        T[:3, 3] = (1 - a) * Ts[lo][:3, 3] + a * Ts[h][:3, 3]
        out[i] = T
    return out, near >= 0


def _images(folder: Path) -> tuple[list[Path], list[float | None], Path | None]:
    rgb_txt = folder / "rgb.txt"
    if rgb_txt.is_file():
        lst = _file_list(rgb_txt, folder, "image list")
        return [p for _, p in lst], [t for t, _ in lst], rgb_txt
    # a capture's folders, not a user's photo folder: files must stay inside it (links out are refused)
    for sub in ("rgb", "images"):
        files = find_images(folder / sub, inside=folder) if (folder / sub).is_dir() else []
        if files:
            return files, [_as_time(p.stem) for p in files], None
    files = find_images(folder, inside=folder)
    return files, [_as_time(p.stem) for p in files], None


def _depths(folder: Path, images: list[Path], times: list[float | None],
            max_dt: float) -> tuple[list[Path | None], Path | None, int]:
    """Depth file per image (None where none matches), the depth list (depth.txt or depth/) and how many
    depth files it holds."""
    depth_txt = folder / "depth.txt"
    if depth_txt.is_file():
        lst = _file_list(depth_txt, folder, "depth list")
        if not lst:
            return [None] * len(images), depth_txt, 0
        if any(t is None for t in times):
            raise InputError("depth.txt pairs depth by timestamp, but the images have none (no rgb.txt)", depth_txt)
        idx = nearest(np.array(times, dtype=np.float64), np.array([t for t, _ in lst]), max_dt)
        return [lst[j][1] if j >= 0 else None for j in idx], depth_txt, len(lst)
    ddir = folder / "depth"
    if not ddir.is_dir():
        return [None] * len(images), None, 0
    files = {p.stem: p for p in list_files(ddir, (".png", ".tif", ".tiff", ".npy"), inside=folder)}
    out = [files.get(p.stem) for p in images]
    if not any(out) and files and all(t is not None for t in times):
        dkeys = list(files)
        dt = np.array([_as_time(k) if _as_time(k) is not None else np.nan for k in dkeys])
        if np.all(np.isfinite(dt)):
            idx = nearest(np.array(times, dtype=np.float64), dt, max_dt)
            out = [files[dkeys[j]] if j >= 0 else None for j in idx]
    return out, ddir, len(files)


def read(path: str | Path, max_dt: float = MAX_DT) -> Dataset:
    """A TUM-style folder (or its pose list) -> Dataset (see module docstring)."""
    path = Path(path)
    folder = path.parent if path.is_file() else path
    pose_file = path if path.is_file() else find_pose_file(folder)
    intr_file = find_intrinsics_file(folder)
    if pose_file is None:
        raise InputError(f"no pose list here (expected one of {', '.join(POSE_FILES)})", folder)
    if intr_file is None:
        raise InputError(f"no intrinsics file beside the pose list (expected one of {', '.join(INTRINSICS_FILES)} "
                         f"with fx fy cx cy width height)", folder)
    intr = read_intrinsics(intr_file)
    poses = read_pose_list(pose_file)
    keys = [k for k, _ in poses]
    images, times, rgb_txt = _images(folder)
    if not images:
        raise InputError("no images found (rgb.txt, rgb/ or images/)", folder)
    by_id = _match_by_id(keys, [(p.stem, p.name) for p in images])
    if len(by_id) >= max(1, len(images) // 2):
        match = by_id
        mode = "id"
    else:
        pose_t = [_as_time(k) for k in keys]
        if any(t is None for t in pose_t) or any(t is None for t in times):
            bad = next((k for k, t in zip(keys, pose_t) if t is None), None)
            raise InputError("pose ids match no image names and are not all timestamps"
                             + (f" (e.g. {bad[:40]!r})" if bad is not None else "")
                             + " (or the images have no timestamps: add rgb.txt or name the images by time)", pose_file)
        track = {"t": np.array(pose_t, dtype=np.float64), "T_world_cam": np.array([T for _, T in poses]),
                 "image_times": {}, "max_dt": max_dt, "pose_file": str(pose_file)}
        T_at, ok = interpolate(np.array(times, dtype=np.float64), track["t"], track["T_world_cam"], max_dt)
        match = {i: T_at[i] for i in range(len(images)) if ok[i]}
        track["image_times"] = {str(images[i]): float(times[i]) for i in match}  # type: ignore[arg-type]
        mode = "timestamp"
    if mode == "id":
        match = {i: poses[j][1] for i, j in match.items()}
    if not match:
        raise InputError(f"no image has a pose (matched by {mode}"
                         + (f", within {max_dt} s" if mode == "timestamp" else "") + ")", pose_file)
    missing = [images[i].name for i in range(len(images)) if i not in match]
    if missing:
        log.warning("%s: %d of %d images have no pose (matched by %s) and are skipped, e.g. %s", pose_file,
                    len(missing), len(images), mode, ", ".join(missing[:3]))
    depths, depth_src, n_depth = _depths(folder, images, times, max_dt)
    depth_txt = depth_src if depth_src is not None and depth_src.is_file() else None
    n_with = sum(depths[i] is not None for i in match)
    if n_depth and n_with < len(match):
        # depth paired with nothing used to vanish silently (a capture then trains without its depth)
        how = f"within {max_dt} s" if depth_txt is not None else "by name or timestamp"
        if n_with == 0 and depth_txt is not None:
            raise InputError(f"none of its {n_depth} depth images is {how} of one of the {len(match)} posed images "
                             f"(check the timestamps, or remove depth.txt to go without depth)", depth_txt)
        log.warning("%s: %d of %d posed images have no depth image %s (of %d depth images)", depth_src,
                    len(match) - n_with, len(match), how, n_depth)
    depth_scale = intr.depth_scale
    used = [depths[i] for i in match if depths[i] is not None]
    if used and depth_scale is None:
        # float depth (32FC1, TIFF F, .npy) is metres; the 5000/m default is for TUM's 16-bit PNGs only
        kinds = {p: default_depth_scale(p) for p in used}
        if len(set(kinds.values())) > 1:
            f = next(p for p, k in kinds.items() if k == 1.0)
            raise InputError("depth images mix integer and float values; give one kind (and its unit in the "
                             "intrinsics file)", f)
        if next(iter(kinds.values())) == 1.0:
            depth_scale = None  # metres, `load_depth`'s float default
        elif depth_txt is None:
            raise InputError("depth images found but the intrinsics file gives no depth unit: add depth_factor "
                             "(units per metre, e.g. 1000 for millimetres, 5000 for TUM) or depth_scale (metres "
                             "per unit)", intr_file)
        else:
            log.warning("%s: no depth unit (depth_factor / DepthMapFactor / depth_scale); assuming the TUM RGB-D "
                        "benchmark's %g units per metre for its 16-bit depth", intr_file, TUM_DEPTH_FACTOR)
            depth_scale = 1.0 / TUM_DEPTH_FACTOR
    frames = []
    for i, img in enumerate(images):
        if i not in match:
            continue
        w, h = image_size(img)
        if (w, h) != (intr.width, intr.height):
            raise InputError(f"image is {w}x{h} but the intrinsics file says {intr.width}x{intr.height}", img)
        cam = Camera(K=intr.K, width=w, height=h, T_world_cam=match[i], dist=intr.dist, name=img.stem)
        frames.append(Frame(image_path=img, camera=cam, depth_path=depths[i]))
    files = [pose_file, intr_file] + [f for f in (rgb_txt, depth_txt) if f is not None]
    meta = {"format": "tum", "path": str(pose_file), "files": [str(f) for f in files], "matched_by": mode,
            "sequential": True, "intrinsics_file": str(intr_file)}
    if mode == "timestamp":
        meta[POSE_TRACK] = track  # for --poses.time-offset-ms and the latency check (`poses_at_offset`)
    return Dataset(root=folder, frames=frames, has_poses=True, depth_scale=depth_scale, meta=meta)


POSE_TRACK = "pose_track"  # Dataset.meta key: the pose list and image times of a capture matched by timestamp


def poses_at_offset(track: dict, image_paths: list, offset_s: float,
                    max_dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses T_world_cam [N,4,4] of the images (as read: `Frame.image_path`) at their timestamp + offset_s
    (seconds), interpolated in the capture's pose list (`read`'s meta[POSE_TRACK]) as `read` matches them
    (`interpolate`, within max_dt: default the one `read` used), and ok [N]: False where no pose is within
    reach (or the image has no timestamp)."""
    t_img = np.array([track["image_times"].get(str(p), np.nan) for p in image_paths], dtype=np.float64)
    has = np.isfinite(t_img)
    T = np.tile(np.eye(4), (len(t_img), 1, 1))
    ok = np.zeros(len(t_img), dtype=bool)
    if has.any():
        T_at, ok_at = interpolate(t_img[has] + float(offset_s), track["t"], track["T_world_cam"],
                                  track["max_dt"] if max_dt is None else max_dt)
        T[has], ok[has] = T_at, ok_at
    return T, ok


__all__ = ["Intrinsics", "read", "read_intrinsics", "read_pose_list", "write_intrinsics",
           "write_pose_list", "nearest", "interpolate", "is_capture", "POSE_TRACK", "poses_at_offset"]
