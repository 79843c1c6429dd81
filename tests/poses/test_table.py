"""Table plane + known length; known-length parsing; plane RANSAC on synthetic points."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses import KnownLength, PoseOptions, estimate_poses
from splattwin.poses.align import umeyama
from splattwin.poses.table import fit_table_plane


def test_plane_ransac_finds_table_under_clutter():
    rng = np.random.default_rng(0)
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1, 0, 0]); u /= np.linalg.norm(u)
    v = np.cross(n, u)
    table = rng.uniform(-1, 1, (400, 2)) @ np.stack([u, v]) + 0.3 * n + rng.normal(0, 0.002, (400, 1)) * n
    clutter = rng.uniform(-1, 1, (150, 3)) + [0, 0, 0.5]
    pts = np.vstack([table, clutter])
    fit = fit_table_plane(pts, camera_centres=np.array([[0, 0, 3.0]]))
    assert np.degrees(np.arccos(fit.normal @ n)) < 0.5
    assert abs(fit.d + 0.3) < 0.005
    assert fit.inliers[:400].mean() > 0.97 and fit.inliers[400:].mean() < 0.2
    flipped = fit_table_plane(pts, camera_centres=np.array([[0, 0, -3.0]]))
    assert flipped.normal @ n < 0  # normal always points towards the cameras


@pytest.mark.parametrize("text,ok", [("camera_height=0.6", True), ("camera_height@train_003=0.5", True),
                                     ("baseline@a,b=0.2", True), ("baseline@a=0.2", False), ("height=1", False),
                                     ("camera_height=-1", False), ("camera_height", False),
                                     ("camera_height=1e-300", False), ("baseline@a,b=1e308", False)])
def test_known_length_parse(text: str, ok: bool):
    if ok:
        kl = KnownLength.parse(text)
        assert kl.value > 0
    else:
        with pytest.raises(InputError):
            KnownLength.parse(text)


def _check_metric_table_frame(gt, res):
    g = {f.image_path.name: f.camera for f in gt.frames}
    src = np.array([f.camera.center for f in res.frames])
    tgt = np.array([g[f.image_path.name].center for f in res.frames])
    fit = umeyama(src, tgt)
    assert abs(fit.scale - 1.0) < 0.01
    R = fit.S[:3, :3] / fit.scale
    assert np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))) < 1.0      # our z = world z (table normal)
    # table top at z = 0 in both frames: GT camera heights equal ours
    np.testing.assert_allclose(src[:, 2], tgt[:, 2], atol=0.01)


def test_table_plane_with_camera_height(default_unscaled, sfm_default_dir, caplog):
    import logging

    from tests.poses.conftest import stripped

    gt, _ = default_unscaled
    h = float(np.mean([f.camera.center[2] for f in gt.frames]))
    with caplog.at_level(logging.INFO, logger="splattwin.poses.estimate"):
        res = estimate_poses(stripped(gt, depth=True), PoseOptions(method="sfm", work_dir=sfm_default_dir,
                                                                   progress=False,
                                                                   known_length=KnownLength("camera_height", h)))
    assert res.frame.source == "table_plane+known_length" and res.frame.scaled
    assert "metric scale from" in caplog.text   # the log says which scale was applied, not only frame.json
    assert 0 < res.frame.scale_uncertainty_rel < 0.01
    _check_metric_table_frame(gt, res)
    assert res.depth_xyz is not None
    assert np.median(np.abs(res.depth_xyz[:, 2])) < 0.01  # depth cloud: mostly the table top, at z = 0


def test_table_plane_with_baseline(default_unscaled, sfm_default_dir):
    from tests.poses.conftest import stripped

    gt, _ = default_unscaled
    g = {f.camera.name: f.camera for f in gt.frames}
    d = float(np.linalg.norm(g["train_000"].center - g["train_007"].center))
    res = estimate_poses(stripped(gt), PoseOptions(method="sfm", work_dir=sfm_default_dir, progress=False,
                                                   known_length=KnownLength("baseline", d, ("train_000", "train_007.png"))))
    _check_metric_table_frame(gt, res)
    with pytest.raises(InputError, match="nope"):
        estimate_poses(stripped(gt), PoseOptions(method="sfm", work_dir=sfm_default_dir, progress=False,
                                                 known_length=KnownLength("baseline", d, ("train_000", "nope"))))
