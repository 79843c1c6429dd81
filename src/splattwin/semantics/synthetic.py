"""Synthetic data with a known answer for the semantics stage (tests, benchmarks, demos).

`make_synth`: a tiny analytic tabletop: a table plane, two boxes, a floater blob.

Ground truth comes from exact ray casting (plane + slab tests), independent of the code under test.
Noisy masks: GT dilated by `bleed` pixels (the SAM "bleeding effect") plus a false blob on the table.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from splattwin.capture.camera import Camera, look_at
from splattwin.semantics.fusion import View
from splattwin.semantics.masks import MaskSet
from splattwin.transforms import quat_wxyz_z_to

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
# Gaussians for the embedded scene: `splattwin.scene.synthetic_gaussians` when it exists, else a local
# stand-in sampled on the scene's GT meshes (area-uniform, 1 mm jitter) plus ghost floaters hovering
# 4-8 cm above each object (the artefacts the fusion must reject). Returns (Gaussians, labels_gt [N]).

def scene_gaussians(scene_dir: Path, n: int | None = None, seed: int = 0):
    """(Gaussians, labels_gt) for a generated scene: `splattwin.scene.synthetic_gaussians` (GT surfaces
    with realistic artefacts) scaled to about `n` Gaussians, or the local stand-in when that is missing."""
    try:
        from splattwin.scene import synthetic_gaussians
    except ImportError:
        return sample_scene_gaussians(scene_dir, n or 60000, seed)
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


def sample_scene_gaussians(scene_dir: Path, n: int = 60000, seed: int = 0, floaters: int = 60):
    """Stand-in for `splattwin.scene.synthetic_gaussians`: Gaussians on the GT meshes of a generated scene.

    About half the points on the table, the rest on the objects by area. Gaussians are flat discs in
    the surface (scales s, s, s/5 with s = 0.7 x the local point spacing, so the splats cover the
    surface like a trained model), opacity 0.9, colour = object id hue. Plus a ghost floater blob of
    `floaters` points 4-8 cm above each object. Returns (Gaussians, labels_gt [N] int32).
    """
    import trimesh

    from splattwin.splat.gaussians import Gaussians, rgb_to_sh0

    scene_dir = Path(scene_dir)
    meta = json.loads((scene_dir / "scene.json").read_text())
    rng = np.random.default_rng(seed)
    from splattwin.meshio import load_mesh
    from splattwin.paths import confined

    where = scene_dir / "scene.json"
    parts = [("table", 0, load_mesh(confined(scene_dir, meta["table"]["mesh"], where), process=True))]
    parts += [(o["name"], int(o["label"]), load_mesh(confined(scene_dir, o["mesh"], where), process=True))
              for o in meta["objects"]]
    obj_area = np.array([m.area for _, _, m in parts[1:]])
    counts = [n // 2] + list(np.maximum((n // 2) * obj_area / obj_area.sum(), 200).astype(int))
    pts, nrm, scl, labs = [], [], [], []
    for (name, lab, mesh), c in zip(parts, counts):
        p, fi = trimesh.sample.sample_surface(mesh, int(c), seed=int(rng.integers(1 << 31)))
        pts.append(np.asarray(p))
        nrm.append(np.asarray(mesh.face_normals[fi]))
        scl.append(np.full(len(p), 0.7 * np.sqrt(mesh.area / max(int(c), 1))))
        labs.append(np.full(len(p), lab, np.int32))
    for (name, lab, mesh) in parts[1:]:  # floaters: small detached blobs above each object
        c = mesh.bounds.mean(axis=0)
        c[2] = mesh.bounds[1, 2] + rng.uniform(0.04, 0.08)
        blob = c + rng.normal(scale=0.006, size=(floaters, 3))
        pts.append(blob)
        nrm.append(np.tile([0.0, 0.0, 1.0], (floaters, 1)))
        scl.append(np.full(floaters, 0.003))
        labs.append(np.zeros(floaters, np.int32))
    means = np.concatenate(pts) + rng.normal(scale=0.0005, size=(sum(len(p) for p in pts), 3))
    normals = np.concatenate(nrm)
    s = np.concatenate(scl)
    labels = np.concatenate(labs)
    N = len(means)
    quats = quat_wxyz_z_to(normals)
    hue = np.array([[0.6, 0.6, 0.6], [0.6, 0.45, 0.3], [0.2, 0.3, 0.8], [0.9, 0.8, 0.1], [0.8, 0.2, 0.2], [0.3, 0.7, 0.4]])
    rgb = hue[np.minimum(labels, len(hue) - 1)]
    g = Gaussians(means=means, quats=quats, scales=np.stack([s, s, 0.2 * s], 1), opacities=np.full(N, 0.9),
                  sh=rgb_to_sh0(rgb)[:, None, :])
    return g, labels
