"""Cluster fixtures: one in-process Ray instance shared by these tests (start-up costs ~10 s on 2 cores),
a ground-truth twin of the default scene, and a helper that kills a Ray worker by its task name."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest


@pytest.fixture(scope="package")
def ray_session():
    """ray.init(num_cpus=2) once for all the cluster tests; shut down after the last of them."""
    import ray

    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="session")
def gt_twin(scene_default: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from splattwin.twin.groundtruth import twin_from_scene

    out = tmp_path_factory.mktemp("cluster_gt_twin")
    twin_from_scene(scene_default, out)
    return out


def worker_pids(task_prefix: str) -> list[int]:
    """PIDs of this session's Ray workers now running a task whose name starts with `task_prefix`
    (Ray titles a busy worker process `ray::<task name>`); only descendants of this process."""
    import psutil

    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if p.name().startswith(f"ray::{task_prefix}") or " ".join(p.cmdline()).startswith(f"ray::{task_prefix}"):
                out.append(p.pid)
        except psutil.Error:
            continue
    return out


def kill_worker_when(task_prefix: str, ready, timeout: float = 600.0) -> int | None:
    """Wait until `ready()` is true and a worker runs a `task_prefix` task, then SIGKILL it; its PID."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        pids = worker_pids(task_prefix) if ready() else []
        if pids:
            os.kill(pids[0], signal.SIGKILL)
            return pids[0]
        time.sleep(0.2)
    return None
