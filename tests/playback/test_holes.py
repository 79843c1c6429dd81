"""Hole fill under a picked object: the footprint is covered with the table's own texture and marked."""

from __future__ import annotations

import numpy as np

from splattwin.capture.camera import Camera, look_at
from splattwin.playback.holes import CELL, MARGIN
from splattwin.playback.compositor import PlaybackRenderer
from splattwin.playback.scene import DynamicScene

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
