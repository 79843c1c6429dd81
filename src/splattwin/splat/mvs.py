"""Plane-sweep multi-view stereo on the training views: dense initial points for sparse captures.

SfM on a handful of photos leaves a thin cloud (the statue: 1380 points for 7 training views), on corners
and strong texture only; the surfaces between them are then grown by densification, which on few views
fits each photo with floaters of its own. Per-pixel depth from the training views' own stereo puts
initial Gaussians on those surfaces from the start.

Method (the classic plane sweep, Collins 1996, with the fusion test of COLMAP's stereo fusion):
1. Each training view is a reference in turn, with its `n_src` nearest training cameras as sources. For
   `n_planes` fronto-parallel planes, uniform in inverse depth between the reference's SfM point depths
   (1st percentile x 0.7 to 99th x 1.5), every source image (grey) is warped onto the reference through
   the plane and compared by zero-mean normalised cross-correlation over `window` x `window` pixels;
   a plane scores the mean of its best two sources (occlusion in the others is tolerated). Each pixel
   takes the best-scoring plane (winner-take-all).
2. Fusion: a pixel's point is kept when its score passes `ncc_min` and at least `min_agree` other views,
   whose own depth at the point's projection also scored above `ncc_min`, see it at the same depth
   within `rel_tol`. Textureless areas (sky, walls) and occlusion boundaries fail one or the other.

Why our own code: COLMAP's PatchMatch stereo (pycolmap) runs only with CUDA, OpenCV's block matchers
need rectified image pairs, and Open3D has no MVS. The sweep is a few dozen torch lines (grid_sample +
box filters) and runs on all cores.

The photos are read through `trainer.load_views`, which resamples a distorted photo to its ideal pinhole
camera (`capture.undistort`), so the sweep's pinhole model holds. Units: depths in the cameras' world
units (metres when the capture is metric), pixels at the stereo size (`max_side`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from splattwin.capture import Camera, Frame
from splattwin.errors import InputError

log = logging.getLogger(__name__)

FLAT_VAR = 1e-5   # grey-level variance below which a patch counts as flat


@dataclass(frozen=True)
class StereoOptions:
    """Plane-sweep settings (see the module docstring). Statue photos, 7 training views at 480 px:
    35-42 % of the middle views' pixels pass the fusion test; 2 % on the cake walk-around (wide
    baselines)."""

    max_side: int = 480       # px: stereo image size (longest side)
    n_planes: int = 96
    n_src: int = 4            # source views per reference (nearest camera centres)
    window: int = 7           # px, odd: NCC window
    ncc_min: float = 0.5
    rel_tol: float = 0.01     # depth agreement, relative
    min_agree: int = 2        # other views that must agree


def _gray(img: np.ndarray) -> np.ndarray:
    return img[..., :3].mean(axis=-1)


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over k x k windows of [B,H,W] (the border averages what is inside the image)."""
    return F.avg_pool2d(x[:, None], k, 1, k // 2, count_include_pad=False)[:, 0]


def zncc(ref: torch.Tensor, src: torch.Tensor, window: int) -> torch.Tensor:
    """Zero-mean normalised cross-correlation of ref [H,W] with each of src [S,H,W] over window x window
    pixels -> [S,H,W] in [-1, 1] (0 where either patch is flat)."""
    r = ref[None]
    mr, ms = _box(r, window), _box(src, window)
    vr = (_box(r * r, window) - mr * mr).clamp_min(0)
    vs = (_box(src * src, window) - ms * ms).clamp_min(0)
    cov = _box(r * src, window) - mr * ms
    # a patch flatter than ~1 grey level (std 0.003) carries no evidence (float32 cancellation noise)
    ok = (vr > FLAT_VAR) & (vs > FLAT_VAR)
    return torch.where(ok, cov / torch.sqrt(vr * vs).clamp_min(1e-12), torch.zeros_like(cov))


def plane_sweep(ref_gray: np.ndarray, ref_cam: Camera, src_grays: Sequence[np.ndarray],
                src_cams: Sequence[Camera], depth_min: float, depth_max: float, n_planes: int = 96,
                window: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Winner-take-all depth [H,W] (z in the reference camera, world units) and its score [H,W] (mean
    NCC of the best two sources, or the only one; -1 where no source sees the pixel at any depth).

    ref_gray [H,W] and src_grays [Hs,Ws] in [0,1] at their cameras' sizes."""
    if not 0 < depth_min < depth_max:
        raise ValueError(f"plane sweep needs 0 < depth_min < depth_max, got {depth_min}, {depth_max}")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    h, w = ref_cam.height, ref_cam.width
    ref = torch.as_tensor(ref_gray, dtype=torch.float32)
    rays = ref_cam.pixel_rays().reshape(-1, 3)
    T_world_ref = ref_cam.T_world_cam
    # per source: q(d) = d * (R_src_ref rays) + t_src_ref, so one matrix product per source, not per plane
    a_list, b_list = [], []
    for c in src_cams:
        T_src_ref = c.T_cam_world @ T_world_ref
        a_list.append(torch.as_tensor(rays @ T_src_ref[:3, :3].T, dtype=torch.float32))
        b_list.append(torch.as_tensor(T_src_ref[:3, 3], dtype=torch.float32))
    srcs = [torch.as_tensor(g, dtype=torch.float32)[None, None] for g in src_grays]
    best = torch.full((h, w), -1.0)
    best_d = torch.zeros((h, w))
    k = min(2, len(src_cams))
    for inv_d in np.linspace(1.0 / depth_min, 1.0 / depth_max, n_planes):
        d = float(1.0 / inv_d)
        warped, valid = [], []
        for c, a, b, s in zip(src_cams, a_list, b_list, srcs):
            q = a * d + b
            z = q[:, 2]
            zs = z.clamp_min(1e-9)
            gx = (c.fx * q[:, 0] / zs + c.cx) / c.width * 2 - 1
            gy = (c.fy * q[:, 1] / zs + c.cy) / c.height * 2 - 1
            ok = (z > 1e-9) & (gx.abs() <= 1) & (gy.abs() <= 1)
            grid = torch.stack([gx, gy], -1).reshape(1, h, w, 2)
            warped.append(F.grid_sample(s, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0])
            valid.append(ok.reshape(h, w))
        score = zncc(ref, torch.stack(warped), window)
        score = torch.where(torch.stack(valid), score, torch.full_like(score, -1.0))
        top = score.topk(k, dim=0).values.mean(0)
        better = top > best
        best = torch.where(better, top, best)
        best_d = torch.where(better, torch.full_like(best_d, d), best_d)
    return best_d.numpy().astype(np.float64), best.numpy().astype(np.float64)


def fuse(cams: Sequence[Camera], depths: Sequence[np.ndarray], scores: Sequence[np.ndarray],
         images: Sequence[np.ndarray], ncc_min: float = 0.5, rel_tol: float = 0.01, min_agree: int = 2
         ) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """World points [M,3] and colours [M,3] of the pixels that pass the score and agreement tests, and the
    kept fraction of each view's pixels."""
    xyz_all, rgb_all, kept = [], [], []
    for i, cam in enumerate(cams):
        d = depths[i].reshape(-1)
        p_cam = cam.pixel_rays().reshape(-1, 3) * d[:, None]
        T = cam.T_world_cam
        p_world = p_cam @ T[:3, :3].T + T[:3, 3]
        agree = np.zeros(len(d), dtype=np.int32)
        for j, other in enumerate(cams):
            if j == i:
                continue
            # pinhole, as the sweep (Camera.project would add the lens distortion the sweep ignores)
            q = other.world_to_cam(p_world)
            z = q[:, 2]
            zs = np.maximum(z, 1e-9)
            u = np.floor(other.fx * q[:, 0] / zs + other.cx).astype(np.int64)
            v = np.floor(other.fy * q[:, 1] / zs + other.cy).astype(np.int64)
            inb = (z > 1e-9) & (u >= 0) & (u < other.width) & (v >= 0) & (v < other.height)
            dj = np.zeros(len(d))
            sj = np.full(len(d), -1.0)
            dj[inb] = depths[j][v[inb], u[inb]]
            sj[inb] = scores[j][v[inb], u[inb]]
            agree += (inb & (sj > ncc_min) & (np.abs(dj - z) <= rel_tol * z)).astype(np.int32)
        keep = (scores[i].reshape(-1) > ncc_min) & (agree >= min_agree) & (d > 0)
        kept.append(float(keep.mean()))
        xyz_all.append(p_world[keep])
        rgb_all.append(images[i][..., :3].reshape(-1, 3)[keep].astype(np.float64))
    if not xyz_all:
        return np.zeros((0, 3)), np.zeros((0, 3)), kept
    return np.concatenate(xyz_all), np.concatenate(rgb_all), kept


def dense_points(frames: Sequence[Frame], points_xyz: np.ndarray, max_points: int,
                 opts: StereoOptions = StereoOptions(), seed: int = 0, progress: bool = True
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Up to `max_points` fused stereo points [M,3] (world) with colours [M,3] in [0,1] from the frames'
    images and cameras (use the TRAINING frames only: held-out photos must not shape the model).
    `points_xyz` [N,3] (the sparse SfM/triangulated cloud) bounds each view's depth range; views that see
    fewer than 8 of its points are skipped as references. InputError with fewer than 2 frames."""
    from splattwin.poses.progress import StageProgress
    from splattwin.splat.resolution import Resolution
    from splattwin.splat.trainer import load_views

    if len(frames) < 2:
        raise InputError(f"stereo needs at least 2 training views, got {len(frames)}")
    if points_xyz is None or np.size(points_xyz) < 3 * 8:
        raise InputError("stereo needs a sparse point cloud (at least 8 points, e.g. SfM's) to bound its depth range")
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    views = load_views(list(frames), Resolution(1, opts.max_side, f"stereo: longest side at most {opts.max_side} px"))
    cams = [v.camera for v in views]
    images = [v.image.numpy()[..., :3] for v in views]
    grays = [_gray(im) for im in images]
    centers = np.array([c.center for c in cams])
    depths, scores = [], []
    with StageProgress(progress, prefix="stereo") as bar:
        for i, cam in enumerate(cams):
            bar.update("stereo: plane sweep per training view", i, len(cams))
            z = cam.world_to_cam(pts)[:, 2]
            z = z[z > 0]
            if len(z) < 8:
                depths.append(np.zeros((cam.height, cam.width)))
                scores.append(np.full((cam.height, cam.width), -1.0))
                continue
            order = np.argsort(np.linalg.norm(centers - centers[i], axis=1))
            src = [j for j in order if j != i][:opts.n_src]
            d, sc = plane_sweep(grays[i], cam, [grays[j] for j in src], [cams[j] for j in src],
                                float(np.percentile(z, 1)) * 0.7, float(np.percentile(z, 99)) * 1.5,
                                opts.n_planes, opts.window)
            depths.append(d)
            scores.append(sc)
        bar.update("stereo: plane sweep per training view", len(cams), len(cams))
    xyz, rgb, kept = fuse(cams, depths, scores, images, opts.ncc_min, opts.rel_tol, opts.min_agree)
    log.info("stereo: %d fused points from %d views (kept %s of their pixels)", len(xyz), len(cams),
             " ".join(f"{k:.0%}" for k in kept))
    if len(xyz) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    return xyz, np.clip(rgb, 0.0, 1.0)
