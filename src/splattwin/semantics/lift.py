"""File-level semantic lifting: splats PLY + dataset + masks -> labels, object splats, label maps.

Output folder layout (`fuse_to_dir`):
    OUT/labels.npy                 int32 per Gaussian (0 background), order of the input PLY
    OUT/fusion.json                objects, options, per-round history, timings, metrics (mIoU when GT
                                   exists; with metrics=True consistency, ghost index, kappa sweep)
    OUT/objects/<name>.ply         each object's Gaussians (world frame, standard 3DGS PLY)
    OUT/label_maps/<view>.png      rendered label map, colour-coded with a legend (all dataset views)
    OUT/label_maps/raw/<view>.png  the same as uint8 label ids (for metrics / other tools)
    OUT/masks_vs_labels/<view>.png 2D masks | fused labels (with metrics=True)
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from splattwin import io
from splattwin.errors import InputError
from splattwin.semantics.fusion import FusionOptions, FusionResult, View, fuse, naive_fusion, splat_normals
from splattwin.semantics.masks import MaskSet, MaskWarning, safe_name, load_masks, scene_objects
from splattwin.semantics.options import RENDERERS
from splattwin.semantics.label_render import PointDepth, SplatDepth, colorize, render_label_maps

log = logging.getLogger(__name__)

def dataset_objects(dataset_root: Path) -> dict[str, int] | None:
    """name -> label from a generated scene's scene.json next to the dataset (a scene folder), or in the
    twin's scene/ when the dataset is a twin's poses/ (its ground-truth label images use those ids), else None."""
    root = Path(dataset_root)
    root = root if root.is_dir() else root.parent
    for d in (root, root.parent / "scene"):
        if (d / "scene.json").is_file():
            return scene_objects(d)
    return None


def label_objects(ds) -> dict[str, int] | None:
    """name -> id of the objects in a loaded dataset's ground-truth label images: what its transforms.json
    records (`label_objects`, kept by the poses stage), else `dataset_objects`. Masks are numbered by it
    on every route, and the metrics match objects by these names."""
    return dict(ds.meta["label_objects"]) if ds.meta.get("label_objects") else dataset_objects(ds.root)


def prompt_labels(dataset, prompt: str, folder: str | Path | None = None) -> dict[str, int] | None:
    """phrase -> label for `segment_images(..., labels=)` so that prompted masks get the ids of a generated
    scene's objects (as `splattwin segment` numbers them, and as `fuse` and the metrics expect): from the
    scene.json in the dataset's folder when every phrase of `prompt` is one of its objects' prompts (or
    names); None otherwise (the segmenter numbers the phrases 1..K). dataset: a loaded Dataset; folder: where
    scene.json is looked for (default: the dataset's root)."""
    from splattwin.semantics.segment import parse_prompt

    objs = label_objects(dataset)
    scene_json = Path(dataset.root if folder is None else folder) / "scene.json"
    if not objs or not scene_json.is_file():
        return None
    labels = _scene_prompts(io.read_json(scene_json), objs, scene_json)
    return labels if all(ph in labels for ph in parse_prompt(prompt)) else None


def _scene_prompts(meta, objs: dict[str, int], where: Path) -> dict[str, int]:
    """prompt (or name), lower case -> label of scene.json's objects named in `objs`; InputError naming
    scene.json when it is not an object with an `objects` list, or an object's label is not an id in
    [1, MAX_LABEL_ID] (a JSON integer: "2" and 2.0 are refused, as everywhere labels are read; the objects may
    come from transforms.json, so `scene_objects` has not read the file)."""
    from splattwin.errors import short_repr
    from splattwin.semantics.masks import MAX_LABEL_ID, whole_number

    if not isinstance(meta, dict):
        raise InputError(f"scene.json must hold a JSON object, got {type(meta).__name__}", where)
    objects = meta.get("objects", [])
    if not isinstance(objects, list):
        raise InputError(f"scene.json 'objects' must be a list, got {type(objects).__name__}", where)
    labels = {}
    for o in objects:
        if not (isinstance(o, dict) and isinstance(o.get("name"), str) and o["name"] in objs and "label" in o):
            continue
        # the project's one integer check (as the masks' index.json labels): "2", 2.0 and True are refused
        label = whole_number(o["label"], where, f"scene.json label of object {short_repr(o['name'])}", 1, MAX_LABEL_ID)
        labels[str(o.get("prompt", o["name"])).lower()] = label
    return labels


def views_for(frames, masks: MaskSet, where: Path | None = None, all_frames=None) -> list[View]:
    """Views (cameras) of the frames that have masks; InputError when none match by name."""
    views = [View(f.name, f.camera) for f in frames if f.name in masks.sizes]
    unknown = sorted(set(masks.views) - {f.name for f in all_frames or frames})
    if unknown:
        warnings.warn(MaskWarning(f"{len(unknown)} mask views match no dataset image and are ignored: "
                                  f"{', '.join(unknown[:5])}"))
    if not views:
        names = ", ".join(sorted(f.name for f in frames)[:5])
        raise InputError(f"no mask view matches a dataset image (masks: {', '.join(masks.views[:5])}...; "
                         f"images: {names}...)", where)
    missing = sorted(f.name for f in frames if f.name not in masks.sizes)
    if missing:   # fusion votes only in views with masks: 1 of 7 fused gave mIoU 0.05 with no word said
        warnings.warn(MaskWarning(f"masks cover {len(views)} of {len(frames)} training views; fusion ignores the "
                                  f"other {len(missing)} (no mask file: {', '.join(missing[:5])}"
                                  f"{', ...' if len(missing) > 5 else ''})"))
    return views


def rasterizer_usable() -> bool:
    """True when the splat stage's rasterizer imports and renders on this machine."""
    try:
        from splattwin.capture.camera import Camera
        from splattwin.splat.gaussians import Gaussians

        g = Gaussians(means=[[0.0, 0.0, 1.0]], quats=[[1.0, 0, 0, 0]], scales=[[0.01] * 3], opacities=[0.9],
                      sh=np.zeros((1, 1, 3)))
        SplatDepth(g)(None, [Camera.from_fov(1.0, 8, 8)])
        return True
    except Exception as e:  # noqa: BLE001 - any failure of the optional backend -> fallback
        log.info("rasterizer unavailable (%s)", e)
        return False


def make_depth_renderer(gaussians, renderer: str = "auto", raster: tuple[str, float | None] = ("classic", None)):
    """Depth for the visibility test: "splat" (the rasterizer's expected depth of the trained splats, as
    the method prescribes; 200k Gaussians x 15 views x 3 rounds in ~7 s on 2 cores) or "points" (a
    z-buffer of the Gaussian centres, ~5x faster, agreeing on >99 % of the labels of trained splats).
    "auto" = "splat" when the rasterizer is usable here, else "points". raster: the splats' trained
    (rasterize_mode, eps2d) for "splat"."""
    if renderer not in RENDERERS:
        raise InputError(f"unknown renderer {renderer!r}; choose one of {', '.join(RENDERERS)}")
    if renderer in ("splat", "auto"):
        if rasterizer_usable():
            return SplatDepth(gaussians, raster=raster)
        if renderer == "splat":
            raise InputError("the splat rasterizer is not usable here; use --renderer points")
        log.info("rasterizer unavailable: using the point z-buffer depth")
    return PointDepth(gaussians.means)


def scaled_options(options: FusionOptions | None, ds, frame="beside") -> FusionOptions:
    """`options` (default FusionOptions()) with their metric lengths in the units of the dataset's frame:
    `frame` a TwinFrame, "beside" (the frame.json next to the dataset's file, `frame_beside`) or None (as
    given). See `fuse_to_dir`."""
    from splattwin.options import scale_lengths
    from splattwin.poses.twin_frame import TwinFrame, frame_beside

    options = options if options is not None else FusionOptions()
    if isinstance(frame, str):
        if frame != "beside":
            raise ValueError(f"frame must be a TwinFrame, 'beside' or None, got {frame!r}")
        frame = frame_beside(ds.meta.get("path", ds.root))
    if frame is None:
        return options
    if not isinstance(frame, TwinFrame):
        raise ValueError(f"frame must be a TwinFrame (splattwin.poses.load_frame), 'beside' or None, got "
                         f"{type(frame).__name__}")
    return scale_lengths(options, frame.length_scale())


def fuse_to_dir(splats: "str | Path | Gaussians", dataset: "str | Path | Dataset", masks: str | Path | MaskSet,
                out_dir: str | Path, options: FusionOptions | None = None, renderer: str = "auto",
                label_maps: bool = True, naive: bool = False, progress: bool = True, maps_renderer: str = "auto",
                metrics: bool = False, raster: tuple[str, float | None] | None = None,
                frame: "TwinFrame | None | str" = "beside") -> FusionResult:
    """Run the fusion on files and write the output folder (layout in the module docstring); fusion.json
    is written last, once, with everything in it (it marks a finished output).

    splats / dataset: paths, or already loaded objects (the pipeline passes those it also uses afterwards).
    renderer: depth for the visibility test (`make_depth_renderer`). maps_renderer: label maps through
    the rasterizer ("splat"), the centre z-buffer ("points"), or "auto" (splat when usable).
    metrics: also the paper's 3D projection consistency and ghost index, the kappa sweep, and 2D masks |
    fused labels pictures (OUT/masks_vs_labels/, with label maps).
    raster: (rasterize_mode, eps2d) the splats were trained with, for the rasterizer's depth and label
    maps; None: from the train.json beside a splat file (`splat.config.filter_beside`), else classic.
    (An antialiased demo twin drawn classic: held-out mIoU 0.909 instead of 0.944.)
    frame: the twin frame the poses are in, whose units the options' lengths (depth tolerance, depth-DBSCAN
    eps, gate; given in metres) are scaled to (`TwinFrame.length_scale`: 1 for a metric frame, the nominal
    metre for an unscaled SfM one), as the stage and the CLI do. "beside" (default): the frame.json next to
    the dataset's transforms.json, as the poses stage writes it (none there: metric); None: no scaling.
    """
    from splattwin.capture import Dataset, load_dataset
    from splattwin.splat.gaussians import Gaussians

    from splattwin.capture.dataset import refuse_video

    if not isinstance(dataset, Dataset):
        refuse_video(dataset, "fuse")
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    g = splats if isinstance(splats, Gaussians) else Gaussians.load_ply(splats)
    if raster is None:
        from splattwin.splat.config import filter_beside, trained_filter

        raster = trained_filter(None) if isinstance(splats, Gaussians) else filter_beside(splats)
    if len(g.means) == 0:
        raise InputError("the splat file has no Gaussians", None if isinstance(splats, Gaussians) else splats)
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    options = scaled_options(options, ds, frame)
    objs = label_objects(ds)
    ms = masks if isinstance(masks, MaskSet) else load_masks(masks, objects=objs)
    where = None if isinstance(masks, MaskSet) else Path(masks)
    views = views_for(ds.train() or ds.frames, ms, where, all_frames=ds.frames)
    depth = make_depth_renderer(g, renderer, raster)
    res = fuse(g.means, views, ms, options, depth_renderer=depth, normals=splat_normals(g.quats, g.scales),
               progress=progress)
    labels = res.labels
    if naive:
        labels = naive_fusion(g.means, views, ms)
        res.labels = labels
    written = set()
    for k in res.label_ids:
        sel = labels == k
        if sel.any():
            written.add(f"{safe_name(res.names[k])}.ply")
            with io.atomic_path(out_dir / "objects" / f"{safe_name(res.names[k])}.ply") as tmp:
                g.subset(sel).save_ply(tmp)
    io.remove_stale(out_dir / "objects", written, suffix=".ply")   # objects of an earlier fusion that are gone
    summary = {"depth_renderer": getattr(depth, "name", "custom"), "n_views_fused": len(views)}
    if label_maps:
        if maps_renderer not in RENDERERS:
            raise InputError(f"unknown label-map renderer {maps_renderer!r}; choose one of {', '.join(RENDERERS)}")
        mr = maps_renderer if maps_renderer != "auto" else ("splat" if rasterizer_usable() else "points")
        summary.update(write_label_maps(g, labels, ds.frames, res.names, out_dir, renderer=mr, progress=progress,
                                        raster=raster, gt_objects=objs))
        summary["label_map_views"] = [f.name for f in ds.frames]   # the report shows these, not a glob
    compared: set[str] = set()
    if metrics:
        summary.update(fusion_metrics(res, g.means, views, ms))
        if label_maps:
            compared = write_mask_comparisons(res, ms, ds, out_dir)
            summary.update(heldout_mask_miou(ms, ds, out_dir, res.label_ids))
    # pictures of views an earlier fusion had and this one has not (a rebuild from fewer or other views)
    mapped = {f"{f.name}.png" for f in ds.frames} if label_maps else set()
    for sub, keep in (("label_maps", mapped), ("label_maps/raw", mapped), ("masks_vs_labels", compared)):
        io.remove_stale(out_dir / sub, keep, suffix=".png")
    summary["seconds_total"] = time.perf_counter() - t0
    summary["method"] = "naive" if naive else "visibility-aware"
    res.save(out_dir, extra=summary)
    return res


KAPPA_SWEEP = (2.0, 1.8, 1.5, 1.2, 1.0)


def fusion_metrics(res: FusionResult, means: np.ndarray, views: Sequence[View], masks: MaskSet) -> dict:
    """The paper's 3D projection consistency (%) and ghost index (%) of the result, and both for the
    consensus labels of each kappa in KAPPA_SWEEP (tau = N / kappa)."""
    from splattwin.semantics.metrics import ghost_index, projection_consistency

    sweep = [{"kappa": k, "consistency": projection_consistency(means, res.relabel(k), views, masks),
              "ghost_index": ghost_index(res, k)} for k in KAPPA_SWEEP]
    return {"consistency": projection_consistency(means, res.labels, views, masks), "ghost_index": ghost_index(res),
            "kappa_sweep": sweep}


def _mask_map(masks: MaskSet, view: str) -> np.ndarray:
    """[H,W] int label image of a view's 2D masks (0 = none; where masks overlap the higher label wins)."""
    h, w = masks.sizes[view]
    mask_map = np.zeros((h, w), np.int32)
    for k in sorted(masks.masks.get(view, {})):
        mask_map[masks.masks[view][k]] = k
    return mask_map


def heldout_mask_miou(masks: MaskSet, dataset, out_dir: Path, label_ids: Sequence[int]) -> dict:
    """mIoU of the fused labels rendered in the held-out views (OUT/label_maps/raw) against the 2D masks
    given for those views, which the fusion never used: the label quality that a real capture without
    ground-truth label images can still measure (its masks are only as good as the segmenter or the
    user's). {"miou_heldout_masks": float, "miou_heldout_masks_views": [names]}, or {} when no held-out
    view has masks."""
    from splattwin.capture import load_mask
    from splattwin.semantics.metrics import miou

    pred, ref, names = [], [], []
    for f in dataset.frames:
        raw = out_dir / "label_maps" / "raw" / f"{f.name}.png"
        if f.split != "heldout" or f.name not in masks.sizes or not raw.is_file():
            continue
        fused = load_mask(raw).astype(np.int32)
        mask_map = _mask_map(masks, f.name)
        if fused.shape == mask_map.shape:
            pred.append(fused)
            ref.append(mask_map)
            names.append(f.name)
    if not names:
        return {}
    return {"miou_heldout_masks": miou(pred, ref, sorted(label_ids)), "miou_heldout_masks_views": names}


def write_mask_comparisons(res: FusionResult, masks: MaskSet, dataset, out_dir: Path, n: int = 3) -> set[str]:
    """OUT/masks_vs_labels/<view>.png for the first `n` training views and the first `n` held-out views
    with masks: the 2D masks (the fusion's input; on held-out views unused by it) | the fused labels
    rendered (OUT/label_maps/raw). Returns the file names written."""
    from splattwin.capture import load_image, load_mask
    from splattwin.pictures import side_by_side

    with_masks = [fr for fr in dataset.frames if fr.name in masks.sizes]
    written: set[str] = set()
    for f in [fr for fr in with_masks if fr.split != "heldout"][:n] + [fr for fr in with_masks if fr.split == "heldout"][:n]:
        mask_map = _mask_map(masks, f.name)
        img = load_image(f.image_path)
        fused = load_mask(out_dir / "label_maps" / "raw" / f"{f.name}.png").astype(np.int32)
        pic = side_by_side([colorize(mask_map, res.names, img, legend=False), colorize(fused, res.names, img)])
        io.write_image(out_dir / "masks_vs_labels" / f"{f.name}.png", (pic * 255 + 0.5).astype(np.uint8))
        written.add(f"{f.name}.png")
    return written


def write_label_maps(g, labels: np.ndarray, frames: Sequence, names: dict[int, str], out_dir: Path,
                     renderer: str = "points", progress: bool = False,
                     raster: tuple[str, float | None] = ("classic", None),
                     gt_objects: dict[str, int] | None = None) -> dict:
    """Render and save label maps for all frames; mIoU per split when the frames carry GT label images.

    gt_objects: name -> id in the GT label images. Given, the fused objects are matched to the GT by name
    (an object the GT lacks scores 0), so masks numbered otherwise than the GT cannot lower the mIoU;
    without it by label id ("miou_matched_by" says which)."""
    from splattwin.capture import load_image
    from splattwin.semantics.metrics import miou

    from splattwin.progress import track

    n = max(names, default=0)
    scores: dict[str, list] = {}
    for f in track(frames, "label maps", unit="view", enabled=progress):
        lab = render_label_maps(g, labels, [f.camera], n, renderer=renderer, raster=raster)[0]
        img = None
        try:
            img = load_image(f.image_path)
        except InputError:
            pass
        io.write_image(out_dir / "label_maps" / f"{f.name}.png", colorize(lab, names, img))
        io.write_image(out_dir / "label_maps" / "raw" / f"{f.name}.png", lab.astype(np.uint8))
        if f.label_path is not None and Path(f.label_path).is_file():
            from splattwin.semantics.masks import read_mask_image

            gt = read_mask_image(Path(f.label_path))
            if gt.ndim == 2 and gt.shape == lab.shape:
                scores.setdefault(f.split, []).append((lab, gt))
    out: dict = {"label_map_renderer": renderer}
    if not scores:
        return out
    ids = {k: k for k in names}
    if gt_objects:
        spare = max([*gt_objects.values(), *names, 0]) + 1
        for k in sorted(names):  # unmatched names get ids absent from the GT
            ids[k] = gt_objects[names[k]] if names[k] in gt_objects else spare + k
    lut = np.arange(max([n, *ids.values()]) + 1)
    for k, v in ids.items():
        lut[k] = v
    for split, pairs in scores.items():
        out[f"miou_{split}"] = miou([lut[p] for p, _ in pairs], [g_ for _, g_ in pairs], sorted(ids.values()))
    out["miou_matched_by"] = "name" if gt_objects else "label id"
    return out
