"""Fixtures of the poses tests: SfM runs once per session per scene (later calls resume the model)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import Dataset, load_dataset


def stripped(ds: Dataset, depth: bool = False) -> Dataset:
    """The same images with identity poses and guessed intrinsics and no depth: what a photo folder gives
    (depth=True keeps the depth images: SfM then takes its metric scale from them unless another scale is
    given, tests/poses/test_depth_scale.py)."""
    from dataclasses import replace

    from splattwin.capture import Camera

    frames = [replace(f, camera=Camera.from_fov(np.radians(60.0), f.camera.width, f.camera.height,
                                                name=f.camera.name), depth_path=f.depth_path if depth else None)
              for f in ds.frames]
    # the scene's train/held-out split is kept as the capture's own (else the default hold-out re-splits)
    return Dataset(root=ds.root, frames=frames, has_poses=False, meta={"format": "images", "split": True})


@pytest.fixture(scope="session")
def sfm_default_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """SfM work folder for scene_default (filled by the first estimate_poses call, then re-used)."""
    return tmp_path_factory.mktemp("poses_sfm_default")


@pytest.fixture(scope="session")
def default_unscaled(scene_default: Path, sfm_default_dir: Path):
    """(ground-truth dataset, PoseResult) of SfM on scene_default with poses stripped, no scale given."""
    from splattwin.poses import PoseOptions, estimate_poses

    gt = load_dataset(scene_default)
    res = estimate_poses(stripped(gt), PoseOptions(method="sfm", work_dir=sfm_default_dir, progress=False))
    return gt, res


@pytest.fixture(scope="session")
def marker_result(scene_marker: Path, tmp_path_factory: pytest.TempPathFactory):
    """(ground-truth dataset, scene.json dict, PoseResult) of SfM + marker on scene_marker."""
    import json

    from splattwin.poses import PoseOptions, estimate_poses

    gt = load_dataset(scene_marker)
    scene = json.loads((scene_marker / "scene.json").read_text())
    m = scene["marker"]
    res = estimate_poses(stripped(gt), PoseOptions(method="sfm", marker_size=m["size"], marker_dict=m["dictionary"],
                                                   marker_id=m["id"], work_dir=tmp_path_factory.mktemp("poses_sfm_marker"),
                                                   progress=False))
    return gt, scene, res
