"""Options of `splattwin sweep` and `splattwin batch` (the commands' own; the stages' options they pass on
stay in their stages' dataclasses). The single source of their defaults and help (`splattwin.options`).
Light: no numpy/torch (`splattwin --help`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from splattwin.errors import InputError
from splattwin.executor import ExecutorOptions
from splattwin.options import option
from splattwin.robot.options import MAX_TRIALS


@dataclass
class SweepOptions:
    """A parameter grid over a twin. Value lists are comma-separated text (parsed by the target field's
    type in `splattwin.cluster.params`); the grid is their product. The trials' task, robot, base pose,
    planner and seed are the robot stage's options (`RobotOptions`, from the twin's resolved config when
    the flags do not give them)."""

    kappa: str | None = option(None, "fusion.kappa values, e.g. 1.2,1.5,2.0 (consensus tau = N / kappa)")
    fusion_iters: str | None = option(None, "fusion.iters values (refinement rounds), e.g. 1,3")
    clean: tuple[str, ...] = option((), "geometry cleaning options (GeometryOptions fields) and their values, "
                                    "NAME=V1,V2 ..., e.g. min_opacity=0.05,0.1 dbscan_eps=0.01,0.02")
    sigma: str | None = option(None, "trials.sigma values: per-axis standard deviation of the objects' x/y error, "
                               "e.g. 0.003,0.005,0.01 (none: the robot stage's --sigma)", unit="m")
    param: tuple[str, ...] = option((), "any other sweep parameter, TARGET.FIELD=V1,V2 ..., TARGET one of fusion, "
                                    "geometry, trials, e.g. fusion.depth_tol=0.01,0.02 trials.sigma_yaw=0.02,0.05")
    trials: int = option(20, "trials per cell (a cell without pose error runs one)")
    masks: Path | None = option(None, "2D masks for the fusion cells and the objects' silhouette coverage in the "
                                "cells' twins (none: those the twin carries: its embedded scene or "
                                "semantics/masks2d)", path=True)
    scene: Path | None = option(None, "embedded-scene folder with ground truth for F1 (none: TWIN/scene when "
                                "present)", path=True)
    resume: bool = option(True, "reuse finished fusion runs, twins and trials with the same key (--no-resume: redo "
                          "every cell)", hashed=False)
    cluster: ExecutorOptions = option(factory=ExecutorOptions, help="where the sweep's tasks run", hashed=False)

    def validate(self) -> None:
        if not 1 <= self.trials <= MAX_TRIALS:   # the robot stage's bound, per cell
            raise InputError(f"--trials must be in [1, {MAX_TRIALS}], got {self.trials}")


@dataclass
class BatchOptions:
    """Where and how each capture's build runs. A build is two tasks: its reconstruction (capture, poses,
    training; on a GPU when the cluster has one) and the rest of the build (CPUs only)."""

    cpus_per_build: float = option(2.0, "CPUs each build task reserves on a Ray node and the threads it uses")
    gpus_per_build: float | None = option(None, "GPUs of each reconstruction task (none: 1 when the Ray cluster "
                                          "has GPUs, else 0)")
    cluster: ExecutorOptions = option(factory=ExecutorOptions, help="where the builds run (local: workers = builds "
                                      "at once, none: CPU count / cpus_per_build)", hashed=False)

    def validate(self) -> None:
        if not self.cpus_per_build > 0:
            raise InputError(f"--cpus-per-build must be > 0, got {self.cpus_per_build}")
        if self.gpus_per_build is not None and self.gpus_per_build < 0:
            raise InputError(f"--gpus-per-build must be >= 0, got {self.gpus_per_build}")
        self.cluster.resolve()
