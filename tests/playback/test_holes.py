"""Hole fill under a picked object: the footprint is covered with the table's own texture and marked."""

from __future__ import annotations

import numpy as np

from splattwin.capture.camera import Camera, look_at
from splattwin.playback.holes import CELL, MARGIN, MIRROR_DEPTH, fill_hole, mirror_source
from splattwin.playback.compositor import PlaybackRenderer
from splattwin.playback.scene import DynamicScene
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0

from .conftest import OBJ_CENTRE, OBJ_HALF, table_colour


def test_fill_covers_the_footprint_with_table_texture(tiny_twin):
    sc = DynamicScene.load(tiny_twin)
    f = sc.fills["blue_box"]
    # the footprint: the box's base plus the margin, nothing far away
    xy = f.cells_xy
    reach = MARGIN + 2 * CELL
    inside_box = np.all(np.abs(xy - OBJ_CENTRE[:2]) <= OBJ_HALF[:2] + reach, axis=1)
    assert inside_box.all()
    base = (2 * OBJ_HALF[0]) * (2 * OBJ_HALF[1])
    assert base <= f.area_m2 <= (2 * OBJ_HALF[0] + 2 * reach) * (2 * OBJ_HALF[1] + 2 * reach)
    # fill Gaussians lie in the footprint, on the table plane, with the table's colours
    fm = f.gaussians.means
    assert len(fm) > 0.5 * f.area_m2 / 0.004 ** 2
    assert np.all(np.abs(fm[:, :2] - OBJ_CENTRE[:2]) <= OBJ_HALF[:2] + reach + 0.004)
    assert np.abs(fm[:, 2]).max() < 1e-6
    tc = table_colour(fm[:, :2])
    assert np.abs(f.gaussians.colors - tc).mean() < 0.12   # mirrored texture continues the pattern
    d = f.to_dict()
    assert d["fill_gaussians"] == len(f.gaussians) and len(d["outline_xy"]) >= 3


def test_moved_object_leaves_table_not_a_hole(tiny_twin):
    sc = DynamicScene.load(tiny_twin)
    r = PlaybackRenderer(sc, backend="cpu")
    cam = Camera.from_fov(np.radians(40), 96, 72, look_at(np.array([0.02, -0.03, 0.45]), OBJ_CENTRE * [1, 1, 0]))
    T = np.eye(4)
    T[:3, 3] = [-0.12, 0.12, OBJ_CENTRE[2]]
    moved = r.render(cam, {"blue_box": T})
    uv, _ = cam.project(np.array([[OBJ_CENTRE[0], OBJ_CENTRE[1], 0.0]]))
    u, v = uv[0].astype(int)
    patch = moved.rgb[v - 3:v + 4, u - 3:u + 4].reshape(-1, 3)
    assert moved.alpha[v - 3:v + 4, u - 3:u + 4].min() > 0.9      # covered, not a black hole
    # plausible: within the table's own colour range (the mirrored texture, not black, not the object)
    ring = table_colour(np.random.default_rng(0).uniform(-0.1, 0.1, (2000, 2)))
    assert np.all(patch.mean(0) >= ring.min(0) - 0.03) and np.all(patch.mean(0) <= ring.max(0) + 0.03)
    # without the fill the same pixels are empty
    sc_nofill = DynamicScene.load(tiny_twin, fill_holes=False)
    bare = PlaybackRenderer(sc_nofill, backend="cpu").render(cam, {"blue_box": T})
    assert bare.alpha[v, u] < 0.5
    # the report's mark: the fill mask is on at the footprint, off far from it
    mask = r.fill_mask(cam, {"blue_box": T})
    assert mask[v, u] > 0.8
    assert mask[2, 2] < 0.01 and mask[-3, -3] < 0.01
    # object unmoved: no fill drawn, the object covers its place
    at_rest = r.render(cam, {})
    assert np.abs(at_rest.rgb[v, u] - patch.mean(0)).max() > 0.1


def _flat_table(colour_of, half: float = 0.15, spacing: float = 0.003) -> Gaussians:
    """Flat table Gaussians (z = 0) on a grid, coloured by colour_of(xy [N,2]) -> [N,3]."""
    g = np.arange(-half, half + 1e-9, spacing)
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    n = len(xy)
    return Gaussians(np.concatenate([xy, np.zeros((n, 1))], 1), np.tile([1.0, 0, 0, 0], (n, 1)),
                     np.tile([spacing * 0.7, spacing * 0.7, 1e-4], (n, 1)), np.full(n, 0.9),
                     rgb_to_sh0(colour_of(xy))[:, None, :])


def test_fill_does_not_copy_a_marking_far_beyond_the_footprint():
    # demo: the target frame's orange tape 3.3 cm beyond the blue box's footprint was mirrored into the middle of
    # the hole (the mirror reached as far out as the footprint's inradius): an orange blob where plain wood was
    wood, tape = np.array([0.74, 0.54, 0.35]), np.array([0.88, 0.33, 0.05])
    half = 0.04                                # an 8 cm square object: footprint 11 cm with the margin
    edge = half + MARGIN                       # footprint boundary (m)
    stripe = (edge + 0.03, edge + 0.048)       # a tape 3 cm beyond it, parallel to it

    def colour(xy):
        on = (xy[:, 1] >= stripe[0]) & (xy[:, 1] <= stripe[1])
        return np.where(on[:, None], tape, wood)

    bg = _flat_table(colour)
    under = np.all(np.abs(bg.means[:, :2]) < half, axis=1)      # never seen: under the object
    bg = bg.subset(~under)
    u = np.linspace(-half, half, 30)
    obj = np.stack(np.meshgrid(u, u, [0.01, 0.05], indexing="ij"), -1).reshape(-1, 3)
    f = fill_hole("box", obj, bg, 0.0)
    assert len(f.gaussians) > 0.5 * f.area_m2 / 0.003 ** 2      # the hole is covered
    assert np.allclose(f.gaussians.colors, wood, atol=1e-6)    # with wood only: no tape copied into it
    # every source lies within the mirror depth of the footprint
    src = bg.means[f.source, :2]
    beyond = np.abs(src).max(1) - edge
    assert beyond.max() <= MIRROR_DEPTH + 3 * CELL
    # within the mirror depth the fill is the exact mirror, as before
    t = np.array([3.0, 5.0, 12.0])
    p = np.stack([np.zeros(3), -t], 1).astype(np.int64)
    b = np.zeros((3, 2), np.int64)
    assert np.array_equal(mirror_source(p, b, t, 10.0), np.stack([np.zeros(3), [3, 5, 8]], 1))
