"""Sub-commands of the semantics stage: `segment` (2D masks) and `fuse` (masks -> per-Gaussian labels)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from splattwin.options import add_command, add_options, add_progress_flag, from_args
from splattwin.semantics.options import FusionOptions, SegmentOptions, SemanticsOptions
from splattwin.wording import plural

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "segment", _segment)
    p.add_argument("dataset", type=Path, help="dataset folder (transforms.json, COLMAP, BOP scene, TUM pose list + "
                   "intrinsics, images...)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--prompt", help='objects as phrases separated by ".", e.g. "blue box. yellow cube. toy hammer"')
    src.add_argument("--masks", type=Path, help="existing masks to import and check against the dataset images")
    p.add_argument("--out", type=Path, default=None, help="output mask folder (default DATASET/masks/segment)")
    add_options(p, SegmentOptions)
    p.add_argument("--split", default="all", choices=["all", "train", "heldout"], help="which views to segment")
    add_progress_flag(p)

    f = add_command(sub, "fuse", _fuse)
    f.add_argument("--splats", type=Path, required=True, help="3DGS PLY of the scene")
    f.add_argument("--dataset", type=Path, required=True, help="dataset with the cameras of the masks")
    f.add_argument("--masks", type=Path, required=True, help="mask folder / COCO JSON (see `splattwin segment`)")
    f.add_argument("--out", type=Path, required=True, help="output folder")
    add_options(f, FusionOptions)
    add_options(f, SemanticsOptions, include=("renderer", "maps_renderer", "maps", "naive"))
    add_progress_flag(f)


def _segment(args: argparse.Namespace) -> int:
    """2D object masks per view from text prompts (Grounding DINO + SAM) or mask files.

    Makes a mask set (<out>/masks.json + <view>/<object>.png) for a dataset, either from text prompts
    (open-vocabulary, weights from the local Hugging Face cache) or by importing masks (PNG folders, label
    images, COCO RLE JSON, polygon JSON)."""
    from splattwin.capture import load_dataset
    from splattwin.capture.dataset import refuse_video
    from splattwin.semantics.lift import label_objects, prompt_labels
    from splattwin.semantics.masks import load_masks
    from splattwin.semantics.segment import segment_images

    refuse_video(args.dataset, "segment")   # before its frames would be extracted beside it
    ds = load_dataset(args.dataset)
    frames = ds.frames if args.split == "all" else [f for f in ds.frames if f.split == args.split]
    out = args.out or Path(args.dataset) / "masks" / "segment"
    from splattwin.lock import output_lock

    with output_lock(out):
        objs = label_objects(ds)  # as `fuse` numbers them
        if args.masks is not None:
            # every mask checked against its own image as it is read (as `build` does), so a wrong-size
            # file is named, not the next mask of its view
            sizes = {f.name: (f.camera.height, f.camera.width) for f in ds.frames}
            ms = load_masks(args.masks, objects=objs, image_sizes=sizes)
            ms.validate({f.name: sizes[f.name] for f in frames}, args.masks)
        else:
            opts = from_args(SegmentOptions, args)
            labels = prompt_labels(ds, args.prompt, Path(args.dataset))  # phrases -> a generated scene's labels
            ms = segment_images({f.name: f.image_path for f in frames}, args.prompt, opts, labels=labels, out_dir=out,
                                progress=args.progress)
        ms.save(out)
    print(f"{len(ms.views)} views, objects: " + ", ".join(
        f"{n} ({ms.n_views_with(k)} views)" for k, n in sorted(ms.objects.items())) + f" -> {out}")
    return 0


def _fuse(args: argparse.Namespace) -> int:
    """Lift 2D masks onto the Gaussians (visibility-aware fusion).

    Visibility-aware semantic fusion (depth agreement, DBSCAN depth isolation, weighted consensus
    tau = N/kappa, refinement with KNN smoothing). Writes labels.npy, fusion.json, objects/<name>.ply and
    label_maps/."""
    from splattwin.capture.dataset import refuse_video
    from splattwin.lock import output_lock
    from splattwin.semantics.lift import fuse_to_dir

    refuse_video(args.dataset, "fuse")   # no poses: said before --out is created or frames extracted
    opts = from_args(SemanticsOptions, args, fusion=from_args(FusionOptions, args))
    with output_lock(args.out):  # fuse_to_dir scales the lengths to an unscaled frame (frame.json beside)
        res = fuse_to_dir(args.splats, args.dataset, args.masks, args.out, opts.fusion, renderer=opts.renderer,
                          label_maps=opts.maps, naive=opts.naive, maps_renderer=opts.maps_renderer, metrics=True,
                          progress=args.progress)
    from splattwin import io

    meta = io.read_record(Path(args.out) / "fusion.json")   # written just now; read like any record (bounded)
    meta = meta if isinstance(meta, dict) else {}
    counts = ", ".join(f"{n}: {c}" for n, c in res.counts().items())
    extra = "".join(f", {k} {meta[k]:.3f}" for k in ("miou_train", "miou_heldout") if k in meta)
    if "miou_heldout_masks" in meta:
        extra += (f", held-out mIoU against the 2D masks {meta['miou_heldout_masks']:.3f} "
                  f"({plural(len(meta['miou_heldout_masks_views']), 'view')} the fusion did not use)")
    print(f"labelled {int((res.labels > 0).sum())} of {len(res.labels)} Gaussians ({counts}) in "
          f"{res.seconds:.1f} s{extra} -> {args.out}")
    return 0
