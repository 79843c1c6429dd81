import numpy as np
import pytest
import trimesh

from splattwin.geometry.meshing import (MeshRepairWarning, add_bottom, densify_gaussians, simplify, solid_mesh,
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


def test_densify_samples_follow_the_covariance():
    rng = np.random.default_rng(1)
    R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    s = np.array([0.01, 0.003, 0.001])
    pts = densify_gaussians(np.zeros((1, 3)), R[None], s[None], samples=40000, sigma_clip=10.0)
    cov = np.cov(pts.T)
    assert np.allclose(cov, R @ np.diag(s**2) @ R.T, atol=3e-6)
    clipped = densify_gaussians(np.zeros((1, 3)), np.eye(3)[None], np.ones((1, 3)), samples=2000, sigma_clip=2.0)
    assert np.linalg.norm(clipped, axis=1).max() <= 2.0 + 1e-9
