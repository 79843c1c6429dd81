import numpy as np
import trimesh

from splattwin.geometry.metrics import fidelity, sample_surface


def test_fidelity_analytic_offsets():
    gt = np.random.default_rng(0).uniform(0, 1, (4000, 3))
    gt[:, 2] = 0.0
    rec = gt.copy()
    rec[:, 2] = 0.003  # every point 3 mm off
    f = fidelity(rec, gt, 0.005)
    assert f.precision == 1.0 and f.recall == 1.0 and f.f1 == 1.0
    assert np.isclose(f.chamfer, 0.003, atol=1e-9)
    rec2 = np.concatenate([gt, gt[:1000] + [0, 0, 0.5]])  # 1000 outliers 0.5 m away
    f2 = fidelity(rec2, gt, 0.005)
    assert np.isclose(f2.precision, 4000 / 5000) and f2.recall == 1.0
    assert np.isclose(f2.f1, 2 * 0.8 / 1.8)
    assert np.isclose(f2.chamfer, 0.5 * (1000 * 0.5 / 5000), rtol=1e-6)


def test_sample_surface_drops_supported_bottom():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    box.apply_translation([0, 0, 0.05])
    all_pts = sample_surface(box, 0.004)
    seen = sample_surface(box, 0.004, drop_supported=0.0)
    def on_bottom(p):  # strictly inside the bottom face (side faces touch z = 0 only at their edge)
        return (p[:, 2] < 1e-9) & (np.abs(p[:, :2]).max(axis=1) < 0.049)

    assert on_bottom(all_pts).sum() > 100 and not on_bottom(seen).any()
    assert 0.75 < len(seen) / len(all_pts) < 0.92  # 5 of 6 faces


def test_mesh_fidelity_known_answers():
    from splattwin.geometry.metrics import mesh_fidelity

    box = trimesh.creation.box([0.1, 0.08, 0.06])
    same = mesh_fidelity(box, box)
    assert same.f1 == 1.0 and same.chamfer < 0.002
    near = box.copy()
    near.apply_translation([0.003, 0, 0])  # 3 mm off: within the 5 mm threshold everywhere
    assert mesh_fidelity(near, box).f1 == 1.0
    grown = trimesh.creation.box([0.12, 0.1, 0.08])  # every face 1 cm out: nothing within 5 mm
    f = mesh_fidelity(grown, box)
    assert f.precision == 0.0 and f.recall == 0.0 and 0.009 < f.chamfer < 0.013
