"""`splattwin plan --record DIR`: each run (nominal + perturbed trials from the process pool) as a
LeRobot-layout episode, read back and checked frame by frame against the run's rollout."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from splattwin.cli import main
from splattwin.playback.episode import check_episode, read_episode, sample_indices
from splattwin.playback.record import Recorder, staging_dir
from splattwin.robot.rollout import Rollout
from splattwin.robot.world import BasePose

TASK = "- pick: yellow_cube\n  place_on: blue_box\n"


def _plan(twin: Path, tmp_path: Path, ds: Path, *extra: str) -> int:
    task = tmp_path / "task.yaml"
    task.write_text(TASK)
    return main(["plan", str(twin), "--task", str(task), "--no-render", "--trials", "2", "--sigma", "0.004",
                 "--workers", "2", "--record", str(ds), "--record-fps", "4", "--record-width", "48",
                 "--record-camera", "capture:0", *extra])


def test_plan_record_episodes_match_their_runs(splat_gt_twin: Path, tmp_path: Path):
    twin = tmp_path / "twin"
    shutil.copytree(splat_gt_twin, twin)
    ds = tmp_path / "dataset"
    assert _plan(twin, tmp_path, ds) == 0
    robot = twin / "robot"
    res = json.loads((robot / "results.json").read_text())
    rollouts = [Rollout.load(robot / "rollout.npz")] + [Rollout.load(robot / "trials" / r["rollout"])
                                                       for r in res["trials"]["results"]]
    assert len(rollouts) == 3
    info = json.loads((ds / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 3 and info["fps"] == 4.0 and info["total_videos"] == 6
    assert set(info["features"]) >= {"observation.images.wrist", "observation.images.scene", "observation.state",
                                     "action"}
    assert info["features"]["observation.state"]["names"][-1] == "gripper_width"
    assert not staging_dir(ds).exists()       # the staging folder became the dataset

    # a fresh renderer of the same twin, robot base and cameras checks every frame
    rec = Recorder(twin, BasePose().matrix(), camera="capture:0", width=48, fps=4.0)
    metas = [json.loads(line) for line in (ds / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert [m["run"] for m in metas] == ["nominal", "trial 1", "trial 2"]
    assert [m["seed"] for m in metas[1:]] == [r["seed"] for r in res["trials"]["results"]]
    assert metas[0]["tasks"] == ["move yellow_cube to blue_box"]
    firsts = []
    for i, ro in enumerate(rollouts):
        ep = read_episode(ds, i)
        assert len(ep) == len(sample_indices(ro.t, 4.0)) > 10
        assert ep.videos["observation.images.wrist"].shape[1:] == (36, 48, 3)
        # images against a fresh render of each frame's state (H.264 at 48x36 with 4:2:0 chroma: ~27 dB)
        assert check_episode(ep, ro, rec.renderer, rec.cameras, min_psnr=24.0) == len(ep)
        # the gripper closes on the cube and opens again in every run: the state column shows it
        w = np.stack(ep.columns["observation.state"])[:, -1]
        assert w.max() > 0.06 and w.min() < 0.05
        firsts.append(ro.object_poses["yellow_cube"][0])
        with pytest.raises(AssertionError):   # an episode is not the record of another run
            check_episode(ep, rollouts[(i + 1) % 3])
    # the trials start from perturbed object poses (as without --record), the nominal from the twin's
    d1, d2 = (np.linalg.norm(f[:2, 3] - firsts[0][:2, 3]) for f in firsts[1:])
    assert d1 > 1e-4 and d2 > 1e-4


def test_plan_record_refuses_before_running(splat_gt_twin: Path, tmp_path: Path, capsys):
    twin = tmp_path / "twin"
    shutil.copytree(splat_gt_twin, twin)
    other = tmp_path / "not_a_dataset"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert _plan(twin, tmp_path, other) == 2
    assert "not a LeRobot dataset" in capsys.readouterr().err and (other / "notes.txt").is_file()
    below = tmp_path / "below.yaml"
    below.write_text("eye: [0.0, 0.0, -0.2]\nlook_at: [0.0, 0.0, 0.0]\nup: [0, 1, 0]\n")
    task = tmp_path / "task.yaml"
    task.write_text(TASK)
    assert main(["plan", str(twin), "--task", str(task), "--no-render", "--record", str(tmp_path / "ds"),
                 "--record-camera", str(below)]) == 2
    assert "below the table" in capsys.readouterr().err
    assert not (twin / "robot" / "results.json").exists() and not (tmp_path / "ds").exists()


def test_plan_record_twin_without_splats_exit_2(meshonly_twin: Path, tmp_path: Path, capsys):
    assert main(["plan", str(meshonly_twin), "--no-render", "--record", str(tmp_path / "ds")]) == 2
    assert "no splats" in capsys.readouterr().err
