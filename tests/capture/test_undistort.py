"""capture.undistort: pinhole cameras for distorted photos and resampling between the two, checked against
an analytic picture (a smooth function of the ray direction) drawn through both cameras."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.capture.camera import Camera, distort
from splattwin.capture.undistort import (_border_pixels, _source_pixels, covering_pinhole, distort_image, photo_rays,
                                         pinhole_for, undistort_image)
from splattwin.errors import InputError

K = np.array([[300.0, 0, 161.0], [0, 310.0, 118.5], [0, 0, 1]])


def _cam(dist) -> Camera:
    return Camera(K=K, width=320, height=240, dist=dist, name="cam")


def _picture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth scene as a function of the normalised ray (x, y): what any camera sees along that ray."""
    return (np.sin(9 * x) + np.cos(7 * y) + x * y).astype(np.float32)


def _pinhole_rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    return (u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy


def test_no_distortion_is_unchanged():
    cam = _cam(None)
    assert pinhole_for(cam) is cam
    img = np.random.default_rng(0).random((240, 320, 3)).astype(np.float32)
    assert undistort_image(img, cam) is img


@pytest.mark.parametrize("dist, zoom_in", [([0.05, 0.0, 0.0, 0.0], True), ([-0.08, 0.01, 0.0, 0.0], False),
                                           ([0.03, -0.01, 0.001, -0.002, 0.001], True)])
def test_pinhole_samples_inside_the_photo_with_the_tightest_focal(dist, zoom_in):
    cam = _cam(dist)
    pin = pinhole_for(cam)
    assert pin.dist is None and (pin.width, pin.height) == (cam.width, cam.height)
    assert np.allclose(pin.T_world_cam, cam.T_world_cam) and (pin.cx, pin.cy) == (cam.cx, cam.cy)
    scale = pin.fx / cam.fx
    assert np.isclose(pin.fy / cam.fy, scale)
    assert (scale > 1.0) == zoom_in  # pincushion crops in, barrel takes in more of the photo
    us, vs = _border_pixels(cam.width, cam.height)
    su, sv = _source_pixels(cam, pin.K, us, vs)
    assert su.min() >= 0 and sv.min() >= 0 and su.max() <= cam.width and sv.max() <= cam.height
    # 0.1 % wider and some border pixel falls outside the photo: the focal is the tightest that works
    wider = pin.K.copy()
    wider[0, 0] /= 1.001
    wider[1, 1] /= 1.001
    su, sv = _source_pixels(cam, wider, us, vs)
    assert su.min() < 0 or sv.min() < 0 or su.max() > cam.width or sv.max() > cam.height


def test_unusable_lens_model_is_refused():
    with pytest.raises(InputError, match="cannot be undistorted"):
        pinhole_for(_cam([-8.0, 0.0, 0.0, 0.0]))  # folds back inside the image: no lens


def test_photo_rays_invert_the_model():
    cam = _cam([0.05, -0.01, 0.001, 0.0005])
    x, y = photo_rays(cam)
    xd, yd = distort(x, y, cam.dist)
    v, u = np.mgrid[0:240, 0:320]
    assert np.abs(cam.fx * xd + cam.cx - (u + 0.5)).max() < 1e-6
    assert np.abs(cam.fy * yd + cam.cy - (v + 0.5)).max() < 1e-6


def test_undistort_image_matches_the_analytic_picture():
    cam = _cam([0.05, -0.01, 0.001, 0.0005])
    photo = _picture(*photo_rays(cam))  # the distorted photo of the scene
    pin = pinhole_for(cam)
    out = undistort_image(photo, cam, pin)
    truth = _picture(*_pinhole_rays(pin))
    # bilinear interpolation of a function with gradients ~0.03 per pixel: errors of a few 1e-3; a half-pixel
    # convention slip or the model applied the wrong way round would give ~1e-2 to 1e-1
    assert np.abs(out - truth).max() < 5e-3
    naive = _picture(*_pinhole_rays(cam))  # ignoring the distortion, as training did before
    assert np.abs(photo - naive).max() > 0.04


@pytest.mark.parametrize("dist", [[-0.06, 0.01, 0.0, 0.001], [0.05, 0.0, 0.002, 0.0]])
def test_distort_image_is_the_inverse_resampling(dist):
    cam = _cam(dist)
    pin = covering_pinhole(cam)
    assert pin.dist is None and (pin.fx < cam.fx) == (dist[0] < 0)  # barrel: wider to hold the corners
    x, y = photo_rays(cam)  # every photo ray lies in the covering pinhole's image
    u, v = pin.fx * x + pin.cx, pin.fy * y + pin.cy
    assert u.min() >= 0 and v.min() >= 0 and u.max() <= pin.width and v.max() <= pin.height
    assert min(u.min(), v.min(), pin.width - u.max(), pin.height - v.max()) < 1.0  # and tightly
    render = _picture(*_pinhole_rays(pin.scaled(2.0)))  # a render of any size at the pinhole camera
    back = distort_image(render, pin.scaled(2.0), cam)
    assert back.shape == (240, 320)
    # the photo's outermost pixels lie up to half a pixel beyond the render's last pixel centres (edge-clamped)
    assert np.abs(back - _picture(x, y))[1:-1, 1:-1].max() < 2e-3
    assert np.abs(back - _picture(x, y)).max() < 2e-2


def test_nearest_keeps_values_and_channels():
    cam = _cam([0.04, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(1)
    depth = rng.choice(np.array([0.5, 0.75, np.inf], np.float32), size=(240, 320))
    out = undistort_image(depth, cam, nearest=True)
    assert set(np.unique(out)) <= {np.float32(0.5), np.float32(0.75), np.float32(np.inf)}
    many = rng.random((240, 320, 6)).astype(np.float32)
    out6 = undistort_image(many, cam)
    assert out6.shape == (240, 320, 6)
    assert np.allclose(out6[..., 5], undistort_image(np.ascontiguousarray(many[..., 5]), cam))
    with pytest.raises(ValueError, match="but the camera is"):
        undistort_image(depth[:100], cam)
