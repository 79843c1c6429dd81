from __future__ import annotations

import math

import numpy as np
import pytest

from splattwin.scene.cameras import heldout_indices, scan_cameras


@pytest.mark.parametrize("views,heldout", [(15, 5), (8, 3), (2, 1), (2, 5), (30, 2), (10, 0), (5, 5)])
def test_heldout_positions_are_interleaved(views, heldout):
    idx = heldout_indices(views, heldout)
    n = views + heldout
    assert len(idx) == heldout
    assert all(b > a for a, b in zip(idx, idx[1:]))
    assert all(1 <= i <= n - 2 for i in idx)  # first and last arc positions are training views
    if heldout > 1 and views > heldout:
        # evenly spread: no two held-out views adjacent, gaps within one of the average spacing
        gaps = np.diff(idx)
        assert gaps.min() >= 2 and gaps.max() - gaps.min() <= 2


def test_scan_cameras_look_at_the_target_from_the_arc():
    target = np.array([0.02, -0.03, 0.03])
    cams = scan_cameras(15, 5, 320, 240, math.radians(70), target, seed=0)
    assert [c.name for c in cams].count("train_000") == 1 and sum(c.name.startswith("heldout") for c in cams) == 5
    az = []
    for c in cams:
        # the optical axis passes within a few cm of the target (jittered look-at)
        to_t = target - c.center
        along = c.T_world_cam[:3, 2] @ to_t
        miss = np.linalg.norm(to_t - along * c.T_world_cam[:3, 2])
        assert along > 0 and miss < 0.06
        assert 0.45 <= np.linalg.norm(c.center) <= 0.8
        el = math.degrees(math.asin(c.center[2] / np.linalg.norm(c.center)))
        assert 30 <= el <= 70
        az.append(math.atan2(c.center[1], c.center[0]) % (2 * math.pi))
    # scan order follows the arc (monotone azimuth) around the robot side (-x), spanning > 180 degrees
    assert np.all(np.diff(az) > 0) and math.degrees(az[-1] - az[0]) > 180
    assert min(az) > math.radians(40) and max(az) < math.radians(320)
