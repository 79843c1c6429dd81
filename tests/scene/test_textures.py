from __future__ import annotations

import numpy as np

from splattwin.scene import textures as tx


def test_value_noise_kernel_matches_numpy_reference():
    p = np.random.default_rng(0).uniform(-2, 2, (5000, 3))
    for freq, seed in [(3.0, 0), (np.array([5.0, 40.0, 17.0]), 7), (450.0, 123)]:
        a = tx.value_noise(p, freq, seed)
        b = tx.value_noise_reference(p, freq, seed)
        np.testing.assert_allclose(a, b, atol=1e-6)
        assert a.dtype == np.float32 and 0.0 <= a.min() and a.max() <= 1.0


def test_value_noise_is_smooth_and_seeded():
    p = np.random.default_rng(1).uniform(0, 1, (2000, 3))
    a = tx.value_noise(p, 10.0, 1)
    # continuity: a 1e-5 m step changes the value by far less than the lattice scale would allow
    b = tx.value_noise(p + 1e-5, 10.0, 1)
    assert np.abs(a - b).max() < 1e-3
    # the seed matters, and values cover the range (not constant)
    c = tx.value_noise(p, 10.0, 2)
    assert np.abs(a - c).mean() > 0.1
    assert a.std() > 0.1
    # at lattice points value noise equals the lattice hash exactly
    grid = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]])
    h = tx._hash(grid[:, 0].astype(np.int64), grid[:, 1].astype(np.int64), grid[:, 2].astype(np.int64), 9)
    np.testing.assert_allclose(tx.value_noise(grid, 1.0, 9), h, atol=1e-7)


def test_materials_are_distinct_and_textured():
    rng = np.random.default_rng(2)
    p = rng.uniform(-0.04, 0.04, (4000, 3))
    axes = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]])
    n = axes[rng.integers(0, 5, 4000)]
    mats = {
        "table": tx.table_albedo(0, np.array([0.3, 0.3, 0.0]), 0.2),
        "card": tx.cardboard_albedo(0, np.array([0.2, 0.15, 0.1])),
        "blue": tx.blue_box_albedo(0),
        "yellow": tx.yellow_cube_albedo(0),
        "hammer": tx.hammer_albedo(0, 0.05),
        "bottle": tx.bottle_albedo(0, 0.035, 0.16),
    }
    means = {}
    for name, f in mats.items():
        rgb = f(p, n)
        assert rgb.shape == (4000, 3) and rgb.min() >= 0 and rgb.max() <= 1
        assert rgb.std(axis=0).max() > 0.05, name  # textured, not flat
        means[name] = rgb.mean(axis=0)
    names = list(means)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert np.abs(means[names[i]] - means[names[j]]).max() > 0.03, (names[i], names[j])
