"""`splattwin sweep`: a grid over fusion, geometry cleaning and trial parameters on a small built twin,
on Ray; every parameter reaches its options object; a re-run on the local pool resumes everything and
gives the same table."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.executor import LocalExecutor, RayExecutor
from splattwin.cluster.sweep import SweepSpec, run_sweep
from splattwin.robot.trials import TrialSpec, wilson_interval
from splattwin.semantics.options import FusionOptions

SCENE = {"seed": 0, "width": 160, "height": 120, "views": 8, "heldout": 3}
SPLAT = {"iters": 800, "max_gaussians": 20000, "checkpoint_every": 200}


@pytest.fixture(scope="module")
def small_twin(tmp_path_factory) -> Path:
    """A built twin (scene, poses, splats, semantics, twin) of a small embedded scene. Its yellow cube keeps
    fewer than 50 points after cleaning and covers its masks: usable with geometry.min_points_whole=10, not
    with 50 (an object needs min(min_points, min_points_whole) points at least)."""
    from splattwin.pipeline.build import BuildOptions, build

    out = tmp_path_factory.mktemp("sweep_twin") / "twin"
    opts = BuildOptions.from_dict({"scene": SCENE, "poses": {"method": "known"}, "splat": SPLAT})
    build(out, opts, until="twin", progress=False)
    return out


def _rows(summary: dict) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "twin"} for r in summary["cells"]]


@pytest.mark.slow
def test_sweep_grid_on_ray_then_resumed_locally(small_twin: Path, ray_session, tmp_path: Path):
    from splattwin.capture import load_dataset
    from splattwin.semantics.lift import fuse_to_dir
    from splattwin.semantics.masks import load_masks
    from splattwin.twin.manifest import Manifest

    grid = {"fusion.kappa": [1.5, 2.0], "geometry.min_points_whole": [10, 50], "trials.sigma": [0.004]}
    spec = SweepSpec(twin=small_twin, grid=grid, trials=2, trial=TrialSpec(str(small_twin), None))
    out = tmp_path / "sweep"
    with RayExecutor() as ex:
        s = run_sweep(spec, out, ex, progress=False)
    cells = s["cells"]
    assert [(c["fusion.kappa"], c["geometry.min_points_whole"]) for c in cells] == [(1.5, 10), (1.5, 50), (2.0, 10),
                                                                                    (2.0, 50)]
    assert len(list((out / "fusion").iterdir())) == 2 and len(list((out / "twins").iterdir())) == 4
    for c in cells:
        assert 0 <= c["consistency"] <= 100 and 0 <= c["ghost_index"] <= 100 and 0 < c["miou_heldout"] <= 1
        man = Manifest.load(c["twin"])
        # the geometry parameter reached GeometryOptions, the fusion one FusionOptions (the cell twin's resolved
        # config, nested as `build` records it); the others kept the twin's own values
        base = Manifest.load(small_twin).config["build"]
        assert man.config["build"]["geometry"]["min_points_whole"] == c["geometry.min_points_whole"]
        assert man.config["build"]["semantics"]["fusion"]["kappa"] == c["fusion.kappa"]
        assert man.config["build"]["geometry"]["dbscan_eps"] == base["geometry"]["dbscan_eps"]
        assert man.config["build"]["splat"] == base["splat"]
        if c["geometry.min_points_whole"] == 50:   # the cube is too small for 50: reported, no trials
            assert "yellow_cube" in c["error"] and "not usable" in c["error"] and c["trials"] is None
        else:
            assert c["error"] is None and c["trials"] == 2 and c["objects_usable"] == "5/5"
            # whole by its masks: the cells' twins measure silhouette coverage as `build` does
            assert man.object("yellow_cube").silhouette_coverage >= 0.5
            assert [c["ci95_lo"], c["ci95_hi"]] == list(wilson_interval(c["successes"], 2))
            trial_files = sorted(Path(out / "cells").glob("*/trials/*.json"))
            keys = [json.loads(f.read_text())["key"] for f in trial_files]
            assert {k["twin"] for k in keys} == {str(Path(c["twin"]).resolve()) for c in cells if c["trials"]}  # noqa: E501
            assert {k["sigma"] for k in keys} == {0.004}
    # the fusion parameter reached FusionOptions: the cell's labels are those of a direct fusion with kappa 2
    fusion_dir = next(d for d in (out / "fusion").iterdir() if json.loads((d / "fusion.json").read_text())["options"]["kappa"] == 2.0)
    direct = fuse_to_dir(small_twin / "splat" / "point_cloud.ply", load_dataset(small_twin / "poses" / "transforms.json"),
                         load_masks(out / "masks"), tmp_path / "direct", FusionOptions(kappa=2.0, iters=3),
                         label_maps=False, progress=False)
    np.testing.assert_array_equal(np.load(fusion_dir / "labels.npy"), direct.labels)
    # one table: CSV rows = JSON cells
    rows = list(csv.DictReader((out / "sweep.csv").open()))
    assert [r["fusion.kappa"] for r in rows] == ["1.5", "1.5", "2.0", "2.0"]
    assert [r["successes"] for r in rows] == ["" if c["successes"] is None else str(c["successes"]) for c in cells]
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a re-run (here on the local pool) reuses every finished task and gives the same table
    done = {p: p.stat().st_mtime_ns for p in out.rglob("*.json") if p.parent.name != "sweep"
            and p.name not in ("sweep.json", "masks.json")}
    with LocalExecutor(2) as ex:
        again = run_sweep(spec, out, ex, progress=False)
    assert _rows(again) == _rows(s)
    assert {p: p.stat().st_mtime_ns for p in done} == done, "a finished task ran again"


@pytest.mark.slow
def test_sweep_cli_sigma_grid_on_ray(gt_twin: Path, ray_session, tmp_path: Path, capsys):
    from splattwin.cli import main

    out = tmp_path / "sw"
    rc = main(["sweep", str(gt_twin), "--out", str(out), "--sigma", "0.004,0.008", "--trials", "2", "--executor", "ray"])
    s = json.loads((out / "sweep.json").read_text())
    assert rc == 0 and [c["trials.sigma"] for c in s["cells"]] == [0.004, 0.008]
    assert all(c["trials"] == 2 and c["error"] is None for c in s["cells"])
    assert all(c["twin"] == str(gt_twin.resolve()) for c in s["cells"])        # no fusion/geometry: the twin itself
    assert not (out / "fusion").exists() and not (out / "twins").exists()
    assert "Ray" in s["executor"]
    assert "sweep of" in capsys.readouterr().out


def test_sweep_cli_bad_input(gt_twin: Path, tmp_path: Path, capsys):
    from splattwin.cli import main

    assert main(["sweep", str(gt_twin), "--out", str(tmp_path / "a")]) == 2
    assert "nothing to sweep" in capsys.readouterr().err
    assert main(["sweep", str(gt_twin), "--out", str(tmp_path / "b"), "--param", "fusion.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["sweep", str(tmp_path), "--out", str(tmp_path / "c"), "--sigma", "0.004"]) == 2
    assert "twin.json" in capsys.readouterr().err
    # fusion cells re-run from the twin's splats: a ground-truth twin has none
    assert main(["sweep", str(gt_twin), "--out", str(tmp_path / "d"), "--kappa", "1.2"]) == 2
    assert "no splat file" in capsys.readouterr().err


def test_sweep_starts_from_the_twins_resolved_config(gt_twin: Path, tmp_path: Path):
    """The values a sweep does not vary are those twin.json records (config.build, nested as `build`
    writes it): fusion, geometry and the trials' robot options; a bad entry names twin.json."""
    import shutil

    from splattwin.cluster.sweep import base_options, trial_options
    from splattwin.geometry.options import GeometryOptions
    from splattwin.twin.manifest import Manifest

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin, twin)
    man = Manifest.load(twin)
    man.config["build"] = {"semantics": {"fusion": {"kappa": 2.5, "iters": 1}},
                           "geometry": {"min_opacity": 0.2, "alpha_factors": [2.0]},
                           "robot": {"planner": "RRTstar", "seed": 7, "cluster": {"executor": "ray"}}}
    man.save(twin)
    man = Manifest.load(twin)
    fusion, geometry = base_options(twin, man)
    assert (fusion.kappa, fusion.iters, fusion.depth_tol) == (2.5, 1, FusionOptions().depth_tol)
    assert (geometry.min_opacity, geometry.alpha_factors) == (0.2, (2.0,))
    assert geometry.dbscan_eps == GeometryOptions().dbscan_eps
    robot = trial_options(twin, man)
    assert (robot.planner, robot.seed) == ("RRTstar", 7)
    assert robot.cluster.executor is None     # where the build's trials ran is not where the sweep's run
    man.config["build"]["geometry"]["min_opacity"] = "high"
    man.save(twin)
    with pytest.raises(Exception, match="min_opacity") as e:
        base_options(twin, Manifest.load(twin))
    assert "twin.json" in str(e.value)


def test_sweep_does_not_follow_paths_recorded_in_a_received_twin(tmp_path: Path, caplog):
    """A received twin.json's config.build.robot named a task YAML (and could name an MJCF) outside the twin
    folder: sweep read and used it. Paths outside the twin are dropped with a warning; inside, kept."""
    import logging

    from splattwin.cluster.sweep import trial_options
    from splattwin.twin.manifest import Manifest

    twin, outside = tmp_path / "twin", tmp_path / "outside"
    twin.mkdir(), outside.mkdir()
    (outside / "task.yaml").write_text("steps: []\n")
    (outside / "arm.xml").write_text("<mujoco/>\n")
    (twin / "mine.yaml").write_text("steps: []\n")
    man = Manifest(config={"build": {"robot": {"task": str(outside / "task.yaml"), "robot_mjcf": "../outside/arm.xml",
                                               "record": str(outside / "rec"), "record_camera": "/etc/cam.yaml",
                                               "planner": "RRTstar"}}})
    caplog.set_level(logging.WARNING, logger="splattwin.cluster.sweep")
    robot = trial_options(twin, man)
    assert robot.task is None and robot.robot_mjcf is None and robot.record is None
    assert robot.record_camera == "capture:0" and robot.planner == "RRTstar"
    assert "ignoring the recorded task" in caplog.text and "--task" in caplog.text
    man.config["build"]["robot"] = {"task": "mine.yaml", "record_camera": "train_000"}
    robot = trial_options(twin, man)
    assert Path(robot.task) == twin / "mine.yaml" and robot.record_camera == "train_000"


@pytest.mark.parametrize("array, needle", [
    (np.array([1, None, 2], dtype=object), "Python objects"),   # was a ValueError failing the cell (exit 1)
    (np.array([0.0, 1.5, 2.0]), "integer labels"),
    (np.array([0, 1]), "3 integer labels"),
    (np.array([0, 1, 1_500_000_000]), r"\[0, 65535\]"),
    (np.array([0, -1, 2]), r"\[0, 65535\]"),
])
def test_sweep_checks_the_twins_labels_file(tmp_path: Path, array, needle):
    from splattwin.cluster.sweep import _labels
    from splattwin.errors import InputError

    p = tmp_path / "labels.npy"
    np.save(p, array, allow_pickle=True)
    with pytest.raises(InputError, match=needle) as e:
        _labels(p, 3)
    assert e.value.path == p


def test_fusion_sweep_without_masks_says_why_the_recorded_path_is_not_used(tmp_path):
    """twin.json records the masks a build read; sweep does not follow such a path (a twin may come from
    someone else) and now says so instead of only asking for --masks."""
    from types import SimpleNamespace

    from splattwin.cluster.sweep import sweep_masks
    from splattwin.errors import InputError

    man = SimpleNamespace(objects=[], config={"build": {"semantics": {"masks": "/data/cake_masks"}}})
    with pytest.raises(InputError, match=r"pass --masks DIR \(twin.json records '/data/cake_masks', which sweep does "
                                         r"not follow"):
        sweep_masks(tmp_path, man, None, None, None)


def test_the_sweep_plot_leaves_the_callers_matplotlib_backend(tmp_path: Path):
    """The sweep's plot called matplotlib.use("Agg"), switching a notebook's backend (audit 10A L11)."""
    import matplotlib
    from PIL import Image

    from splattwin.cluster.sweep import plot

    summary = {"cells": [{"success_rate": 0.5, "ci95_lo": 0.2, "ci95_hi": 0.8, "fusion.kappa": 1.5},
                         {"success_rate": 0.75, "ci95_lo": 0.4, "ci95_hi": 0.9, "fusion.kappa": 2.0}],
               "grid": {"fusion.kappa": [1.5, 2.0]}, "trials_per_cell": 4}
    before = matplotlib.get_backend()
    matplotlib.use("svg")   # stands for the caller's own (a notebook's inline) backend
    try:
        out = plot(summary, tmp_path / "sweep.png")
        assert matplotlib.get_backend() == "svg"
        assert Image.open(out).format == "PNG"
    finally:
        matplotlib.use(before)
