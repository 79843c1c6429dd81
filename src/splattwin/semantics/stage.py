"""The semantics stage as the pipeline runs it: `run(SemanticsInputs, SemanticsOptions) -> SemanticsResult`.

Reads the posed dataset, the trained splats and the 2D masks — from `options.masks`, from text prompts
(`options.prompt`, segmented into OUT/masks2d/), or the embedded scene's simulated segmenter
(`inputs.scene_dir`; only training views are fused, held-out views stay unseen for the metrics), or a
robot-style capture's own masks (BOP mask_visib/, TUM-layout masks/: `scene_default_masks`).
Writes (`splattwin.semantics.lift.fuse_to_dir`, the only writer of each): OUT/labels.npy, OUT/fusion.json
(with the metrics), OUT/objects/, OUT/label_maps/, OUT/masks_vs_labels/; and OUT/objects.json (the objects
[name, label, prompt] handed to the twin stage).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

from splattwin.errors import InputError
from splattwin.semantics.options import SemanticsOptions

log = logging.getLogger(__name__)


@dataclass
class SemanticsInputs:
    transforms: Path               # posed dataset (the cameras of the masks)
    splats: Path                   # trained 3DGS PLY
    out_dir: Path                  # the stage's folder (TWIN/semantics)
    scene_dir: Path | None = None  # an embedded scene's folder: its object names and simulated masks
    # the splat stage's refined_poses.json (training with pose refinement): its poses replace the dataset's, so
    # that the masks are projected with the cameras the splats were fitted to (`splattwin.splat.refined_poses`)
    refined_poses: Path | None = None


@dataclass
class SemanticsResult:
    labels: Path                   # int32 per Gaussian, 0 background
    objects: Path                  # objects.json: [[name, label, prompt], ...]
    fusion: Path                   # fusion.json: options, history, metrics
    miou_heldout: float | None = None


def load_stage_masks(options: SemanticsOptions, frames, scene_dir: Path | None, segment_dir: Path | None = None,
                     image_sizes: dict | None = None, fresh: bool = False):
    """(MaskSet, the path its masks came from): options.masks, options.prompt (segmenting `frames` into
    `segment_dir`; views segmented there before with the same photo and options are reused unless
    `fresh`) or the embedded scene's simulated segmenter (training views only). image_sizes: view ->
    (H, W), checked for every mask file as it is read."""
    from splattwin.semantics.masks import load_masks, scene_masks, scene_objects

    objs = scene_objects(scene_dir) if scene_dir is not None else None
    if options.masks:
        return load_masks(options.masks, objects=objs, image_sizes=image_sizes), Path(options.masks)
    if options.prompt:
        from splattwin.semantics.segment import segment_images

        if segment_dir is None:
            raise InputError("text prompts are segmented when the stage runs (after poses)")
        ms = segment_images({f.name: f.image_path for f in frames if f.split == "train"}, options.prompt,
                            options.segment, out_dir=segment_dir, resume=not fresh)
        return ms, segment_dir
    if scene_dir is not None:
        src = scene_default_masks(scene_dir)
        if src is None:
            raise InputError(f"no 2D masks: this capture has none of its own ({', '.join(OWN_MASKS)}): pass "
                             "--masks DIR or --prompt 'blue box. yellow cube', or build only the splats with "
                             "--until splats", scene_dir)
        if src != Path(scene_dir) / "masks" / "noisy":   # a robot-style capture's own masks, read as --masks would
            if src not in _SAID:   # once per process: pre-flight, semantics and twin stages all read them
                _SAID.add(src)
                log.info("2D masks: no --masks or --prompt given, so the capture's own masks %s are used (give --masks "
                         "DIR or --prompt for others)", src)
            return load_masks(src, objects=objs, image_sizes=image_sizes), src
        ms = scene_masks(scene_dir, kind="noisy")
        train = {f.name for f in frames if f.split == "train"}
        for d in (ms.masks, ms.scores, ms.sizes):
            for view in [v for v in d if v not in train]:
                del d[view]
        return ms, scene_dir / "masks" / "noisy"
    raise InputError("no 2D masks: pass --masks DIR or --prompt 'blue box. yellow cube'")


_SAID: set = set()   # the capture mask folders whose use was logged


# what a scene folder's own masks may be, in this order (`scene_default_masks`)
OWN_MASKS = ("masks/noisy/ (the embedded scene's simulated segmenter)",
             "BOP mask_visib/ or mask/ with scene_gt.json", "per-instance masks/ with masks/instances.json")


def scene_default_masks(scene_dir: Path) -> Path | None:
    """The masks a build of a scene folder (one with scene.json) uses when neither --masks nor --prompt is
    given: the embedded scene's simulated noisy masks (masks/noisy/); else the capture's own masks, as a
    robot-style capture (`scene generate --robot-capture`) writes them: a BOP scene's mask_visib/ (or
    mask/), or per-instance masks/ with instances.json (TUM layout); None when it has none."""
    from splattwin.capture.bop import MASK_DIRS
    from splattwin.semantics.masks import INSTANCES_FILE, find_bop_scene

    scene_dir = Path(scene_dir)
    if (scene_dir / "masks" / "noisy").is_dir():
        return scene_dir / "masks" / "noisy"
    if find_bop_scene(scene_dir) is not None:
        return next(scene_dir / d for d in MASK_DIRS if (scene_dir / d).is_dir())
    if (scene_dir / "masks" / INSTANCES_FILE).is_file():
        return scene_dir / "masks"
    return None


def check_masks(options: SemanticsOptions, frames, scene_dir: Path | None = None) -> None:
    """Before any stage runs: the mask files the semantics stage will read (`options.masks`, or without
    --masks and --prompt the scene folder's own, `scene_default_masks`) exist, read, fit the capture's
    images `frames` and name at least one of them (InputError naming the mask file otherwise)."""
    if not options.masks and (options.prompt or scene_dir is None):
        return
    sizes = {f.name: (f.camera.height, f.camera.width) for f in frames}
    ms, where = load_stage_masks(options, frames, scene_dir, image_sizes=sizes)
    ms.validate(None, where)  # an empty set or an object that is in no view
    if not [v for v in ms.views if v in sizes]:
        raise InputError(f"no mask view matches an image of the input (masks: {', '.join(ms.views[:5])}...; "
                         f"images: {', '.join(sorted(sizes)[:5])}...)", where)


def fusion_options_for(fusion, transforms: Path):
    """The fusion options for the posed dataset at `transforms`: as given in a metric frame; in an unscaled
    one (frame.json beside it says so) every length (depth tolerance, depth-DBSCAN eps, gate) multiplied by
    the frame's nominal metre (`TwinFrame.length_scale`), so they keep their share of the scene."""
    from splattwin.options import scale_lengths
    from splattwin.poses.twin_frame import frame_beside

    frame = frame_beside(transforms)
    return fusion if frame is None else scale_lengths(fusion, frame.length_scale())


def input_files(inputs: SemanticsInputs, options: SemanticsOptions) -> dict:
    """What the stage reads from outside the twin (hashed by content for its key)."""
    scene_json = inputs.scene_dir / "scene.json" if inputs.scene_dir is not None else None
    out: dict = {"masks": options.masks, "scene.json": scene_json}
    if not options.masks and not options.prompt and inputs.scene_dir is not None:
        own = scene_default_masks(inputs.scene_dir)
        out["scene_masks"] = own
        if own is not None and (inputs.scene_dir / "scene_gt.json").is_file():   # BOP: the instances' objects
            out["scene_gt"] = inputs.scene_dir / "scene_gt.json"
    return out


def run(inputs: SemanticsInputs, options: SemanticsOptions, *, progress: bool = True,
        fresh: bool = False) -> SemanticsResult:
    from splattwin import io
    from splattwin.capture import load_dataset
    from splattwin.semantics.fusion import check_views
    from splattwin.semantics.lift import fuse_to_dir, views_for
    from splattwin.semantics.masks import MaskWarning
    from splattwin.splat.config import filter_beside
    from splattwin.splat.gaussians import Gaussians

    from splattwin.splat import refined_poses

    ds = refined_poses.apply(load_dataset(inputs.transforms), inputs.refined_poses)
    # fresh (`build --from semantics` or earlier): segment every view again, reuse nothing
    ms, masks_from = load_stage_masks(options, ds.frames, inputs.scene_dir, inputs.out_dir / "masks2d",
                                      {f.name: (f.camera.height, f.camera.width) for f in ds.frames}, fresh=fresh)
    # checked here with the masks' path, so that a size or empty-mask error names it
    with warnings.catch_warnings():  # fuse_to_dir warns about unmatched views itself
        warnings.simplefilter("ignore", MaskWarning)
        check_views(views_for(ds.train() or ds.frames, ms, masks_from, all_frames=ds.frames), ms, masks_from)
    g = Gaussians.load_ply(inputs.splats)
    # an unscaled frame's lengths: fuse_to_dir scales them by the frame.json beside the transforms
    res = fuse_to_dir(g, ds, ms, inputs.out_dir, options.fusion, renderer=options.renderer, label_maps=options.maps,
                      naive=options.naive, progress=progress, maps_renderer=options.maps_renderer, metrics=True,
                      raster=filter_beside(inputs.splats))
    prompts = ms.prompts or {}
    objects = [[res.names[k], int(k), prompts.get(k, res.names[k].replace("_", " "))] for k in res.label_ids]
    io.write_json(inputs.out_dir / "objects.json", objects)
    fusion = io.read_json(inputs.out_dir / "fusion.json")
    if inputs.refined_poses is not None:  # recorded only then: a twin without refinement is unchanged
        fusion["poses"] = refined_poses.describe(ds)
        io.write_json(inputs.out_dir / "fusion.json", fusion)
    return SemanticsResult(labels=inputs.out_dir / "labels.npy", objects=inputs.out_dir / "objects.json",
                           fusion=inputs.out_dir / "fusion.json", miou_heldout=fusion.get("miou_heldout"))
