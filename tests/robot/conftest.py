"""Robot-stage fixtures: ground-truth twins of the shared embedded scenes (session-scoped, read-only)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def gt_twin_small(scene_small: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_twin_small")
    twin_from_scene(scene_small, out)
    return out


@pytest.fixture(scope="session")
def gt_twin_default(scene_default: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("gt_twin_default")
    twin_from_scene(scene_default, out)
    return out


@pytest.fixture(scope="session")
def panda():
    from splattwin.robot.assets import RobotModel

    return RobotModel.panda()
