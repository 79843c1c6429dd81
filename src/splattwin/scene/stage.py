"""The embedded scene as the pipeline's first stage (the demo's input): `run(SceneInputs, SceneOptions)
-> SceneResult`. Writes the generated scene into OUT (see `splattwin.scene.generator`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from splattwin.scene.options import SceneOptions


@dataclass
class SceneInputs:
    out_dir: Path      # the scene folder (TWIN/scene)


@dataclass
class SceneResult:
    scene_json: Path   # ground truth: objects, meshes, target frame; beside images/, masks/, transforms.json


def run(inputs: SceneInputs, options: SceneOptions, *, progress: bool = True) -> SceneResult:
    from splattwin.scene.generator import generate

    out = generate(inputs.out_dir, options, progress=progress)
    return SceneResult(scene_json=Path(out) / "scene.json")
