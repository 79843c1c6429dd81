import numpy as np
import pytest
import trimesh

from splattwin.geometry.meshing import (MeshRepairWarning, add_bottom, ellipsoid_samples, level_radii, simplify, solid_mesh,
                                        voxel_solid)
from splattwin.geometry.metrics import fidelity, sample_surface


def _box_surface(extent, n=6000, seed=0, bottom=False):
    box = trimesh.creation.box(extent)
    box.apply_translation([0, 0, extent[2] / 2])
    pts, fid = trimesh.sample.sample_surface(box, n, seed=seed)
    if not bottom:
        pts = pts[box.face_normals[fid][:, 2] > -0.9]
    return box, pts


def test_solid_mesh_of_open_bottom_box_is_closed_and_accurate():
    box, pts = _box_surface([0.1, 0.06, 0.04])
    res = solid_mesh(add_bottom(pts, 0.002), pitch=0.0025)
    m = res.mesh
    assert res.method == "alpha" and m.is_watertight and m.is_volume
    assert abs(m.volume / box.volume - 1) < 0.2
    f = fidelity(sample_surface(m, 0.002), sample_surface(box, 0.002), 0.005)
    assert f.f1 > 0.95


def test_voxel_remesh_path_and_simplify_keep_watertight():
    box, pts = _box_surface([0.08, 0.08, 0.03], bottom=True)
    res = solid_mesh(pts, pitch=0.0025, use_alpha=False)
    assert res.method == "voxel_remesh" and res.mesh.is_watertight
    s = simplify(res.mesh, 300)
    assert len(s.faces) <= 300 and s.is_watertight and abs(s.volume / res.mesh.volume - 1) < 0.1


def test_voxel_solid_fills_interior():
    box, pts = _box_surface([0.05, 0.05, 0.05], n=8000, bottom=True)
    sol = voxel_solid(pts, 0.0025)
    assert abs(sol.occ.sum() * 0.0025**3 / box.volume - 1) < 0.35


def test_fallback_emits_named_warning():
    # two separate blobs: neither the alpha shape nor the voxel remesh is one closed volume
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(0, 0.01, (800, 3)), rng.normal(0, 0.01, (800, 3)) + [0.3, 0, 0]])
    with pytest.warns(MeshRepairWarning, match="convex hull"):
        res = solid_mesh(pts, 0.0025, alpha_factors=(1.5,), name="blobs")
    assert res.method == "convex_hull" and res.mesh.is_watertight



def test_level_radii_is_where_a_splat_alone_reaches_the_level():
    op = np.array([0.3, 0.5, 0.6, 0.9, 0.99])
    r = level_radii(op, 0.5)
    assert r[0] == 0.0 and r[1] == 0.0  # never half opaque on its own
    np.testing.assert_allclose(op[2:] * np.exp(-0.5 * r[2:] ** 2), 0.5, rtol=1e-12)
    assert np.all(np.diff(r) >= 0)
    np.testing.assert_allclose(level_radii(np.array([0.9]), 0.3) ** 2, 2 * np.log(3.0))


def test_ellipsoid_samples_lie_on_the_ellipsoid_and_reach_its_poles():
    rng = np.random.default_rng(3)
    R = np.stack([trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3] for _ in range(4)])
    s = rng.uniform(0.001, 0.01, (4, 3))
    mu = rng.normal(size=(4, 3))
    radii = np.array([0.0, 0.5, 1.0, 2.0])
    pts = ellipsoid_samples(mu, R, s, radii).reshape(4, 26, 3)
    local = np.einsum("nji,nsj->nsi", R, pts - mu[:, None])  # Gaussian frame
    maha = np.linalg.norm(local / s[:, None], axis=2)
    np.testing.assert_allclose(maha, np.broadcast_to(radii[:, None], maha.shape), atol=1e-9)
    # the extreme along each principal axis is radius * scale (the thin-axis pole is the surface estimate)
    np.testing.assert_allclose(np.abs(local).max(axis=1), radii[:, None] * s, rtol=1e-9, atol=1e-15)


def _open_box_shell(extent=(0.1, 0.06, 0.05), spacing=0.0015, missing_wall=True):
    """Surface points of a box standing on z = 0: top and side walls, no bottom, and (by default) no
    +x wall, like a trained splat whose back side no camera saw."""
    box = trimesh.creation.box(extent)
    box.apply_translation([0, 0, extent[2] / 2])
    pts, fid = trimesh.sample.sample_surface_even(box, int(box.area / spacing**2), seed=0)
    n = box.face_normals[fid]
    keep = (n[:, 2] > -0.9) & ~((n[:, 0] > 0.9) & missing_wall)
    return box, pts[keep]


def test_support_fill_makes_a_solid_of_a_shell_open_on_one_side():
    box, pts = _open_box_shell()
    pitch = 0.003
    leaky = voxel_solid(add_bottom(pts, pitch / 2, z_floor=0.0), pitch)
    filled = voxel_solid(add_bottom(pts, pitch / 2, z_floor=0.0), pitch, floor_z=0.0)
    v_leaky, v_filled = leaky.occ.sum() * pitch**3, filled.occ.sum() * pitch**3
    _, closed_pts = _open_box_shell(missing_wall=False)
    closed = voxel_solid(add_bottom(closed_pts, pitch / 2, z_floor=0.0), pitch)  # hole filling works here
    v_closed = closed.occ.sum() * pitch**3
    assert abs(v_closed / box.volume - 1) < 0.2  # occupancy: about half a voxel beyond each face
    assert v_leaky < 0.6 * v_closed  # hole filling alone finds no interior: a thick shell
    assert abs(v_filled / v_closed - 1) < 0.08  # grids differ: the floor layer is centred on z = 0 here
    # the floor lies on a layer of voxel centres, and nothing is filled below it
    k = np.argwhere(filled.occ)[:, 2].min()
    assert abs(filled.origin[2] + (k + 0.5) * pitch) < 1e-9


def test_support_fill_does_not_fill_a_floating_object():
    box, pts = _open_box_shell(missing_wall=False)
    pts = pts + [0, 0, 0.05]  # 5 cm above the floor: solid_mesh is only told the floor when it rests on it
    res = solid_mesh(add_bottom(pts, 0.0015), 0.003)
    assert res.mesh.bounds[0, 2] > 0.045
