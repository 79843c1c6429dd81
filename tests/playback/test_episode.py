"""LeRobot-layout episodes: written from a rollout, read back and checked frame by frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.playback.cameras import EyeInHand, resolve_camera
from splattwin.playback.episode import check_episode, read_episode, sample_indices, write_episode
from splattwin.playback.compositor import PlaybackRenderer
from splattwin.playback.robot import RobotSplats
from splattwin.playback.scene import DynamicScene
from splattwin.robot.rollout import Rollout

from .rollouts import synthetic_rollout


def test_sample_indices():
    t = np.arange(0, 1.0001, 0.01)
    idx = sample_indices(t, 10)
    assert len(idx) == 11 and idx[0] == 0 and idx[-1] == 100
    np.testing.assert_allclose(t[idx], np.arange(11) / 10, atol=1e-9)


def test_rollout_save_load(tmp_path):
    r = synthetic_rollout(0.2)
    back = Rollout.load(r.save(tmp_path / "r.npz"))
    for k in ("t", "qpos", "q_arm", "gripper_width", "action_q_arm", "action_gripper", "step_index"):
        np.testing.assert_array_equal(getattr(back, k), getattr(r, k))
    np.testing.assert_array_equal(back.object_poses["blue_box"], r.object_poses["blue_box"])
    assert back.joint_names == r.joint_names
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError):
        Rollout.load(tmp_path / "bad.npz")


def test_episode_round_trip(tiny_twin, tmp_path):
    rollout = synthetic_rollout(0.6)
    scene = DynamicScene.load(tiny_twin)
    T_base = np.eye(4)
    T_base[:3, 3] = [-0.45, 0, 0]
    renderer = PlaybackRenderer(scene, RobotSplats.panda(T_base), backend="cpu")
    cameras = {"wrist": EyeInHand(width=64, height=48), "scene": resolve_camera("view_0", tiny_twin)}
    root = tmp_path / "dataset"
    meta = write_episode(root, rollout, renderer, cameras, fps=10, task="put the blue box down")
    assert meta["length"] == 7
    ep = read_episode(root, 0)
    assert set(ep.videos) == {"observation.images.wrist", "observation.images.scene"}
    assert ep.videos["observation.images.wrist"].shape == (7, 48, 64, 3)
    assert ep.videos["observation.images.scene"].shape == (7, 72, 96, 3)
    checked = check_episode(ep, rollout, renderer, cameras)
    assert checked == len(sample_indices(rollout.t, 10)) == 7
    # the wrist view changes as the hand moves; a wrong rollout fails the check
    w = ep.videos["observation.images.wrist"].astype(float)
    assert np.abs(w[0] - w[-1]).mean() > 5
    wrong = synthetic_rollout(0.6)
    wrong.q_arm = wrong.q_arm + 0.01
    with pytest.raises(AssertionError, match="state"):
        check_episode(ep, wrong)
    # a second episode appends; the meta files agree
    write_episode(root, synthetic_rollout(0.3), renderer, cameras, fps=10, task="put the blue box down")
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2 and info["total_frames"] == 7 + 4 and info["total_videos"] == 4
    assert info["codebase_version"] == "v2.1" and info["features"]["observation.state"]["shape"] == [8]
    ep1 = read_episode(root, 1, videos=False)
    np.testing.assert_array_equal(ep1.columns["index"], 7 + np.arange(4))
    # untrusted path templates stay inside the dataset
    info["data_path"] = "../../etc/{episode_index}"
    (root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(InputError, match="outside"):
        read_episode(root, 0)


def test_read_jsonl_bounded_and_checked(tmp_path, monkeypatch):
    """An episode folder may come from someone else: its JSON-lines metadata is read within a bound and
    every line must be a JSON object; each failure names the file (and the line)."""
    from splattwin import limits
    from splattwin.playback.episode import read_jsonl

    p = tmp_path / "episodes.jsonl"
    assert read_jsonl(p) == []                                  # no file: no rows
    p.write_text('{"episode_index": 0}\n\n{"episode_index": 1}\n')
    assert [r["episode_index"] for r in read_jsonl(p)] == [0, 1]
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 16)
    with pytest.raises(InputError, match=r"JSON-lines file is 4\d bytes, more than the limit of 16 bytes") as e:
        read_jsonl(p)
    assert "episodes.jsonl" in str(e.value)
    monkeypatch.undo()
    for text, what in (('{"a": 1}\n[1, 2]\n', "line 2 is not a JSON object"),
                       ('{"a": 1}\n{oops\n', "line 2 is not JSON"),
                       ("[" * 100_000 + "]" * 100_000 + "\n", "line 1 is nested too deeply"),
                       ('{"a": ' + "9" * 5000 + "}\n", "line 1 is not JSON")):
        p.write_text(text)
        with pytest.raises(InputError, match=what) as e:
            read_jsonl(p)
        assert "episodes.jsonl" in str(e.value)
