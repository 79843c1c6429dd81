"""Generate the embedded tabletop benchmark scene (layout in docs/CONTRACTS.md, "Embedded scene").

`generate(out_dir, SceneOptions(...)) -> out_dir`: lays out the objects (seeded), renders RGB / z-depth /
GT labels for every view by CPU ray casting, simulates a segmenter's masks per view and object, and writes
meshes, nerfstudio `transforms.json` and `scene.json`. Same seed and options give byte-identical files
(PNG with fixed settings, no timestamps, JSON with exact float reprs).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import trimesh

from splattwin.capture.camera import Camera, opencv_from_opengl
from splattwin.errors import InputError
from splattwin.io import atomic_path, write_image, write_json, write_npy
from splattwin.scene import textures as tx
from splattwin.scene.cameras import scan_cameras
from splattwin.scene.marker import TableMarker
from splattwin.scene.objects import (ROBOT_BASE_XY, TABLE_EXTENT, TABLE_THICKNESS, SceneObject, make_objects,
                                     sample_layout, table_mesh)
from splattwin.scene.options import SceneOptions
from splattwin.scene.raycast import AMBIENT, DIFFUSE, LIGHT_DIR, SceneRenderer, Surface
from splattwin.scene.segmenter import segment

log = logging.getLogger(__name__)

FORMAT_VERSION = 1


def build_scene(options: SceneOptions) -> tuple[list[SceneObject], dict, TableMarker | None, SceneRenderer]:
    """Objects with poses, layout info, optional marker and a renderer over table + objects."""
    objects = make_objects(options.seed)
    layout = sample_layout(objects, options.seed, options.marker_size)
    marker = None
    if options.marker:
        mx, my = layout["marker_xy"]
        marker = TableMarker(options.marker_id, options.marker_size, float(mx), float(my), layout["marker_yaw"])
    tf = layout["target_frame"]
    table_albedo = tx.table_albedo(options.seed, np.array(tf["center"]), tf["size"], tf["tape_width"],
                                   marker=marker.texture() if marker is not None else None)
    surfaces = [Surface("table", 0, table_mesh(), np.eye(4), table_albedo)]
    surfaces += [Surface(o.name, o.label, o.mesh_world(), o.T_world_obj, o.albedo) for o in objects]
    return objects, layout, marker, SceneRenderer(surfaces, shadows=options.shadows)


def look_target(objects: list[SceneObject]) -> np.ndarray:
    """Point the scan looks at: centre of the objects' footprint centres, 3 cm above the table."""
    xy = np.mean([o.T_world_obj[:2, 3] for o in objects], axis=0)
    return np.array([xy[0], xy[1], 0.03])


def write_mesh_ply(path: Path, mesh: trimesh.Trimesh) -> None:
    """Binary PLY of `mesh`'s vertices and faces at `path`, written atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=False))


def to_u8(rgb: np.ndarray) -> np.ndarray:
    """uint8 image [...] of colours [...] in [0, 1], rounded and clipped."""
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


PALETTE = np.array([[0, 0, 0], [230, 160, 60], [40, 90, 255], [255, 230, 0], [255, 40, 40], [40, 200, 90]] +
                   [[int(x) for x in np.random.default_rng(k).integers(60, 255, 3)] for k in range(250)],
                   dtype=np.uint8)


def preview_image(views: list[dict[str, np.ndarray]], noisy: list[np.ndarray]) -> np.ndarray:
    """Contact sheet [3H, nW, 3] uint8: rendered views; GT labels over the image; depth (near = bright)
    with the union of the noisy masks outlined in white."""
    rows = [[], [], []]
    for v, nm in zip(views, noisy):
        rgb = to_u8(v["rgb"])
        rows[0].append(rgb)
        lab = v["labels"]
        over = rgb.copy()
        on = lab > 0
        over[on] = (0.35 * rgb[on] + 0.65 * PALETTE[lab[on]]).astype(np.uint8)
        rows[1].append(over)
        d = v["depth"]
        fin = np.isfinite(d)
        g = np.zeros(d.shape, np.uint8)
        if fin.any():
            lo, hi = float(d[fin].min()), float(d[fin].max())
            g[fin] = np.round(255 * (1 - (d[fin] - lo) / max(hi - lo, 1e-6)) * 0.8 + 40).astype(np.uint8)
        dep = np.repeat(g[..., None], 3, axis=2)
        edge = nm & ~cv2.erode(nm.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        dep[edge] = [255, 60, 200]
        rows[2].append(dep)
    return np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)


def transforms_json(cameras: list[Camera], objects: list[SceneObject] = ()) -> dict:
    """nerfstudio transforms.json (shared intrinsics, OpenGL camera-to-world per frame). `label_objects`
    names the ids of the ground-truth label images (`label_path`), so that metrics match objects by name."""
    c0 = cameras[0]
    frames = []
    for cam in cameras:
        split = "heldout" if cam.name.startswith("heldout") else "train"
        frames.append({"file_path": f"images/{cam.name}.png", "transform_matrix": cam.T_world_cam_gl.tolist(),
                       "depth_file_path": f"depth/{cam.name}.npy", "label_path": f"masks/gt/{cam.name}.png",
                       "split": split})
    return {
        "camera_model": "OPENCV", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy,
        "w": c0.width, "h": c0.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
        "train_filenames": [f["file_path"] for f in frames if f["split"] == "train"],
        "test_filenames": [f["file_path"] for f in frames if f["split"] == "heldout"],
        "label_objects": {o.name: int(o.label) for o in objects if o.label > 0},
    }


def generate(out_dir: str | Path, options: SceneOptions | None = None, progress: bool = True) -> Path:
    """Write the scene into `out_dir` (created; existing scene files are overwritten). Returns `out_dir`.

    Raises InputError for invalid options or an `out_dir` that is a file.
    """
    options = options or SceneOptions()
    options.validate()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a directory", out)
    out.mkdir(parents=True, exist_ok=True)
    # scene.json is written last and marks a complete scene: drop an old one first, so a run killed while
    # overwriting a scene never leaves a folder that looks complete
    (out / "scene.json").unlink(missing_ok=True)

    objects, layout, marker, renderer = build_scene(options)
    cameras = scan_cameras(options.views, options.heldout, options.width, options.height, options.fov_x,
                           look_target(objects), options.seed)

    for surf in renderer.surfaces:
        write_mesh_ply(out / "meshes" / f"{surf.name}.ply", surf.mesh_world)

    _remove_stale_views(out, {c.name for c in cameras}, [o.name for o in objects])
    noise_events: dict[str, dict] = {}
    preview_at = set(np.linspace(0, len(cameras) - 1, min(4, len(cameras))).round().astype(int).tolist())
    previews: list[tuple[dict, np.ndarray]] = []
    from splattwin.progress import Progress

    with Progress(len(cameras), "rendering scene views", unit="view", enabled=progress) as bar:
        for vi, cam in enumerate(cameras):
            view = renderer.render(cam, options.supersample)
            write_image(out / "images" / f"{cam.name}.png", to_u8(view["rgb"]))
            write_npy(out / "depth" / f"{cam.name}.npy", view["depth"])
            write_image(out / "masks" / "gt" / f"{cam.name}.png", view["labels"])
            ev = {}
            union = np.zeros(view["labels"].shape, bool)
            for obj in objects:
                rng = np.random.default_rng([options.seed, 3, vi, obj.label])
                mask, e = segment(view["labels"], view["depth"], obj.label, options.noise, rng)
                write_image(out / "masks" / "noisy" / cam.name / f"{obj.name}.png", mask.astype(np.uint8) * 255)
                ev[obj.name] = e
                union |= mask
            if vi in preview_at:
                previews.append((view, union))
            noise_events[cam.name] = ev
            bar.update(1)

    write_image(out / "preview.png", preview_image([v for v, _ in previews], [m for _, m in previews]))
    write_json(out / "transforms.json", transforms_json(cameras, objects))
    scene = scene_record(options, objects, layout, marker, [c.name for c in cameras])
    scene["preview"] = "preview.png"
    scene["noise"] = {**options.noise.to_dict(), "events": noise_events}
    write_json(out / "scene.json", scene)
    log.debug("scene written to %s", out)
    return out


def scene_record(options: SceneOptions, objects: list[SceneObject], layout: dict, marker: TableMarker | None,
                 views: list[str]) -> dict:
    """The ground-truth part of scene.json (world frame, robot base, table, objects, target, light)."""
    return {
        "format_version": FORMAT_VERSION,
        "seed": options.seed,
        "options": options.to_dict(),
        "world_frame": "table frame: z up, table top at z = 0, origin at the table centre; metres",
        "robot_base": {"T_world_base": [[1, 0, 0, float(ROBOT_BASE_XY[0])], [0, 1, 0, float(ROBOT_BASE_XY[1])],
                                        [0, 0, 1, 0], [0, 0, 0, 1]]},
        "table": {"extent": list(TABLE_EXTENT), "thickness": TABLE_THICKNESS, "mesh": "meshes/table.ply",
                  "label": 0},
        "objects": [o.to_json() for o in objects],
        "target_frame": {**layout["target_frame"], "for": "toy_hammer"},
        "marker": marker.to_json() if marker is not None else None,
        "light": {"direction_world": LIGHT_DIR.tolist(), "ambient": AMBIENT, "diffuse": DIFFUSE,
                  "shadows": options.shadows},
        "views": views,
    }


def _remove_stale_views(out: Path, views: set[str], objects: list[str]) -> None:
    """Delete view files of an earlier generation into the same folder that this one will not rewrite."""
    for sub, ext in (("images", ".png"), ("depth", ".npy"), ("masks/gt", ".png")):
        for p in (out / sub).glob(f"*{ext}"):
            if p.stem.startswith(("train_", "heldout_")) and p.stem not in views:
                p.unlink()
    noisy = out / "masks" / "noisy"
    for d in noisy.glob("*") if noisy.is_dir() else []:
        if d.is_dir() and d.name.startswith(("train_", "heldout_")) and d.name not in views:
            for f in d.glob("*.png"):
                if f.stem in objects:
                    f.unlink()
            if not any(d.iterdir()):
                d.rmdir()


def load_scene(scene_dir: str | Path) -> dict:
    """Read `scene_dir/scene.json` (InputError if missing or malformed)."""
    from splattwin.limits import read_json

    path = Path(scene_dir) / "scene.json"
    d = read_json(path, missing="no scene.json: not a generated scene directory")   # bounded
    if not isinstance(d, dict):
        raise InputError(f"scene.json must hold a JSON object, got {type(d).__name__}", path)
    for key in ("objects", "table", "target_frame", "seed"):
        if key not in d:
            raise InputError(f"scene.json lacks '{key}'", path)
    return d


def scene_cameras(scene_dir: str | Path) -> list[Camera]:
    """The cameras written to `scene_dir/transforms.json`, in file order, OpenCV convention, named by view."""
    from splattwin.limits import read_json

    path = Path(scene_dir) / "transforms.json"
    d = read_json(path, missing="no transforms.json: not a generated scene directory")   # bounded
    try:
        K = np.array([[d["fl_x"], 0, d["cx"]], [0, d["fl_y"], d["cy"]], [0, 0, 1.0]], dtype=np.float64)
        return [Camera(K=K, width=d["w"], height=d["h"], T_world_cam=opencv_from_opengl(
                    np.array(f["transform_matrix"], dtype=np.float64)), name=Path(f["file_path"]).stem)
                for f in d["frames"]]
    except (KeyError, TypeError, ValueError, IndexError) as e:   # another writer's file: not the scene's layout
        raise InputError(f"not a generated scene's transforms.json ({type(e).__name__}: {e})", path) from None
