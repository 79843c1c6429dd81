"""MP4 round trip and `splattwin render`."""

from __future__ import annotations

import numpy as np
import pytest

from splattwin.cli import main
from splattwin.playback.video import Mp4Writer, probe_mp4, read_mp4, write_mp4


def test_mp4_round_trip_odd_size(tmp_path):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:25, 0:33]
    frames = [np.stack([(xx * 7 + k * 20) % 256, (yy * 9) % 256, np.full_like(xx, 40 * k)], -1).astype(np.uint8)
              for k in range(7)]
    p = write_mp4(tmp_path / "a.mp4", frames, fps=12)
    info = probe_mp4(p)
    assert info["frames"] == 7 and info["fps"] == 12 and info["codec"] == "h264"
    back = read_mp4(p, size=(33, 25))
    assert back.shape == (7, 25, 33, 3)
    err = np.abs(back.astype(float) - np.stack(frames).astype(float)).mean()
    assert err < 6.0   # lossy but faithful
    # frames are in order (each frame's blue level)
    assert np.all(np.diff(back[..., 2].mean(axis=(1, 2))) > 20)
    # the index (moov) before the frames (mdat): plays while it downloads (it was written last)
    data = p.read_bytes()
    assert 0 < data.find(b"moov") < data.find(b"mdat")
    # an exception while writing leaves no file behind
    try:
        with Mp4Writer(tmp_path / "b.mp4", 10) as w:
            w.write(frames[0])
            raise RuntimeError("killed")
    except RuntimeError:
        pass
    assert not (tmp_path / "b.mp4").exists() and not list(tmp_path.glob(".b.mp4*"))
    del rng


def test_render_cli_writes_video(tiny_twin, tmp_path):
    from .rollouts import synthetic_rollout

    r = synthetic_rollout(0.3).save(tmp_path / "r.npz")
    out = tmp_path / "v.mp4"
    code = main(["render", str(tiny_twin), "--camera", "view_0", "--out", str(out), "--rollout", str(r),
                 "--fps", "20", "--no-robot"])
    assert code == 0
    info = probe_mp4(out)
    assert info["frames"] == 7 and (info["width"], info["height"]) == (96, 72)
    v = read_mp4(out)
    assert np.abs(v[0].astype(float) - v[-1].astype(float)).mean() > 1.0   # the object moved


def test_render_cli_keep_view_dependence(tiny_twin, tmp_path, monkeypatch):
    """--keep-view-dependence reaches the scene (view_fade=False); without it the fade is on. (The effect
    itself is tested in test_scene.py; frames of an MP4 carry codec noise of the same size.)"""
    from splattwin.playback.scene import DynamicScene

    from .rollouts import synthetic_rollout

    r = synthetic_rollout(0.3).save(tmp_path / "r.npz")
    seen = []
    load = DynamicScene.load.__func__

    def spy(cls, *a, **kw):
        sc = load(cls, *a, **kw)
        seen.append(sc.view_fade)
        return sc

    monkeypatch.setattr(DynamicScene, "load", classmethod(spy))
    for extra in ([], ["--keep-view-dependence"]):
        assert main(["render", str(tiny_twin), "--camera", "view_0", "--out", str(tmp_path / "v.mp4"),
                     "--rollout", str(r), "--fps", "20", "--no-robot", *extra]) == 0
    assert seen == [True, False]


def test_a_killed_writer_s_half_video_is_removed_by_the_next_run(tmp_path):
    """The half-written MP4 of a killed `report`/`render` carries our temporary name, so the next run
    that takes the folder's lock removes it (it was `.name.<random>.mp4` and stayed for ever)."""
    import os

    from splattwin import io

    with Mp4Writer(tmp_path / "task.mp4", 10) as w:
        w.write(np.zeros((16, 16, 3), np.uint8))
        tmp = [p for p in tmp_path.iterdir() if p.name != "task.mp4"]
        assert len(tmp) == 1
        m = io._TEMP_RE.match(tmp[0].name)
        assert m is not None and int(m.group("pid")) == os.getpid()
    assert (tmp_path / "task.mp4").is_file() and not tmp[0].exists()


def test_render_of_a_failed_run_says_so(tiny_twin, tmp_path, capsys):
    """The twin's own rollout of a failed run: the video is written, and the command says the run failed and
    where (before, nothing told the video from one of the task done)."""
    import shutil

    from splattwin import io
    from splattwin.robot.outputs import twin_digest

    from .rollouts import synthetic_rollout

    twin = tmp_path / "twin"
    shutil.copytree(tiny_twin, twin)
    synthetic_rollout(0.2).save(twin / "robot" / "rollout.npz")
    steps = [{"index": 1, "pick": "blue_box", "goal": "tray", "success": False,
              "failure": "'blue_box' slipped out of the gripper"}]
    for success, note in ((False, True), (True, False)):
        io.write_json(twin / "robot" / "results.json", {"twin_digest": twin_digest(twin), "nominal": {
            "success": success, "steps": [{**st, "success": success} for st in steps]}})
        assert main(["render", str(twin), "--camera", "view_0", "--out", str(tmp_path / "v.mp4"), "--fps", "10",
                     "--no-robot", "--no-progress"]) == 0
        cap = capsys.readouterr()
        said = ("note: this rollout is of a failed run (step 1 (blue_box -> tray) failed: 'blue_box' slipped out "
                "of the gripper)" in cap.err)
        assert said == note and ("a failed run" in cap.out) == note
    # a run written elsewhere (`plan --out DIR`): its results.json beside the rollout says so too
    run = tmp_path / "run"
    synthetic_rollout(0.2).save(run / "rollout.npz")
    io.write_json(run / "results.json", {"nominal": {"success": False, "steps": steps}})
    assert main(["render", str(twin), "--camera", "view_0", "--out", str(tmp_path / "v.mp4"), "--fps", "10",
                 "--no-robot", "--no-progress", "--rollout", str(run / "rollout.npz")]) == 0
    assert "note: this rollout is of a failed run (step 1" in capsys.readouterr().err


def test_render_refuses_an_out_it_cannot_write_before_rendering(tiny_twin, tmp_path, capsys):
    """--out naming a folder rendered every frame, then failed renaming onto it; a path under a file failed at
    the first frame: both were "internal error" (exit 1). Now exit 2 naming the path, before the render."""
    from .rollouts import synthetic_rollout

    r = synthetic_rollout(0.2).save(tmp_path / "r.npz")
    (tmp_path / "v.mp4").mkdir()
    (tmp_path / "file").write_text("x")
    for out, msg in ((tmp_path / "v.mp4", "--out is a folder"), (tmp_path / "file" / "v.mp4", "cannot create")):
        assert main(["render", str(tiny_twin), "--camera", "view_0", "--out", str(out), "--rollout", str(r),
                     "--no-robot", "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert msg in err and "internal error" not in err


def test_render_takes_the_base_pose_of_the_run_that_made_the_rollout(tiny_twin, tmp_path, monkeypatch):
    """`plan --out DIR --base-pose ...` writes rollout.npz and results.json into DIR; `render --rollout
    DIR/rollout.npz` drew the robot at TWIN/robot/results.json's base (another run's) or the default, so the
    arm stood away from the objects physics moved."""
    import shutil

    from splattwin import io
    from splattwin.playback.robot import RobotSplats
    from splattwin.robot.outputs import twin_digest

    from .rollouts import synthetic_rollout

    twin = tmp_path / "twin"
    shutil.copytree(tiny_twin, twin)
    io.write_json(twin / "robot" / "results.json", {"base_pose": {"x": -0.5, "y": 0.0, "z": 0.0, "yaw": 0.0},
                                                    "twin_digest": twin_digest(twin), "nominal": {"success": True}})
    run = tmp_path / "run"
    r = synthetic_rollout(0.1).save(run / "rollout.npz")
    io.write_json(run / "results.json", {"base_pose": {"x": -0.62, "y": 0.1, "z": 0.0, "yaw": 0.3}})
    bases = []

    def spy(T, *a, **kw):
        bases.append(np.asarray(T))
        raise RuntimeError("enough")

    monkeypatch.setattr(RobotSplats, "panda", staticmethod(spy))
    for rollout, x in ((r, -0.62), (None, -0.5)):
        synthetic_rollout(0.1).save(twin / "robot" / "rollout.npz")
        args = ["render", str(twin), "--camera", "view_0", "--out", str(tmp_path / "v.mp4"), "--no-progress"]
        main(args + (["--rollout", str(rollout)] if rollout else []))
        assert bases[-1][0, 3] == pytest.approx(x)
