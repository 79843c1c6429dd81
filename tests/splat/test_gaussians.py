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


@pytest.mark.parametrize("field,value,match", [
    ("means", np.zeros(12), r"means must be \[N,3\], got shape \(12,\)"),
    ("quats", np.zeros((2, 8)), r"quats must be \[4,4\] with N=4 .*got shape \(2, 8\)"),
    ("scales", np.full(12, 0.01), r"scales must be \[4,3\] with N=4 .*got shape \(12,\)"),
    ("opacities", np.full((2, 2), 0.5), r"opacities must be \[4\] with N=4 .*got shape \(2, 2\)"),
    ("opacities", np.full((4, 1), 0.5), r"opacities must be \[4\] with N=4 .*got shape \(4, 1\)"),
    ("sh", np.zeros((4, 3, 4)), r"sh must be \[N,K,3\].*got shape \(4, 3, 4\)"),
])
def test_wrong_shapes_are_refused_not_reshaped(field, value, match):
    ok = dict(means=np.zeros((4, 3)), quats=np.tile([1.0, 0, 0, 0], (4, 1)), scales=np.full((4, 3), 0.01),
              opacities=np.full(4, 0.5), sh=np.zeros((4, 1, 3)))
    Gaussians(**ok)
    with pytest.raises(ValueError, match=match):
        Gaussians(**{**ok, field: value})


@pytest.mark.parametrize("field,value,match", [
    ("scales", [[-1.0, 0.01, 0.01]], "1 Gaussians have negative scales"),
    ("opacities", [3.0], r"opacities outside \[0, 1\]"),
    ("quats", [[0.0, 0, 0, 0]], "zero quaternion"),
    ("means", [[np.nan, 0, 0]], "non-finite means"),
    ("sh", [[[np.inf, 0, 0]]], "non-finite sh"),
])
def test_invalid_values_are_refused_on_construction(field, value, match):
    from splattwin.errors import InputError

    ok = dict(means=[[0.0, 0, 1]], quats=[[1.0, 0, 0, 0]], scales=[[0.01] * 3], opacities=[0.5],
              sh=np.zeros((1, 1, 3)))
    with pytest.raises(InputError, match=match):
        Gaussians(**{**ok, field: value})


def test_save_ply_never_writes_a_file_load_ply_refuses(tmp_path):
    from splattwin.errors import InputError

    g = _g(3)
    for edit, match in ((lambda g: g.scales.__setitem__((1, 0), -1.0), "negative scales"),
                        (lambda g: g.opacities.__setitem__(2, 3.0), r"opacities outside \[0, 1\]"),
                        (lambda g: g.quats.__setitem__(0, 0.0), "zero quaternion"),
                        (lambda g: g.means.__setitem__((0, 0), 1e39), "beyond float32's range")):
        bad = _g(3)
        edit(bad)  # the arrays are mutable: save_ply checks again
        p = tmp_path / "bad.ply"
        with pytest.raises(InputError, match=match):
            bad.save_ply(p)
        assert not p.exists()
    # valid extremes still round-trip
    e = Gaussians(np.zeros((2, 3)), [[1.0, 0, 0, 0]] * 2, [[0.0, 0.01, 0.01]] * 2, [0.0, 1.0], np.zeros((2, 1, 3)))
    e2 = Gaussians.load_ply(e.save_ply(tmp_path / "e.ply"))
    assert len(e2) == 2 and e2.scales[0, 0] == 0.0
    assert len(Gaussians.load_ply(g.save_ply(tmp_path / "g.ply"))) == 3
    assert len(Gaussians.load_ply(Gaussians.empty(2).save_ply(tmp_path / "empty.ply"))) == 0


def test_equality_is_by_value_and_a_ply_round_trip_compares_equal(tmp_path):
    """`==` on Gaussians raised ValueError (numpy arrays in the generated dataclass __eq__); audit 10A L1."""
    g = _g(20, deg=2)
    assert g == _g(20, deg=2) and g != _g(20, deg=2, seed=1) and g != _g(19, deg=2)
    once = Gaussians.load_ply(g.save_ply(tmp_path / "a.ply"))   # float32 storage: not bit-equal to g
    twice = Gaussians.load_ply(once.save_ply(tmp_path / "b.ply"))
    assert twice == once and once in [g, twice]
    assert once != g   # exact comparison: the float64 originals were rounded to float32
