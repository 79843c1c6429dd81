from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from splattwin.robot.trials import TrialSpec, YAW_LEVER, perturb_poses, run_trials, wilson_interval


def test_wilson_interval_reference_values():
    # reference values of the Wilson score interval (z = 1.96)
    lo, hi = wilson_interval(20, 20)
    assert lo == pytest.approx(0.8389, abs=1e-3) and hi == 1.0
    lo, hi = wilson_interval(9, 10)
    assert lo == pytest.approx(0.5958, abs=1e-3) and hi == pytest.approx(0.9821, abs=1e-3)
    lo, hi = wilson_interval(0, 5)
    assert lo == 0.0 and hi == pytest.approx(0.4345, abs=1e-3)


def test_perturbation_statistics():
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.025]
    rng = np.random.default_rng(0)
    sigma = 0.005
    samples = [perturb_poses({"o": T}, sigma, rng)["o"] for _ in range(4000)]
    dxy = np.array([s[:2, 3] - T[:2, 3] for s in samples])
    yaw = np.array([math.atan2(s[1, 0], s[0, 0]) for s in samples])
    assert math.sqrt(np.mean(np.sum(dxy ** 2, axis=1))) == pytest.approx(sigma, rel=0.05)   # RMS planar error
    assert np.std(yaw) == pytest.approx(sigma / YAW_LEVER, rel=0.05)
    assert all(s[2, 3] == T[2, 3] and abs(s[2, 2] - 1) < 1e-12 for s in samples)               # still on the table


def test_two_perturbed_trials_in_process_pool(gt_twin_default: Path):
    summary = run_trials(TrialSpec(str(gt_twin_default), None), n=2, sigma=0.005, workers=2, progress=False)
    assert summary["trials"] == 2 and summary["workers"] == 2
    assert summary["successes"] == 2, [r.get("error") or [s["failure"] for s in r["steps"]] for r in summary["results"]]
    assert summary["collisions"] == 0
    assert summary["ci95"][0] == pytest.approx(wilson_interval(2, 2)[0])
    assert {r["seed"] for r in summary["results"]} == {1, 2}
