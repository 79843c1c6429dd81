"""The twin stage as the pipeline runs it: `run(TwinInputs, TwinOptions) -> TwinResult`.

Reads the trained splats, the fused labels and objects, the frame definition; writes the twin folder
(twin.json, objects/, background/, export/: `splattwin.twin.build`, the only writer of twin.json) with
the build's resolved options recorded in twin.json (`config.build`). With an embedded scene's ground
truth (`inputs.scene_dir`): its goal region travels into twin.json (`config.target_frame`) and each
object's visual mesh is scored against the GT mesh (TWIN/geometry_metrics.json, written only here).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from splattwin.twin.options import TwinOptions


@dataclass
class TwinInputs:
    splats: Path                          # trained 3DGS PLY (twin frame, m)
    labels: Path                          # labels.npy, int per Gaussian (0 background)
    objects: Path                         # objects.json: [[name, label, prompt], ...]
    frame: Path                           # frame.json of the poses stage
    twin_dir: Path                        # the twin folder (written in place)
    cameras: str | None = None            # cameras file referenced by the manifest (relative to twin_dir)
    refined_poses: Path | None = None     # the splat stage's refined_poses.json (its poses replace the cameras')
    scene_dir: Path | None = None         # an embedded scene's folder (ground truth), if the input is one
    config: dict = field(default_factory=dict)   # the build's resolved options, recorded in twin.json
    masks: Any = None                     # the semantics stage's 2D masks (MaskSet): each object's silhouette
                                          # coverage (geometry.completeness); None: not measured


@dataclass
class TwinResult:
    manifest: Path                        # twin.json
    fidelity: Path | None = None          # geometry_metrics.json (with ground truth)


def run(inputs: TwinInputs, options: TwinOptions, *, progress: bool = True) -> TwinResult:
    from splattwin import io
    from splattwin.limits import load_npy
    from splattwin.poses.twin_frame import load_frame
    from splattwin.splat.gaussians import Gaussians
    from splattwin.twin.build import build_twin

    twin = Path(inputs.twin_dir)
    g = Gaussians.load_ply(inputs.splats)
    labels = load_npy(inputs.labels, "label array")
    objects = [tuple(x) for x in io.read_json(inputs.objects)]
    frame = load_frame(inputs.frame)
    scene = _read_scene(inputs.scene_dir)  # a malformed scene.json is refused before the twin folder is written
    man = build_twin(g, labels, objects, twin, frame=frame, cameras_path=inputs.cameras, options=options.geometry,
                     formats=options.export.resolve("export.formats"), progress=progress, masks=inputs.masks,
                     export_options=options.export, splats_path=inputs.splats,
                     refined_poses=inputs.refined_poses)
    # the objects' meshes and the scene's GT meshes, loaded once: the alignment and the fidelity both use them
    gt_pairs = list(_meshes_with_gt(man, twin, inputs.scene_dir)) if scene is not None else None
    T_twin_gt = _scene_facts(man, twin, inputs.scene_dir, scene, frame, pairs=gt_pairs)
    if inputs.config:
        man.config["build"] = inputs.config
    man.splats = man.splats or twin_relative(inputs.splats, twin)
    man.labels = man.labels or twin_relative(inputs.labels, twin)
    man.save(twin)
    fidelity = None
    if T_twin_gt is not None:
        fidelity = write_fidelity(twin, inputs.scene_dir, options.geometry.f1_threshold, T_twin_gt, pairs=gt_pairs)
    return TwinResult(manifest=twin / "twin.json", fidelity=fidelity)


def _scene_facts(man, twin: Path, scene_dir: Path | None, scene: dict | None, frame, pairs: list | None = None):
    """With an embedded scene's ground truth (scene: its scene.json, `_read_scene`): the alignment note and
    the scene's goal region (`config.target_frame`, in the twin frame) into `man` (not saved); returns
    T_twin_gt or None. pairs: `_meshes_with_gt`'s meshes when already loaded (else loaded here)."""
    if scene is None:
        return None
    info: dict = {}
    T_twin_gt, gt_note = gt_alignment(man, twin, scene_dir, frame, info=info, pairs=pairs)
    man.config["ground_truth"] = {"alignment": gt_note, **info}
    if scene.get("target_frame") and T_twin_gt is not None:  # a scene fact the robot task needs (its goal)
        man.config["target_frame"] = _moved_region(scene["target_frame"], T_twin_gt)
    return T_twin_gt


def _read_scene(scene_dir: Path | None) -> dict | None:
    """The embedded scene's scene.json (None: no scene, or no scene.json in it); InputError naming it when
    it is not a JSON object (its values are checked where they are used)."""
    from splattwin import io
    from splattwin.errors import InputError

    scene_json = Path(scene_dir) / "scene.json" if scene_dir is not None else None
    if scene_json is None or not scene_json.is_file():
        return None
    scene = io.read_json(scene_json)
    if not isinstance(scene, dict):
        raise InputError(f"scene.json must hold a JSON object, got {type(scene).__name__}", scene_json)
    return scene


def add_scene_goal(twin_dir: str | Path, scene_dir: str | Path):
    """What the twin stage adds to a twin built from an embedded scene, for a twin made with `build_twin`
    from Python: the scene's goal region (`config.target_frame`, which the default task's place_in names)
    moved into the twin frame, and the ground-truth alignment note; twin.json saved again. Returns the
    Manifest. InputError when `scene_dir` holds no scene.json or the twin's frame cannot be aligned to it."""
    from splattwin.errors import InputError
    from splattwin.twin.manifest import Manifest

    twin, scene_dir = Path(twin_dir), Path(scene_dir)
    if not (scene_dir / "scene.json").is_file():
        raise InputError("no scene.json here: not a generated scene (splattwin.scene.generate)", scene_dir)
    man = Manifest.load(twin)
    if _scene_facts(man, twin, scene_dir, _read_scene(scene_dir), man.frame) is None:
        raise InputError(f"the twin's frame ({man.frame.source}) cannot be aligned to the scene: "
                         f"{man.config.get('ground_truth', {}).get('alignment')}", twin / "twin.json")
    if "target_frame" not in man.config:
        raise InputError("the scene defines no goal region (target_frame)", scene_dir / "scene.json")
    man.save(twin)
    return man


# The twin frame is the scene's own when the poses were the scene's (its transforms.json, or its robot-style
# capture turned z up by an exact quarter/half turn): the ground truth is then used where it lies, so a pose
# error of the reconstruction counts. A robot base frame (robot poses, or SfM aligned to them) whose base the
# scene names (scene.json robot_base.T_world_base) is known too: the ground truth is placed there by that
# transform, so a global offset of the twin in the base frame, the error a real arm meets, counts (audit 8c
# H3). Otherwise (SfM's table frame, a tilted world moved into the table frame, a robot frame the scene does
# not place) the ground truth is brought into the twin frame by the objects' centres, as trajectory benchmarks
# align before they score, and the note says so.
SAME_FRAME_SOURCES = ("ground_truth", "known_poses")
ROBOT_FRAME_SOURCES = ("robot", "sfm+robot")


def scene_robot_base(scene_dir: Path):
    """scene.json's robot_base.T_world_base ([4,4] rigid, the base in the scene's world) or None when the
    scene does not give a usable one."""
    import numpy as np

    scene = _read_scene(scene_dir) or {}
    base = scene.get("robot_base")
    T = base.get("T_world_base") if isinstance(base, dict) else None
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        return None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        return None
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        return None
    return T


def gt_alignment(man, twin: Path, scene_dir: Path, frame, info: dict | None = None, pairs: list | None = None):
    """(T_twin_gt [4,4] or None, a note): how the scene's ground truth maps into the twin frame. Identity
    when the twin frame is the scene's (`SAME_FRAME_SOURCES`, not moved into a table frame); the inverse of
    scene.json's robot base when the twin frame is the robot base frame (`ROBOT_FRAME_SOURCES`, metric) and
    the scene gives the base; else a rigid fit (with scale for an unscaled twin) of the GT objects' centres
    (their oriented boxes') to the twin's, which needs 3 usable objects; None (no comparison, logged)
    without them. `info` (filled when given): "placement" (scene_frame, robot_base or centre_fit), and with
    a known placement the diagnostics of the twin's objects against it: "global_offset_m" (the norm of the
    mean displacement of the twin's object centres from the placed ground truth's: what a centre fit would
    hide), "global_offset_xyz_m", "centre_fit_residual_rms_m". pairs: `_meshes_with_gt(man, twin, scene_dir)`
    when the caller has loaded them (the twin stage, which scores the same meshes next); else loaded here."""
    import logging

    import numpy as np

    from splattwin.poses.align import umeyama

    log = logging.getLogger(__name__)
    info = {} if info is None else info
    src, tgt = [], []
    for _, mesh, gt in (_meshes_with_gt(man, twin, scene_dir) if pairs is None else pairs):
        src.append(gt.bounding_box_oriented.centroid)
        tgt.append(mesh.bounding_box_oriented.centroid)
    known, how = None, None
    if frame.source in SAME_FRAME_SOURCES and not (frame.up_check or {}).get("moved_to_table_frame"):
        known, how, note = np.eye(4), "scene_frame", "the twin frame is the scene's"
    elif frame.source in ROBOT_FRAME_SOURCES and frame.scaled:
        T_world_base = scene_robot_base(scene_dir)
        if T_world_base is not None:
            known, how = np.linalg.inv(T_world_base), "robot_base"
            note = (f"ground truth placed in the twin ({frame.source}: robot base frame) by scene.json's "
                    f"robot_base.T_world_base (no fit)")
    if known is not None:
        info["placement"] = how
        if src:
            d = np.asarray(tgt) - (np.c_[np.asarray(src), np.ones(len(src))] @ known.T)[:, :3]
            off = d.mean(axis=0)
            info["global_offset_m"] = round(float(np.linalg.norm(off)), 6)
            info["global_offset_xyz_m"] = [round(float(v), 6) for v in off]
            info["objects"] = len(src)
        if how == "robot_base" and len(src) >= 3:
            try:
                info["centre_fit_residual_rms_m"] = round(float(umeyama(np.asarray(src), np.asarray(tgt),
                                                                        with_scale=False).rms), 6)
            except ValueError:
                pass
        if how == "robot_base":
            if "global_offset_m" in info:
                note += (f"; the twin's object centres lie {info['global_offset_m'] * 1000:.1f} mm off it on average "
                         f"(global offset, over {len(src)} objects)")
            log.info("%s", note)
        return known, note
    info["placement"] = "centre_fit"
    if len(src) < 3:
        log.warning("no ground-truth comparison: the twin frame (%s) is not the scene's, and %d usable object(s) "
                    "are too few to align them (3 needed)", frame.source, len(src))
        return None, f"twin frame ({frame.source}) not the scene's; too few objects to align"
    try:
        fit = umeyama(np.asarray(src), np.asarray(tgt), with_scale=not frame.scaled)
    except ValueError as e:   # centres in a line or at one point: no rotation follows from them
        log.warning("no ground-truth comparison: the twin frame (%s) is not the scene's, and the objects' centres "
                    "cannot align them (%s)", frame.source, e)
        return None, f"twin frame ({frame.source}) not the scene's; objects' centres do not fix an alignment"
    info["centre_fit_residual_rms_m" if frame.scaled else "centre_fit_residual_rms"] = round(float(fit.rms), 6)
    note = (f"ground truth aligned to the twin ({frame.source} frame) by {len(src)} object centres "
            f"({'rigid' if frame.scaled else 'similarity'}, residual RMS {fit.rms:.4g}); a global offset of the "
            f"twin is not measured")
    log.info("%s", note)
    return fit.S, note


def _meshes_with_gt(man, twin: Path, scene_dir: Path):
    """(name, visual mesh placed in the twin frame, GT mesh as stored) of each usable object the scene has a
    ground-truth mesh for (scene_dir/meshes/<name>.ply)."""
    from splattwin.meshio import load_mesh

    for obj in man.objects:
        gt_path = Path(scene_dir) / "meshes" / f"{obj.name}.ply"
        if not obj.usable or not obj.visual_mesh or not gt_path.is_file():
            continue
        mesh = load_mesh(twin / obj.visual_mesh, f"visual mesh of {obj.name!r}")
        mesh.apply_transform(obj.pose)
        yield obj.name, mesh, load_mesh(gt_path, "ground-truth mesh")


def _moved_region(region: dict, T) -> dict:
    """The scene's goal region {center, size, ...} in the twin frame: the centre moved by T (a similarity),
    the size scaled by its scale."""
    import numpy as np

    from splattwin.poses.align import sim3_scale, transform_points

    if not isinstance(region, dict):
        return region   # malformed: the robot stage names it (robot.world._outline_region)
    if np.array_equal(T, np.eye(4)):
        return dict(region)
    out = dict(region)
    c = region.get("center")
    if not (isinstance(c, list) and len(c) in (2, 3) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             and np.isfinite(v) for v in c)):
        return out      # malformed: kept as given, for the robot stage to name
    c3 = np.array([c[0], c[1], c[2] if len(c) > 2 else 0.0], dtype=float)
    out["center"] = transform_points(T, c3[None])[0].round(6).tolist()
    s = sim3_scale(T)
    for k in ("size", "tape_width"):
        if isinstance(region.get(k), (int, float)) and not isinstance(region.get(k), bool):
            out[k] = float(region[k]) * s
    return out


def twin_relative(path: Path, twin: Path) -> str:
    return Path(path).resolve().relative_to(Path(twin).resolve()).as_posix()


def write_fidelity(twin: Path, scene_dir: Path, threshold: float, T_twin_gt=None, pairs: list | None = None) -> Path:
    """TWIN/geometry_metrics.json: Chamfer / precision / recall / F1 @threshold of each usable object's
    visual mesh (placed by its pose) vs the scene's GT mesh (scene_dir/meshes/<name>.ply), brought into the
    twin frame by T_twin_gt (`gt_alignment`; identity when the frames are one). pairs: the meshes
    `_meshes_with_gt` gave `gt_alignment` for this twin (not modified here), else they are loaded."""
    from splattwin import io
    from splattwin.geometry.metrics import mesh_fidelity
    from splattwin.twin.manifest import Manifest

    meshes, gt = {}, {}
    if pairs is None:
        pairs = _meshes_with_gt(Manifest.load(twin), twin, scene_dir)
    for name, mesh, gt_mesh in pairs:
        meshes[name] = mesh
        # a copy is moved: the caller's meshes stay as loaded
        gt[name] = gt_mesh if T_twin_gt is None else gt_mesh.copy().apply_transform(T_twin_gt)
    rows = {k: mesh_fidelity(m, gt[k], threshold=threshold).to_dict() for k, m in meshes.items()}
    return io.write_json(twin / "geometry_metrics.json", rows)
