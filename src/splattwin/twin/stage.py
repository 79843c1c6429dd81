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
    man = build_twin(g, labels, objects, twin, frame=frame, cameras_path=inputs.cameras, options=options.geometry,
                     formats=options.export.resolve("export.formats"), progress=progress, masks=inputs.masks,
                     export_options=options.export, splats_path=inputs.splats)
    scene_json = inputs.scene_dir / "scene.json" if inputs.scene_dir is not None else None
    if scene_json is not None and scene_json.is_file():
        scene = io.read_json(scene_json)
        if scene.get("target_frame"):  # a scene fact the robot task needs (its goal region)
            man.config["target_frame"] = scene["target_frame"]
    if inputs.config:
        man.config["build"] = inputs.config
    man.splats = man.splats or twin_relative(inputs.splats, twin)
    man.labels = man.labels or twin_relative(inputs.labels, twin)
    man.save(twin)
    fidelity = None
    if scene_json is not None and scene_json.is_file():
        fidelity = write_fidelity(twin, inputs.scene_dir, options.geometry.f1_threshold)
    return TwinResult(manifest=twin / "twin.json", fidelity=fidelity)


def twin_relative(path: Path, twin: Path) -> str:
    return Path(path).resolve().relative_to(Path(twin).resolve()).as_posix()


def write_fidelity(twin: Path, scene_dir: Path, threshold: float) -> Path:
    """TWIN/geometry_metrics.json: Chamfer / precision / recall / F1 @threshold of each usable object's
    visual mesh (placed by its pose) vs the scene's GT mesh (scene_dir/meshes/<name>.ply)."""
    from splattwin import io
    from splattwin.geometry.metrics import mesh_fidelity
    from splattwin.meshio import load_mesh
    from splattwin.twin.manifest import Manifest

    man = Manifest.load(twin)
    meshes, gt = {}, {}
    for obj in man.objects:
        gt_path = Path(scene_dir) / "meshes" / f"{obj.name}.ply"
        if not obj.usable or not obj.visual_mesh or not gt_path.is_file():
            continue
        mesh = load_mesh(twin / obj.visual_mesh, f"visual mesh of {obj.name!r}")
        mesh.apply_transform(obj.pose)
        meshes[obj.name] = mesh
        gt[obj.name] = load_mesh(gt_path, "ground-truth mesh")
    rows = {k: mesh_fidelity(m, gt[k], threshold=threshold).to_dict() for k, m in meshes.items()}
    return io.write_json(twin / "geometry_metrics.json", rows)
