"""Silhouette coverage of an object's cleaned splats against its 2D masks (splattwin.geometry.completeness)
and its use in deciding whether an object is whole (geometry.convert)."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull
from skimage.draw import polygon

from splattwin.capture.camera import Camera, look_at
from splattwin.geometry.completeness import coverage, mask_views, resample_mask, view_coverage
from splattwin.geometry.convert import IncompleteObjectWarning, ObjectUnusableWarning, object_geometry
from splattwin.geometry.options import GeometryOptions
from splattwin.scene.synthetic import trained_like_gaussians
from splattwin.semantics.masks import MaskSet


def _ring(target, n: int = 8, size=(160, 120)) -> list[Camera]:
    """`n` cameras on a ring 0.3 m out and 0.3 m up around `target`, looking at it."""
    return [Camera.from_fov(np.radians(60.0), *size, name=f"view{i}",
                            T_world_cam=look_at([target[0] + 0.3 * np.cos(a), target[1] + 0.3 * np.sin(a), 0.3], target))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))]


def _mask(mesh: trimesh.Trimesh, cam: Camera) -> np.ndarray:
    """The exact silhouette of a convex mesh: the pixels whose centres lie in its projected vertices' hull."""
    uv, _ = cam.project(mesh.vertices)
    hull = uv[ConvexHull(uv).vertices]
    rr, cc = polygon(hull[:, 1] - 0.5, hull[:, 0] - 0.5, (cam.height, cam.width))
    m = np.zeros((cam.height, cam.width), dtype=bool)
    m[rr, cc] = True
    return m


def _box(size, seed: int = 0, n: int = 1500):
    """A GT box of `size` (m) standing on z = 0, trained-like splats on it (haze dropped, as the cleaning
    does), and the ring's cameras with the box's exact masks."""
    mesh = trimesh.creation.box(size)
    mesh.apply_translation([0.0, 0.0, size[2] / 2])
    g = trained_like_gaussians(mesh, n, seed=seed)
    g = g.subset(g.opacities > 0.1)
    cams = _ring([0.0, 0.0, size[2] / 2])
    return mesh, g, [(c, _mask(mesh, c)) for c in cams]


@pytest.fixture(scope="module")
def bar():
    """A 19 cm bar (the toy hammer's length), 3 cm thick."""
    return _box([0.19, 0.03, 0.03])


@pytest.fixture(scope="module")
def cube():
    """The robot-style capture's 2.5 cm cube with 48 splats (it keeps 48 after cleaning)."""
    return _box([0.025, 0.025, 0.025], n=48)


def test_view_coverage_hand_worked():
    """A 10x10 mask and a silhouette of its left half: recall 0.5, precision 1 without tolerance; with 1 px
    the silhouette reaches one more column (0.6). A silhouette beside the mask: recall 0, precision 0
    (1 px away: within the tolerance, both count). An empty silhouette covers nothing."""
    mask = np.zeros((12, 24), bool)
    mask[1:11, 1:11] = True
    half = np.zeros_like(mask)
    half[1:11, 1:6] = True
    assert view_coverage(half, mask, tol_px=0) == (0.5, 1.0)
    assert view_coverage(half, mask, tol_px=1) == pytest.approx((0.6, 1.0))
    beside = np.zeros_like(mask)
    beside[1:11, 13:20] = True
    assert view_coverage(beside, mask, tol_px=1) == (0.0, 0.0)
    touching = np.zeros_like(mask)
    touching[1:11, 11:13] = True
    r, p = view_coverage(touching, mask, tol_px=1)
    assert r == pytest.approx(0.1) and p == pytest.approx(0.5)
    assert view_coverage(np.zeros_like(mask), mask) == (0.0, 0.0)


def test_resample_mask_reads_pixel_centres():
    """Halving a 6x4 mask reads the pixels whose centres the small pixels' centres fall on: columns 1, 3,
    5 and rows 1, 3."""
    m = np.zeros((4, 6), bool)
    m[0:2, 0:4] = True
    m[3, 5] = True
    assert resample_mask(m, 3, 2).tolist() == [[True, True, False], [False, False, True]]
    assert np.array_equal(resample_mask(m, 6, 4), m)


def test_a_whole_object_covers_its_masks_and_a_fragment_does_not(bar, cube):
    """The whole bar covers its silhouettes (recall >= 0.95, precision >= 0.9); its last 3.5 cm (a sixth
    of it) about a quarter; the 35 splats nearest its end (a hammer-head-sized fragment, as the tiny
    robot-capture build kept) almost nothing. The 48-splat cube covers its small silhouettes whole."""
    _, g, views = bar
    whole = coverage(g, views)
    assert whole.views == 8 and whole.recall >= 0.95 and whole.precision >= 0.9, whole
    end = coverage(g.subset(g.means[:, 0] > 0.06), views)
    assert 0.1 < end.recall < 0.35 and end.precision >= 0.9, end
    tip = np.argsort(np.linalg.norm(g.means - g.means[np.argmax(g.means[:, 0])], axis=1))[:35]
    assert coverage(g.subset(tip), views).recall < 0.15
    _, gc, vc = cube
    assert len(gc) == 48
    c = coverage(gc, vc)
    assert c.views == 8 and c.recall >= 0.9, c


def test_views_are_capped_spread_and_tiny_masks_skipped(bar):
    _, g, views = bar
    assert coverage(g, views, max_views=3).views == 3
    assert coverage(g, views, max_side=16, min_mask_px=9).views < 8   # the bar's thin end-on views drop out
    assert coverage(g, views, min_mask_px=10_000) is None            # nothing left to measure
    # a mask whose size is not its camera's image is not this camera's: ignored
    cam, m = views[0]
    assert coverage(g, [(cam, m[:, :-1])]) is None


def test_mask_views_pair_masks_with_frames_by_name(bar):
    from types import SimpleNamespace

    _, _, views = bar
    ms = MaskSet()
    for cam, m in views[:3]:
        ms.add(cam.name, 4, m, name="toy_hammer")
    ms.add("view5", 7, np.ones((5, 5), bool), name="wrong_size")     # not the frame's image size
    ms.add("elsewhere", 4, views[3][1])                             # no frame of that name
    frames = [SimpleNamespace(name=c.name, camera=c) for c, _ in views]
    out = mask_views(ms, frames)
    assert sorted(out) == [4]
    assert [c.name for c, _ in out[4]] == ["view0", "view1", "view2"]
    assert all(np.array_equal(m, views[i][1]) for i, (_, m) in enumerate(out[4]))


def _object(g, idx, views, name="obj", **opts):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = object_geometry(g, np.asarray(idx), name, 1, GeometryOptions(carve=False, **opts).resolved(1.2),
                            support_z=0.0, masks=views)
    return r, [w.category for w in caught]


def test_coverage_decides_whether_a_small_object_is_whole(bar, cube):
    """Below min_points (50) an object is usable when its masks show it whole (the 48-splat cube, coverage
    recorded), and not without masks (the count alone) nor as a fragment (35 splats of the bar's end: its
    problem names the coverage); below min_points_whole (20) never. Above min_points a fragment stays
    usable but is flagged (IncompleteObjectWarning, problem naming the coverage); the whole bar is not."""
    _, gc, vc = cube
    r, cats = _object(gc, np.arange(len(gc)), vc, "yellow_cube")
    assert r.usable and r.problem is None and r.coverage.recall >= 0.9 and r.collision.is_watertight, r.problem
    assert ObjectUnusableWarning not in cats and IncompleteObjectWarning not in cats
    r, cats = _object(gc, np.arange(len(gc)), None, "yellow_cube")
    assert not r.usable and r.problem == "too few points after cleaning (48 < 50)" and r.coverage is None
    assert ObjectUnusableWarning in cats
    r, _ = _object(gc, np.arange(19), vc, "yellow_cube")
    assert not r.usable and r.problem == "too few points after cleaning (19 < 20)"
    # the old floor of 30 as min_points, without masks, admits what the coverage rejects
    _, g, views = bar
    tip = np.argsort(np.linalg.norm(g.means - g.means[np.argmax(g.means[:, 0])], axis=1))[:35]
    assert _object(g, tip, None, "toy_hammer", min_points=30)[0].usable
    r, cats = _object(g, tip, views, "toy_hammer")
    assert not r.usable and "not whole" in r.problem and f"cover {r.coverage.recall:.0%}" in r.problem, r.problem
    assert ObjectUnusableWarning in cats
    end = np.flatnonzero(g.means[:, 0] > 0.06)
    assert len(end) > 50
    r, cats = _object(g, end, views, "toy_hammer")
    assert r.usable and r.problem.startswith("possibly incomplete") and IncompleteObjectWarning in cats, r.problem
    r, cats = _object(g, np.arange(len(g)), views, "toy_hammer")
    assert r.usable and r.problem is None and r.coverage.recall >= 0.95 and IncompleteObjectWarning not in cats
    # coverage_views 0: not measured, the count decides
    r, _ = _object(gc, np.arange(len(gc)), vc, "yellow_cube", coverage_views=0)
    assert not r.usable and r.coverage is None


def test_clusters_inside_the_masks_rejoin_the_largest_and_floaters_do_not(bar):
    """On a sparse real capture DBSCAN's largest cluster cut off parts of the object (the cake's dark side:
    0.72 of its masks covered, 0.91 with the parts that lie inside its masks). The 19 cm bar with a 3 cm gap
    (> eps 2 cm) splits in two; a floater 12 cm beside it lies outside its masks in most views. With the
    masks both parts are kept and the floater is not; without them (or rejoin_precision 0) the larger part
    alone, as the paper's DBSCAN step."""
    from dataclasses import replace as dc_replace

    from splattwin.geometry.convert import clean_indices
    from splattwin.geometry.options import scene_scale
    from splattwin.splat.gaussians import Gaussians

    _, g, views = bar
    x = g.means[:, 0]
    part = g.subset((x < 0.0) | (x > 0.03))   # a 3 cm gap across the bar
    rng = np.random.default_rng(1)
    fl = part.subset(np.arange(40))
    fl = dc_replace(fl, means=np.array([0.0, 0.12, 0.10]) + rng.normal(0, 0.004, (40, 3)))
    both = Gaussians(*(np.concatenate([getattr(part, k), getattr(fl, k)])
                       for k in ("means", "quats", "scales", "opacities", "sh")))
    labels = np.ones(len(both), dtype=np.int64)
    is_floater = np.arange(len(both)) >= len(part)
    left, right = (part.means[:, 0] < 0.0).sum(), (part.means[:, 0] > 0.03).sum()
    assert left > right > 40   # two parts, the floater is the smallest cluster
    opts = GeometryOptions().resolved(scene_scale(both.means), 1.0)
    alone = clean_indices(both, labels, 1, opts, attribute=False)
    assert len(alone) == left and not is_floater[alone].any()
    rejoined = clean_indices(both, labels, 1, opts, attribute=False, masks=views)
    assert len(rejoined) == len(part) and not is_floater[rejoined].any()
    assert coverage(both.subset(rejoined), views).recall > coverage(both.subset(alone), views).recall + 0.15
    off = clean_indices(both, labels, 1, dc_replace(opts, rejoin_precision=0.0), attribute=False, masks=views)
    assert np.array_equal(off, alone)
