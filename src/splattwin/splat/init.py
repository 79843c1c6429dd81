"""Initial Gaussians from a point cloud: SfM points, back-projected depth maps, points triangulated from
the known poses, or (last resort, with a warning) random points inside the cameras' common view.

Scales start isotropic at the mean distance to the 3 nearest neighbours (scipy cKDTree), opacities at 0.1,
rotations at identity, DC colour from the point colour, higher SH at zero (as 3DGS does).

Depth back-projection also places pixels whose depth is missing (inf/0: the ray hits nothing, e.g. the
room behind a tabletop) on a far sphere around the scene, with the pixel's colour, so the background
is represented from the start instead of being faked by floaters near the cameras.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from splattwin.capture import Camera, Frame, load_depth, load_image
from splattwin.capture.undistort import rays_through
from splattwin.errors import InputError
from splattwin.splat.gaussians import Gaussians, num_sh_bases, rgb_to_sh0

log = logging.getLogger(__name__)


def scene_center_and_scale(cameras: Sequence[Camera]) -> tuple[np.ndarray, float]:
    """Centre of the camera centres and 1.1 x their largest distance from it (3DGS 'cameras_extent'), m.
    A single camera (or coincident ones) gets scale 1."""
    c = np.array([cam.center for cam in cameras])
    center = c.mean(axis=0)
    radius = float(np.linalg.norm(c - center, axis=1).max()) * 1.1 if len(c) > 1 else 0.0
    return center, radius if radius > 1e-6 else 1.0


def knn_scales(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """[N] mean distance of each point to its k nearest neighbours (m), floored at 1e-7."""
    n = len(xyz)
    if n < 2:
        return np.full(n, 0.01)
    k = min(k, n - 1)
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)
    return np.maximum(d[:, 1:].mean(axis=1), 1e-7)


def gaussians_from_points(xyz: np.ndarray, rgb: np.ndarray, sh_degree: int = 3, opacity: float = 0.1,
                          scale_factor: float = 1.0) -> Gaussians:
    """Isotropic Gaussians on points [N,3] with colours [N,3] in [0,1]."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    s = knn_scales(xyz) * scale_factor
    sh = np.zeros((n, num_sh_bases(sh_degree), 3))
    sh[:, 0] = rgb_to_sh0(np.clip(rgb, 0, 1))
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    return Gaussians(means=xyz, quats=quats, scales=np.repeat(s[:, None], 3, axis=1),
                     opacities=np.full(n, opacity), sh=sh)


def backproject_depth(depth: np.ndarray, camera: Camera, image: np.ndarray | None = None, stride: int = 1,
                      far_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World points [M,3] (and colours [M,3] in [0,1], grey without an image) of the pixels of a z-depth
    map [H,W] (m), every `stride`-th pixel through its centre. Pixels with depth inf/nan/<=0 are
    dropped, or placed at `far_depth` along their ray when it is given. A camera with lens distortion
    casts each pixel's ray through its model (`capture.undistort`)."""
    h, w = depth.shape
    if (w, h) != (camera.width, camera.height):
        camera = camera.scaled(w / camera.width)
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    if far_depth is not None:
        z = np.where(ok, z, far_depth)
        ok = np.ones_like(ok)
    u, v, z = u[ok], v[ok], z[ok]
    rx, ry = rays_through(camera, u + 0.5, v + 0.5)  # through the lens model, if the camera has one
    x, y = rx * z, ry * z
    p_cam = np.stack([x, y, z], axis=1)
    T = camera.T_world_cam
    p_world = p_cam @ T[:3, :3].T + T[:3, 3]
    if image is None:
        rgb = np.full((len(p_world), 3), 0.5)
    else:
        if image.shape[:2] != (h, w):
            raise InputError(f"image is {image.shape[1]}x{image.shape[0]} but its depth map is {w}x{h}")
        rgb = image[v, u].astype(np.float64)
    return p_world, rgb


def points_from_depth(frames: Sequence[Frame], depth_scale: float | None = None, max_points: int = 30_000,
                      background_fraction: float = 0.1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fused back-projection of the frames' depth maps, randomly subsampled to `max_points`, of which at
    most `background_fraction` are far-sphere background points. Raises InputError without depth maps."""
    with_depth = [f for f in frames if f.depth_path is not None]
    if not with_depth:
        raise InputError("--init depth needs depth maps, but no training frame has one")
    center, scale = scene_center_and_scale([f.camera for f in frames])
    fg_xyz, fg_rgb, bg_xyz, bg_rgb = [], [], [], []
    for f in with_depth:
        depth = load_depth(f.depth_path, depth_scale, size=(f.camera.width, f.camera.height))  # fits a smaller map
        img = load_image(f.image_path)
        if img.shape[:2] != depth.shape:
            raise InputError(f"depth map is {depth.shape[1]}x{depth.shape[0]} but its image is "
                             f"{img.shape[1]}x{img.shape[0]}", f.depth_path)
        stride = max(1, int(np.sqrt(depth.size * len(with_depth) / (4 * max_points))))
        xyz, rgb = backproject_depth(depth, f.camera, img, stride)
        fg_xyz.append(xyz)
        fg_rgb.append(rgb)
        if background_fraction > 0:
            miss = ~(np.isfinite(depth) & (depth > 0))
            sel = miss[::stride, ::stride].ravel()
            if sel.any():  # rays that hit nothing: on a sphere of 3 x the scene scale around the centre
                xyz_b, rgb_b = _rays_to_sphere(f.camera, img, stride, sel, center, 3.0 * scale)
                bg_xyz.append(xyz_b)
                bg_rgb.append(rgb_b)
    rng = np.random.default_rng(seed)
    xyz, rgb = np.concatenate(fg_xyz), np.concatenate(fg_rgb)
    n_bg_max = int(max_points * background_fraction)
    if bg_xyz and n_bg_max > 0:
        bxyz, brgb = np.concatenate(bg_xyz), np.concatenate(bg_rgb)
        # the whole far sphere, evenly, in the mean background colour: directions no training view saw
        # (but a new view may) render as plausible background instead of the black void
        n_fill = n_bg_max // 2
        fill = center + 3.0 * scale * fibonacci_sphere(n_fill)
        if len(bxyz) > n_bg_max - n_fill:
            keep = rng.choice(len(bxyz), n_bg_max - n_fill, replace=False)
            bxyz, brgb = bxyz[keep], brgb[keep]
        bxyz = np.concatenate([bxyz, fill])
        brgb = np.concatenate([brgb, np.repeat(brgb.mean(axis=0, keepdims=True), n_fill, axis=0)])
    else:
        bxyz, brgb = np.zeros((0, 3)), np.zeros((0, 3))
    n_fg = max_points - len(bxyz)
    if len(xyz) > n_fg:
        keep = np.sort(rng.choice(len(xyz), n_fg, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    return np.concatenate([xyz, bxyz]), np.concatenate([rgb, brgb])


def fibonacci_sphere(n: int) -> np.ndarray:
    """[n,3] nearly uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _rays_to_sphere(camera: Camera, image: np.ndarray, stride: int, sel: np.ndarray, center: np.ndarray,
                    radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Points where the rays of the selected strided pixels leave a sphere (centre, radius)."""
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        camera = camera.scaled(w / camera.width)
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    u, v = u.ravel()[sel], v.ravel()[sel]
    rx, ry = rays_through(camera, u + 0.5, v + 0.5)
    d_cam = np.stack([rx, ry, np.ones(len(u))], 1)
    R, o = camera.T_world_cam[:3, :3], camera.T_world_cam[:3, 3]
    d = d_cam @ R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    oc = o - center
    b = d @ oc
    c = oc @ oc - radius**2
    t = -b + np.sqrt(np.maximum(b * b - c, 0.0))  # camera inside the sphere: the far root is positive
    return o + t[:, None] * d, image[v, u].astype(np.float64)


def random_points(n: int, center: np.ndarray, half_extent: float | np.ndarray, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """n points uniform in the box centre +- half_extent (m) with uniform random colours."""
    rng = np.random.default_rng(seed)
    xyz = np.asarray(center) + rng.uniform(-1, 1, size=(n, 3)) * np.asarray(half_extent)
    return xyz, rng.uniform(0, 1, size=(n, 3))


def look_at_point(cameras: Sequence[Camera]) -> np.ndarray | None:
    """[3] least-squares point nearest to all optical axes (where inward-facing cameras look), or None when
    the axes are (nearly) parallel or the point is behind a camera."""
    if len(cameras) < 2:
        return None
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = c.T_world_cam[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e6:
        return None
    x = np.linalg.solve(A, b)
    if any(c.world_to_cam(x[None])[0, 2] <= 0 for c in cameras):
        return None
    return x


def random_points_in_view(cameras: Sequence[Camera], n: int, seed: int = 0, min_view_fraction: float = 0.5
                          ) -> tuple[np.ndarray, np.ndarray]:
    """n random points inside the cameras' common view: uniform in a cube around the point the cameras
    look at (half side = the largest camera distance to it), kept where at least `min_view_fraction` of the
    cameras (and at least 2) see them in front of them and inside the image (fewer when too few such
    points exist).
    Random colours. The cameras' own surroundings, where random points become floaters that each view
    overfits, stay empty."""
    rng = np.random.default_rng(seed)
    center, scale = scene_center_and_scale(cameras)
    target = look_at_point(cameras)
    if target is None:  # no common focus: a point one scene radius ahead of the mean camera
        d = np.mean([c.T_world_cam[:3, 2] for c in cameras], axis=0)
        target = center + (d / max(np.linalg.norm(d), 1e-9)) * scale
    half = max(float(np.max([np.linalg.norm(c.center - target) for c in cameras])), 1e-6)
    need = min(len(cameras), max(2, int(np.ceil(min_view_fraction * len(cameras)))))  # >= 2 views: no floaters
    kept: list[np.ndarray] = []
    loose: list[np.ndarray] = []
    total = 0
    for _ in range(50):
        cand = target + rng.uniform(-1, 1, size=(max(4 * n, 1000), 3)) * half
        seen = np.zeros(len(cand), int)
        for c in cameras:
            uv, z = c.project(cand)
            seen += c.in_image(uv) & (z > 0.02 * half)
        kept.append(cand[seen >= need])
        loose.append(cand[(seen >= 1) & (seen < need)])
        total += len(kept[-1])
        if total >= n:
            break
    xyz = np.concatenate(kept)[:n]
    if len(xyz) < n:
        xyz = np.concatenate([xyz, np.concatenate(loose)[: n - len(xyz)]])
    if len(xyz) == 0:
        xyz = target + rng.uniform(-1, 1, size=(n, 3)) * half
    return xyz, rng.uniform(0, 1, size=(len(xyz), 3))


def points_from_known_poses(frames: Sequence[Frame], work_dir: str | None = None, progress: bool = True
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points triangulated from the frames' images with their cameras held fixed (COLMAP's point
    triangulator, `splattwin.poses.triangulate`); colours in [0, 1]. InputError when nothing triangulates."""
    from splattwin.poses.triangulate import triangulate_known_poses

    tri = triangulate_known_poses([f.image_path for f in frames], [f.camera for f in frames], work_dir,
                                  progress=progress)
    return tri.points_xyz, tri.points_rgb.astype(np.float64) / 255.0


def _images_exist(frames: Sequence[Frame]) -> bool:
    from pathlib import Path

    return len(frames) >= 2 and all(f.image_path is not None and Path(f.image_path).is_file() for f in frames)


def initial_gaussians(method: str, train_frames: Sequence[Frame], points_xyz: np.ndarray | None = None,
                      points_rgb: np.ndarray | None = None, depth_scale: float | None = None, sh_degree: int = 3,
                      max_points: int = 30_000, seed: int = 0, stereo_points: int = 0,
                      progress: bool = True, points_source: str | None = None) -> tuple[Gaussians, str]:
    """Initial Gaussians by `method` ("auto" | "sfm" | "depth" | "triangulate" | "random"); returns
    (gaussians, method used). "auto" takes the SfM/dataset points if present, else depth maps if present,
    else points triangulated from the images with their known poses, else (with a warning) random points
    in the cameras' common view. stereo_points > 0: up to that many plane-sweep stereo points from the
    training views (`splattwin.splat.mvs`) join the SfM/triangulated ones (the total stays within
    max_points; method reported as e.g. "sfm+stereo"). points_source: what made `points_xyz` (the poses
    stage's `points_source`, `poses_points_source`: e.g. "depth back-projection"), named in the log
    instead of "sfm"."""
    tri: tuple[np.ndarray, np.ndarray] | None = None
    if method == "auto":
        if points_xyz is not None and len(points_xyz) >= 4:
            method = "sfm"
        elif any(f.depth_path is not None for f in train_frames):
            method = "depth"
        elif _images_exist(train_frames):
            try:
                tri = points_from_known_poses(train_frames)
                method = "triangulate" if len(tri[0]) >= 4 else "random"
            except InputError as e:
                log.warning("could not triangulate points from the known poses: %s", e)
                method = "random"
        else:
            method = "random"
    if method == "sfm":
        if points_xyz is None or len(points_xyz) < 4:
            raise InputError("--init sfm needs a point cloud in the dataset (SfM points / ply_file_path); "
                             "none was found")
        xyz = np.asarray(points_xyz, np.float64)
        rgb = np.full((len(xyz), 3), 0.5) if points_rgb is None else np.asarray(points_rgb, np.float64) / 255.0
        if len(xyz) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
            xyz, rgb = xyz[keep], rgb[keep]
    elif method == "depth":
        xyz, rgb = points_from_depth(train_frames, depth_scale, max_points=max_points, seed=seed)
    elif method == "triangulate":
        xyz, rgb = tri if tri is not None else points_from_known_poses(train_frames)
        if len(xyz) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
            xyz, rgb = xyz[keep], rgb[keep]
    elif method == "random":
        n = min(max_points, 20_000)
        log.warning("no point cloud, depth maps or triangulated points: starting from %d random Gaussians inside "
                    "the cameras' common view. Expect a hazy result; give depth maps, a point cloud, or images "
                    "with enough texture to triangulate", n)
        xyz, rgb = random_points_in_view([f.camera for f in train_frames], n, seed)
    else:
        raise InputError(f"unknown --init method {method!r}; choose auto, sfm, depth, triangulate or random")
    room = min(stereo_points, max_points - len(xyz))
    if method in ("sfm", "triangulate") and room > 0:
        from splattwin.splat.mvs import dense_points

        s_xyz, s_rgb = dense_points(train_frames, xyz, room, seed=seed, progress=progress)
        if len(s_xyz):
            xyz, rgb = np.concatenate([xyz, s_xyz]), np.concatenate([rgb, s_rgb])
            method = f"{method}+stereo"
    ok = np.all(np.isfinite(xyz), axis=1)
    if not ok.all():
        log.warning("dropping %d non-finite initial points", int((~ok).sum()))
        xyz, rgb = xyz[ok], rgb[ok]
    what = method
    if points_source and method.startswith("sfm"):   # "sfm": the posed dataset's points, whatever made them
        what = points_source + (" + stereo" if method.endswith("+stereo") else "")
    log.info("initialised %d Gaussians from %s", len(xyz), what)
    return gaussians_from_points(xyz, rgb, sh_degree=sh_degree), method


def poses_report_path(dataset):
    """Where the poses stage's report of a posed dataset lies: poses_report.json beside its transforms.json."""
    from pathlib import Path

    from splattwin.paths import own_file

    p = Path(dataset.meta.get("path", dataset.root))
    folder = p.parent if p.is_file() else p
    return own_file(folder, folder / "poses_report.json", "poses_report.json")   # only splattwin writes one


def poses_points_source(dataset) -> str | None:
    """What made a posed dataset's point cloud, from the poses_report.json beside it (`points_source`; for
    reports written before it, read from `initial_points` / `depth_points`); None when not known."""
    from splattwin.errors import InputError
    from splattwin.limits import MAX_RECORD_BYTES, read_json

    rep = poses_report_path(dataset)
    try:   # a file of the twin (untrusted): bounded; only a log line depends on it, so any fault is "unknown"
        stats = read_json(rep, max_bytes=MAX_RECORD_BYTES)
    except (InputError, OSError):
        return None
    if not isinstance(stats, dict):
        return None
    if isinstance(stats.get("points_source"), str):
        return stats["points_source"]
    base = "SfM points" if stats.get("method") == "sfm" else "the capture's points"
    if stats.get("initial_points"):
        return f"{base} + depth back-projection"
    if stats.get("depth_points") and stats.get("method") == "robot":
        return "depth back-projection"
    return None
