"""SfM on a real capture: the cake photos (8 video frames at 683x384 walking around a slice of cake on
grass, weak texture, wide baselines). Default settings register only 2 of them; the retries register 6
consistently (every camera above the table, looking down at the cake). Two more, frame000069 and
frame000096, get registered by the guided / more-features retries from ~18 observations (matches with the
rest are mostly grass: a PnP on the 6 good cameras' points finds 5-7 inliers of 58 correspondences for
frame000069 and 4 correspondences for frame000096), at the table's height looking up: the registration
sanity check must drop them, with the reason, and not count them. The photos are read in place (CC BY-NC)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REAL = Path(os.environ.get("SPLATTWIN_REAL_DATA", Path(__file__).resolve().parents[3] / "shared" / "data" / "real"))
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real")
CAKE = REAL / "cake" / "images"


@pytest.mark.slow
@pytest.mark.skipif(not CAKE.is_dir(), reason=f"real captures not available at {CAKE}")
def test_cake_registers_consistently_and_drops_the_wrong_poses(tmp_path: Path):
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.splat.init import look_at_point

    ds = load_dataset(CAKE)
    assert len(ds.frames) == 8
    res = estimate_poses(ds, PoseOptions(work_dir=tmp_path / "w", progress=False))
    st = res.stats
    bad = {"frame000069.jpg", "frame000096.jpg"}
    assert st["registered"] == 6 and {Path(u).name for u in res.unregistered} == bad
    assert set(st["failures"]) == bad and set(st["registration_check"]["dropped"]) <= bad
    for why in st["failures"].values():
        assert "dropped by the registration sanity check" in why and "observes only" in why
    assert any("table plane" in why or "inconsistent with the other cameras" in why for why in st["failures"].values())
    # the six kept cameras: one height band above the table plane, all looking down at it
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
    # the report names the retries; the CLI-facing failures dict is empty
    out = res.save(tmp_path / "out")
    import json

    rep = json.loads((out.parent / "poses_report.json").read_text())
    assert rep["registered"] == 6 and len(rep["attempts"]) >= 2
    assert {Path(u).name for u in rep["unregistered"]} == bad and set(rep["failures"]) == bad
