"""What limits psnr_final_objects (bench/photoreal.py)? Upper bounds and controls on the moved objects' pixels.

On the demo twin and the rollout that bench/photoreal.py recorded (its --out holds rollout.npz), the final
arrangement from every held-out camera, PSNR over the moved objects' pixels (ground-truth labels of the
final arrangement), each figure the mean over the views:

fused_relit     the twin as trained (`DynamicScene.load(view_fade=False)`: splats.ply + labels + bbox
                carry, SH as trained), re-lit under the light estimated from its shadows (`playback.relight`),
                against the ray-cast ground truth of the moved objects
unlit_relit     the same without re-lighting (every splat its trained colour)
oracle_relit    membership: the moving sets replaced by every Gaussian whose centre lies within
                ORACLE_MARGIN of the ground-truth object's surface at its start pose (or inside it),
                above the table plane
fused_baked     shading: the twin without re-lighting against a ground truth that does NOT re-light the moved
                objects (their hits shaded as at the start pose in the start arrangement: the capture's n.l
                and cast shadows carried along), i.e. what a perfect splat that cannot re-light would show
sh_dc_relit     view dependence: the moved objects drawn with their SH degree-0 colour only (what
                `DynamicScene.view_fade`, the default, does to an object that moved > VIEW_FADE_M)
photo_gt_geom   an image-based bound with no splat at all: each object pixel takes the colour of the
                training photos at the EXACT (ground-truth) surface point at its start pose (visible
                views, weighted by their sampling density), i.e. what the photos hold about that point
photo_twin_mesh the same through the twin's own visual meshes instead of the exact geometry
blur_1.5x       the ground truth itself area-downsampled 1.5x and upsampled back: how much any blur of
                this size costs on these textures
inner / ring    fused_relit split into the object pixels one pixel inside the outline and the outline ring
<obj>_same_view the twin in its START arrangement seen from the held-out camera moved by the inverse of
                the object's motion (the object seen exactly as the final view sees it, nothing moved,
                backdrop not drawn) against the start ground truth: the splat's own quality from that
                direction
<obj>_train_fit the twin at start against its own TRAINING photos over the object's pixels

Measured (Nov 2026, demo twin of seed 0, its three-step task; 2 shared cores), means over the 5 views:
fused_relit 20.49, oracle_relit 20.44 (membership is not it: the fused sets hold 451 of the oracle's 455
blue-box Gaussians), fused_baked 20.72 (re-lighting: 0.2 dB), sh_dc_relit 20.99 (+0.5), photo_gt_geom
24.28, photo_twin_mesh 19.33, blur_1.5x 20.67, inner 20.84 / ring 18.54 (the outline is ~12 % of the
pixels and ~20 % of the error), same_view blue box 19.2 / yellow cube 26.3 / hammer 26.6, train_fit
26.2 / 31.1 / 30.4. Reading: the splats of the moved objects are blurred (the blue box fits its own
training photos to only 26 dB) and lose more from the directions and distances the final arrangement is
seen from; a blur of 1.5 px on these textures alone costs as much. The photos hold enough
(24.3 dB through the exact geometry) but not through the twin's geometry (19.3 dB through its meshes).
Rebuilding the twin's splats with 2x the Gaussians (56k) gave 20.80, 6000 iterations 20.87, the depth
loss (depth_lambda 0.1) +0.04 dB (21.03 vs 20.99, both with the SH fade): none comes near 24.
Since then (#19): training antialiased 21.03 (whole final image 27.79 -> 28.51, held-out start 32.01 ->
34.10); plus the object refinement (`splattwin.playback.refine`: the objects' Gaussians trained again with
the rest frozen, split on their own 4x budget) 21.66-21.71, the blue box's training-photo fit 27.3 -> 30.0
(classic) but after the task only 19.1 -> 19.8: one of its faces, which two final views see at cos
0.72-0.74, no training view saw at more than cos 0.45 (the box crossed the table: its far side now faces them).
This bench on that demo twin (antialiased + refined, its own rollout): fused_relit 21.42, oracle_relit 21.28,
fused_baked 21.94, sh_dc_relit 21.71 (= psnr_final_objects), photo_gt_geom 24.48, photo_twin_mesh 20.22,
blur_1.5x 20.65, inner 21.99 / ring 18.97, same_view 22.38 / 28.79 / 29.38, train_fit 29.15 / 35.73 / 33.73.
What is left to 24 dB: the image-based bound itself is 24.5; re-lighting (new cast shadows, e.g. the cube's
on the box) ~0.5 dB; the outline ring 3 dB below the inside; the blue box 2.9 dB below its own same_view
(19.49 relit in the arrangement vs 22.38 from the same relative view at the start).
With the refinement's silhouette loss (fresh demo twin, its own rollout): fused_relit 22.36, oracle 22.22,
fused_baked 23.10, sh_dc_relit 22.37 (= psnr_final_objects), photo_gt_geom 24.48, inner 22.78 / ring 20.47
(the ring +1.5 dB), same_view 22.24 / 28.64 / 29.13, train_fit 29.10 / 33.80 / 33.53. Left to 24 dB:
re-lighting 0.74 dB (fused_baked - fused_relit), the ring 2.3 dB below the inside, the blue box 1.8 dB below
its own same_view.
Re-lit (`playback.relight`, fresh demo twin, its own rollout): fused_relit 23.56 (unlit_relit 22.24,
fused_baked 22.99), photo_gt_geom 24.30, inner 23.75 / ring 22.62; blue box 21.57 vs its same_view 22.15,
yellow cube 25.18 / 28.15, hammer 28.06 / 28.98. Left to 24 dB: the blue box (62-87 % of the error).
With the antialiased low-pass at Mip-Splatting's 0.1 px^2 instead of 0.3 (`splat.rasterize.DEFAULT_EPS2D`;
fresh demo twin, its own rollout): fused_relit 25.18 (unlit_relit 23.53, fused_baked 24.47), oracle 25.21,
photo_gt_geom 24.74 (the twin is now above the image-based bound), inner 25.48 / ring 23.68; blue box 23.25
vs its same_view 24.66, yellow cube 24.96 / 30.53, hammer 30.09 / 31.37; train_fit 35.0 / 36.5 / 39.0 (the
0.3 low-pass had blurred every Gaussian wider than the box-filtered pixel, which capped the print's fit).

Pictures: bounds_<view>.png = GT relit | GT baked | twin (fused) | photos on the exact geometry.
LAST line one JSON object.

    python bench/objects_bounds.py --twin /tmp/splattwin_demo_twin --rollout /tmp/splattwin_photoreal_bench/rollout.npz
"""

from __future__ import annotations

import splattwin.runtime

splattwin.runtime.configure()

import argparse  # noqa: E402
import copy  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from photoreal import gt_renderer, masked_psnr  # noqa: E402

ORACLE_MARGIN = 0.004      # m: oracle membership, distance to the ground-truth surface
VIS_TOL_EXACT = 0.004      # m: a training view sees a point when its first hit lies this close to it
VIS_TOL_MESH = 0.012       # m: the same through the twin's meshes (alpha shapes are a few mm off)
VIEW_WEIGHT_POWER = 8.0    # photo blending weight (sqrt(cos) * f / z) ** power: ~ the best-sampling view


def baked_render(r_final, r_start, motions_idx: dict[int, np.ndarray], camera, s: int = 5) -> np.ndarray:
    """Final arrangement, moved objects shaded as at their start pose in the start arrangement.

    r_final / r_start: `SceneRenderer`s over the same surface list (same geometry ids); motions_idx:
    {surface index: T_new_old (world)}. -> rgb [H,W,3], supersampled s x s as the ground truth"""
    from splattwin.scene import textures as tx
    from splattwin.scene.raycast import _MISS

    H, W = camera.height, camera.width
    rays = r_final.camera_rays(camera, s).reshape(-1, 6)
    ans = r_final.cast(rays)
    gid, t = ans["gid"].reshape(-1), ans["t"].reshape(-1)
    hit = gid != _MISS
    d = rays[:, 3:] / np.linalg.norm(rays[:, 3:], axis=1, keepdims=True)
    rgb = np.empty((len(rays), 3), np.float32)
    rgb[~hit] = tx.background_rgb(d[~hit])
    pts = rays[:, :3] + rays[:, 3:] * np.where(hit, t, 0)[:, None]
    nrm = ans["normal"].reshape(-1, 3)
    sidx = np.full(len(gid), -1)
    for g, i in r_final.gid_to_index.items():
        sidx[gid == g] = i
    moved = np.isin(sidx, list(motions_idx))
    rest = hit & ~moved
    rgb[rest] = r_final.colour_hits(pts[rest], nrm[rest], gid[rest], d[rest])
    for i, M in motions_idx.items():
        sel = sidx == i
        if sel.any():
            Minv = np.linalg.inv(M)
            R, tt = Minv[:3, :3].astype(np.float32), Minv[:3, 3].astype(np.float32)
            rgb[sel] = r_start.colour_hits(pts[sel] @ R.T + tt, nrm[sel] @ R.T, gid[sel], d[sel] @ R.T)
    return rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3))


def _raycaster(meshes: dict[str, "trimesh.Trimesh"]):
    """Open3D scene over world-frame meshes. -> (scene, {geometry id: name})"""
    import open3d as o3d

    sc = o3d.t.geometry.RaycastingScene()
    ids = {}
    for n, m in meshes.items():
        g = sc.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                             o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
        ids[int(g)] = n
    return sc, ids


def oracle_members(full_means: np.ndarray, meshes_world: dict, h: float, margin: float = ORACLE_MARGIN
                   ) -> dict[str, np.ndarray]:
    """{name: indices of Gaussians within `margin` of (or inside) the object's surface, above the table}
    (nearest object wins)."""
    import open3d as o3d

    q = o3d.core.Tensor(full_means.astype(np.float32))
    names, D = list(meshes_world), []
    for n in names:
        sc, _ = _raycaster({n: meshes_world[n]})
        inside = sc.compute_occupancy(q, nsamples=3).numpy() > 0.5
        D.append(np.where(inside, 0.0, sc.compute_distance(q).numpy()))
    D = np.stack(D, 1)
    best = D.argmin(1)
    ok = (D.min(1) <= margin) & (full_means[:, 2] > h + 0.001)
    return {n: np.flatnonzero(ok & (best == i)) for i, n in enumerate(names)}


def oracle_scene(twin: Path, members: dict[str, np.ndarray], base):
    """A `DynamicScene` like `base` whose objects are the given Gaussian sets (indices into the full splats)."""
    from splattwin.playback.scene import DynamicScene, _off_table
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.manifest import Manifest
    from splattwin.twin.splats import transform_gaussians

    man = Manifest.load(twin)
    full = Gaussians.load_ply(twin / man.splats)
    keep = np.ones(len(full), bool)
    objects = {}
    for n, idx in members.items():
        objects[n] = transform_gaussians(full.subset(idx), np.linalg.inv(base.T_world_obj0[n]))
        keep[idx] = False
    h = base.table_height
    back = keep & _off_table(full.means, man.background.table_extent, h)
    front = keep & ~back
    sc = DynamicScene(background=full.subset(front), objects=objects, T_world_obj0=dict(base.T_world_obj0),
                      residue={}, table_height=h, twin_dir=twin, backdrop=full.subset(back), view_fade=base.view_fade,
                      rasterize_mode=base.rasterize_mode, eps2d=base.eps2d, meshes=base.meshes, light=base.light, unit=base.unit)
    sc.fill_holes()
    return sc


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """img [H,W,3] at pixel coordinates uv [N,2] (pixel centres at +0.5) -> [N,3]"""
    H, W = img.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, W - 1.001)
    y = np.clip(uv[:, 1] - 0.5, 0, H - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
            + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)


def photo_colour(p_world: np.ndarray, n_world: np.ndarray, cams, photos, occluders, tol: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Colour of surface points [N,3] (normals [N,3], towards the viewer) from the photos that see them
    (first hit of the ray through `occluders` within `tol` of the point), weighted by sampling density.
    -> (rgb [N,3], seen [N] bool)"""
    import open3d as o3d

    num, den = np.zeros((len(p_world), 3)), np.zeros(len(p_world))
    for c, img in zip(cams, photos):
        C = c.T_world_cam[:3, 3]
        v = p_world - C
        d = np.linalg.norm(v, axis=1)
        v /= d[:, None]
        pc = p_world @ c.T_cam_world[:3, :3].T + c.T_cam_world[:3, 3]
        uvw = pc @ c.K.T
        uv = uvw[:, :2] / np.maximum(uvw[:, 2:], 1e-9)
        ok = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        rays = np.concatenate([np.repeat(C[None], len(p_world), 0), v], 1).astype(np.float32)
        ok &= np.abs(occluders.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() - d) < tol
        cos = np.clip(-np.einsum("ij,ij->i", v, n_world), 0, 1)
        ok &= cos > 0.05
        w = np.where(ok, (np.sqrt(cos) * c.K[0, 0] / np.maximum(pc[:, 2], 1e-6)) ** VIEW_WEIGHT_POWER, 0)
        num += w[:, None] * _bilinear(img, uv)
        den += w
    return num / np.maximum(den, 1e-300)[:, None], den > 0


def photo_render(base_rgb: np.ndarray, camera, hits, moved_of: dict[str, np.ndarray], motions, cams, photos,
                 occluders0, tol: float) -> np.ndarray:
    """base_rgb with the moved objects' pixels (centre rays) replaced by `photo_colour` of their surface
    point mapped back to the start pose. hits: rays [HW,6], t [HW], normal [HW,3]; moved_of: {name: [HW] bool}."""
    rays, t, nrm = hits
    img = base_rgb.reshape(-1, 3).copy()
    for n, sel in moved_of.items():
        if not sel.any():
            continue
        p = rays[sel, :3] + rays[sel, 3:] * t[sel, None]
        nn = nrm[sel]
        nn = np.where((np.einsum("ij,ij->i", nn, rays[sel, 3:]) > 0)[:, None], -nn, nn)
        Mi = np.linalg.inv(motions[n])
        col, seen = photo_colour(p @ Mi[:3, :3].T + Mi[:3, 3], nn @ Mi[:3, :3].T, cams, photos, occluders0, tol)
        img[np.flatnonzero(sel)[seen]] = col[seen]
    return img.reshape(base_rgb.shape)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--twin", type=Path, default=Path("/tmp/splattwin_demo_twin"))
    ap.add_argument("--rollout", type=Path, default=Path("/tmp/splattwin_photoreal_bench/rollout.npz"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/splattwin_objects_bounds"))
    ap.add_argument("--margin", type=float, default=ORACLE_MARGIN, help="oracle membership margin (m)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    import open3d as o3d
    import torch
    import trimesh
    from PIL import Image
    from scipy import ndimage

    from splattwin import io
    from splattwin.capture.dataset import load_image
    from splattwin.playback.cameras import capture_cameras
    from splattwin.playback.compositor import PlaybackRenderer
    from splattwin.playback.scene import DynamicScene
    from splattwin.robot.rollout import Rollout
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.manifest import Manifest

    twin = args.twin
    man = Manifest.load(twin)
    ro = Rollout.load(args.rollout)
    final = {n: T[-1] for n, T in ro.object_poses.items()}
    scene = DynamicScene.load(twin, view_fade=False)   # the splats as trained; sh_dc_relit is the fade's effect
    moved = scene.moved(final)
    motions = {n: final[n] @ np.linalg.inv(man.object(n).pose) for n in moved}
    r_final, labels_of, _ = gt_renderer(twin / "scene", motions)
    r_start, _, _ = gt_renderer(twin / "scene", {})
    idx_of = {s.name: i for i, s in enumerate(r_final.surfaces)}
    motions_idx = {idx_of[n]: M for n, M in motions.items()}
    gid_of = {r_final.surfaces[i].name: g for g, i in r_final.gid_to_index.items()}

    # membership: oracle sets from the exact geometry at the start pose
    meshes0 = {s.name: s.mesh_world for s in r_start.surfaces[1:] if s.name in scene.objects}
    full = Gaussians.load_ply(twin / man.splats)
    members = oracle_members(full.means, meshes0, scene.table_height, args.margin)
    counts = {n: {"fused": len(scene.objects[n]), "oracle": len(members[n])} for n in scene.objects}
    r_fused, r_oracle = PlaybackRenderer(scene), PlaybackRenderer(oracle_scene(twin, members, scene))
    r_unlit = PlaybackRenderer(scene, relight=False)
    dc = copy.copy(scene)
    dc.objects = {n: (Gaussians(g.means, g.quats, g.scales, g.opacities,
                                np.concatenate([g.sh[:, :1], np.zeros_like(g.sh[:, 1:])], 1)) if n in moved else g)
                  for n, g in scene.objects.items()}
    r_dc = PlaybackRenderer(dc)
    nb = copy.copy(scene)
    nb.backdrop = None   # a camera moved by an object's inverse motion can stand among the surroundings
    r_nobackdrop = PlaybackRenderer(nb)

    # image-based bound: photos, exact geometry and the twin's meshes (with a table plane) at the start
    cams = {c.name: c for c in capture_cameras(twin)}
    held = [n for n in cams if n.startswith("heldout")]
    train = [cams[n] for n in cams if n.startswith("train")]
    photos = [load_image(twin / "scene" / "images" / f"{c.name}.png") for c in train]
    h = scene.table_height
    plane = trimesh.Trimesh([[-3, -3, h], [3, -3, h], [3, 3, h], [-3, 3, h]], [[0, 1, 2], [0, 2, 3]])

    def twin_meshes(poses):
        out = {"table": plane}
        for o in man.objects:
            if o.visual_mesh:
                m = trimesh.load(twin / o.visual_mesh, process=False, force="mesh")
                m.apply_transform(np.asarray(poses.get(o.name, o.pose)))
                out[o.name] = m
        return out

    occ_exact0, _ = _raycaster({s.name: s.mesh_world for s in r_start.surfaces})
    occ_twin0, _ = _raycaster(twin_meshes({}))
    twin_final, twin_ids = _raycaster(twin_meshes(final))

    rows = []
    u8 = lambda a: (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    for name in held:
        cam = cams[name]
        ref = r_final.render(cam)
        mask = np.isin(ref["labels"], [labels_of[n] for n in moved])
        baked = baked_render(r_final, r_start, motions_idx, cam)
        tf = r_fused.render(cam, final).rgb
        tu = r_unlit.render(cam, final).rgb
        rays = r_final.camera_rays(cam, 1).reshape(-1, 6)
        a = r_final.cast(rays)
        exact = photo_render(tf, cam, (rays, a["t"].reshape(-1), a["normal"].reshape(-1, 3)),
                             {n: a["gid"].reshape(-1) == gid_of[n] for n in moved}, motions, train, photos,
                             occ_exact0, VIS_TOL_EXACT)
        b = twin_final.cast_rays(o3d.core.Tensor(rays))
        tg = b["geometry_ids"].numpy().reshape(-1)
        mesh = photo_render(tf, cam, (rays, b["t_hit"].numpy().reshape(-1), b["primitive_normals"].numpy().reshape(-1, 3)),
                            {n: tg == g for g, n in twin_ids.items() if n in moved}, motions, train, photos,
                            occ_twin0, VIS_TOL_MESH)
        g = torch.from_numpy(ref["rgb"]).permute(2, 0, 1)[None]
        blur = torch.nn.functional.interpolate(torch.nn.functional.interpolate(g, scale_factor=1 / 1.5, mode="area"),
                                               size=g.shape[-2:], mode="bilinear", align_corners=False)
        inner = ndimage.binary_erosion(mask, iterations=1)
        row = {"view": name, "px": int(mask.sum()),
               "fused_relit": masked_psnr(tf, ref["rgb"], mask),
               "oracle_relit": masked_psnr(r_oracle.render(cam, final).rgb, ref["rgb"], mask),
               "fused_baked": masked_psnr(tu, baked, mask),
               "unlit_relit": masked_psnr(tu, ref["rgb"], mask),
               "sh_dc_relit": masked_psnr(r_dc.render(cam, final).rgb, ref["rgb"], mask),
               "photo_gt_geom": masked_psnr(exact, ref["rgb"], mask),
               "photo_twin_mesh": masked_psnr(mesh, ref["rgb"], mask),
               "blur_1.5x": masked_psnr(blur[0].permute(1, 2, 0).numpy(), ref["rgb"], mask),
               "inner": masked_psnr(tf, ref["rgb"], inner), "ring": masked_psnr(tf, ref["rgb"], mask & ~inner),
               "baked_vs_relit": masked_psnr(baked, ref["rgb"], mask)}
        for n in moved:
            m = ref["labels"] == labels_of[n]
            row[f"{n}_relit"] = masked_psnr(tf, ref["rgb"], m)
            vc = dataclasses.replace(cam, T_world_cam=np.linalg.inv(motions[n]) @ cam.T_world_cam)
            g0 = r_start.render(vc)
            row[f"{n}_same_view"] = masked_psnr(r_nobackdrop.render(vc, {}).rgb, g0["rgb"], g0["labels"] == labels_of[n])
        rows.append(row)
        gap = np.full((cam.height, 4, 3), 255, np.uint8)
        io.write_image(args.out / f"bounds_{name}.png",
                       np.concatenate([u8(ref["rgb"]), gap, u8(baked), gap, u8(tf), gap, u8(exact)], axis=1))
        print(json.dumps({k: (round(v, 2) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)

    fit: dict[str, list[float]] = {n: [] for n in moved}
    for c, photo in zip(train, photos):
        lab0 = np.asarray(Image.open(twin / "scene" / "masks" / "gt" / f"{c.name}.png"))
        img = r_fused.render(c, {}).rgb
        for n in moved:
            if (lab0 == labels_of[n]).sum() >= 20:
                fit[n].append(masked_psnr(img, photo, lab0 == labels_of[n]))
    keys = [k for k in rows[0] if k not in ("view", "px")]
    out = {k: round(float(np.nanmean([r[k] for r in rows])), 3) for k in keys}
    out.update({f"{n}_train_fit": round(float(np.mean(v)), 3) for n, v in fit.items() if v})
    out["gaussians"] = counts
    io.write_json(args.out / "bounds.json", {**out, "views": rows})
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
