"""Object-focused refinement of a twin's splats: a short extra training phase on the labelled objects only.

Why: the 3DGS run spends its Gaussian budget where the photometric gradient is, mostly on the table and
the surroundings; a small, finely printed object ends up with a few hundred Gaussians that blur its
print (demo twin: the blue box fits its own training photos to 26 dB, the others to 30-31). Once the
robot moves it, the blur is seen from new distances and directions (bench/objects_bounds.py).

What: every object Gaussian the playback moves (`DynamicScene.load`: the object's splats.ply plus what it
carries) is trained again on the training photos with the rest of the scene frozen, rendered in one
depth-sorted pass as the splat stage trained it: only the objects' parameters get gradients, so every
step's loss works on them. Densification (3DGS clone/split, `splat.densify`) runs on the objects alone
with a lower gradient threshold and its own budget (`RefineOptions.max_factor` times the object's
count), so the extra Gaussians go where the object's print is under-reconstructed; selected Gaussians
larger than `split_scale` (1.5 mm) split, since the splat stage's rule (1 % of the scene scale, ~7 mm)
would clone nearly every object Gaussian onto itself, which adds no resolution (measured: 1500 steps of
clones gave +0.12 dB on the moved objects, splits +0.27). `dc_only` trains the objects' degree-0 colour
alone (a moved object is drawn with it: `playback.scene`'s view fade); it measured no better (21.24 vs
21.26 dB), so it is off.

Measured (bench/photoreal.py, demo twin of seed 0, moved objects' PSNR after the three-step task, the
same rollout): classic splats 20.99 -> 21.26 dB (1500 steps); antialiased splats 21.03 -> 21.66 dB (800 or
1500 steps; an 8x budget 21.64), the whole final image 28.51 -> 28.55, the held-out start views 34.10 ->
34.38. What it does not fix: the blue box stays near 19.8 dB after the task (vs ~26 from the held-out
views at the start): one of its faces, which two final views see at cos 0.72-0.74, no training view saw
at more than cos 0.45 (bench/objects_bounds.py has the bounds).

Silhouette loss (`RefineOptions.mask_lambda`, on by default): the outline of a moved object is where its
error is worst (a 1-px ring 3 dB below the inside): Gaussians of the table around the footprint or half
transparent skirts were fused into the object and travel with it. Each step renders, in the same depth-sorted
pass as the colours, one coverage channel per object (its Gaussians' accumulated weight, occlusion by the
rest included) and adds the area-normalised L1 to the object's 2D mask of that view (the semantics
stage's: user masks, Grounded-SAM's, or the embedded scene's simulated noisy segmenter). Masks are noisy
(detector IoU 0.4-0.6 on small objects, false detections): a mask joins only if its IoU with the object as
the twin renders it before refinement is >= `mask_min_iou` (0.7: 52 of the demo's 70 masks). Measured on
the demo twin (moved objects after the task, mean over 5 held-out views; control 21.61): weight 0.005 /
0.01 / 0.03 -> 22.20 / 22.27 / 22.07 with the filtered noisy masks; 0.03 unfiltered 21.60 (the yellow cube
fell 23.0 -> 19.3 on the false detections); 0.03 with exact masks 22.32 (exact masks are a bound: BOP
`mask_visib` files are that good).

Output, in the twin folder: refined/point_cloud.ply (background as before + the refined objects, in the
twin frame), refined/labels.npy, and each refined object's splats.ply rewritten (object frame); twin.json's
`splats` / `labels` point to the refined files, so the playback, viewer and exports use them. The splat
stage's own output is left untouched.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.playback.options import RefineOptions

log = logging.getLogger(__name__)

REFINED_DIR = "refined"


def _object_sets(twin_dir: Path):
    """(DynamicScene without fills, manifest, {name: world-frame Gaussians the playback moves at its twin
    pose}, {name: label})."""
    from splattwin.playback.scene import DynamicScene
    from splattwin.twin.manifest import Manifest
    from splattwin.twin.splats import transform_gaussians

    scene = DynamicScene.load(twin_dir, fill_holes=False, relight=False)
    man = Manifest.load(twin_dir)
    world = {n: transform_gaussians(g, scene.T_world_obj0[n]) for n, g in scene.objects.items()}
    label_of = {o.name: int(o.label) for o in man.objects if o.name in scene.objects}
    return scene, man, world, label_of


def refine_objects(twin_dir: str | Path, frames, opts: RefineOptions | None = None, resolution: int = 0,
                   cpu_max_side: int = 640, progress: bool = False, masks=None) -> dict:
    """Refine the twin's object Gaussians on the training `frames` (capture `Frame`s with poses, in the twin
    frame); writes the refined splats into the twin (module docstring). masks: the semantics stage's
    `MaskSet` (labels as the twin's objects), used by the silhouette loss (`opts.mask_lambda`).
    -> statistics dict."""
    import torch

    from splattwin.io import write_json
    from splattwin.playback.scene import concat
    from splattwin.runtime import torch_threads
    from splattwin.splat import densify
    from splattwin.splat.config import LearningRates
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.init import scene_center_and_scale
    from splattwin.splat.losses import photometric_loss
    from splattwin.splat.model import GaussianModel
    from splattwin.splat.rasterize import rasterization, view_colors
    from splattwin.splat.resolution import resolve as resolve_resolution
    from splattwin.splat.trainer import load_views

    opts = opts or RefineOptions(iters=800)
    twin_dir = Path(twin_dir)
    if opts.iters <= 0:
        raise ValueError(f"iters must be positive, got {opts.iters}")
    if not frames:
        raise InputError("no training frames to refine the objects on", twin_dir)
    scene, man, world, label_of = _object_sets(twin_dir)
    if not world:
        return {"objects": {}, "iters": 0}
    names = sorted(world)
    deg = scene.sh_degree
    views = load_views(frames, resolve_resolution(resolution, cpu_max_side, "cpu"))
    center, scale = scene_center_and_scale([v.camera for v in views])
    # the frozen rest of the scene, in one pass with the objects as the splat stage trained it
    rest = concat([g for g in (scene.backdrop, scene.background) if g is not None], deg)
    fz = {k: torch.tensor(np.asarray(v), dtype=torch.float32) for k, v in
          (("means", rest.means), ("quats", rest.quats), ("scales", rest.scales), ("opacities", rest.opacities),
           ("sh", rest.with_sh_degree(deg).sh))}
    lrs = LearningRates(means=opts.means_lr)
    models, states, caps = {}, {}, {}
    for n in names:
        g = world[n].with_sh_degree(deg)
        if opts.dc_only:
            g = Gaussians(g.means, g.quats, g.scales, g.opacities,
                          np.concatenate([g.sh[:, :1], np.zeros_like(g.sh[:, 1:])], 1))
        models[n] = GaussianModel.from_gaussians(g, max_sh_degree=deg, lrs=lrs, scene_scale=scale,
                                                 scene_center=torch.tensor(center))
        if opts.dc_only:
            models[n].params["shN"].requires_grad_(False)
        states[n] = densify.new_state(len(g))
        caps[n] = int(math.ceil(opts.max_factor * len(g)))
    start_counts = {n: len(models[n]) for n in names}
    dcfg = {n: densify.DensifyConfig(grad_threshold=opts.grad_threshold, refine_every=opts.refine_every,
                                     reset_every=0, max_gaussians=caps[n],
                                     grow_scale3d=opts.split_scale / scale) for n in names}
    viewmats = torch.tensor(np.stack([v.camera.T_cam_world for v in views]), dtype=torch.float32)
    Ks = torch.tensor(np.stack([v.camera.K for v in views]), dtype=torch.float32)
    targets = _silhouette_targets(views, names, label_of, masks) if opts.mask_lambda > 0 else {}
    with_cover = bool(targets)  # render one coverage channel per object beside the colours
    bg = torch.zeros(1, 3 + (len(names) if with_cover else 0))
    gen = torch.Generator().manual_seed(opts.seed)
    order: list[int] = []
    stop = int(opts.refine_stop * opts.iters)
    ema = math.nan

    def render(i: int):
        """The view `i` with every Gaussian (objects trainable, the rest frozen): [1,H,W,3 (+ M coverage)]."""
        acts = [models[n].activated() for n in names]
        cat = lambda k: torch.cat([fz[k]] + [a[k] for a in acts])  # noqa: E731
        feats, sh_deg = cat("sh"), deg
        if with_cover:  # colours + one coverage channel per object, in the same depth-sorted pass
            parts = [torch.zeros(len(rest), len(names))] + [
                torch.nn.functional.one_hot(torch.full((len(a["means"]),), k), len(names)).float()
                for k, a in enumerate(acts)]
            feats = torch.cat([view_colors(cat("means"), feats, viewmats[i:i + 1], deg, backend="cpu"),
                               torch.cat(parts)[None]], -1)
            sh_deg = None
        img, _, meta = rasterization(cat("means"), cat("quats"), cat("scales"), cat("opacities"), feats,
                                     viewmats[i:i + 1], Ks[i:i + 1], views[i].camera.width,
                                     views[i].camera.height, sh_degree=sh_deg, backgrounds=bg,
                                     backend="cpu", eps2d=scene.eps2d, rasterize_mode=scene.rasterize_mode)
        return img, meta

    mask_stats: dict = {}
    with torch_threads(1):
        if with_cover:  # masks that disagree with what the twin already shows there are detector errors
            with torch.no_grad():
                cover0 = {i: render(i)[0][0, ..., 3:] for i in targets}
            n_all = sum(len(ks) for ks, _ in targets.values())
            targets = _agreeing(targets, cover0, opts.mask_min_iou)
            mask_stats = {"masks": n_all, "used": sum(len(ks) for ks, _ in targets.values())}
            if not targets:  # every mask disagreed: colours only, as without masks
                with_cover, bg = False, torch.zeros(1, 3)
            log.info("refine: silhouette loss on %d of %d object masks (the rest disagree with the twin: IoU < %.2f)",
                     mask_stats["used"], n_all, opts.mask_min_iou)
        from splattwin.progress import Progress

        with Progress(opts.iters, "refine objects", unit="it", enabled=progress) as bar:
            for step in range(opts.iters):
                if not order:
                    order = torch.randperm(len(views), generator=gen).tolist()
                i = order.pop(0)
                for n in names:
                    models[n].set_step(step, opts.iters)
                img, meta = render(i)
                loss = photometric_loss(img[0, ..., :3], views[i].image, opts.ssim_lambda)
                if i in targets:
                    ks, target = targets[i]
                    loss = loss + opts.mask_lambda * silhouette_loss(img[0, ..., 3:][..., ks], target)
                loss.backward()
                for n in names:
                    models[n].step()
                    models[n].zero_grad()
                lv = float(loss.detach())
                ema = lv if math.isnan(ema) else 0.95 * ema + 0.05 * lv
                if step < stop:
                    g2d, radii = meta["means2d"].grad, meta["radii"]
                    o = len(rest)
                    for n in names:
                        k = len(models[n])
                        densify.accumulate(states[n], g2d[:, o:o + k], radii[:, o:o + k], views[i].camera.width,
                                           views[i].camera.height)
                        o += k
                    if (step + 1) % opts.refine_every == 0:
                        for n in names:
                            densify.refine(models[n], states[n], dcfg[n], step + 1, gen)
                            if opts.dc_only:
                                models[n].params["shN"].requires_grad_(False)
                if (step + 1) % 10 == 0:
                    bar.set_postfix(loss=f"{ema:.4f}", gaussians=sum(len(m) for m in models.values()))
                bar.update(1)
        log.info("refine: loss %.4f, Gaussians per object %s", ema, {n: len(models[n]) for n in names})
    refined = {n: models[n].to_gaussians() for n in names}
    _write(twin_dir, scene, man, refined, label_of, deg)
    stats = {"iters": opts.iters, "loss": ema,
             "objects": {n: {"before": start_counts[n], "after": len(refined[n])} for n in names}}
    if mask_stats:
        stats["silhouette"] = mask_stats
    write_json(twin_dir / REFINED_DIR / "refine.json", stats)
    return stats


def silhouette_loss(cover, target):
    """Mean over objects of sum |cover - target| / target area: cover [H,W,M] each object's rendered
    coverage (its Gaussians' accumulated weight, occlusion included), target [H,W,M] its 2D mask in [0, 1].
    Normalised by the mask's area so that a small object weighs as much as a large one."""
    area = target.sum(dim=(0, 1)).clamp_min(1.0)
    return ((cover - target).abs().sum(dim=(0, 1)) / area).mean() if target.shape[-1] else cover.sum() * 0.0


def _silhouette_targets(views, names: list[str], label_of: dict[str, int], masks) -> dict:
    """{view index: (object columns, float [H,W,M] masks at the view's training size, area-averaged)} for the
    views where the mask set has a mask of some object; objects without a mask there are not supervised
    (a detector that missed an object is no evidence that it is absent)."""
    import torch

    if masks is None:
        return {}
    out = {}
    for i, v in enumerate(views):
        ks, ms = [], []
        for k, n in enumerate(names):
            m = masks.get(v.name, label_of.get(n, -1))
            if m is None or not m.any():
                continue
            t = torch.from_numpy(np.asarray(m, np.float32))[None, None]
            ms.append(torch.nn.functional.interpolate(t, size=(v.camera.height, v.camera.width), mode="area")[0, 0])
            ks.append(k)
        if ks:
            out[i] = (ks, torch.stack(ms, -1))
    return out


def _agreeing(targets: dict, cover: dict, min_iou: float) -> dict:
    """`targets` without the masks whose IoU with the object's rendered coverage (> 0.5) is below
    `min_iou`: a missed part, a wrong object or a false detection, which the loss would otherwise paint in."""
    out = {}
    for i, (ks, t) in targets.items():
        keep = []
        for j, k in enumerate(ks):
            m, c = t[..., j] > 0.5, cover[i][..., k] > 0.5
            union = int((m | c).sum())
            if union and int((m & c).sum()) / union >= min_iou:
                keep.append(j)
        if keep:
            out[i] = ([ks[j] for j in keep], t[..., keep])
    return out


def _write(twin_dir: Path, scene, man, refined: dict, label_of: dict[str, int], deg: int) -> None:
    """refined/point_cloud.ply + labels.npy (the frozen rest, then each refined object), objects' splats.ply,
    twin.json pointing to them."""
    from splattwin.io import atomic_path
    from splattwin.playback.scene import concat, load_labels
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.splats import transform_gaussians

    names = sorted(refined)
    parts = [g for g in (scene.backdrop, scene.background) if g is not None and len(g)]
    rest = concat(parts, deg)
    # the rest keeps the labels it had: object-labelled Gaussians there are the objects' residue (cleaned
    # out of splats.ply), which the playback hides once their object moved
    labels = [_labels_of(rest.means, Gaussians.load_ply(twin_dir / man.splats).means,
                         load_labels(twin_dir / man.labels) if man.labels else None)]
    for n in names:
        parts.append(refined[n])
        labels.append(np.full(len(refined[n]), label_of[n], np.int64))
    full = concat(parts, deg)
    out = twin_dir / REFINED_DIR
    out.mkdir(parents=True, exist_ok=True)
    full.save_ply(out / "point_cloud.ply")
    with atomic_path(out / "labels.npy") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.concatenate(labels))
    for o in man.objects:
        if o.name in refined:
            g = transform_gaussians(refined[o.name], np.linalg.inv(scene.T_world_obj0[o.name]))
            g.save_ply(twin_dir / o.splat_ply)
    man.splats = f"{REFINED_DIR}/point_cloud.ply"
    man.labels = f"{REFINED_DIR}/labels.npy"
    man.save(twin_dir)


def _labels_of(means: np.ndarray, full_means: np.ndarray, full_labels: np.ndarray | None) -> np.ndarray:
    """Labels of Gaussians taken unchanged from the full set (`means` [M,3] coincide with rows of
    `full_means`); 0 without labels."""
    if full_labels is None or len(means) == 0:
        return np.zeros(len(means), np.int64)
    from scipy.spatial import cKDTree

    d, idx = cKDTree(full_means).query(means)
    if not np.all(d < 1e-9):
        raise ValueError("Gaussians of the rest of the scene do not coincide with the twin's splats")
    return np.asarray(full_labels, np.int64)[idx]
