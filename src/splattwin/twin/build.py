"""Build the twin folder from labelled Gaussians: geometry per object + background, then exporters.

Layout (docs/CONTRACTS.md): splat/point_cloud.ply, semantics/labels.npy, objects/<name>/{splats.ply,
visual.obj, collision.obj, parts/part_XXX.obj} (object frame), background/{splats.ply, collision.obj,
parts/} (twin frame), export/..., twin.json. Every file is written atomically; the manifest is written
last, so a killed build never leaves a manifest pointing at missing files. Objects whose geometry failed
are listed with usable=False and a `problem`, and get no geometry files.

Object names become folder and file names: they are checked (`splattwin.names`) before anything is
written, and every folder written or removed is verified to lie inside the twin folder
(`splattwin.paths`), so nothing outside it is ever written or deleted.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from splattwin import io
from splattwin.geometry.convert import Conversion, check_objects, convert
from splattwin.geometry.options import GeometryOptions
from splattwin.names import check_unique, export_id, object_name
from splattwin.paths import LinkOutside, child, relative_to
from splattwin.poses.twin_frame import TwinFrame
from splattwin.splat.ply import write_gaussians_ply
from splattwin.twin.manifest import Background, Manifest, ObjectEntry, mass_source, units_text, unscaled_note  # noqa: F401
from splattwin.twin.options import FORMATS, ExportOptions
from splattwin.twin.splats import write_object_splats

log = logging.getLogger(__name__)


def default_formats(frame: TwinFrame) -> tuple[str, ...]:
    """The exports written when none are asked for: all of them (an unscaled twin's are marked so)."""
    return ExportOptions().resolve()


def check_formats(frame: TwinFrame, formats, where: str | Path | None = None) -> None:
    """InputError, before anything is written, for unknown formats."""
    from splattwin.errors import InputError

    for fmt in formats:
        if fmt not in FORMATS:
            raise InputError(f"unknown export format {fmt!r} (choose from {', '.join(FORMATS)})", where)


_VERSIONED = ("splattwin", "numpy", "scipy", "scikit-learn", "open3d-cpu", "trimesh", "coacd", "scikit-image", "mujoco",
              "torch")


def package_versions() -> dict[str, str]:
    out = {}
    for p in _VERSIONED:
        try:
            out[p] = importlib.metadata.version(p)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out


def write_mesh(path: Path, mesh: trimesh.Trimesh, header: str | None = None) -> Path:
    """Atomic mesh write; format from the suffix (.obj keeps vertex colours). header: `#` comment lines
    of an OBJ (its units and frame: OBJ has no unit field)."""
    kw = {"header": header} if header and path.suffix == ".obj" else {}
    with io.atomic_path(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lstrip("."), **kw)
    return path


def file_header(frame: TwinFrame, what_frame: str) -> str:
    """Comment lines (newline-separated, without the comment marker) of a written mesh or splat file."""
    return f"splattwin twin file; {units_text(frame)}\nframe: {what_frame}"


def _write_parts(folder: Path, parts: list, twin_dir: Path, header: str | None = None) -> list[str]:
    """Write part_XXX.obj into a fresh temporary folder, then swap it in: stale parts of an earlier build
    never survive and a killed build leaves the old complete set (or the new one; temporary folders of
    a killed build are removed by the next run, see `splattwin.io.clean_temp`)."""
    child(twin_dir, relative_to(folder, twin_dir) or str(folder))  # inside the twin folder, or InputError
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = io.temp_dir(folder.parent, folder.name)
    old = None
    try:
        for i, p in enumerate(parts):
            p.export(tmp / f"part_{i:03d}.obj", file_type="obj", **({"header": header} if header else {}))
            io.fsync_path(tmp / f"part_{i:03d}.obj")
        if folder.exists():
            old = io.temp_dir(folder.parent, f"{folder.name}.old")
            folder.rename(old / folder.name)
        tmp.rename(folder)
        io.fsync_path(folder.parent)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
        if old is not None and old.exists():
            shutil.rmtree(old)
    return [(folder / f"part_{i:03d}.obj").relative_to(twin_dir).as_posix() for i in range(len(parts))]


def _check_numbers(conv: Conversion, frame: TwinFrame, where: Path) -> None:
    """The manifest's checks (`Manifest.validate`) of what twin.json will record of `conv` -- labels,
    poses, box sizes, masses, the table -- before any file of the twin is written: a conversion the
    manifest refuses (a 3000 km obstacle box) leaves no half-written twin folder. Paths come later."""
    entries = []
    for r in conv.objects:
        e = ObjectEntry(name=r.name, label=r.label, prompt=r.prompt, usable=r.usable, problem=r.problem)
        if r.usable or r.obstacle:
            e.T_world_obj = np.asarray(r.T_world_obj).tolist()
            e.bbox_extent = np.asarray(r.extent).tolist()
            e.obstacle_only = not r.usable
        if r.usable:
            e.mass, e.volume = r.mass, r.volume
        entries.append(e)
    b = conv.background
    bg = Background() if b is None else Background(table_height=b.table_height, table_extent=list(b.table_extent),
                                                   table_thickness=b.table_thickness, table_default=b.default_reason)
    Manifest(frame=frame, objects=entries, background=bg).validate(where=where)


def write_geometry(conv: Conversion, g, labels: np.ndarray, out_dir: Path, frame: TwinFrame,
                   cameras_path: str | Path | None = None, splats_path: str | Path | None = None,
                   refined_poses: str | Path | None = None) -> Manifest:
    """Write splats, meshes and parts of a Conversion into the twin folder; return the manifest (not saved).
    splats_path: the file `g` was read from; when it is the twin's own splat/point_cloud.ply (the pipeline's
    splats stage wrote it) it is not rewritten: the stage recorded its contents, and new bytes (the unit
    comment) would make every later build train again."""
    out_dir = Path(out_dir)
    for r in conv.objects:
        object_name(r.name)
    check_unique([r.name for r in conv.objects])
    _check_numbers(conv, frame, out_dir / "twin.json")
    twin_hdr = file_header(frame, "twin frame (z up)")
    obj_hdr = file_header(frame, "object frame (z up; twin.json T_world_obj places it in the twin frame)")
    scene_ply = out_dir / "splat" / "point_cloud.ply"
    if not (splats_path is not None and scene_ply.is_file() and Path(splats_path).resolve() == scene_ply.resolve()):
        write_gaussians_ply(scene_ply, g, twin_hdr.split("\n"))
    io.write_npy(out_dir / "semantics" / "labels.npy", np.asarray(labels, dtype=np.int32))
    entries = []
    # an earlier build's objects that are not in this one (masks changed): their folders go too
    io.remove_stale(out_dir / "objects", {r.name for r in conv.objects}, dirs=True)
    for r in conv.objects:
        e = ObjectEntry(name=r.name, label=r.label, prompt=r.prompt, usable=r.usable, problem=r.problem,
                        export_id=export_id(r.name))
        if r.coverage is not None:
            e.silhouette_coverage = round(r.coverage.recall, 4)
            e.silhouette_precision = round(r.coverage.precision, 4)
        odir = child(child(out_dir, "objects"), r.name)
        if r.usable:
            write_object_splats(odir / "splats.ply", g.subset(r.indices), r.T_world_obj, obj_hdr.split("\n"))
            write_mesh(odir / "visual.obj", r.visual, obj_hdr)
            write_mesh(odir / "collision.obj", r.collision, obj_hdr)
            e.T_world_obj = np.asarray(r.T_world_obj).tolist()
            e.bbox_extent = np.asarray(r.extent).tolist()
            e.mass, e.volume = r.mass, r.volume
            if r.mass is not None:
                e.mass_source = mass_source(conv.options.density, frame.scaled)
            e.splat_ply = f"objects/{r.name}/splats.ply"
            e.visual_mesh = f"objects/{r.name}/visual.obj"
            e.collision_mesh = f"objects/{r.name}/collision.obj"
            e.convex_parts = _write_parts(odir / "parts", r.parts, out_dir, obj_hdr)
        else:
            if odir.exists():  # never leave geometry of an earlier build behind for an unusable object
                shutil.rmtree(odir)
            if r.obstacle:  # where the real object stands: a static box in every collision export
                e.obstacle_only = True
                e.T_world_obj = np.asarray(r.T_world_obj).tolist()
                e.bbox_extent = np.asarray(r.extent).tolist()
                ext = " x ".join(f"{v:.3g}" for v in r.extent)  # problem stays the cause: obstacle_only says the rest
                unit = "m" if frame.scaled else "frame units"
                log.warning("object %r is unusable (%s): kept in the collision exports as a static obstacle box "
                            "%s %s at (%s) %s, an estimate; a robot cannot grasp it", r.name, r.problem, ext, unit,
                            ", ".join(f"{v:.3g}" for v in r.T_world_obj[:3, 3]), unit)
            else:
                e.problem = (f"{r.problem}; no splats of it survive, so it has no geometry at all: it is in no "
                             f"collision export and nothing marks where it stands")
                log.warning("object %r is unusable (%s) and has no geometry at all: it is in no collision export; "
                            "if it is in the scene, a robot will not see it", r.name, r.problem)
        entries.append(e)
    bg = Background()
    b = conv.background
    if b is not None:
        bg = Background(table_height=b.table_height, table_extent=list(b.table_extent), table_thickness=b.table_thickness,
                        table_default=b.default_reason)
        if len(b.indices):
            write_gaussians_ply(out_dir / "background" / "splats.ply", g.subset(b.indices), twin_hdr.split("\n"))
            bg.splat_ply = "background/splats.ply"
        if b.collision is not None:
            write_mesh(out_dir / "background" / "collision.obj", b.collision, twin_hdr)
            bg.collision_mesh = "background/collision.obj"
            bg.convex_parts = _write_parts(out_dir / "background" / "parts", b.parts, out_dir, twin_hdr)
    cams = None
    config: dict = {"geometry": conv.options.to_dict(), "depth_carving": depth_carving_record(conv)}
    if cameras_path is not None:
        # referenced, not copied: a path relative to the twin folder when inside it (a relative path that
        # exists inside the twin folder is taken as relative to it). A cameras file outside the twin is
        # only recorded (config.cameras_source): twin.json holds no path leading out of the folder.
        cp = Path(cameras_path)
        if not cp.is_absolute() and (out_dir / cp).exists():
            cams = relative_to(out_dir / cp, out_dir)
        else:
            cams = relative_to(cp, out_dir)
        if cams is None:
            config["cameras_source"] = str(cp.resolve())
    if refined_poses is not None:  # the cameras' poses as refined with the splats (absent without refinement)
        config["refined_poses"] = relative_to(Path(refined_poses), out_dir) or str(Path(refined_poses).resolve())
    return Manifest(frame=frame, objects=entries, background=bg, cameras=cams, splats="splat/point_cloud.ply",
                    labels="semantics/labels.npy", config=config,
                    versions=package_versions(), timings={f"geometry.{k}": round(float(v), 4) for k, v in conv.timings.items()})


def _exporter(fmt: str):
    if fmt == "mjcf":
        try:
            return importlib.import_module("splattwin.twin.mjcf").export_mjcf
        except (ImportError, AttributeError):
            return None
    mod = importlib.import_module(f"splattwin.twin.{fmt}")
    return getattr(mod, f"export_{fmt}")


# the files each exporter writes under TWIN/export/ (urdf: also one <object>.urdf per usable object)
EXPORT_FILES = {
    "mjcf": ("scene.xml",),
    "urdf": ("scene.urdf",),
    "moveit": ("moveit/scene.scene", "moveit/scene_boxes.scene", "moveit/collision_objects.yaml",
               "moveit/collision_objects_boxes.yaml"),
    "gltf": ("scene.glb",),
}


def remove_exports(twin_dir: str | Path, formats) -> list[Path]:
    """Remove the files of the exports `formats` from TWIN/export/: only our own file names (every
    *.urdf for urdf), never through a link; export/moveit/ goes when it is then empty. Returns what went."""
    out = Path(twin_dir) / "export"
    removed: list[Path] = []
    if out.is_symlink() or not out.is_dir():
        return removed
    for fmt in formats:
        if fmt == "urdf":
            removed += io.remove_stale(out, set(), suffix=".urdf")
        by_folder: dict[str, list[str]] = {}
        for rel in EXPORT_FILES.get(fmt, ()):
            folder, _, name = rel.rpartition("/")
            by_folder.setdefault(folder, []).append(name)
        for folder, names in by_folder.items():
            removed += io.remove_files(out / folder if folder else out, names, empty_folder=bool(folder))
    return removed


def export_twin(twin_dir: str | Path, manifest: Manifest | None = None, formats=FORMATS, prune: bool = False,
                options: ExportOptions | None = None) -> Manifest:
    """Run the exporters on a twin folder and record their outputs and timings in the manifest (saved).
    See `write_exports`; returns the manifest."""
    twin_dir = Path(twin_dir)
    manifest = manifest or Manifest.load(twin_dir)
    write_exports(twin_dir, manifest, formats, prune=prune, options=options)
    return manifest


def _file_entry(path: str, fmt: str, frame: str, manifest: Manifest, **more) -> dict:
    f = manifest.frame
    return {"path": path, "format": fmt, "frame": frame, "units": "m" if f.scaled else "unscaled",
            "scaled": bool(f.scaled), **more}


def describe_exports(twin_dir: Path, manifest: Manifest, written, options: ExportOptions) -> list[dict]:
    """twin.json `export_files`: every file of the twin a consumer opens, with its format, frame, units,
    scale status and conventions. Exports of formats written now are described with this run's options;
    the entries of earlier runs' exports (still listed in `exports`) are kept; files not on disk are left out."""
    twin_dir = Path(twin_dir)
    out: list[dict] = []
    obj_frame = "object frame of {} (z up; twin.json T_world_obj places it in the twin frame)"
    if manifest.splats:
        out.append(_file_entry(manifest.splats, "3DGS PLY", "twin (z up)", manifest))
    b = manifest.background
    if b.splat_ply:
        out.append(_file_entry(b.splat_ply, "3DGS PLY", "twin (z up)", manifest))
    if b.collision_mesh:
        out.append(_file_entry(b.collision_mesh, "OBJ", "twin (z up)", manifest))
    # the convex parts: the meshes MJCF and URDF load (`file="../background/parts/part_001.obj"`); part 0 is
    # the table box, which every export writes as a box primitive
    part = "convex collision part (loaded by the MJCF and URDF exports)"
    table = "the table box as a mesh (the exports write it as a box primitive)"
    for k, p in enumerate(b.convex_parts or []):
        out.append(_file_entry(str(p), "OBJ", "twin (z up)", manifest, role=part if k else table))
    for o in manifest.objects:
        frame = obj_frame.format(o.export_id or export_id(o.name))
        for k, fmt in (("splat_ply", "3DGS PLY"), ("visual_mesh", "OBJ"), ("collision_mesh", "OBJ")):
            if getattr(o, k):
                out.append(_file_entry(getattr(o, k), fmt, frame, manifest, object=o.name))
        for p in o.convex_parts or []:
            out.append(_file_entry(str(p), "OBJ", frame, manifest, object=o.name, role=part))
    uri = options.urdf_uri
    for fmt, rel in manifest.exports.items():
        if fmt not in written:   # an earlier run's export: its description stays as recorded
            out += [e for e in manifest.export_files if e.get("export") == fmt]
            continue
        if fmt == "mjcf":
            out.append(_file_entry(rel, "MJCF", "twin (the MuJoCo world frame, z up)", manifest, export=fmt,
                                   quaternion="wxyz", mesh_paths="relative to the file"))
        elif fmt == "urdf":
            out.append(_file_entry(rel, "URDF", "twin (link world, z up)", manifest, export=fmt, orientation="rpy",
                                   mesh_paths=uri))
            for o in manifest.objects:
                if o.usable:
                    out.append(_file_entry(f"export/{export_id(o.name)}.urdf", "URDF", obj_frame.format(
                        export_id(o.name)), manifest, export=fmt, object=o.name, mesh_paths=uri))
        elif fmt == "moveit":
            for name, kind in (("scene.scene", "MoveIt .scene text"), ("scene_boxes.scene", "MoveIt .scene text"),
                               ("collision_objects.yaml", "moveit_msgs/CollisionObject list (YAML)"),
                               ("collision_objects_boxes.yaml", "moveit_msgs/CollisionObject list (YAML)")):
                out.append(_file_entry(f"export/moveit/{name}", kind, f"twin (frame_id {options.moveit_frame!r}, "
                                       f"z up; not the robot base)", manifest, export=fmt, quaternion="xyzw",
                                       shapes="object boxes" if "boxes" in name else "collision meshes"))
        elif fmt == "gltf":
            out.append(_file_entry(rel, "glTF binary", "glTF y up: root node twin_z_up rotates the z-up twin frame "
                                   "(-90 degrees about x)", manifest, export=fmt, quaternion="xyzw"))
    return [e for e in out if (twin_dir / e["path"]).is_file()]


def write_exports(twin_dir: str | Path, manifest: Manifest, formats=FORMATS, prune: bool = False,
                  options: ExportOptions | None = None) -> dict[str, str]:
    """Run the exporters of `formats`; returns {format: path relative to the twin} of those written now.
    options: the exports' options (URDF mesh URIs, MoveIt frame); `manifest.export_files` then
    describes every file (`describe_exports`).

    prune=False (`splattwin export` on an unchanged twin): `manifest.exports` (saved) then records what is
    on disk: the formats written now, plus exports of earlier runs whose file is still there (an export
    only reads the twin, so they still describe it); an earlier export whose file is gone is dropped,
    so twin.json never lists a missing file.
    prune=True (the geometry was just rebuilt, `build_twin`): earlier exports describe meshes that are
    gone, so the files of every format not written now (not asked for, or its exporter unavailable)
    are removed (`remove_exports`) and twin.json lists only this run's exports.
    Each exporter writes its files atomically (temporary name, then rename), so a re-export replaces
    files whole or not at all. Unknown formats raise InputError."""
    twin_dir = Path(twin_dir)
    options = options or ExportOptions()
    check_formats(manifest.frame, formats, twin_dir / "twin.json")
    # entries of files that are gone (or of formats rewritten now) go before an exporter saves the manifest
    manifest.export_files = [e for e in manifest.export_files if (twin_dir / e["path"]).is_file()
                             and e.get("export") not in formats]
    if prune:   # before exporting: a failing exporter then leaves no stale file of another format behind
        remove_exports(twin_dir, [f for f in FORMATS if f not in formats])
    # drop before exporting: an exporter may save the manifest itself (export_mjcf does)
    for fmt, rel in list(manifest.exports.items()):
        if (prune and fmt not in formats) or not (twin_dir / rel).is_file():   # rel was confined to the twin folder when loaded
            log.info("export %s (%s) no longer exists; dropped from twin.json", fmt, rel)
            del manifest.exports[fmt]
    written: dict[str, str] = {}
    for fmt in formats:
        fn = _exporter(fmt)
        if fn is None:
            log.warning("export format %s not available yet (splattwin.twin.%s missing); skipped", fmt, fmt)
            if prune:
                remove_exports(twin_dir, [fmt])
                manifest.exports.pop(fmt, None)
            continue
        t0 = time.perf_counter()
        path = Path(fn(twin_dir, manifest, options=options))
        written[fmt] = manifest.exports[fmt] = path.resolve().relative_to(twin_dir.resolve()).as_posix()
        manifest.timings[f"export.{fmt}"] = round(time.perf_counter() - t0, 4)
    manifest.export_files = describe_exports(twin_dir, manifest, written, options)
    manifest.save(twin_dir)
    return written


def _capture(out_dir: Path, cameras_path, refined_poses=None) -> tuple[list | None, float | None]:
    """(frames, depth scale): the capture's frames (names, cameras in the twin frame, depth files) from the
    cameras file and its metres per raw depth unit (`Dataset.depth_scale`), or (None, None) (no file, or
    unreadable: the cameras only refine the geometry, so a bad file is a warning here, never a failed build).
    refined_poses: the splat stage's refined_poses.json (`splattwin.splat.refined_poses`), whose poses replace
    the file's (the splats were fitted to those cameras)."""
    if cameras_path is None:
        return None, None
    cp = Path(cameras_path)
    cp = out_dir / cp if not cp.is_absolute() and (out_dir / cp).exists() else cp
    if not cp.is_file():
        return None, None
    try:
        from splattwin.capture import load_dataset

        from splattwin.splat import refined_poses as rp

        ds = load_dataset(cp, validate=False, require_images=False)
        return list(rp.apply(ds, refined_poses).frames), ds.depth_scale
    except LinkOutside:   # not a bad file but a planted link: nothing is read through it
        raise
    except Exception as e:  # noqa: BLE001 - see the docstring
        log.warning("cameras not read from %s (geometry without them): %s", cp, e)
        return None, None


def _measured_depth(frames: list | None, depth_scale: float | None, silhouettes: dict | None, frame: TwinFrame,
                    opts: GeometryOptions):
    """(label -> [(camera, sensor depth)], None) for carving the meshes against the capture's measured depth
    (`geometry.carving.measured_views`, one object at a time), or (None, why not). Depth maps are read
    (`load_depth`, metres) only for the views chosen, at most `carve_views` per object; one that cannot be
    read is left out with a warning (the depth only refines the geometry)."""
    from splattwin.capture.dataset import load_depth
    from splattwin.errors import InputError
    from splattwin.geometry.carving import measured_views

    if not opts.carve_depth:
        return None, "off (--no-geometry.carve-depth)"
    if not frames or not any(f.depth_path is not None for f in frames):
        return None, "the capture has no depth maps"
    if not frame.scaled:
        return None, "the twin is unscaled (its units are not the depth's metres)"
    by_cam = {id(f.camera): f for f in frames}
    has_depth = lambda cam: by_cam[id(cam)].depth_path is not None  # noqa: E731
    if not silhouettes or not any(has_depth(c) for v in silhouettes.values() for c, _ in v):
        return None, "no view with both a depth map and a 2D mask of an object (the depth is only trusted inside " \
                     "an object's own visible mask)"

    def depth_of(cam):
        f = by_cam[id(cam)]
        try:
            return load_depth(f.depth_path, depth_scale, size=(cam.width, cam.height))
        except InputError as e:
            log.warning("depth map not read for carving (%s): view %s left out", e, f.name)
            return np.zeros((cam.height, cam.width), np.float32)

    def of(label: int) -> list:
        return measured_views(silhouettes.get(int(label), []), depth_of, has_depth, max_views=opts.carve_views,
                              erode_px=opts.carve_depth_erode)
    return of, None


@dataclasses.dataclass
class CaptureViews:
    """What the geometry sees of the capture (`capture_views`): the cameras (twin frame) or None, the
    objects' 2D masks paired with them ({label: [(camera, bool mask [H,W])]}) or None, the measured depth
    for carving (label -> [(camera, sensor depth [H,W] m)], `convert`'s `measured`) or None, and why that
    carving is skipped (None when it runs)."""

    cameras: list | None
    silhouettes: dict | None
    measured: Callable[[int], list] | None
    depth_skipped: str | None


def capture_views(out_dir: str | Path, cameras_path, frame: TwinFrame, options: GeometryOptions | None = None,
                  masks=None, refined_poses=None) -> CaptureViews:
    """The capture as `build_twin` hands it to `convert`: its frames from the cameras file (a path relative to
    `out_dir` when it exists there; poses replaced by `refined_poses`, `_capture`), the MaskSet `masks`
    paired with them by view name (`geometry.completeness.mask_views`), and their depth maps for carving
    against the measured depth (`_measured_depth`: a metric frame, views with both depth and a mask).
    One place for the twin stage and bench/geometry.py --twin-from, so the bench carves as a build does."""
    from splattwin.geometry.completeness import mask_views

    frames, depth_scale = _capture(Path(out_dir), cameras_path, refined_poses)
    silhouettes = mask_views(masks, frames) if masks is not None and frames else None
    measured, skipped = _measured_depth(frames, depth_scale, silhouettes, frame, options or GeometryOptions())
    return CaptureViews([f.camera for f in frames] if frames else None, silhouettes, measured, skipped)


def depth_carving_record(conv: Conversion) -> dict:
    """twin.json config.depth_carving: whether the meshes were carved against the capture's measured depth
    (`used`, or `skipped` with why), the options that set it, and per object the views used and how many of
    its points (centres and ellipsoid samples) were dropped as free space."""
    o = conv.options
    rec: dict = {"used": conv.depth_skipped is None, "tolerance": o.carve_depth_tolerance,
                 "noise_1m": o.carve_depth_noise, "erode_px": o.carve_depth_erode}
    if conv.depth_skipped is not None:
        rec["skipped"] = conv.depth_skipped
        return rec
    rec["objects"] = {r.name: {"views": r.depth_views, "points": r.depth_points, "dropped": r.depth_carved}
                      for r in conv.objects if r.depth_points is not None}
    return rec


def _estimated_nominal_metre(gaussians, cameras: list | None) -> float:
    """An unscaled frame without a recorded nominal metre (e.g. `splattwin geometry --frame unscaled`):
    estimated from the cameras and the splat centres, else from the scene's extent."""
    from splattwin.geometry.options import scene_scale
    from splattwin.poses.table import nominal_metre

    if cameras:
        value = nominal_metre(cameras, gaussians.means)
        if value is not None:
            return value
    return scene_scale(gaussians.means) / NOMINAL_SCENE_SIZE


def table_plane(frame: TwinFrame):
    """The table plane z = 0 when the poses stage built the frame on the table (`poses.up`'s evidence
    names it), else None (fitted). The frame's plane came from the SfM points, free of the splats' far
    field, so it is the better estimate; refitting on the splats took a far plane (the cake)."""
    from splattwin.geometry.clustering import Plane

    table = (frame.up_check or {}).get("table")
    if table in ("dominant plane", "level plane under a wall"):
        return Plane(normal=np.array([0.0, 0.0, 1.0]), d=0.0)
    return None


# robust diagonal (m) of a tabletop scene's splats (the embedded scene's is about this): the last-resort
# guess of an unscaled twin's nominal metre when there are no cameras to measure the viewing distance
NOMINAL_SCENE_SIZE = 1.2


def build_twin(gaussians, labels: np.ndarray, objects: list, out_dir: str | Path, frame: TwinFrame | None = None,
               cameras_path: str | Path | None = None, options: GeometryOptions | None = None,
               formats=FORMATS, progress: bool = True, masks=None, export_options: ExportOptions | None = None,
               splats_path: str | Path | None = None, refined_poses: str | Path | None = None) -> Manifest:
    """Labelled Gaussians -> twin folder with manifest and exports.

    gaussians: splattwin.splat.Gaussians [N] (twin frame, m) or a PLY path; labels [N] int (0 = background);
    objects: [(name, label, prompt)] (`check_objects`). masks: the 2D masks the labels were fused from (a
    `semantics.masks.MaskSet`, labels as in `objects`), paired with the cameras file's frames by view
    name: each object's silhouette coverage (`geometry.completeness`) is measured and decides, with its
    splat count, whether it is whole; None: the count alone. refined_poses: the splat stage's
    refined_poses.json (training with pose refinement): the cameras file's poses are replaced by its ones
    (recorded in twin.json config.refined_poses). Returns the saved Manifest."""
    from splattwin.errors import require_type
    from splattwin.lock import prepare_output_dir
    from splattwin.splat.gaussians import Gaussians

    if isinstance(gaussians, (str, Path)):   # a PLY path, as fuse_to_dir takes (a str failed deep inside)
        gaussians = Gaussians.load_ply(gaussians)
    require_type(gaussians, Gaussians, "gaussians", "or a 3DGS PLY path")
    objects = check_objects(objects)
    out_dir = prepare_output_dir(out_dir, "twin folder")
    frame = frame or TwinFrame()
    check_formats(frame, formats, out_dir / "twin.json")
    t0 = time.perf_counter()
    views = capture_views(out_dir, cameras_path, frame, options, masks, refined_poses)
    cameras = views.cameras
    length_scale = frame.length_scale(None if frame.scaled else _estimated_nominal_metre(gaussians, cameras))
    if not frame.scaled:
        log.info("unscaled twin: metric thresholds x %.4g (frame units per nominal metre)", length_scale)
        frame = dataclasses.replace(frame, nominal_metre=frame.nominal_metre or round(length_scale, 6))
    conv = convert(gaussians, labels, objects, options, progress=progress, length_scale=length_scale, cameras=cameras,
                   table_plane=table_plane(frame), masks=views.silhouettes, measured=views.measured)
    if views.depth_skipped is not None:
        conv.depth_skipped = views.depth_skipped
    t1 = time.perf_counter()
    manifest = write_geometry(conv, gaussians, labels, out_dir, frame, cameras_path, splats_path, refined_poses)
    manifest.timings["write"] = round(time.perf_counter() - t1, 4)
    manifest.timings["geometry"] = round(t1 - t0, 4)
    manifest.save(out_dir)
    # the geometry was rebuilt: exports of formats not written now would describe meshes that are gone
    return export_twin(out_dir, manifest, formats, prune=True, options=export_options)
