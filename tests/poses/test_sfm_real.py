"""SfM on a real capture: the cake photos (8 video frames at 683x384 walking around a slice of cake on
grass, weak texture, wide baselines). Default settings register only 2 of them; the retries register 6
consistently (every camera above the table, looking down at the cake). Two more, frame000069 and
frame000096, get registered by the guided / more-features retries from ~18 observations (matches with the
rest are mostly grass: a PnP on the 6 good cameras' points finds 5-7 inliers of 58 correspondences for
frame000069 and 4 correspondences for frame000096), at the table's height looking up: the registration
sanity check must drop them, with the reason. The recover step then re-registers them against the six
trusted cameras (frame000096 by the table-plane homography with frame000112, frame000069 by structure-less
resectioning with the points 096 brought), and they must land where a walk around the cake puts them:
between their neighbouring frames, above the table, looking at the cake. The photos are read in place
(CC BY-NC)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.mark.slow
def test_cake_drops_the_wrong_poses_and_re_registers_them_on_the_walk(cake_images: Path, cake_sfm, tmp_path: Path):
    from splattwin.capture import load_dataset
    from splattwin.splat.init import look_at_point

    assert len(load_dataset(cake_images).frames) == 8
    # estimate_poses(load_dataset(cake_images), PoseOptions(work_dir=..., progress=False)), once per session
    # (conftest.py: tests/pipeline/test_unscaled_real.py uses the same run)
    _, res, _ = cake_sfm
    st = res.stats
    bad = {"frame000069.jpg", "frame000096.jpg"}
    assert st["registered"] == 8 and not res.unregistered and not st["failures"]
    # dropped by the check in the retries, then re-registered by the recover step
    dropped_somewhere = {n for a in st["attempts"] for n in a.get("dropped", [])}
    assert bad <= dropped_somewhere
    rec = st["attempts"][-1]
    assert rec["name"] == "recover" and set(rec["recovered"]) == bad and rec["rejected"] == {}
    assert set(st["registration_check"]["recovered"]) == bad and st["registration_check"]["dropped"] == {}
    for how in rec["recovered"].values():
        assert how["observations"] >= 30
    # all eight cameras: one height band above the table plane, all looking down at it
    for c in res.cameras:
        d = c.T_world_cam[:3, 2]
        assert np.degrees(np.arcsin(-d[2])) > 25
    h = np.array([c.center[2] for c in res.cameras])
    assert h.min() > 0.8 * np.median(h) and h.max() < 1.25 * np.median(h)
    assert [a["name"] for a in st["attempts"]][0] == "default" and len(st["attempts"]) >= 2  # it took retries
    assert st["mean_reproj_error"] < 1.5 and st["num_points"] > 300
    # a walk around the cake: every optical axis passes close to one common point
    cams = res.cameras
    target = look_at_point(cams)
    assert target is not None
    for c in cams:
        ray = target - c.center
        cos = ray @ c.T_world_cam[:3, 2] / np.linalg.norm(ray)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 12.0
    # the walk: azimuths about the look-at point advance with the frame number, 1-4 deg per frame
    order = sorted(cams, key=lambda c: int(Path(c.name).stem.replace("frame", "")))
    az = np.unwrap([np.arctan2(*(c.center - target)[[1, 0]]) for c in order])
    steps = np.degrees(np.diff(az)) * np.sign(az[-1] - az[0])
    frames = np.diff([int(Path(c.name).stem.replace("frame", "")) for c in order])
    assert np.all(steps / frames > 1.0) and np.all(steps / frames < 4.0), (steps, frames)
    # the report names the retries; the CLI-facing failures dict is empty
    out = res.save(tmp_path / "out")
    import json

    rep = json.loads((out.parent / "poses_report.json").read_text())
    assert rep["registered"] == 8 and len(rep["attempts"]) >= 2
    assert not rep["unregistered"] and not rep["failures"]
