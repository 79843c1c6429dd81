import numpy as np

from splattwin.geometry.filtering import attribute_mask
from splattwin.geometry.options import GeometryOptions, scene_scale


def test_attribute_mask_known_answer():
    op = np.array([0.05, 0.5, 0.9, 0.9, 0.9, 0.09999, 0.1])
    sc = np.array([[1, 1, 0.1], [1, 1, 0.1], [100, 1, 1], [1, 2, 20], [1, 1, 1], [1, 1, 1], [1, 2, 3]]) * 1e-3
    opts = GeometryOptions(max_scale=0.05, max_aspect=8.0)
    keep, st = attribute_mask(op, sc, opts)
    # 0: low opacity; 2: needle (100 vs 1); 3: 20/2 = 10 > 8 needle; 5: just below 0.1
    assert keep.tolist() == [False, True, False, False, True, False, True]
    assert (st.low_opacity, st.needle, st.kept) == (2, 2, 3)


def test_flat_discs_survive_but_oversized_do_not():
    op = np.ones(3)
    sc = np.array([[0.004, 0.004, 1e-6], [0.06, 0.06, 0.001], [0.004, 0.004, 0.004]])
    keep, st = attribute_mask(op, sc, GeometryOptions(max_scale=0.05))
    assert keep.tolist() == [True, False, True] and st.oversized == 1
    keep, _ = attribute_mask(op, sc, GeometryOptions(max_scale=0.05, max_flatness=100.0))
    assert keep.tolist() == [False, False, True]


def test_auto_thresholds_scale_with_scene():
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (1000, 3))
    s1 = scene_scale(pts)
    s2 = scene_scale(pts * 3)
    assert np.isclose(s2, 3 * s1)
    o1, o2 = GeometryOptions().resolved(s1), GeometryOptions().resolved(s2)
    assert np.isclose(o2.max_scale, 3 * o1.max_scale)
    assert GeometryOptions(max_scale=0.01).resolved(s1).max_scale == 0.01


def test_short_elongated_edge_splats_are_kept_long_needles_dropped():
    # trained splats line edges with short elongated Gaussians (largest / middle 6-10, a few mm long):
    # they are surface, not the long spikes the needle test is for
    op = np.full(4, 0.9)
    sc = np.array([[0.004, 0.0005, 0.0003], [0.0059, 0.0006, 0.0003], [0.0061, 0.0006, 0.0003],
                   [0.02, 0.001, 0.001]])
    keep, st = attribute_mask(op, sc, GeometryOptions(max_scale=0.05))
    assert keep.tolist() == [True, True, False, False] and st.needle == 2
    keep, _ = attribute_mask(op, sc, GeometryOptions(max_scale=0.05, needle_length=0.0))  # aspect alone
    assert keep.tolist() == [False, False, False, False]
