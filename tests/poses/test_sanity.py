"""The registration sanity check (splattwin.poses.sanity) on synthetic tabletop captures, and the model it
leaves (colmap_worker's drop step) on the embedded scene's SfM model."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.capture.camera import Camera
from splattwin.poses.sanity import SanityOptions, check_registration


def _look_at(centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam (OpenCV: +z forward, +y down) of a camera at `centre` looking at `target`."""
    c, t = np.asarray(centre, float), np.asarray(target, float)
    z = (t - c) / np.linalg.norm(t - c)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = c
    return T


def _cam(T: np.ndarray, name: str) -> Camera:
    K = np.array([[460.0, 0, 341.5], [0, 460.0, 192.0], [0, 0, 1]])
    return Camera(K=K, width=683, height=384, T_world_cam=T, name=name)


def _capture(n: int = 8, seed: int = 0):
    """A walk around a table (z = 0 plane, 2 x 2 units) at height 3, radius 4, all looking at its centre;
    points: 600 on the table, 100 on an object above it. Returns (cameras, observations, points)."""
    rng = np.random.default_rng(seed)
    cams = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        cams[f"img{i}"] = _cam(_look_at([4 * np.cos(a), 4 * np.sin(a), 3.0 + 0.2 * rng.standard_normal()],
                                        [0.1 * rng.standard_normal(), 0.1 * rng.standard_normal(), 0.2]), f"img{i}")
    table = np.column_stack([rng.uniform(-1, 1, (600, 2)), 0.003 * rng.standard_normal(600)])
    obj = rng.uniform([-0.2, -0.2, 0.0], [0.2, 0.2, 0.5], (100, 3))
    obs = {k: 300 for k in cams}
    return cams, obs, np.vstack([table, obj])


def test_good_capture_keeps_every_camera():
    cams, obs, pts = _capture()
    chk = check_registration(cams, obs, pts)
    assert chk.tabletop and chk.dropped == {}
    for v in chk.per_image.values():
        assert 0.8 < v["height_rel"] < 1.2 and 30 < v["pitch_deg"] < 45 and v["off_axis_deg"] < 10


def test_camera_below_the_table_is_dropped():
    cams, obs, pts = _capture()
    # mirrored through the table plane: the classic wrong solution of a planar scene (height -3, looking up)
    M = np.diag([1.0, 1.0, -1.0])
    T = cams["img3"].T_world_cam.copy()
    T[:3, 3] = M @ T[:3, 3]
    T[:3, :3] = M @ T[:3, :3] @ np.diag([1.0, -1.0, 1.0])  # a proper rotation again (image y flipped)
    cams["img3"] = _cam(T, "img3")
    chk = check_registration(cams, obs, pts)
    assert set(chk.dropped) == {"img3"}
    assert "below the table plane" in chk.dropped["img3"] and "up" in chk.dropped["img3"]
    assert chk.per_image["img3"]["height_rel"] < 0


def test_camera_at_the_table_height_looking_up_is_dropped():
    """What guided matching made of two cake frames: centre on the table plane, looking 12 degrees up."""
    cams, obs, pts = _capture()
    c = cams["img5"].center
    target = np.array([0.0, 0.0, 0.0]) + np.array([0, 0, np.tan(np.radians(12)) * np.linalg.norm(c[:2])])
    cams["img5"] = _cam(_look_at([c[0], c[1], 0.0], target), "img5")
    chk = check_registration(cams, obs, pts)
    assert set(chk.dropped) == {"img5"} and "at or below the table plane" in chk.dropped["img5"]


def test_camera_looking_up_from_above_is_dropped():
    cams, obs, pts = _capture()
    c = cams["img2"].center
    cams["img2"] = _cam(_look_at(c, c + np.array([-c[0], -c[1], 2.0])), "img2")  # 27 deg above the horizon
    chk = check_registration(cams, obs, pts)
    assert set(chk.dropped) == {"img2"} and "above the horizon" in chk.dropped["img2"]


def test_flipped_camera_looking_away_is_dropped():
    cams, obs, pts = _capture()
    c = cams["img6"].center
    away = c + np.array([c[0], c[1], -c[2]])  # turned 180 degrees about the vertical: still looks down
    cams["img6"] = _cam(_look_at(c, away), "img6")
    chk = check_registration(cams, obs, pts)
    assert set(chk.dropped) == {"img6"} and "looks away" in chk.dropped["img6"]
    assert chk.per_image["img6"]["off_axis_deg"] > 90


def test_too_few_observations_is_dropped():
    cams, obs, pts = _capture()
    obs["img1"] = 7
    chk = check_registration(cams, obs, pts, SanityOptions(min_observations=12))
    assert set(chk.dropped) == {"img1"} and "only 7 points" in chk.dropped["img1"]
    assert check_registration(cams, obs, pts, SanityOptions(min_observations=5)).dropped == {}


def test_low_shot_is_kept_when_well_supported_and_dropped_when_weak():
    """A low camera looking almost level: trusted with many observations, not with a handful."""
    cams, obs, pts = _capture()
    c = cams["img4"].center
    cams["img4"] = _cam(_look_at([c[0], c[1], 0.7], [0, 0, 0.5]), "img4")
    assert check_registration(cams, obs, pts).dropped == {}
    obs["img4"] = 35  # above the plain minimum (30), below the weak-support bound (40)
    chk = check_registration(cams, obs, pts)
    assert set(chk.dropped) == {"img4"} and "weakly supported" in chk.dropped["img4"]


def test_no_table_plane_skips_the_geometric_checks():
    cams, obs, _ = _capture()
    rng = np.random.default_rng(1)
    blob = rng.standard_normal((700, 3))  # no dominant plane
    c = cams["img3"].center
    cams["img3"] = _cam(_look_at([c[0], c[1], -3.0], [0, 0, 0]), "img3")
    chk = check_registration(cams, obs, blob)
    assert not chk.tabletop and chk.skipped and chk.dropped == {}


def test_drop_step_removes_the_image_and_keeps_the_others(default_unscaled, sfm_default_dir, tmp_path):
    """colmap_worker's drop step on a real SfM model: the image is gone (with its observations), the
    others keep their poses (bundle adjustment moves them only slightly) and the points stay consistent."""
    import pycolmap

    from splattwin.poses.colmap_worker import step_drop

    base = sfm_default_dir / "sparse"
    rec0 = pycolmap.Reconstruction(str(base))
    names = sorted(rec0.image(i).name for i in rec0.reg_image_ids())
    gone = names[len(names) // 2]
    res = step_drop({"base": str(base), "out": str(tmp_path / "m"), "names": [gone]})
    rec = pycolmap.Reconstruction(str(tmp_path / "m"))
    left = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    assert res["registered"] == len(names) - 1 == len(left) and gone not in left
    for p in rec.points3D.values():  # no observation of the dropped image survives
        assert all(rec.image(el.image_id).name != gone for el in p.track.elements)
        assert p.track.length() >= 2
    c0 = {rec0.image(i).name: rec0.image(i).projection_center() for i in rec0.reg_image_ids()}
    spread = np.ptp(np.array(list(c0.values())), axis=0).max()
    for n, im in left.items():
        assert np.linalg.norm(im.projection_center() - c0[n]) < 0.02 * spread
    assert rec.compute_mean_reprojection_error() < 1.0


def test_few_observations_and_below_the_table_gives_both_reasons():
    """The cake's frame000069: 18 observations and posed on the table plane; the report names both, and
    the other cameras' medians ignore it."""
    cams, obs, pts = _capture()
    c = cams["img5"].center
    cams["img5"] = _cam(_look_at([c[0], c[1], -0.1], [0, 0, 1.0]), "img5")
    obs["img5"] = 18
    chk = check_registration(cams, obs, pts)
    why = chk.dropped["img5"]
    assert set(chk.dropped) == {"img5"} and "only 18 points" in why and "below the table plane" in why
    assert chk.per_image["img5"]["height_rel"] < 0 and chk.per_image["img5"]["pitch_deg"] < 0
