"""`splattwin geometry SPLAT.ply ...`: the geometry stage run by hand — clean a labelled splat, mesh it and
write a twin folder (registered by the twin package, which writes twin folders; the geometry package
itself knows nothing of twins)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from splattwin.errors import InputError
from splattwin.geometry.options import GeometryOptions
from splattwin.names import check_unique, object_name
from splattwin.options import add_command, add_options, add_progress_flag, dest, from_args
from splattwin.twin.options import ExportOptions

log = logging.getLogger(__name__)


def _parse_object(text: str) -> tuple[str, int, str]:
    """NAME=LABEL[:PROMPT]"""
    name, sep, rest = text.partition("=")
    label, _, prompt = rest.partition(":")
    try:
        lab = int(label)
    except ValueError:
        lab = -1
    if not sep or not name or lab <= 0:
        raise InputError(f"object must be NAME=LABEL[:PROMPT] with LABEL a positive integer, got {text!r}", "--object")
    return object_name(name, "--object"), lab, prompt


def _object_masks(ms, objects: list, where):
    """The masks of `ms` (a MaskSet) numbered by the objects' labels, matched by name (a saved mask set
    numbers its objects itself); InputError when no mask names one of the objects."""
    from splattwin.semantics.masks import MaskSet

    label = {name: lab for name, lab, *_ in objects}
    out = MaskSet(source=ms.source)
    for view in ms.views:
        for lab, m in ms.masks.get(view, {}).items():
            if ms.objects.get(lab) in label:
                out.add(view, label[ms.objects[lab]], m, name=ms.objects[lab])
    if not out.objects:
        raise InputError(f"no mask names one of the objects (masks: {', '.join(sorted(ms.objects.values()))}; "
                         f"objects: {', '.join(label)})", where)
    return out


def _run(args: argparse.Namespace) -> int:
    """Clean a labelled splat and build collision geometry + twin folder.

    Attribute filtering, DBSCAN connectivity pruning, alpha-shape meshing, convex decomposition and mass
    per object; table plane + obstacles for the background (label 0). Writes a twin folder (twin.json,
    meshes, splats, exports)."""
    from splattwin.lock import output_lock

    with output_lock(args.out):
        return _run_locked(args)


def _run_locked(args: argparse.Namespace) -> int:
    from splattwin.splat.gaussians import Gaussians
    from splattwin.poses.twin_frame import FRAME_SOURCES, TwinFrame
    from splattwin.twin.build import build_twin, check_formats

    ply = Path(args.splat)
    if args.frame not in FRAME_SOURCES:
        raise InputError(f"unknown frame source {args.frame!r} (choose from {', '.join(FRAME_SOURCES)})", "--frame")
    frame = TwinFrame(source=args.frame, scaled=args.frame != "unscaled")
    exports = from_args(ExportOptions, args)
    formats = exports.resolve()
    if not frame.scaled:
        print(f"note: the twin is unscaled (--frame {args.frame}): lengths in the splat's units, thresholds "
              "derived from the cameras or the scene size, every export marked unscaled")
    check_formats(frame, formats, "--formats")
    if not ply.is_file():
        raise InputError("no such splat PLY", ply)
    g = Gaussians.load_ply(ply)
    g.validate(ply)
    if len(g) == 0:
        raise InputError("the splat PLY holds no Gaussians (0 vertices)", ply)
    if args.labels:
        from splattwin.limits import load_npy

        lp = Path(args.labels)
        if not lp.is_file():
            raise InputError("no such label file", lp)
        arr = load_npy(lp, "label array")
        if arr.dtype.kind not in "iub":
            raise InputError(f"labels must be integers, got dtype {arr.dtype}", lp)
        # one label per Gaussian, as labels.npy is written (semantics' loader refuses other shapes too): a (1, N)
        # or (N, 1) array was flattened silently, and an (N, 3) array of something else would have been misread
        if arr.ndim != 1:
            raise InputError(f"labels must be a 1-D array (one label per Gaussian), got shape {arr.shape}", lp)
        labels = arr.astype(np.int64)
        if len(labels) != len(g):
            raise InputError(f"{len(labels)} labels for {len(g)} Gaussians in {ply.name}", lp)
        from splattwin.twin.manifest import MAX_LABEL

        # a negative label made no object at all, and the error then named the masks ("no mask names one of
        # the objects"); twin.json refuses labels above MAX_LABEL (16-bit label images)
        if len(labels) and (int(labels.min()) < 0 or int(labels.max()) > MAX_LABEL):
            raise InputError(f"labels must be within [0, {MAX_LABEL}] (0 = background), got {int(labels.min())} to "
                             f"{int(labels.max())}", lp)
        objects = [_parse_object(o) for o in args.object]
        if not objects and args.gt_scene and (Path(args.gt_scene) / "scene.json").is_file():
            from splattwin.twin.groundtruth import load_scene_gt

            objects = list(load_scene_gt(args.gt_scene)[0])  # the scene's names, prompts and labels
        objects = objects or [(f"object_{k}", int(k), "") for k in np.unique(labels) if k > 0]
    else:  # the whole splat is one object
        labels = np.ones(len(g), dtype=np.int64)
        objects = [(_parse_object(args.object[0])[0] if args.object else
                    object_name(ply.stem, ply, "object name (from the PLY file name; pass --object NAME=1)"), 1, "")]
    check_unique([o[0] for o in objects], "--object")
    opts = from_args(GeometryOptions, args)
    masks = None
    if args.masks:
        from splattwin.semantics.masks import load_masks

        if not args.cameras:
            raise InputError("--masks needs --cameras (the cameras the masks were drawn in, by view name)", "--masks")
        if not Path(args.masks).exists():
            raise InputError("no such mask file or folder", args.masks)
        masks = _object_masks(load_masks(args.masks, objects={name: label for name, label, *_ in objects}), objects,
                              args.masks)
    m = build_twin(g, labels, objects, args.out, frame, cameras_path=args.cameras, options=opts,
                   formats=formats, progress=args.progress, masks=masks, export_options=exports,
                   splats_path=ply)
    for o in m.objects:
        state = f"mass {o.mass:.3f} kg, {len(o.convex_parts)} convex part(s)" if o.usable else (
            f"UNUSABLE: {o.problem}" + ("; kept as a static obstacle box (an estimate)" if o.obstacle_only else ""))
        if o.silhouette_coverage is not None:
            state += f", covers {o.silhouette_coverage:.0%} of its masks"
        if o.usable and o.problem:
            state += f"; WARNING: {o.problem}"
        print(f"{o.name:16s} {state}")
    if args.gt_scene:
        evaluate(g, labels, objects, Path(args.gt_scene), opts, Path(args.out))
    print(f"twin written to {args.out}")
    return 0


def evaluate(g, labels, objects, scene_dir: Path, opts, out_dir: Path) -> dict:
    """Print the four-configuration ablation (paper Table 5) against a generated scene's GT meshes and
    write it to OUT/geometry_ablation.json."""
    from splattwin.console import console
    from rich.table import Table

    from splattwin import io
    from splattwin.geometry.convert import CONFIGS, ablation
    from splattwin.twin.groundtruth import load_scene_gt

    if not (scene_dir / "scene.json").is_file():
        raise InputError("not a generated scene (no scene.json)", scene_dir)
    _, meshes = load_scene_gt(scene_dir)
    ab = ablation(g, labels, objects, meshes, opts)
    t = Table(title=f"Fidelity vs ground truth (F1 threshold {opts.f1_threshold * 1000:.0f} mm)")
    t.add_column("object")
    for c in CONFIGS:
        t.add_column(f"{c}: CD mm / F1", justify="right")
    for name in ab["full"]:
        t.add_row(name, *[f"{ab[c][name].chamfer * 1e3:.2f} / {ab[c][name].f1:.3f}" for c in CONFIGS])
    console().print(t)
    result = {c: {n: f.to_dict() for n, f in v.items()} for c, v in ab.items()}
    io.write_json(out_dir / "geometry_ablation.json", result)
    return result


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "geometry", _run)
    p.add_argument("splat", metavar="SPLAT.ply", help="3DGS PLY (twin frame, metres)")
    p.add_argument("--labels", help="per-Gaussian int label array (.npy, 0 = background); omit: one object")
    p.add_argument("--object", action="append", default=[], metavar="NAME=LABEL[:PROMPT]",
                   help="object to build (repeatable); default: every label > 0")
    p.add_argument("--out", required=True, help="twin folder to write")
    p.add_argument("--cameras", help="cameras file (transforms.json, twin frame): referenced in the manifest, and the "
                   "meshes are carved against the splats' rendered depth from these cameras")
    p.add_argument("--masks", help="2D masks of the objects in the cameras' images (any layout `semantics` reads; "
                   "names as the objects'): each object's silhouette coverage decides with its splat count whether "
                   "it is whole (needs --cameras)")
    p.add_argument("--frame", default="unscaled", help="twin frame source recorded in the manifest")
    add_options(p, ExportOptions)
    p.add_argument("--gt-scene", help="generated scene folder: print + save the raw/attribute/cluster/full "
                                      "fidelity table against its GT meshes")
    add_options(p, GeometryOptions)
    p.add_argument("--voxel-remesh", dest=dest("use_alpha"), action="store_false", default=argparse.SUPPRESS,
                   help="= --no-use-alpha: marching cubes instead of alpha shapes (faster)")
    add_progress_flag(p)
