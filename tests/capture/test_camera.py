import numpy as np
import pytest

from splattwin.capture import Camera, invert_se3, look_at, opencv_from_opengl, opengl_from_opencv
from splattwin.errors import InputError


def test_opencv_opengl_roundtrip_and_axes():
    T = look_at(np.array([0.3, -0.4, 0.5]), np.zeros(3))
    T_gl = opengl_from_opencv(T)
    np.testing.assert_allclose(opencv_from_opengl(T_gl), T, atol=1e-12)
    # OpenGL camera looks down -z: its -z axis is OpenCV's +z (viewing direction).
    np.testing.assert_allclose(-T_gl[:3, 2], T[:3, 2], atol=1e-12)
    # y flips (OpenCV y down, OpenGL y up); position unchanged
    np.testing.assert_allclose(-T_gl[:3, 1], T[:3, 1], atol=1e-12)
    np.testing.assert_allclose(T_gl[:3, 3], T[:3, 3])


def test_look_at_projects_target_to_principal_point():
    cam = Camera.from_fov(np.deg2rad(60), 320, 240, look_at(np.array([0.5, 0.2, 0.6]), np.array([0.05, -0.02, 0.0])))
    uv, z = cam.project(np.array([[0.05, -0.02, 0.0]]))
    np.testing.assert_allclose(uv[0], [160, 120], atol=1e-9)
    assert z[0] == pytest.approx(np.linalg.norm([0.45, 0.22, 0.6]))
    # world up (+z) points up in the image (smaller v)
    uv2, _ = cam.project(np.array([[0.05, -0.02, 0.05]]))
    assert uv2[0, 1] < 120


def test_invert_se3_matches_numpy():
    T = look_at(np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.0]))
    np.testing.assert_allclose(invert_se3(T), np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(invert_se3(np.stack([T, T]))[1], np.linalg.inv(T), atol=1e-12)


def test_projection_with_distortion_matches_opencv():
    import cv2

    K = np.array([[200.0, 0, 160], [0, 210.0, 120], [0, 0, 1]])
    dist = np.array([-0.1, 0.02, 0.001, -0.002, 0.003])
    T = look_at(np.array([0.0, -0.5, 0.5]), np.zeros(3))
    cam = Camera(K=K, width=320, height=240, T_world_cam=T, dist=dist)
    pts = np.random.default_rng(1).uniform(-0.1, 0.1, (50, 3))
    uv, _ = cam.project(pts)
    Tcw = cam.T_cam_world
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(Tcw[:3, :3])[0], Tcw[:3, 3], K, dist)
    np.testing.assert_allclose(uv, ref[:, 0, :], atol=1e-6)


def test_points_behind_camera_are_nan_and_outside():
    cam = Camera.from_fov(1.0, 64, 48)
    uv, z = cam.project(np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert np.isnan(uv[0]).all() and z[0] < 0
    assert cam.in_image(uv).tolist() == [False, True]


def test_scaled_camera():
    cam = Camera.from_fov(1.0, 320, 240)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (160, 120)
    assert half.fx == pytest.approx(cam.fx / 2) and half.cx == pytest.approx(80)


@pytest.mark.parametrize("bad", [
    dict(T_world_cam=np.full((4, 4), np.nan)),
    dict(T_world_cam=np.diag([1.0, 1.0, -1.0, 1.0])),  # reflection
    dict(K=np.diag([0.0, 1.0, 1.0])),
    dict(width=0),
    dict(dist=[0.1, 0.2, 0.3]),
])
def test_camera_rejects_bad_values(bad):
    kw = dict(K=np.diag([100.0, 100.0, 1.0]), width=64, height=48, T_world_cam=np.eye(4), name="c0")
    kw.update(bad)
    with pytest.raises(InputError):
        Camera(**kw)


def test_dict_roundtrip():
    cam = Camera(K=np.diag([100.0, 90.0, 1.0]), width=64, height=48, dist=[0.1, 0, 0, 0], name="x",
                 T_world_cam=look_at(np.ones(3), np.zeros(3)))
    back = Camera.from_dict(cam.to_dict())
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.T_world_cam, cam.T_world_cam)
    np.testing.assert_allclose(back.dist, cam.dist)
    assert back.name == "x"


def test_pixel_rays_back_project_to_the_pixel_centres():
    cam = Camera(K=[[50.0, 0, 19.3], [0, 45.0, 14.1], [0, 0, 1]], width=40, height=30,
                 T_world_cam=look_at(np.array([0.2, -0.5, 0.8]), np.zeros(3)))
    rays = cam.pixel_rays()
    assert rays.shape == (30, 40, 3) and np.all(rays[..., 2] == 1.0)
    depth = np.random.default_rng(0).uniform(0.5, 2.0, (30, 40))
    p_cam = (rays * depth[..., None]).reshape(-1, 3)
    p_world = p_cam @ cam.T_world_cam[:3, :3].T + cam.T_world_cam[:3, 3]
    np.testing.assert_allclose(cam.world_to_cam(p_world), p_cam, atol=1e-12)
    uv, z = cam.project(p_world)
    v, u = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(uv, np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1), atol=1e-9)
    np.testing.assert_allclose(z, depth.ravel(), atol=1e-12)


@pytest.mark.parametrize("bad, msg", [
    (dict(K=np.array([[100.0, 0, 32], [0, 100, 24], [0.5, 0, 1]])), r"K must be \[\[fx, 0, cx\]"),
    (dict(K=np.array([[100.0, 3, 32], [0, 100, 24], [0, 0, 1]])), "no skew"),
    (dict(K=np.diag([1e308, 100.0, 1.0])), "focal length fx = 1e\\+308 px is implausible for a 64x48 image"),
    (dict(K=np.diag([100.0, 0.01, 1.0])), "focal length fy = 0.01 px"),
    (dict(K=np.array([[100.0, 0, 200], [0, 100, 24], [0, 0, 1]])), r"principal point \(cx, cy\) = \(200, 24\)"),
    (dict(dist=[1e300, 0, 0, 0]), r"distortion coefficients must be within \+-1000"),
    (dict(T_world_cam=np.diag([1.0, 1, 1, 1]) + np.eye(4, k=3) * 2e9), r"camera position .* more than 1e\+09 m"),
])
def test_plausible_refuses_what_no_camera_is(bad, msg):
    from splattwin.capture.camera import plausible

    kw = dict(K=np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]), width=64, height=48, name="c0")
    assert plausible(Camera(**kw)).fx == 100.0
    kw.update(bad)
    with pytest.raises(InputError, match=msg):
        plausible(Camera(**kw))


@pytest.mark.parametrize("K, T, msg", [
    (np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 0]]), np.eye(4), "0 0 1"),
    (np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 2]]), np.eye(4), "0 0 1"),
    (np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]]), np.vstack([np.eye(4)[:3], [1.0, 2, 3, 1]]), "0 0 0 1"),
    (np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]]), np.diag([1.0, 1, 1, 2]), "0 0 0 1"),
])
def test_camera_refuses_a_projective_K_or_pose_row(K, T, msg):
    """K[2,2]=0 and a pose whose bottom row is [1,2,3,1] were accepted (audit 8A, L6)."""
    with pytest.raises(InputError, match=msg):
        Camera(K, 160, 120, T_world_cam=T)


def test_cameras_compare_by_value():
    """`cam == other` / `cam in cameras` raised ValueError (array fields); audit 10A L1."""
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    cam = Camera(K, 64, 48, look_at(np.array([1.0, 0, 1]), np.zeros(3)), name="v0")
    same = Camera(K.copy(), 64, 48, cam.T_world_cam.copy(), name="v0")
    assert cam == same and cam in [Camera(K, 64, 48), same]
    assert cam != Camera(K, 64, 48, name="v0") and cam != Camera(K, 64, 40, cam.T_world_cam, name="v0")
