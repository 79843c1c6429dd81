"""Synthetic 3DGS reconstruction of a generated scene: Gaussians on the GT surfaces plus the artefacts a
real optimisation leaves, with per-Gaussian GT labels. Lets semantic fusion and geometry cleaning be
tested without training.

Surface Gaussians are flat discs (normal-axis scale 5 % of the tangent scale) centred on points sampled
uniformly on each visible GT surface (object bottoms resting on the table and the table's underside are
skipped), with a little position noise along the normal, and coloured with the scene's textures under the
scene's light (shadows baked in, as 3DGS bakes them). Artefacts (label 0), as listed in the paper:
- haze: large, nearly transparent Gaussians hovering a few cm off the surfaces ("ghost" primitives);
- floaters: small dense clumps detached from every surface, in the air above the table;
- needles: splats stretched (sigma 0.8-2.5 cm) along one axis and ~1 mm along the others, near object edges.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from splattwin.errors import InputError
from splattwin.scene.generator import build_scene, load_scene
from splattwin.scene.options import SceneOptions
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.transforms import quat_wxyz_from_matrix


def _quats_wxyz(R: np.ndarray) -> np.ndarray:
    """[N,3,3] rotations -> [N,4] unit wxyz quaternions (scipy's sign: the scene's bytes stay the same)."""
    return quat_wxyz_from_matrix(R, canonical=False)


def _frames_from_normals(n: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotations [N,3,3] whose third column is the unit normal n [N,3] (random spin about it)."""
    a = rng.standard_normal(n.shape)
    t1 = a - (a * n).sum(1, keepdims=True) * n
    small = np.linalg.norm(t1, axis=1) < 1e-6
    t1[small] = np.cross(n[small], [1.0, 0.0, 0.0]) + np.cross(n[small], [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def _visible_faces(mesh: trimesh.Trimesh, is_table: bool) -> np.ndarray:
    """Faces a camera above the table can see: not an object's bottom on the table, not the table's underside."""
    n = mesh.face_normals
    c = mesh.triangles_center
    hidden = (n[:, 2] < -0.9) & (c[:, 2] < 1e-3 if not is_table else np.ones(len(n), bool))
    return np.nonzero(~hidden)[0]


def _sample_surface(mesh: trimesh.Trimesh, faces: np.ndarray, count: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform area-weighted samples on the given faces. -> points [count,3], normals [count,3]"""
    area = mesh.area_faces[faces]
    f = faces[rng.choice(len(faces), size=count, p=area / area.sum())]
    tri = mesh.triangles[f]
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    p = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return p, mesh.face_normals[f]


def synthetic_gaussians(scene_dir: str | Path, seed: int = 0, density: float = 40000.0,
                        table_density: float | None = None, min_per_object: int = 400,
                        artefacts: bool = True, artefact_fraction: float = 0.08) -> tuple[Gaussians, np.ndarray]:
    """Gaussians sampled on the scene's GT surfaces (+ artefacts) and their GT labels.

    Args:
        scene_dir: a folder written by `splattwin.scene.generator`.
        seed: seeds the sampling (independent of the scene's seed).
        density: object-surface Gaussians per square metre (at least `min_per_object` per object).
        table_density: table-surface Gaussians per m^2; default density / 2.
        artefacts: add haze, floaters and needles (label 0).
        artefact_fraction: artefacts as a fraction of the surface Gaussians (split 45/30/25 between haze,
            floaters and needles).
    Returns:
        (Gaussians with SH degree 0, labels_gt [N] int32: 0 = table/artefact, else object label id).
    """
    if not density > 0 or (table_density is not None and not table_density > 0):
        raise InputError(f"synthetic Gaussians: densities must be > 0, got {density}, {table_density}")
    if not 0 <= artefact_fraction <= 1 or min_per_object < 1:
        raise InputError("synthetic Gaussians: artefact_fraction must be in [0, 1] and min_per_object >= 1")
    scene = load_scene(scene_dir)
    opts = SceneOptions.from_dict(scene["options"])
    objects, _layout, _marker, renderer = build_scene(opts)
    rng = np.random.default_rng([seed, 7])
    table_density = density / 2 if table_density is None else table_density
    index_to_gid = {i: g for g, i in renderer.gid_to_index.items()}

    means, normals, gids, labels = [], [], [], []
    spacing = []
    for i, surf in enumerate(renderer.surfaces):
        is_table = surf.label == 0
        faces = _visible_faces(surf.mesh_world, is_table)
        area = float(surf.mesh_world.area_faces[faces].sum())
        n = int(round(area * (table_density if is_table else density)))
        if not is_table:
            n = max(n, min_per_object)
        p, nrm = _sample_surface(surf.mesh_world, faces, n, rng)
        means.append(p)
        normals.append(nrm)
        gids.append(np.full(n, index_to_gid[i], dtype=np.uint32))
        labels.append(np.full(n, surf.label, dtype=np.int32))
        spacing.append(np.full(n, np.sqrt(area / n)))
    p = np.concatenate(means)
    nrm = np.concatenate(normals)
    gid = np.concatenate(gids)
    lab = np.concatenate(labels)
    sp = np.concatenate(spacing)
    rgb = renderer.colour_hits(p.astype(np.float32), nrm.astype(np.float32), gid)
    N = len(p)
    R = _frames_from_normals(nrm, rng)
    tangent = sp * rng.uniform(0.5, 0.8, N)
    scales = np.stack([tangent, tangent * rng.uniform(0.7, 1.0, N), tangent * 0.05], axis=1)
    p = p + nrm * rng.normal(0, 0.0007, (N, 1))  # reconstructions are never exactly on the surface
    opac = rng.uniform(0.85, 0.99, N)

    parts = [(p, _quats_wxyz(R), scales, opac, rgb, lab)]
    if artefacts and artefact_fraction > 0:
        n_art = int(round(N * artefact_fraction))
        parts += _artefacts(rng, p, nrm, rgb, lab, renderer, objects, n_art)

    means = np.concatenate([a[0] for a in parts])
    g = Gaussians(means=means, quats=np.concatenate([a[1] for a in parts]),
                  scales=np.concatenate([a[2] for a in parts]), opacities=np.concatenate([a[3] for a in parts]),
                  sh=rgb_to_sh0(np.clip(np.concatenate([a[4] for a in parts]), 0.0, 1.0))[:, None, :])
    return g, np.concatenate([a[5] for a in parts]).astype(np.int32)


def _artefacts(rng, p, nrm, rgb, lab, renderer, objects, n_art):
    """Haze, floaters and needles; every artefact has label 0."""
    out = []
    n_haze, n_float = int(0.45 * n_art), int(0.30 * n_art)
    n_needle = n_art - n_haze - n_float

    # haze: large, faint, a few cm off random surface points
    k = rng.integers(0, len(p), n_haze)
    m = p[k] + nrm[k] * rng.uniform(0.005, 0.03, (n_haze, 1)) + rng.normal(0, 0.01, (n_haze, 3))
    s = rng.uniform(0.01, 0.03, (n_haze, 3))
    c = np.clip(rgb[k] + rng.normal(0, 0.08, (n_haze, 3)), 0, 1)
    out.append((m, _quats_wxyz(Rotation.random(n_haze, random_state=rng).as_matrix()), s,
                rng.uniform(0.02, 0.15, n_haze), c, np.zeros(n_haze, np.int32)))

    # floaters: clumps of 3-10 small, fairly dense Gaussians in the air, >= 3 cm from every surface
    surf_tree = cKDTree(p)
    centres = []
    while len(centres) < max(1, n_float // 6):
        q = np.array([rng.uniform(-0.35, 0.35), rng.uniform(-0.45, 0.45), rng.uniform(0.03, 0.35)])
        if surf_tree.query(q)[0] > 0.03:
            centres.append(q)
    centres = np.array(centres)
    which = rng.integers(0, len(centres), n_float)
    m = centres[which] + rng.normal(0, 0.006, (n_float, 3))
    s = rng.uniform(0.002, 0.008, (n_float, 3))
    # colour of some surface elsewhere (mis-placed background, as real floaters are)
    c = rgb[rng.integers(0, len(rgb), len(centres))][which] + rng.normal(0, 0.05, (n_float, 3))
    out.append((m, _quats_wxyz(Rotation.random(n_float, random_state=rng).as_matrix()), s,
                rng.uniform(0.3, 0.9, n_float), np.clip(c, 0, 1), np.zeros(n_float, np.int32)))

    # needles: near object edges (object surface points close to a sharp mesh edge), long along a random axis
    obj_pts = p[lab > 0]
    edges = []
    for o in objects:
        mw = o.mesh_world()
        sharp = mw.face_adjacency_edges[mw.face_adjacency_angles > np.radians(30)]
        if len(sharp):
            seg = mw.vertices[sharp]
            t = rng.random((200, 1))
            e = seg[rng.integers(0, len(seg), 200)]
            edges.append(e[:, 0] + t * (e[:, 1] - e[:, 0]))
    edge_pts = np.concatenate(edges) if edges else obj_pts
    k = rng.integers(0, len(edge_pts), n_needle)
    m = edge_pts[k] + rng.normal(0, 0.004, (n_needle, 3))
    s = np.stack([rng.uniform(0.008, 0.025, n_needle), rng.uniform(0.0005, 0.0015, n_needle),
                  rng.uniform(0.0005, 0.0015, n_needle)], axis=1)
    nearest = cKDTree(p).query(m)[1]
    c = np.clip(rgb[nearest] + rng.normal(0, 0.05, (n_needle, 3)), 0, 1)
    out.append((m, _quats_wxyz(Rotation.random(n_needle, random_state=rng).as_matrix()), s,
                rng.uniform(0.2, 0.6, n_needle), c, np.zeros(n_needle, np.int32)))
    return out
