"""Small synthetic data with a known answer, for the tests and benchmarks of the later stages (the one
home of the test-data generators besides the embedded scene itself, `splattwin.scene.generator`).

Geometry (`synthetic_scene`, `leak_labels`, `trained_like_gaussians`): a 1 x 0.8 m table top (z = 0), a
box, a cube and a T-shaped hammer resting on it; Gaussians on the seen surfaces (no bottoms) plus the 3DGS
artefacts the cleaning must remove: low-opacity haze off the surface, needles and oversized splats, and
detached floaters carrying the object's label.

Semantics (`make_synth`): a tiny analytic tabletop (a table plane, two boxes, a floater blob) whose ground
truth comes from exact ray casting (plane + slab tests), independent of the code under test; noisy masks
are the GT dilated by `bleed` pixels (the SAM "bleeding effect") plus a false blob on the table.
`scene_gaussians`: the embedded scene's synthetic reconstruction scaled to about n Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from splattwin.capture.camera import Camera, look_at
from splattwin.semantics.fusion import View
from splattwin.semantics.masks import MaskSet
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.transforms import quat_wxyz_from_matrix


def _yaw(mesh: trimesh.Trimesh, yaw: float, xy) -> trimesh.Trimesh:
    T = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
    T[:2, 3] = xy
    m = mesh.copy()
    m.apply_transform(T)
    return m


def scene_meshes() -> dict[str, trimesh.Trimesh]:
    box = trimesh.creation.box([0.12, 0.07, 0.05])
    box.apply_translation([0, 0, 0.025])
    cube = trimesh.creation.box([0.05, 0.05, 0.05])
    cube.apply_translation([0, 0, 0.025])
    handle = trimesh.creation.box([0.20, 0.03, 0.03])
    head = trimesh.creation.box([0.04, 0.12, 0.04])
    head.apply_translation([0.10, 0, 0.005])
    handle.apply_translation([-0.02, 0, 0])
    hammer = trimesh.boolean.union([handle, head])
    hammer.apply_translation([0, 0, -hammer.bounds[0, 2]])
    return {"box": _yaw(box, 0.4, [0.15, 0.15]), "cube": _yaw(cube, -0.3, [0.2, -0.15]),
            "hammer": _yaw(hammer, 1.1, [-0.15, 0.0])}


def _surface(mesh: trimesh.Trimesh, n: int, rng) -> np.ndarray:
    pts, fid = trimesh.sample.sample_surface(mesh, n * 2, seed=int(rng.integers(1 << 30)))
    seen = mesh.face_normals[fid][:, 2] > -0.9  # bottoms rest on the table
    return pts[seen][:n]


def _gaussians(means, rng, rgb, scale=0.0015, opacity=(0.5, 1.0)) -> dict:
    n = len(means)
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = rng.uniform(0.5, 1.0, (n, 3)) * scale
    s[:, 0] *= 0.2  # flat discs
    return dict(means=means, quats=q, scales=s, opacities=rng.uniform(*opacity, n),
                sh=np.repeat(rgb_to_sh0(np.asarray(rgb))[None, None], n, axis=0))


def synthetic_scene(n_total: int = 40000, seed: int = 0, artefacts: bool = True, obstacle: bool = False):
    """(Gaussians, labels [N], objects [(name, label, prompt)], gt meshes {name: mesh}).

    obstacle: add an unlabelled 4 x 4 x 20 cm post standing on the table (background, label 0)."""
    rng = np.random.default_rng(seed)
    meshes = scene_meshes()
    objects = [("box", 1, "blue box"), ("cube", 2, "yellow cube"), ("hammer", 3, "toy hammer")]
    colours = {"box": (0.1, 0.2, 0.8), "cube": (0.9, 0.8, 0.1), "hammer": (0.8, 0.2, 0.1)}
    parts, labels = [], []
    n_table = n_total // 2
    n_obj = (n_total - n_table) // 3
    table = np.stack([rng.uniform(-0.5, 0.5, n_table), rng.uniform(-0.4, 0.4, n_table), rng.normal(0, 0.0005, n_table)], 1)
    inside = np.zeros(n_table, bool)
    for m in meshes.values():  # no table points under objects
        inside |= m.contains(table + [0, 0, 0.001])
    table = table[~inside]
    parts.append(_gaussians(table, rng, (0.6, 0.5, 0.4)))
    labels.append(np.zeros(len(table), np.int32))
    for name, label, _ in objects:
        m = meshes[name]
        pts = _surface(m, n_obj, rng) + rng.normal(0, 0.0005, (n_obj, 3))
        parts.append(_gaussians(pts, rng, colours[name]))
        labels.append(np.full(len(pts), label, np.int32))
        if artefacts:
            k = n_obj // 10
            # haze: low opacity, up to 2 cm off the surface
            base = _surface(m, k, rng)
            haze = base + rng.normal(0, 0.01, (len(base), 3)) + [0, 0, 0.01]
            parts.append(_gaussians(haze, rng, colours[name], opacity=(0.01, 0.08)))
            labels.append(np.full(len(haze), label, np.int32))
            # needles touching the surface, sticking out
            nb = _surface(m, k // 2, rng)
            d = rng.standard_normal((len(nb), 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            g = _gaussians(nb + 0.02 * d, rng, colours[name])
            g["scales"][:, 2] = rng.uniform(0.02, 0.05, len(nb))
            g["scales"][:, 1] = g["scales"][:, 0] * 2
            parts.append(g)
            labels.append(np.full(len(nb), label, np.int32))
            # floaters: a detached opaque blob 6-10 cm above the object (mislabelled by segmentation)
            c = m.bounds.mean(axis=0) + [rng.uniform(-0.03, 0.03), 0, m.bounds[1, 2] - m.bounds.mean(axis=0)[2] + 0.08]
            fl = c + rng.normal(0, 0.006, (k // 2, 3))
            parts.append(_gaussians(fl, rng, colours[name]))
            labels.append(np.full(len(fl), label, np.int32))
    if obstacle:
        post = trimesh.creation.box([0.04, 0.04, 0.2])
        post.apply_translation([-0.35, 0.3, 0.1])
        pts = _surface(post, 3000, rng) + rng.normal(0, 0.0005, (3000, 3))
        parts.append(_gaussians(pts, rng, (0.3, 0.3, 0.3)))
        labels.append(np.zeros(len(pts), np.int32))
    if artefacts:  # background floaters and haze
        fl = np.array([0.0, 0.3, 0.25]) + rng.normal(0, 0.01, (300, 3))
        parts.append(_gaussians(fl, rng, (0.5, 0.5, 0.5)))
        labels.append(np.zeros(len(fl), np.int32))
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return Gaussians(**cat), np.concatenate(labels), objects, meshes


def leak_labels(g: Gaussians, labels: np.ndarray, boxes: dict, margin_xy: float = 0.03,
                margin_up: float = 0.08) -> np.ndarray:
    """Labels as a mask-lifting semantic stage gives them: background artefacts (label 0) inside an
    object's world box grown by `margin_xy` sideways and `margin_up` above (but above the table) take
    that object's label — haze, needles and floaters in front of an object fall inside its 2D masks.

    boxes: {label: (lo [3], hi [3])} world-frame bounds. Returns a new label array [N]."""
    out = np.asarray(labels).copy()
    p = g.means
    for label, (lo, hi) in boxes.items():
        m = ((out == 0) & np.all(p[:, :2] > np.asarray(lo)[:2] - margin_xy, axis=1)
             & np.all(p[:, :2] < np.asarray(hi)[:2] + margin_xy, axis=1)
             & (p[:, 2] > lo[2] + 0.003) & (p[:, 2] < hi[2] + margin_up))
        out[m] = label
    return out


def trained_like_gaussians(mesh: trimesh.Trimesh, n: int = 3000, seed: int = 0, inset_sigma: float = 1.5,
                           hidden_dir=(1.0, 0.0, 0.0), hidden_keep: float = 0.03, edge_fraction: float = 0.25,
                           haze_fraction: float = 0.05) -> Gaussians:
    """Gaussians on a GT mesh (world frame, resting on z = 0) with the artefacts of *trained* 3DGS,
    as measured on the demo twin (see bench/geometry.py --twin-from):

    - flat discs whose thin axis follows the surface normal (tangential std 2-5 mm, thin 0.7-1.5 mm),
      centres `inset_sigma` thin std devs *inside* the surface (the photometric loss sees only the front);
    - a side no camera saw head-on (normals within 60 deg of `hidden_dir`) keeps only `hidden_keep` of
      its splats, so the shell of centres is open there;
    - `edge_fraction` short elongated splats (largest / middle 6-9, largest <= 5 mm), as trained splats
      line edges with;
    - `haze_fraction` faint (alpha < 0.1), large splats 0.5-2 cm off the surface.
    The unseen bottom on the table gets none. Returns activated Gaussians (grey)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    pts, fid = trimesh.sample.sample_surface(mesh, 3 * n, seed=int(rng.integers(1 << 30)))
    nrm = mesh.face_normals[fid]
    seen = nrm[:, 2] > -0.9
    hidden = nrm @ np.asarray(hidden_dir, dtype=np.float64) > 0.5
    keep = seen & (~hidden | (rng.random(len(pts)) < hidden_keep))
    pts, nrm = pts[keep][:n], nrm[keep][:n]
    m = len(pts)
    a = rng.standard_normal((m, 3))
    t1 = a - (a * nrm).sum(1, keepdims=True) * nrm
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    R = np.stack([t1, np.cross(nrm, t1), nrm], axis=2)  # columns: tangent, tangent, normal
    tang = rng.uniform(0.002, 0.005, m)
    scales = np.stack([tang, tang * rng.uniform(0.6, 1.0, m), rng.uniform(0.0007, 0.0015, m)], axis=1)
    edge = rng.random(m) < edge_fraction
    scales[edge, 0] = rng.uniform(0.003, 0.005, edge.sum())
    scales[edge, 1] = scales[edge, 0] / rng.uniform(6.0, 9.0, edge.sum())
    scales[edge, 2] = np.minimum(scales[edge, 2], scales[edge, 1])
    means = pts - nrm * (inset_sigma * scales[:, 2])[:, None]
    opac = rng.uniform(0.7, 0.99, m)
    k = int(round(haze_fraction * m))
    hz = rng.integers(0, m, k)
    haze_means = pts[hz] + nrm[hz] * rng.uniform(0.005, 0.02, (k, 1))
    all_means = np.concatenate([means, haze_means])
    all_R = np.concatenate([R, Rotation.random(k, random_state=rng).as_matrix()])
    all_scales = np.concatenate([scales, rng.uniform(0.005, 0.015, (k, 3))])
    all_opac = np.concatenate([opac, rng.uniform(0.01, 0.08, k)])
    quats = quat_wxyz_from_matrix(all_R, canonical=False)
    sh = np.repeat(rgb_to_sh0(np.array([0.5, 0.5, 0.5]))[None, None], len(all_means), axis=0)
    return Gaussians(means=all_means, quats=quats, scales=all_scales, opacities=all_opac, sh=sh)


# -- semantics: the analytic tabletop ---------------------------------------------------------
TABLE = (-0.3, 0.3, -0.25, 0.25)
BOXES = {1: (np.array([0.08, 0.05, 0.05]), np.array([0.05, 0.04, 0.05])),
         2: (np.array([-0.12, -0.08, 0.03]), np.array([0.03, 0.03, 0.03]))}
NAMES = {1: "blue_box", 2: "yellow_cube"}


@dataclass
class Synth:
    means: np.ndarray      # [N,3]
    gt: np.ndarray         # [N] labels (0 background, floaters 0)
    floater: np.ndarray    # [N] bool
    views: list[View]
    gt_maps: list[np.ndarray]
    masks: MaskSet


def _sample_box(rng, c, h, n):
    pts = []
    faces = [(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]
    areas = np.array([4 * np.prod(np.delete(h, ax)) for ax, _ in faces])
    counts = rng.multinomial(n, areas / areas.sum())
    for (ax, s), k in zip(faces, counts):
        p = rng.uniform(-h, h, size=(k, 3))
        p[:, ax] = s * h[ax]
        pts.append(c + p)
    return np.concatenate(pts)


def raycast_labels(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Exact label [H,W] and z-depth [H,W] of the analytic scene (no floaters)."""
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
    R, o = cam.T_world_cam[:3, :3], cam.T_world_cam[:3, 3]
    d = d_cam @ R.T  # world direction with unit camera z
    t_best = np.full(len(d), np.inf)
    lab = np.zeros(len(d), dtype=np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[:, 2]
        p = o + t[:, None] * d
        ok = (t > 0) & (p[:, 0] >= TABLE[0]) & (p[:, 0] <= TABLE[1]) & (p[:, 1] >= TABLE[2]) & (p[:, 1] <= TABLE[3])
        t_best[ok] = t[ok]
        for k, (c, h) in BOXES.items():
            t1, t2 = (c - h - o) / d, (c + h - o) / d
            tn = np.nanmax(np.minimum(t1, t2), axis=1)
            tf = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tn <= tf) & (tn > 0) & (tn < t_best)
            t_best[hit] = tn[hit]
            lab[hit] = k
    return lab.reshape(cam.height, cam.width), t_best.reshape(cam.height, cam.width)


def make_synth(n_views: int = 10, width: int = 128, height: int = 96, n_table: int = 12000, n_box: int = 4000,
               bleed: int = 3, seed: int = 0) -> Synth:
    rng = np.random.default_rng(seed)
    table = np.stack([rng.uniform(TABLE[0], TABLE[1], n_table), rng.uniform(TABLE[2], TABLE[3], n_table),
                      np.zeros(n_table)], 1)
    inside_any = np.zeros(n_table, dtype=bool)
    for c, h in BOXES.values():
        inside_any |= np.all(np.abs(table[:, :2] - c[:2]) < h[:2], axis=1)
    table = table[~inside_any]
    parts, gts = [table], [np.zeros(len(table), np.int32)]
    for k, (c, h) in BOXES.items():
        p = _sample_box(rng, c, h, n_box if k == 1 else n_box // 2)
        parts.append(p)
        gts.append(np.full(len(p), k, np.int32))
    # ghost floaters hovering 10 cm above box 1 (detached in depth from its surface)
    c1 = BOXES[1][0]
    fl = c1 + np.array([0.0, 0.0, 0.11]) + rng.normal(scale=0.008, size=(150, 3))
    parts.append(fl)
    gts.append(np.zeros(len(fl), np.int32))
    means = np.concatenate(parts) + rng.normal(scale=0.001, size=(sum(len(p) for p in parts), 3))
    gt = np.concatenate(gts)
    floater = np.zeros(len(means), bool)
    floater[-len(fl):] = True
    views, gt_maps = [], []
    ms = MaskSet(objects=dict(NAMES), source="synth")
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = np.array([0.55 * np.cos(a), 0.55 * np.sin(a), 0.40 + 0.05 * (i % 2)])
        cam = Camera.from_fov(np.deg2rad(60), width, height, look_at(eye, np.array([0.0, 0.0, 0.03])), name=f"v{i:03d}")
        views.append(View(cam.name, cam))
        lab, _ = raycast_labels(cam)
        gt_maps.append(lab)
        ms.sizes[cam.name] = (height, width)
        for k in NAMES:
            m = ndimage.binary_dilation(lab == k, iterations=bleed)
            if i % 4 == 0:  # a false blob on the table next to the object
                ys, xs = np.nonzero(lab == k)
                if ys.size:
                    yy, xx = np.mgrid[:height, :width]
                    m |= (yy - ys.max()) ** 2 + (xx - xs.mean()) ** 2 < 16
            if m.any():
                ms.add(cam.name, k, m, 0.9)
    return Synth(means=means, gt=gt, floater=floater, views=views, gt_maps=gt_maps, masks=ms)


# -- embedded scene ---------------------------------------------------------------------------
def scene_gaussians(scene_dir: Path, n: int | None = None, seed: int = 0):
    """(Gaussians, labels_gt [N]) for a generated scene: `splattwin.scene.gaussians.synthetic_gaussians` (GT
    surfaces with realistic artefacts) scaled to about `n` Gaussians."""
    from splattwin.scene.gaussians import synthetic_gaussians

    if n is None:
        return synthetic_gaussians(scene_dir, seed=seed)
    # the surface count scales with the density; keep the artefact count of the default density (a denser
    # reconstruction is not hazier), so the artefact fraction shrinks as n grows
    _, lab0 = synthetic_gaussians(scene_dir, seed=seed, artefacts=False)
    _, lab1 = synthetic_gaussians(scene_dir, seed=seed, density=4000.0, artefacts=False)
    n0 = len(lab0)
    d = 40000.0 * n / n0 if len(lab1) >= n0 else 4000.0 + (40000.0 - 4000.0) * (n - len(lab1)) / max(n0 - len(lab1), 1)
    frac = 0.08 * min(1.0, n0 / max(n, 1))
    return synthetic_gaussians(scene_dir, seed=seed, density=max(d, 1000.0), artefact_fraction=frac)
