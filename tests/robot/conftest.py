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


@pytest.fixture(scope="session")
def default_run(gt_twin_default: Path):
    """(World, RunResult) of the paper's three steps on the ground-truth twin (seed 0), executed once per
    session; the world is left as the run ended. Read-only for the tests that share it."""
    from splattwin.robot.execute import Executor
    from splattwin.robot.task import load_task, validate_task
    from splattwin.robot.world import build_world

    w = build_world(gt_twin_default, visual=False)
    task = load_task(None, w.manifest)
    validate_task(task, w.manifest, gt_twin_default, w.base.matrix())
    return w, Executor(w, seed=0).run(task)
