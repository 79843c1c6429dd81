"""Unscaled twins: the geometry's metric thresholds follow the frame's nominal metre.

The same labelled scene, once in metres and once in "SfM units" (every coordinate x S): converted with
length_scale S, the unscaled conversion must keep the same Gaussians and give the same meshes x S
(the thresholds keep their share of the scene); with the metric thresholds as written (length_scale 1)
the cleaning removes every object point, which is the failure this fixes.
"""

from __future__ import annotations

import warnings
from dataclasses import fields

import numpy as np
import pytest

from splattwin.geometry.convert import convert
from splattwin.geometry.options import GeometryOptions, scene_scale
from splattwin.options import scale_lengths, specs
from splattwin.scene.synthetic import synthetic_scene
from splattwin.splat.gaussians import Gaussians

S = 7.3  # SfM units per metre (a COLMAP model of a tabletop is often several units across)


def _scaled(g: Gaussians, s: float) -> Gaussians:
    return Gaussians(g.means * s, g.quats, g.scales * s, g.opacities, g.sh)


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(12000, seed=1)


def _convert(g, labels, objects, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert(g, labels, objects, progress=False, **kw)


def test_scale_lengths_touches_lengths_and_density_only():
    o = GeometryOptions(alpha=None, dbscan_voxel=0.004)
    assert scale_lengths(o, 1.0) is o  # metric twin: the very same options
    t = scale_lengths(o, 3.0)
    for spec in specs(GeometryOptions):
        a, b, unit = getattr(o, spec.name), getattr(t, spec.name), spec.meta.get("unit")
        if unit == "m" and a is not None:
            assert b == pytest.approx(3.0 * a), spec.name
        elif unit == "kg/m^3":
            assert b == pytest.approx(a / 27.0)
        else:
            assert b == a, spec.name  # ratios, counts, flags, None (derived later from scaled values)
    assert t.dbscan_eps == pytest.approx(0.06) and t.needle_length == pytest.approx(0.018)


def test_metric_resolution_is_unchanged():
    o = GeometryOptions()
    a, b = o.resolved(1.3), o.resolved(1.3, 1.0)
    assert [getattr(a, f.name) for f in fields(a)] == [getattr(b, f.name) for f in fields(b)]
    assert a.dbscan_eps == 0.02 and a.mesh_voxel == 0.003 and a.dbscan_voxel == 0.005


def test_unscaled_conversion_matches_metric_times_scale(scene):
    g, labels, objects, _ = scene
    metric = _convert(g, labels, objects)
    gs = _scaled(g, S)
    # the bug: metre thresholds on SfM units (eps 2 cm >> the whole scene here; needles, voxels ...)
    naive = _convert(gs, labels, objects)
    unscaled = _convert(gs, labels, objects, length_scale=S)
    assert unscaled.options.dbscan_eps == pytest.approx(0.02 * S)
    assert unscaled.options.max_scale == pytest.approx(metric.options.max_scale * S)
    assert unscaled.background.table_thickness == pytest.approx(0.03 * S)
    assert scene_scale(gs.means) == pytest.approx(S * scene_scale(g.means))
    for m, u, n in zip(metric.objects, unscaled.objects, naive.objects):
        assert m.usable and u.usable, (m.problem, u.problem)
        # the same Gaussians survive cleaning (voxel grids may round a border point differently)
        a, b = set(m.indices.tolist()), set(u.indices.tolist())
        assert len(a ^ b) <= 0.01 * len(a), m.name
        assert u.volume == pytest.approx(m.volume * S ** 3, rel=0.05)
        assert u.mass == pytest.approx(m.mass, rel=0.05)  # nominal kilograms: density / S^3
        assert np.allclose(u.T_world_obj[:3, 3], m.T_world_obj[:3, 3] * S, atol=0.004 * S)
        assert np.allclose(u.extent, m.extent * S, atol=0.004 * S)
        # the metric thresholds as written remove the object (issue #16: "too few points after cleaning")
        assert not n.usable and "too few points" in n.problem, n.name
    assert unscaled.background.table_height == pytest.approx(metric.background.table_height * S, abs=0.002 * S)


@pytest.mark.parametrize("length_scale, unit", [(1.0, "m"), (S, "frame units")])
def test_an_assumed_tables_reason_gives_its_lengths_units(length_scale, unit):
    """twin.json's table_default (the report's "the table is assumed (...)" warning) read "437 background
    splats within 0.0519 of the frame table plane, ... (DBSCAN eps 0.13)" in the unscaled cake: bare numbers
    in SfM units that a reader takes for metres."""
    from splattwin.geometry.clustering import Plane
    from splattwin.geometry.convert import background_geometry

    rng = np.random.default_rng(0)
    n = 400   # background splats well above the table plane z = 0: no table top among them
    means = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.2, 0.5, n)]) * length_scale
    g = Gaussians(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.003 * length_scale), np.full(n, 0.9),
                  np.zeros((n, 1, 3)))
    opts = GeometryOptions().resolved(scene_scale(g.means), length_scale)
    bg = background_geometry(g, np.arange(n), opts, plane=Plane(normal=np.array([0.0, 0, 1]), d=0.0),
                             length_scale=length_scale)
    assert f"within {2 * opts.plane_distance:.3g} {unit} of the frame table plane" in bg.default_reason
    assert f"DBSCAN eps {opts.dbscan_eps:.3g} {unit})" in bg.default_reason
