from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from splattwin.splat.gaussians import SH_C0, Gaussians


def _g(n=10, deg=1, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return Gaussians(rng.normal(size=(n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                     rng.uniform(0.01, 0.1, (n, 3)), rng.uniform(0.1, 0.9, n), rng.normal(size=(n, (deg + 1) ** 2, 3)))


def test_colors_subset_len_degree():
    g = _g()
    g.sh[:, 0] = (np.array([0.2, 0.5, 0.9]) - 0.5) / SH_C0
    np.testing.assert_allclose(g.colors, np.tile([0.2, 0.5, 0.9], (10, 1)), atol=1e-12)
    mask = np.zeros(10, bool)
    mask[[1, 4, 7]] = True
    s = g.subset(mask)
    assert len(s) == 3 and s.sh_degree == 1
    np.testing.assert_array_equal(s.means, g.means[[1, 4, 7]])
    np.testing.assert_array_equal(g.subset(np.array([7, 1])).opacities, g.opacities[[7, 1]])
    with pytest.raises(ValueError):
        g.subset(np.ones(3, bool))
    assert g.with_sh_degree(3).sh.shape == (10, 16, 3) and g.with_sh_degree(0).sh_degree == 0
    with pytest.raises(ValueError):
        Gaussians(g.means, g.quats, g.scales, g.opacities, np.zeros((10, 5, 3)))


def test_rotations_and_covariances_match_scipy():
    g = _g()
    R_ref = Rotation.from_quat(g.quats[:, [1, 2, 3, 0]]).as_matrix()  # scipy is xyzw
    np.testing.assert_allclose(g.rotation_matrices(), R_ref, atol=1e-12)
    cov = g.covariances()
    np.testing.assert_allclose(cov[0], R_ref[0] @ np.diag(g.scales[0] ** 2) @ R_ref[0].T, atol=1e-14)
