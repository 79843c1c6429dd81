"""`splattwin batch`: two tiny captures and a bad one on Ray, a worker killed in the middle of a build;
the batch completes, every promised output is there and readable, the bad capture is reported; a re-run
on the local pool resumes everything."""

from __future__ import annotations

import csv
import json
import threading
from pathlib import Path

import pytest

from splattwin.cluster.batch import capture_names, lost_outputs, run_batch
from splattwin.executor import LocalExecutor, RayExecutor
from splattwin.pipeline.build import STAGES, BuildOptions

from .conftest import kill_worker_when

OPTS = BuildOptions.from_dict({"poses": {"method": "known"},
                               "splat": {"iters": 80, "max_gaussians": 8000, "checkpoint_every": 20}})


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> list[Path]:
    from splattwin.scene import SceneOptions, generate

    root = tmp_path_factory.mktemp("captures")
    caps = [generate(root / f"scene{s}", SceneOptions(seed=s, width=96, height=72, views=6, heldout=2), progress=False)
            for s in (0, 1)]
    (root / "empty").mkdir()
    return [*caps, root / "empty"]


def test_capture_names_unique_and_safe(tmp_path):
    (tmp_path / "a b").mkdir()
    (tmp_path / "x" / "a b").mkdir(parents=True)
    (tmp_path / "clip.mp4").write_bytes(b"")
    names = [c.name for c in capture_names([tmp_path / "a b", tmp_path / "x" / "a b", tmp_path / "clip.mp4",
                                            tmp_path / "..", tmp_path / "summary.html"])]
    assert names[:3] == ["a_b", "a_b-2", "clip"]
    assert all(n and "/" not in n and n not in (".", "..") for n in names) and len(set(names)) == len(names)
    assert names[4] != "summary.html"
    (tmp_path / "scans" / "logs").mkdir(parents=True)   # OUT/logs holds the build logs
    assert [c.name for c in capture_names([tmp_path / "scans" / "logs"])] == ["logs-2"]


def test_batch_refuses_an_out_among_the_captures(tmp_path):
    """`batch scans/*/ --out scans/` built each twin into its own capture folder, among the photos; now an
    InputError naming the capture before any task (nothing written)."""
    from splattwin.errors import InputError

    scans = tmp_path / "scans"
    (scans / "a").mkdir(parents=True)
    for out, match in ((scans, "the capture itself"), (scans / "a" / "twins", "nested with it")):
        with pytest.raises(InputError, match=match) as e:
            run_batch([scans / "a"], out, OPTS, LocalExecutor(1), progress=False)
        assert e.value.path == scans / "a"
    assert sorted(p.name for p in scans.rglob("*")) == ["a"]


@pytest.mark.slow
def test_batch_on_ray_survives_a_killed_worker(captures: list[Path], ray_session, tmp_path: Path):
    out = tmp_path / "batch"
    twin0 = out / "scene0"
    killed = []
    # kill scene0's reconstruction task once its build is under way (a stage already recorded)
    killer = threading.Thread(target=lambda: killed.append(
        kill_worker_when("batch-recon-scene0", lambda: (twin0 / "pipeline.json").is_file(), timeout=600)))
    killer.start()
    with RayExecutor(max_retries=3) as ex:
        s = run_batch(captures, out, OPTS, ex, cpus=1, progress=False)
    killer.join()
    assert killed and killed[0] is not None, "no reconstruction worker was found to kill"
    by = {c["name"]: c for c in s["captures"]}
    assert s["ok"] == 2 and s["failed"] == 1
    # the killed task was run again by another worker process and the build completed
    assert killed[0] not in by["scene0"]["pids"]
    for name in ("scene0", "scene1"):
        c = by[name]
        assert c["status"] == "ok" and c["error"] is None, c
        state = json.loads((out / name / "pipeline.json").read_text())
        assert list(state) == list(STAGES)
        assert lost_outputs(out / name) == []
        assert c["views"] == "8/8" and c["psnr"] > 10 and 0 < c["ssim"] <= 1 and c["report"] == "report/index.html"
    bad = by["empty"]
    assert bad["status"] == "failed" and bad["failed_stage"] == "preflight" and "no dataset found" in bad["error"]
    assert "Traceback" in Path(bad["log"]).read_text()
    # one summary: CSV rows, JSON and HTML agree
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["name"], r["status"]) for r in rows] == [("scene0", "ok"), ("scene1", "ok"), ("empty", "failed")]
    assert float(rows[0]["psnr"]) == pytest.approx(by["scene0"]["psnr"], abs=1e-4)
    assert json.loads((out / "batch.json").read_text())["ok"] == 2
    html = (out / "summary.html").read_text()
    # the two built captures' held-out view strips (photographic: JPEG, `report.html.picture_bytes`)
    assert "failed in preflight" in html and html.count("data:image/jpeg;base64,") >= 2
    assert 'href="scene0/report/index.html"' in html

    # a re-run on the local pool skips every finished stage of every capture
    finished = {n: {k: v["finished"] for k, v in json.loads((out / n / "pipeline.json").read_text()).items()}
                for n in ("scene0", "scene1")}
    with LocalExecutor(1) as ex:
        again = run_batch(captures, out, OPTS, ex, cpus=1, progress=False)
    assert again["ok"] == 2 and again["failed"] == 1
    for n in ("scene0", "scene1"):
        now = {k: v["finished"] for k, v in json.loads((out / n / "pipeline.json").read_text()).items()}
        assert now == finished[n], f"{n}: a finished stage ran again"
        assert {c["name"]: c for c in again["captures"]}[n]["psnr"] == by[n]["psnr"]


def test_batch_cli_bad_input(tmp_path, capsys):
    from splattwin.cli import main

    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o"), "--from", "poses"]) == 2
    assert "--from" in capsys.readouterr().err
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o"), "--cpus-per-build", "0"]) == 2


def _stub_build(*args) -> dict:
    return {"stages": [], "timings": {}, "wall_s": 0.0, "pid": 0}


class _GpuCluster(LocalExecutor):
    """A local pool that reports a GPU, records the jobs it is given and runs a stub instead of builds."""

    kind = "ray"

    def __init__(self):
        super().__init__(1)
        self.jobs = []

    def gpus(self) -> float:
        return 1.0

    def submit(self, job, attempt=1):
        from dataclasses import replace

        self.jobs.append(job)
        return super().submit(replace(job, fn=_stub_build), attempt)


def test_reconstruction_asks_for_a_gpu_when_the_cluster_has_one(tmp_path):
    """Each capture: a reconstruction task with 1 GPU (training lands on a GPU node), then the rest of its
    build on CPUs only; both reserve --cpus-per-build CPUs."""
    ex = _GpuCluster()
    with ex:
        run_batch([tmp_path / "a", tmp_path / "b"], tmp_path / "out", OPTS, ex, cpus=3, progress=False)
    parts = {(j.key, j.resources.cpus, j.resources.gpus) for j in ex.jobs}
    assert parts == {(("a", "recon"), 3, 1.0), (("b", "recon"), 3, 1.0), (("a", "finish"), 3, 0.0),
                     (("b", "finish"), 3, 0.0)}
    assert all(j.args[2] == "splats" for j in ex.jobs if j.key[1] == "recon")       # until the training
    assert all(j.args[2] is None for j in ex.jobs if j.key[1] == "finish")          # then to the end
    ex2 = _GpuCluster()
    ex2.gpus = lambda: 0.0
    with ex2:
        run_batch([tmp_path / "a"], tmp_path / "out2", OPTS, ex2, cpus=1, progress=False)
    assert {j.resources.gpus for j in ex2.jobs} == {0.0}


def test_batch_cli_flags_reach_the_build_options(tmp_path, monkeypatch):
    """`batch` takes every `build` flag (generated from BuildOptions) and its own (BatchOptions, with the
    executor's); each capture's build gets its input, and its trials a local pool of the task's CPUs."""
    from splattwin.cli import build_parser
    from splattwin.cluster.options import BatchOptions
    from splattwin.executor import ExecutorOptions
    from splattwin.options import from_args
    from splattwin.pipeline.cli import resolve_options

    a = build_parser().parse_args(["batch", "a", "b", "--out", "o", "--iters", "50", "--semantics.fusion.kappa", "2",
                                   "--executor", "ray", "--max-retries", "1", "--cpus-per-build", "3",
                                   "--robot.cluster.executor", "ray", "--task", "default", "--trials", "4"])
    bo = from_args(BatchOptions, a)
    assert bo == BatchOptions(cpus_per_build=3.0, cluster=ExecutorOptions(executor="ray", max_retries=1))
    build = resolve_options(a)
    assert (build.splat.iters, build.semantics.fusion.kappa, build.robot.trials) == (50, 2.0, 4)
    ex = _GpuCluster()
    with ex:
        run_batch([tmp_path / "a"], tmp_path / "out", build, ex, cpus=3, progress=False)
    opts = {j.key[1]: j.args[1] for j in ex.jobs}
    for o in opts.values():
        assert o.input == str((tmp_path / "a").absolute()) and o.splat.iters == 50 and o.robot.trials == 4
        assert o.robot.cluster == ExecutorOptions(executor="local", workers=3)


def test_summary_shows_finished_builds_pictures_and_never_reads_one_being_written(tmp_path):
    """The summary is rewritten as each capture finishes, while others are still building: their eval/
    holds half-written temp files (a Ray run failed reading one)."""
    import numpy as np
    from PIL import Image

    from splattwin.cluster.batch import summary_html

    for name in ("done", "building"):
        ev = tmp_path / name / "splat" / "eval"
        ev.mkdir(parents=True)
        (ev / ".000.png.tmp1-abcd.png").write_bytes(b"\x89PNG half")   # sorts before 000.png
    Image.fromarray(np.full((8, 24, 3), 200, np.uint8)).save(tmp_path / "done" / "splat" / "eval" / "000.png")
    caps = [{"name": "done", "status": "ok", "input": "a"}, {"name": "building", "status": "reconstructed", "input": "b"}]
    page = summary_html(tmp_path, {"captures": caps, "executor": "local", "wall_s": 1.0})
    assert page.count("<img") == 1 and "held-out view 000" in page and "could not be read" not in page


def test_a_build_task_writes_the_stage_lines_to_its_log_once(tmp_path, monkeypatch, capsys):
    """build(progress=False) logs its stage lines (audit 10A L15); a batch task still writes them to the
    capture's log, once, as the command prints them, even in a worker that inherited a root log handler."""
    import logging
    import sys

    from splattwin.cluster.batch import build_task
    from splattwin.pipeline import build as b

    class Ctx:
        results, timings = {}, {}

    def fake_build(twin, options, until=None, progress=True):
        assert progress is False
        logging.getLogger("splattwin.pipeline.build.stages").info("▶ splat")
        return Ctx()

    monkeypatch.setattr(b, "build", fake_build)
    root = logging.getLogger()
    inherited = logging.StreamHandler(sys.stderr)   # what a worker forked from the command has
    root.addHandler(inherited)
    try:
        build_task(str(tmp_path / "twin"), BuildOptions(), None, 1)   # (a log file: its fds, not testable here)
    finally:
        root.removeHandler(inherited)
    assert capsys.readouterr().err == "▶ splat\n"
    assert logging.getLogger("splattwin.pipeline.build.stages").propagate
