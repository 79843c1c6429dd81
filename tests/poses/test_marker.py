"""ArUco marker: corner refinement accuracy and the metric marker frame from SfM."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses.align import umeyama
from splattwin.poses.marker import detect_marker, refine_corners_edges


def _render_square(corners: np.ndarray, H: int = 80, W: int = 100, ss: int = 8) -> np.ndarray:
    """Black convex quad on white, area-sampled with ss x ss rays per pixel. corners [4,2] (pixel i spans [i,i+1))."""
    ys, xs = np.mgrid[0:H * ss, 0:W * ss]
    p = np.stack([(xs + 0.5) / ss, (ys + 0.5) / ss], -1)
    inside = np.ones((H * ss, W * ss), bool)
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        cross = (b[0] - a[0]) * (p[..., 1] - a[1]) - (b[1] - a[1]) * (p[..., 0] - a[0])
        inside &= cross > 0  # clockwise on screen (y down) = positive cross
    img = np.where(inside, 20.0, 230.0)
    return img.reshape(H, ss, W, ss).mean(axis=(1, 3))


def test_edge_refinement_recovers_subpixel_corners():
    truth = np.array([[30.3, 20.7], [62.1, 23.2], [60.4, 55.9], [28.8, 52.6]])  # TL, TR, BR, BL
    img = _render_square(truth)
    start = truth + np.random.default_rng(0).normal(0, 0.6, truth.shape)
    got = refine_corners_edges(img, start)
    assert np.abs(got - truth).max() < 0.1
    assert np.abs(got - truth).mean() < 0.05
    assert np.abs(start - truth).max() > 0.3  # the test starts from a visibly wrong guess


def test_detect_marker_none_and_bad_dictionary():
    assert detect_marker(np.full((60, 80, 3), 0.5, np.float32)) is None
    with pytest.raises(InputError, match="dictionary"):
        detect_marker(np.zeros((60, 80, 3), np.uint8), dictionary="DICT_NOPE")


def test_marker_scale_and_table_normal(marker_result):
    gt, scene, res = marker_result
    assert res.frame.source == "marker" and res.frame.scaled
    assert 0 < res.frame.scale_uncertainty_rel < 0.02
    g = {f.image_path.name: f.camera for f in gt.frames}
    T_world_marker = np.array(scene["marker"]["T_world_marker"])
    src = np.array([f.camera.center for f in res.frames])
    tgt = np.array([g[f.image_path.name].center for f in res.frames])
    fit = umeyama(src, tgt)
    assert abs(fit.scale - 1.0) < 0.01                       # metric scale within 1 %
    R = fit.S[:3, :3] / fit.scale
    n_gt_world = R @ np.array([0.0, 0.0, 1.0])               # our z axis seen in the world frame
    assert np.degrees(np.arccos(np.clip(n_gt_world @ T_world_marker[:3, 2], -1, 1))) < 1.0
    # our frame is the marker frame: centres agree with GT expressed in the marker frame
    Tmw = np.linalg.inv(T_world_marker)
    tgt_marker = tgt @ Tmw[:3, :3].T + Tmw[:3, 3]
    assert np.linalg.norm(src - tgt_marker, axis=1).max() < 0.02


def test_marker_seen_in_too_few_views_is_an_input_error():
    from splattwin.capture import Camera
    from splattwin.poses.marker import fit_marker

    cams = [Camera.from_fov(1.0, 80, 60, name=f"c{i}") for i in range(3)]
    imgs = [np.full((60, 80, 3), 0.5, np.float32)] * 3
    with pytest.raises(InputError, match="need >= 2"):
        fit_marker(cams, imgs, 0.08)
