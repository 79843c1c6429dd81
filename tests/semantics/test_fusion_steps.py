"""Each step of the visibility-aware semantic fusion (paper sec. 3.2) on cases small enough to work out by
hand: a few Gaussians, one or two 4x4 cameras, masks of a few pixels. Expected values are written out,
not recomputed by the code under test.

Camera used throughout: pinhole fx = fy = 10 px, principal point (2, 2), 4x4 pixels, at the world origin
looking down +z (OpenCV), so a point (x, y, z) lands on pixel column floor(10 x / z + 2), row
floor(10 y / z + 2), flat index row * 4 + column.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from splattwin.capture.camera import Camera
# project_to_pixels as the fusion uses it (it lives with the depth renderers)
from splattwin.semantics.fusion import (FusionOptions, View, consensus, dbscan_1d, find_floaters, fuse, grazing,
                                        knn_smooth, project_to_pixels, smooth_labels, soft_gate, view_observations,
                                        visible_mask)
from splattwin.semantics.masks import MaskSet

W = H = 4
K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 2.0], [0.0, 0.0, 1.0]])


def cam(name: str = "v0", T_world_cam: np.ndarray | None = None) -> Camera:
    return Camera(K=K.copy(), width=W, height=H, T_world_cam=np.eye(4) if T_world_cam is None else T_world_cam,
                  name=name)


def flat_mask(pixels: list[int]) -> np.ndarray:
    m = np.zeros(W * H, dtype=bool)
    m[pixels] = True
    return m


# -- 1. visibility: projection + depth test ----------------------------------------------------------

def test_projection_and_depth_test_by_hand():
    pts = np.array([[0.0, 0.0, 1.0],      # column 2, row 2 -> pixel 10, on the rendered surface
                    [0.1, -0.1, 1.0],     # column 3, row 1 -> pixel 7, 3 cm in front of its surface
                    [0.3, 0.0, 1.0],      # column 5: outside
                    [0.0, 0.0, -1.0],     # behind the camera
                    [0.0, 0.0, 2.0],      # pixel 10 again, 1 m behind the surface there: occluded
                    [-0.15, -0.15, 1.0],  # column 0.5, row 0.5 -> pixel 0, where nothing was rendered
                    [0.05, 0.05, 1.0]])   # column 2.5, row 2.5 -> pixel 10, same depth as point 0
    pix, z = project_to_pixels(pts, cam())
    assert pix.tolist() == [10, 7, -1, -1, 10, 0, 10]
    assert z.tolist() == [1.0, 1.0, 1.0, -1.0, 2.0, 1.0, 1.0]
    depth = np.full((H, W), np.inf, np.float32)
    depth[2, 2] = 1.0
    depth[1, 3] = 1.03
    # |z - D| <= 0.02 + 0.01 D: pixel 7 allows 0.0303 >= 0.03 (visible), pixel 10 allows 0.03 < 1.0
    assert visible_mask(pix, z, depth, 0.02, 0.01).tolist() == [True, True, False, False, False, False, True]
    # a tighter tolerance (2 cm flat) rejects the point 3 cm in front
    assert visible_mask(pix, z, depth, 0.02, 0.0).tolist() == [True, False, False, False, False, False, True]


def test_grazing_splats_do_not_count():
    means = np.array([[0.0, 0.0, 1.0]] * 4)
    normals = np.array([[0.0, 0.0, 1.0],                              # facing the camera: |cos| = 1
                        [1.0, 0.0, 0.0],                              # edge-on: cos = 0
                        [math.sin(1.4), 0.0, math.cos(1.4)],          # |cos| = cos(1.4) = 0.170 < 0.25
                        [np.nan, np.nan, np.nan]])                    # not flat: never grazing
    assert grazing(means, normals, np.zeros(3), 0.25).tolist() == [False, True, True, False]


# -- 2. depth DBSCAN gate inside a mask (eps 0.02 m, min_samples 10) -----------------------------------

def test_dbscan_1d_by_hand():
    z = np.array([0.50, 0.501, 0.502, 0.503, 0.504, 0.505, 0.506, 0.507, 0.508, 0.509,   # 10: core points
                  0.52,                                                                 # 1.1 cm on: joins
                  0.80, 0.801, 0.802,                                                   # 3 alone: noise
                  0.47])                                                                # 3 cm in front: noise
    assert dbscan_1d(z, 0.02, 10).tolist() == [0] * 11 + [-1, -1, -1, -1]
    # two clusters, numbered from the nearest
    two = np.concatenate([np.full(10, 0.3), np.full(12, 0.6)])
    assert dbscan_1d(two, 0.02, 10).tolist() == [0] * 10 + [1] * 12
    # min_samples counts the point itself (scikit-learn's convention): 9 points are not a cluster
    assert dbscan_1d(np.full(9, 0.5), 0.02, 10).tolist() == [-1] * 9
    assert dbscan_1d(np.full(10, 0.5), 0.02, 10).tolist() == [0] * 10


def test_soft_gate_weights_by_hand():
    obj = [0.500 + 0.001 * i for i in range(12)]          # the object: one cluster 0.500 .. 0.511
    z = np.array(obj + [0.55, 0.57, 0.47])                # table behind (bleeding), a ghost in front
    w, front = soft_gate(z, eps=0.02, min_samples=10)
    # distance to the main cluster's depth interval [0.500, 0.511]: 0.039, 0.059, 0.030 m
    expect = [1.0] * 12 + [math.exp(-(0.039 / 0.02) ** 2), math.exp(-(0.059 / 0.02) ** 2), math.exp(-(0.030 / 0.02) ** 2)]
    np.testing.assert_allclose(w, expect, rtol=1e-9, atol=0)
    assert w[12] == pytest.approx(0.02231, abs=1e-5) and w[14] == pytest.approx(0.10540, abs=1e-5)
    assert front.tolist() == [False] * 14 + [True]        # only the nearer, gated-out point is "in front"
    # the largest cluster is the object even when a smaller one is nearer the camera
    z2 = np.concatenate([np.full(10, 0.40), np.full(12, 0.60)])
    w2, front2 = soft_gate(z2)
    np.testing.assert_allclose(w2, [math.exp(-(0.2 / 0.02) ** 2)] * 10 + [1.0] * 12, rtol=1e-9)
    assert front2.tolist() == [True] * 10 + [False] * 12
    # gate_sigma widens the soft gate without changing the clustering
    w3, _ = soft_gate(z, sigma=0.04)
    assert w3[12] == pytest.approx(math.exp(-(0.039 / 0.04) ** 2), rel=1e-9)
    # fewer than min_samples in the mask: nothing can be checked, every weight stays 1
    w4, f4 = soft_gate(np.array([0.5, 0.6, 0.7]))
    assert w4.tolist() == [1.0, 1.0, 1.0] and f4.tolist() == [False, False, False]


# -- 3a. observation weights of one view ----------------------------------------------------------------

def test_view_observations_by_hand():
    # 11 object Gaussians at 1.000 .. 1.010 m, 2 table Gaussians at 1.100 m inside the (bleeding) mask of
    # object column 0, one occluded Gaussian inside it, one visible outside it; a second mask (column 1)
    # covers the two table Gaussians only.
    z = np.array([1.000 + 0.001 * i for i in range(11)] + [1.100, 1.100, 1.005, 1.0])
    pix = np.array([0] * 11 + [1, 2, 0, 9])
    vis = np.array([True] * 13 + [False, True])
    view_masks = [(0, flat_mask([0, 1, 2])), (1, flat_mask([1, 2, 3]))]
    obs = view_observations(pix, z, vis, view_masks, FusionOptions())
    assert [o[0] for o in obs] == [0, 1]
    k, idx, w, front = obs[0]
    assert idx.tolist() == list(range(13))                # not the occluded 13, not the outside 14
    gate = math.exp(-((1.100 - 1.010) / 0.02) ** 2)       # 4.5 cm behind the object: ~1.6e-9
    np.testing.assert_allclose(w, [1.0] * 11 + [gate, gate], rtol=1e-9, atol=0)
    assert not front.any()                                # behind, not in front
    k, idx, w, front = obs[1]
    assert idx.tolist() == [11, 12] and w.tolist() == [1.0, 1.0]   # 2 points: no cluster, not gated
    # a mask with no visible Gaussian gives no observation
    assert view_observations(pix, z, vis, [(0, flat_mask([15]))], FusionOptions()) == []


# -- 3b. consensus tau = N / kappa (kappa 1.5) ------------------------------------------------------------

def test_consensus_threshold_by_hand():
    votes = np.array([[2.0, 0.0],     # N 3: tau = 2 -> exactly enough
                      [1.99, 0.0],    # N 3: just short
                      [2.5, 2.9],     # N 3: both pass, the larger vote wins
                      [0.0, 0.0],     # N 0: never visible
                      [0.67, 0.0],    # N 1: tau = 0.667
                      [0.66, 0.0],    # N 1: short of 0.667
                      [4.0, 0.0]])    # N 6: tau = 4
    n_vis = np.array([3, 3, 3, 0, 1, 1, 6])
    labels, conf = consensus(votes, n_vis, 1.5, [3, 7])
    assert labels.tolist() == [3, 0, 7, 0, 3, 0, 3]
    np.testing.assert_allclose(conf, [2 / 3, 1 - 1.99 / 3, 2.9 / 3, 0.0, 0.67, 1 - 0.66, 4 / 6], rtol=1e-12)
    # kappa 1: every visible view must vote; min_views 2 drops Gaussians seen once
    assert consensus(votes, n_vis, 1.0, [3, 7])[0].tolist() == [0, 0, 0, 0, 0, 0, 0]
    assert consensus(votes, n_vis, 1.5, [3, 7], min_views=2)[0].tolist() == [3, 0, 7, 0, 0, 0, 3]


# -- 4. refinement rounds: floaters found, depth re-rendered without them -----------------------------------

class ZBuffer:
    """Depth renderer for the fusion: min z of the kept points per pixel, no hole filling; records calls."""

    def __init__(self, means: np.ndarray):
        self.means = means
        self.calls: list[tuple[list[int] | None, list[str]]] = []

    def __call__(self, keep, cameras):
        self.calls.append((None if keep is None else np.flatnonzero(~keep).tolist(), [c.name for c in cameras]))
        out = []
        for c in cameras:
            pix, z = project_to_pixels(self.means, c)
            ok = (pix >= 0) & (True if keep is None else keep)
            d = np.full(c.width * c.height, np.inf, np.float32)
            np.minimum.at(d, pix[ok], z[ok])
            out.append(d.reshape(c.height, c.width))
        return out


def _floater_scene():
    """12 object Gaussians at z = 1 m on pixels 0-11 (one each), Gaussian 12 also on the object at pixel 5,
    and a ghost (Gaussian 13) 10 cm in front of it on pixel 5. The mask covers pixels 0-11. A second
    camera, turned away, sees nothing."""
    cols, rows = np.arange(12) % 4, np.arange(12) // 4
    obj = np.stack([(cols + 0.5 - 2) / 10, (rows + 0.5 - 2) / 10, np.ones(12)], axis=1)
    means = np.concatenate([obj, [obj[5]], [obj[5] * 0.9]])
    T_away = np.diag([-1.0, 1.0, -1.0, 1.0])                 # camera 2 looks down -z: everything behind it
    views = [View("v0", cam("v0")), View("v1", cam("v1", T_away))]
    masks = MaskSet(objects={1: "box"}, masks={"v0": {1: flat_mask(list(range(12))).reshape(H, W)}},
                    scores={"v0": {1: 1.0}}, sizes={"v0": (H, W), "v1": (H, W)})
    return means, views, masks


def test_refinement_round_reveals_the_surface_behind_a_floater():
    means, views, masks = _floater_scene()
    opts = FusionOptions(knn_k=0)                             # no KNN smoothing: the rounds alone
    r = ZBuffer(means)
    res = fuse(means, views, masks, opts, depth_renderer=r)
    # round 1: pixel 5 shows the ghost (z 0.9): Gaussians 5 and 12 behind it are hidden (N 0,
    # background); the ghost is visible and in the mask but 10 cm in front of the cluster of the 11
    # visible object Gaussians: weight exp(-25), gated in front in its only observation -> floater.
    # Round 2 re-renders only camera v0, without the ghost: 5 and 12 are visible (N 1, weight 1 >= tau
    # 2/3) -> object; the ghost is now hidden -> no new floater -> stop.
    assert r.calls == [(None, ["v0", "v1"]), ([13], ["v0"])]
    assert res.labels.tolist() == [1] * 13 + [0]
    assert res.floaters.tolist() == [False] * 13 + [True]
    assert res.n_visible.tolist() == [1] * 13 + [0]
    assert res.votes[:, 0].tolist() == [1.0] * 13 + [0.0]
    assert [(h["round"], h["changed"], h["floaters"]) for h in res.history] == [(1, 14, 1), (2, 2, 0)]
    # a single pass (iters 1) keeps the ghost's shadow: Gaussians 5 and 12 stay background
    one = fuse(means, views, masks, FusionOptions(knn_k=0, iters=1), depth_renderer=ZBuffer(means))
    assert one.labels.tolist() == [1] * 5 + [0] + [1] * 6 + [0, 0]
    assert one.n_visible.tolist() == [1] * 5 + [0] + [1] * 6 + [0, 1]
    np.testing.assert_allclose(one.votes[13, 0], math.exp(-((1.0 - 0.9) / 0.02) ** 2), rtol=1e-4)  # float32 depths
    assert one.floaters.tolist() == [False] * 13 + [True]


def test_find_floaters_by_hand():
    labels = np.array([0, 0, 0, 1, 0])
    gated_front = np.array([1, 1, 2, 3, 0])
    hits = np.array([[1, 0], [2, 1], [3, 0], [3, 0], [0, 0]])   # in-mask observations per object
    # 1/1 >= 0.5; 1/3 < 0.5; 2/3 >= 0.5; labelled objects are never floaters; never gated: no
    assert find_floaters(labels, gated_front, hits, 0.5).tolist() == [True, False, True, False, False]


# -- 5. KNN boundary smoothing -------------------------------------------------------------------------

def test_knn_smoothing_passes_by_hand():
    # point:         0    1    2    3    4    5      (2 neighbours each)
    labels = np.array([1, 1, 0, 0, 0, 1])
    conf = np.array([0.9, 0.9, 0.1, 0.1, 0.1, 0.5])
    nb = np.array([[1, 2], [0, 2], [0, 1], [2, 1], [3, 5], [4, 3]])
    # one pass: 2 sees (1, 1) -> 1; 5 sees (0, 0) -> 0; 3 sees (0, 1): a tie (share 0.5 < 0.6) -> stays
    one, f = knn_smooth(labels, conf.copy(), nb, threshold=0.6, confidence_gate=0.8)
    assert one.tolist() == [1, 1, 1, 0, 0, 0] and f == 2
    # iterated (smooth_labels, up to iters passes): pass 2 flips 3, whose neighbours 2 and 1 are now 1;
    # pass 3 flips nothing (4 sees 3 = 1 and 5 = 0: a tie) and stops. Points 0 and 1 (confidence 0.9 >=
    # 0.8) are never queried; flipped points take their neighbour share as confidence
    c = conf.copy()
    out, flips = smooth_labels(labels, c, nb, FusionOptions(iters=3))
    assert out.tolist() == [1, 1, 1, 1, 0, 0] and flips == 3
    assert c.tolist() == [0.9, 0.9, 1.0, 1.0, 0.1, 1.0]
    # one pass allowed: as knn_smooth once
    out1, flips1 = smooth_labels(labels, conf.copy(), nb, FusionOptions(iters=1))
    assert out1.tolist() == [1, 1, 1, 0, 0, 0] and flips1 == 2
    # a higher threshold (all neighbours must agree) still flips 2 and 5, whose neighbours agree
    out2, _ = smooth_labels(labels, conf.copy(), nb, FusionOptions(iters=3, knn_threshold=1.0))
    assert out2.tolist() == [1, 1, 1, 1, 0, 0]


def test_knn_smoothing_in_fuse_labels_an_unseen_point_from_its_neighbours():
    # the floater scene with KNN smoothing on and one round: Gaussians 5 and 12, hidden behind the ghost
    # (N 0, confidence 0), have all 13 others as their nearest (k = min(16, N - 1)): 11 labelled object,
    # the other hidden one and the ghost background -> share 11/13 >= 0.6 -> object. The ghost (confidence
    # 1 - exp(-25)) is not queried.
    means, views, masks = _floater_scene()
    res = fuse(means, views, masks, FusionOptions(iters=1, knn_k=16), depth_renderer=ZBuffer(means))
    assert res.labels.tolist() == [1] * 13 + [0]
    assert res.history[0]["knn_flipped"] == 2
    np.testing.assert_allclose(res.confidence[[5, 12]], [11 / 13, 11 / 13], rtol=1e-6)
