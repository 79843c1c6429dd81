"""Back-projected point cloud from depth images (RGB-D): an initialiser for splat training.

Depth is z-depth in metres along the camera's optical axis (nerfstudio / our scene convention); pixels
with non-finite or non-positive depth, or beyond `max_depth`, are skipped. Pixel (i, j) is taken at its
centre (i + 0.5, j + 0.5), matching `splattwin.capture.Camera`. Distortion is removed with OpenCV.
"""

from __future__ import annotations

import numpy as np

from splattwin.capture.camera import Camera


def backproject_depth(depth: np.ndarray, camera: Camera, image: np.ndarray | None = None, stride: int = 1,
                      max_depth: float = np.inf) -> tuple[np.ndarray, np.ndarray | None]:
    """One depth map -> world points.

    Args:
        depth: [H,W] metres (z-depth). image: [H,W,3] float [0,1] or uint8, optional (colours).
        stride: keep every stride-th pixel in u and v. max_depth: metres.
    Returns: xyz [N,3] world frame (camera.T_world_cam), rgb [N,3] uint8 or None.
    """
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    if (W, H) != (camera.width, camera.height):
        raise ValueError(f"depth is {W}x{H} but the camera is {camera.width}x{camera.height}")
    v, u = np.mgrid[0:H:stride, 0:W:stride]
    z = depth[v, u]
    ok = np.isfinite(z) & (z > 0) & (z <= max_depth)
    u, v, z = u[ok], v[ok], z[ok]
    uv = np.stack([u + 0.5, v + 0.5], axis=1).astype(np.float64)
    if camera.dist is not None:
        import cv2

        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.dist).reshape(-1, 2)
    else:
        xy = (uv - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    p_cam = np.column_stack([xy * z[:, None], z])
    T = camera.T_world_cam
    xyz = p_cam @ T[:3, :3].T + T[:3, 3]
    rgb = None
    if image is not None:
        img = np.asarray(image)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).round().astype(np.uint8)
        rgb = img[v, u, :3]
    return xyz, rgb


def backproject_frames(frames, stride: int = 4, max_depth: float = np.inf, depth_scale: float | None = None,
                       max_points: int | None = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fused cloud from every frame with a depth_path (splattwin.capture Frames). Colours from the images.

    Returns xyz [N,3] float64, rgb [N,3] uint8 (randomly subsampled to max_points).
    """
    from splattwin.capture import load_depth, load_image

    xs, cs = [], []
    for f in frames:
        if f.depth_path is None:
            continue
        d = load_depth(f.depth_path, depth_scale, size=(f.camera.width, f.camera.height))  # names a misfit file
        xyz, rgb = backproject_depth(d, f.camera, load_image(f.image_path), stride=stride, max_depth=max_depth)
        xs.append(xyz)
        cs.append(rgb)
    if not xs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz, rgb = np.concatenate(xs), np.concatenate(cs)
    if max_points is not None and len(xyz) > max_points:
        keep = np.random.default_rng(seed).choice(len(xyz), max_points, replace=False)
        xyz, rgb = xyz[keep], rgb[keep]
    return xyz, rgb


def merge_with_depth(points_xyz: np.ndarray, points_rgb: np.ndarray | None, depth_xyz: np.ndarray,
                     depth_rgb: np.ndarray, voxel: float = 0.002, max_points: int = 200_000,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The initial cloud of a metric RGB-D capture that also has sparse points (SfM / the dataset's): the
    sparse points, then the back-projected depth cloud (`backproject_frames`), one point per `voxel` (m)
    cube (the first: a sparse point where there is one, so repeated views of a surface count once), at
    most `max_points` (random, the sparse points kept first). Returns xyz [N,3] float64, rgb [N,3] uint8."""
    pts = np.asarray(points_xyz, np.float64).reshape(-1, 3)
    prgb = (np.full((len(pts), 3), 128, np.uint8) if points_rgb is None
            else np.asarray(points_rgb).reshape(-1, 3).astype(np.uint8))
    xyz = np.concatenate([pts, np.asarray(depth_xyz, np.float64).reshape(-1, 3)])
    rgb = np.concatenate([prgb, np.asarray(depth_rgb).reshape(-1, 3).astype(np.uint8)])
    sparse = np.arange(len(xyz)) < len(pts)
    ok = np.all(np.isfinite(xyz), axis=1)
    xyz, rgb, sparse = xyz[ok], rgb[ok], sparse[ok]
    if voxel > 0 and len(xyz):
        keys = np.floor((xyz - xyz.min(axis=0)) / voxel).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        keep = np.sort(first)            # in order: a voxel's sparse point wins over its depth points
        xyz, rgb, sparse = xyz[keep], rgb[keep], sparse[keep]
    if len(xyz) > max_points:
        rng = np.random.default_rng(seed)
        idx_s, idx_d = np.flatnonzero(sparse), np.flatnonzero(~sparse)
        if len(idx_s) > max_points:
            idx_s = rng.choice(idx_s, max_points, replace=False)
        idx_d = rng.choice(idx_d, max_points - len(idx_s), replace=False)
        keep = np.sort(np.concatenate([idx_s, idx_d]))
        xyz, rgb = xyz[keep], rgb[keep]
    return xyz, rgb
