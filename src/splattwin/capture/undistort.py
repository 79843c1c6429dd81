"""Undistorting photos: a distorted camera's image resampled to an ideal pinhole camera.

The rasterizer draws ideal pinhole images (`splattwin.splat.rendering`), while SfM estimates the photos' lens
distortion (COLMAP's SIMPLE_RADIAL by default) and known-pose captures may give one. Fitting pinhole
renders to distorted photos misplaces the periphery by the distortion: a phone photo with k1 = 0.03 at
1080x1920 is off by ~16 px in its corners, so every view pulls the same surface to a different place.
3DGS and nerfstudio train on COLMAP-undistorted images for this reason; we resample each photo once when it
is loaded for training or evaluation (`splattwin.splat.trainer.load_views`).

`pinhole_for(camera)` keeps the size and principal point and scales the focal length so that every pixel of
the undistorted image samples inside the photo (no blank borders, as COLMAP's undistorter with
blank_pixels = 0): zoomed in a little for pincushion (k1 > 0), out for barrel distortion.
`undistort_image` resamples (bicubic; nearest for depth and labels) with the OpenCV model of
`capture.camera.distort` in our pixel convention (pixel centres at +0.5, `Camera.pixel_rays`).

The other way round, for comparing renders with masks in the photo's own pixel grid (the semantic fusion):
`covering_pinhole(camera)` is the pinhole whose image holds every photo pixel's ray, and `distort_image`
resamples a render at it to the photo's grid.

OpenCV does the sampling (`remap`) and the inverse of the lens model (`undistortPoints`); the maps are
built here from our own `distort`, not with `initUndistortRectifyMap`/`getOptimalNewCameraMatrix`, which
index pixel centres at integers and move the principal point, so that the two conventions cannot drift
apart and the pinhole keeps the photo's principal point.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np

from splattwin.capture.camera import Camera, distort
from splattwin.errors import InputError

# the focal length of the pinhole camera stays within this factor of the photo's (COLMAP's undistorter
# bounds its scale likewise): a model that would need more is not a lens a photo was taken with
MIN_SCALE, MAX_SCALE = 0.5, 2.0


def _border_pixels(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres (u, v) [M] of the image's outermost rows and columns (continuous coordinates)."""
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    us = np.concatenate([u, u, np.full(height, 0.5), np.full(height, width - 0.5)])
    vs = np.concatenate([np.full(width, 0.5), np.full(width, height - 0.5), v, v])
    return us, vs


def _source_pixels(camera: Camera, K_new: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where pixel centres (u, v) of the pinhole camera K_new fall in the (possibly distorted) photo
    (continuous px)."""
    x = (u - K_new[0, 2]) / K_new[0, 0]
    y = (v - K_new[1, 2]) / K_new[1, 1]
    if camera.dist is not None:
        x, y = distort(x, y, camera.dist)
    return camera.fx * x + camera.cx, camera.fy * y + camera.cy


def _valid(camera: Camera, scale: float, us: np.ndarray, vs: np.ndarray) -> bool:
    """Every border pixel of the pinhole camera with focal x `scale` samples inside the photo, on the part
    of the lens model where the distorted radius still grows with the radius (beyond it the model folds
    back and a ray would wrongly look valid)."""
    K_new = _scaled_K(camera, scale)
    su, sv = _source_pixels(camera, K_new, us, vs)
    inside = (su >= 0) & (su <= camera.width) & (sv >= 0) & (sv <= camera.height)
    if not np.all(inside):
        return False
    # radial monotonicity at the border: moving 0.1 % further out must move the sample further out
    cu, cv = K_new[0, 2], K_new[1, 2]
    su2, sv2 = _source_pixels(camera, K_new, cu + (us - cu) * 1.001, cv + (vs - cv) * 1.001)
    r1 = np.hypot(su - camera.cx, sv - camera.cy)
    r2 = np.hypot(su2 - camera.cx, sv2 - camera.cy)
    return bool(np.all(r2 >= r1))


def _scaled_K(camera: Camera, scale: float) -> np.ndarray:
    K = camera.K.copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[0, 1] *= scale
    return K


def pinhole_for(camera: Camera) -> Camera:
    """The ideal pinhole camera an undistorted version of `camera`'s photo is drawn with: the same size,
    pose and principal point, the focal length scaled by the smallest factor in [0.5, 2] at which every
    pixel samples inside the photo. A camera without distortion is returned unchanged.

    Raises InputError when no factor in that range works (a lens model no photo was taken with)."""
    if camera.dist is None:
        return camera
    us, vs = _border_pixels(camera.width, camera.height)
    where = f"camera {camera.name!r}" if camera.name else "camera"
    if not _valid(camera, MAX_SCALE, us, vs):
        raise InputError(f"{where}: lens distortion {np.round(camera.dist, 5).tolist()} cannot be undistorted "
                         f"(no pinhole focal length within {MIN_SCALE}x-{MAX_SCALE}x of {camera.fx:.1f} px keeps "
                         "the image inside the photo)")
    lo, hi = MIN_SCALE, MAX_SCALE
    if _valid(camera, lo, us, vs):
        hi = lo
    else:
        for _ in range(40):  # bisection to ~1e-12 of the range: validity is monotone in the scale
            mid = 0.5 * (lo + hi)
            if _valid(camera, mid, us, vs):
                hi = mid
            else:
                lo = mid
    return replace(camera, K=_scaled_K(camera, hi), dist=None)


def _key(camera: Camera) -> tuple:
    """Hashable intrinsics of a camera (its pose does not enter the resampling)."""
    return (camera.width, camera.height, tuple(camera.K.ravel().tolist()),
            None if camera.dist is None else tuple(camera.dist.tolist()))


def _from_key(key: tuple) -> Camera:
    w, h, k, dist = key
    return Camera(K=np.array(k).reshape(3, 3), width=w, height=h, dist=None if dist is None else np.array(dist))


@functools.lru_cache(maxsize=4)
def _undistort_maps(photo_key: tuple, pinhole_key: tuple) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV remap maps [h,w] float32 (source pixel per pinhole pixel, OpenCV's integer pixel centres).
    Cached: a video's frames share one camera, and a 1080p map takes ~0.4 s."""
    camera, pin = _from_key(photo_key), _from_key(pinhole_key)
    v, u = np.mgrid[0:pin.height, 0:pin.width].astype(np.float64)
    su, sv = _source_pixels(camera, pin.K, u + 0.5, v + 0.5)
    map_u, map_v = (su - 0.5).astype(np.float32), (sv - 0.5).astype(np.float32)
    map_u.setflags(write=False)
    map_v.setflags(write=False)
    return map_u, map_v


def _remap(image: np.ndarray, map_u: np.ndarray, map_v: np.ndarray, nearest: bool, cubic: bool = True) -> np.ndarray:
    """cv2.remap of [H,W(,C)] with edge clamping; more than 4 channels one at a time (OpenCV's limit);
    bicubic results clipped to the input's range (its overshoot at edges is not in the photo)."""
    import cv2

    interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_CUBIC if cubic else cv2.INTER_LINEAR)
    src = np.ascontiguousarray(image)
    if src.ndim == 3 and src.shape[2] > 4:
        out = np.stack([cv2.remap(src[..., c], map_u, map_v, interp, borderMode=cv2.BORDER_REPLICATE)
                        for c in range(src.shape[2])], -1)
    else:
        out = cv2.remap(src, map_u, map_v, interp, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(map_u.shape + image.shape[2:])
    if interp == cv2.INTER_CUBIC and out.size:
        finite = np.isfinite(src)
        if finite.all():
            out = np.clip(out, src.min(), src.max())
    return out


def undistort_image(image: np.ndarray, camera: Camera, pinhole: Camera | None = None,
                    nearest: bool = False) -> np.ndarray:
    """`image` [H,W] or [H,W,C] (float32 or uint8), taken by `camera`, resampled to `pinhole` (default
    `pinhole_for(camera)`; its size may differ). Bicubic (bilinear would blur the photo by up to half a pixel,
    and the photos are both training targets and the held-out yardstick), clipped to the input's range;
    nearest=True for depth maps and label images (values are never mixed: a z-depth keeps its value under
    undistortion, only its pixel moves)."""
    if camera.dist is None and pinhole is None:
        return image
    pin = pinhole_for(camera) if pinhole is None else pinhole
    if image.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the camera is {camera.width}x{camera.height}")
    map_u, map_v = _undistort_maps(_key(camera), _key(pin))
    return _remap(image, map_u, map_v, nearest)


def rays_through(camera: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates (x, y) of the rays through photo pixels (u, v) (continuous px), the
    lens distortion removed by OpenCV's iterative inverse of the model, run to convergence."""
    import cv2

    if camera.dist is None:
        return (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    pts = np.stack([np.ravel(u), np.ravel(v)], -1).astype(np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    xy = cv2.undistortPoints(pts, camera.K, camera.dist, R=None, P=None, criteria=crit).reshape(np.shape(u) + (2,))
    return xy[..., 0], xy[..., 1]


def photo_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates (x, y) [H,W] (z = 1) of the rays through `camera`'s pixel centres,
    its lens distortion removed."""
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    return rays_through(camera, u + 0.5, v + 0.5)


def covering_pinhole(camera: Camera) -> Camera:
    """The pinhole camera (same size, pose and principal point) with the longest focal length whose image
    still holds the ray of every pixel of `camera`'s photo: renders at it cover the whole photo when they
    are resampled to it (`distort_image`), at the price of a blank margin outside the photo (the opposite
    trade to `pinhole_for`). A camera without distortion is returned unchanged."""
    if camera.dist is None:
        return camera
    us, vs = _border_pixels(camera.width, camera.height)
    x, y = rays_through(camera, us, vs)
    # largest s with 0 <= s fx x + cx <= W and 0 <= s fy y + cy <= H for every border ray
    with np.errstate(divide="ignore"):
        sx = np.where(x > 0, (camera.width - camera.cx) / (camera.fx * x),
                      np.where(x < 0, -camera.cx / (camera.fx * x), np.inf))
        sy = np.where(y > 0, (camera.height - camera.cy) / (camera.fy * y),
                      np.where(y < 0, -camera.cy / (camera.fy * y), np.inf))
    scale = float(min(sx.min(), sy.min()))
    if not np.isfinite(scale) or not MIN_SCALE <= scale <= MAX_SCALE:
        where = f"camera {camera.name!r}" if camera.name else "camera"
        raise InputError(f"{where}: lens distortion {np.round(camera.dist, 5).tolist()} cannot be drawn by a "
                         f"pinhole camera within {MIN_SCALE}x-{MAX_SCALE}x of its focal length")
    return replace(camera, K=_scaled_K(camera, scale), dist=None)


def distort_image(image: np.ndarray, pinhole: Camera, camera: Camera, nearest: bool = False) -> np.ndarray:
    """The inverse of `undistort_image`: `image` [h,w(,C)] drawn by the ideal pinhole camera `pinhole`
    (e.g. a render at `covering_pinhole(camera)`, any size) resampled to the pixel grid of the distorted photo
    taken by `camera` [H,W(,C)], so that it can be compared with the photo or its masks pixel for pixel.
    Bilinear (renders are compared with masks here, not photos), or nearest for depth and label maps."""
    if image.shape[:2] != (pinhole.height, pinhole.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the pinhole camera is "
                         f"{pinhole.width}x{pinhole.height}")
    map_u, map_v = _distort_maps(_key(camera), _key(pinhole))
    return _remap(image, map_u, map_v, nearest, cubic=False)


@functools.lru_cache(maxsize=8)
def _distort_maps(photo_key: tuple, pinhole_key: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Remap maps [H,W] float32 from the photo's pixels into the pinhole image (OpenCV's pixel centres).
    Cached by intrinsics (the pose does not enter, so one camera's views share a pair): the fusion resamples
    every view's depth and label maps in each refinement round, and the inverse of the lens model takes
    ~0.4 s for a 1080p photo."""
    camera, pin = _from_key(photo_key), _from_key(pinhole_key)
    x, y = photo_rays(camera)
    map_u = (pin.fx * x + pin.cx - 0.5).astype(np.float32)
    map_v = (pin.fy * y + pin.cy - 0.5).astype(np.float32)
    map_u.setflags(write=False)
    map_v.setflags(write=False)
    return map_u, map_v
