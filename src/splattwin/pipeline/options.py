"""`BuildOptions`: everything a build depends on, as the stages' own option dataclasses nested, not copied
(`build --splat.depth-lambda 0.1`, or `splat: {depth_lambda: 0.1}` in `build --config twin.yaml`).

Each stage's options are defined once, in its package (`splattwin.<stage>.options` / `splat.config`); this
module only nests them. The resolved options are recorded in twin.json (`config.build`) and each stage's
key hashes its own sub-config (`splattwin.pipeline.build.stages`). Light: no numpy/torch (`--help`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from splattwin.geometry.options import GeometryOptions
from splattwin.options import from_dict, option, set_everywhere, to_dict
from splattwin.playback.options import RefineOptions
from splattwin.poses.options import PoseOptions
from splattwin.robot.options import RobotOptions
from splattwin.scene.options import SceneOptions
from splattwin.semantics.options import SemanticsOptions
from splattwin.splat.config import TrainConfig
from splattwin.twin.options import ExportOptions

# The pipeline's stages, in order (`--from`, `--until`, TWIN/pipeline.json).
STAGES = ("scene", "poses", "splats", "semantics", "twin", "robot", "report")


@dataclass
class BuildOptions:
    """input: a dataset (any layout `splattwin.capture.load_dataset` reads), or None with `scene` set (the
    demo generates the embedded scene as its input). robot.task None: no robot stage."""

    input: str | None = option(None, "dataset: image folder, video, transforms.json, COLMAP, cameras.json, BOP "
                               "scene, or TUM pose list + intrinsics", path=True)
    scene: SceneOptions | None = option(None, "generate the embedded tabletop scene as the input (the demo)")
    poses: PoseOptions = option(factory=PoseOptions, help="camera poses and the table frame")
    splat: TrainConfig = option(factory=TrainConfig, help="3D Gaussian Splatting training")
    semantics: SemanticsOptions = option(factory=SemanticsOptions, help="2D masks and their fusion")
    geometry: GeometryOptions = option(factory=GeometryOptions, help="cleaning, meshing, convex parts, mass")
    export: ExportOptions = option(factory=ExportOptions, help="exports of the twin")
    refine: RefineOptions = option(factory=RefineOptions, help="object-focused refinement of the splats (after the "
                                   "twin is built)")
    robot: RobotOptions = option(factory=RobotOptions, help="the robot task validated in physics")

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str | Path | None = None,
                  base: "BuildOptions | None" = None) -> "BuildOptions":
        """From a nested dict as in a config file ({"splat": {"iters": 80}, ...}); InputError naming
        `where` for unknown options or values of the wrong type."""
        return from_dict(cls, data, where, base)

    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    def with_seed(self, seed: int) -> "BuildOptions":
        """Every stage's seed set to `seed` (`build --seed`)."""
        return set_everywhere(self, "seed", seed)
