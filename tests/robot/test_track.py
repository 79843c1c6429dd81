"""The viewer's robot track (robot/playback.npz) made from the recorded rollout."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.robot.track import MAX_FRAMES, RobotTrack, playback_indices, write_playback


def test_playback_indices_spread_in_time():
    t = np.arange(1000) * 0.002
    idx = playback_indices(t, 300)
    assert idx[0] == 0 and idx[-1] == 999 and len(idx) <= 300 and np.all(np.diff(idx) > 0)
    assert np.ptp(np.diff(t[idx])) < 0.0025                  # even in time (within one sample)
    np.testing.assert_array_equal(playback_indices(t[:10], 300), np.arange(10))


@pytest.mark.slow
def test_playback_from_the_rollout(default_run, gt_twin_default: Path, tmp_path: Path):
    """The track poses the robot's visual meshes by forward kinematics of the rollout's qpos: the fingers
    open and close with the gripper, the hand moves with the TCP, and the objects move as recorded."""
    from splattwin.robot.world import build_world

    w_run, r = default_run
    ro = r.rollout
    w = build_world(gt_twin_default, visual=True)
    p = write_playback(tmp_path / "playback.npz", w, ro)
    tr = RobotTrack.load(p)
    T, G = tr.positions.shape[:2]
    assert 100 < T <= MAX_FRAMES and G > 10 and tr.rotations.shape == (T, G, 3, 3)
    idx = np.searchsorted(ro.t, tr.times)
    np.testing.assert_allclose(ro.t[idx], tr.times)
    assert set(tr.object_poses) == set(ro.object_poses)
    np.testing.assert_allclose(tr.object_poses["blue_box"], ro.object_poses["blue_box"][idx], atol=1e-6)
    # a finger geom's distance from the hand's geoms follows the measured gripper width
    geom_body = w.model.geom_bodyid[[int(n[1:]) for n in tr.names]]
    left = np.flatnonzero(geom_body == w.body_id("left_finger"))[0]
    right = np.flatnonzero(geom_body == w.body_id("right_finger"))[0]
    gap = np.linalg.norm(tr.positions[:, left] - tr.positions[:, right], axis=1)
    width = ro.gripper_width[idx]
    assert np.corrcoef(gap, width)[0, 1] > 0.99 and np.ptp(gap) > 0.04
    # the hand's geoms stay rigid with the TCP of the recorded configuration
    hand = np.flatnonzero(geom_body == w.body_id("hand"))[0]
    T_tcp = w.tcp_poses(ro.qpos[idx])
    offs = np.einsum("tji,tj->ti", T_tcp[:, :3, :3], tr.positions[:, hand] - T_tcp[:, :3, 3])
    assert np.ptp(offs, axis=0).max() < 1e-5


def test_track_load_rejects_malformed_files(tmp_path: Path):
    tr = RobotTrack(names=["g1"], vertices=[np.eye(3, dtype=np.float32)], faces=[np.array([[0, 1, 2]], np.uint32)],
                    colors=[(1, 2, 3)], positions=np.zeros((4, 1, 3)), rotations=np.tile(np.eye(3), (4, 1, 1, 1)),
                    times=np.arange(4.0), object_poses={"box": np.tile(np.eye(4), (4, 1, 1))})
    back = RobotTrack.load(tr.save(tmp_path / "ok.npz"))
    assert back.names == ["g1"] and back.colors == [(1, 2, 3)] and back.object_poses["box"].shape == (4, 4, 4)
    assert back == tr   # array-aware equality (audit 10A L1): raised ValueError
    arrays = dict(np.load(tmp_path / "ok.npz", allow_pickle=False))
    np.savez(tmp_path / "bad_face.npz", **{**arrays, "f0": np.array([[0, 1, 7]], np.uint32)})
    with pytest.raises(InputError, match="bad_face.npz"):
        RobotTrack.load(tmp_path / "bad_face.npz")
    np.savez(tmp_path / "bad_shape.npz", **{**arrays, "positions": np.zeros((3, 1, 3))})
    with pytest.raises(InputError, match="positions"):
        RobotTrack.load(tmp_path / "bad_shape.npz")


def test_track_load_refuses_header_shapes_before_reading_any_array(tmp_path: Path, monkeypatch):
    """A playback file claiming more frames than allowed is refused from its .npy headers, unread."""
    import splattwin.robot.track as track_mod

    tr = RobotTrack(names=["g1"], vertices=[np.eye(3, dtype=np.float32)], faces=[np.array([[0, 1, 2]], np.uint32)],
                    colors=[(1, 2, 3)], positions=np.zeros((40, 1, 3)), rotations=np.tile(np.eye(3), (40, 1, 1, 1)),
                    times=np.arange(40.0))
    p = tr.save(tmp_path / "playback.npz")
    monkeypatch.setattr(track_mod, "MAX_TRACK_FRAMES", 10, raising=False)
    read = []
    monkeypatch.setattr(np.lib.format, "read_array", lambda *a, **k: read.append(a))
    monkeypatch.setattr(np, "load", lambda *a, **k: read.append(a))
    with pytest.raises(InputError, match=r"playback\.npz.*40 frames"):
        RobotTrack.load(p)
    assert read == []


def test_viewer_moves_the_objects_with_the_track(gt_twin_small: Path, tmp_path: Path):
    """build_scene draws the track's robot and moves the objects' collision meshes to the recorded poses."""
    import shutil

    import viser

    from splattwin.playback.view_model import load_robot_track
    from splattwin.robot.track import robot_track
    from splattwin.robot.world import build_world
    from splattwin.viewer.app import build_scene

    twin = tmp_path / "twin"
    shutil.copytree(gt_twin_small, twin)
    w = build_world(twin, visual=True)
    q = np.tile(w.qpos(), (3, 1))
    moved = np.tile(np.eye(4), (3, 1, 1))
    moved[:, :3, 3] = [[0.0, 0.0, 0.1], [0.05, 0.1, 0.2], [0.1, 0.2, 0.3]]
    robot_track(w.model, q, np.arange(3.0), bodies=w.robot_bodies,
                object_poses={"blue_box": moved}).save(twin / "robot" / "playback.npz")
    track = load_robot_track(twin)
    assert track is not None and len(track) == 3
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        h = build_scene(server, twin, track)
        assert any(k.startswith("robot/") for k in h)
        h["_slider"].value = 2
        np.testing.assert_allclose(h["col/blue_box/0"].position, [0.1, 0.2, 0.3], atol=1e-6)
    finally:
        server.stop()
