"""`build` on a video: how many frames it takes (--max-frames, --min-change), and input errors found
before any work (small synthetic clips, `tests.capture.test_video_cli`)."""

from __future__ import annotations

import pytest

from splattwin.cli import main
from splattwin.errors import InputError
from tests.capture.test_video_cli import _board, _encode


@pytest.fixture
def clip(tmp_path):
    """A 24-frame 96x64 pan (3 px a frame: no near-duplicates)."""
    video = tmp_path / "vids" / "scan.mp4"
    video.parent.mkdir()
    _encode(video, [_board(3 * i) for i in range(24)])
    return video


def _stop_at_poses(monkeypatch):
    """estimate_poses replaced by one that records the frames it got and stops (no SfM in these tests)."""
    import splattwin.poses.estimate as estimate

    seen = []

    def fake(ds, opts=None):
        seen.append([f.name for f in ds.frames])
        raise InputError("stopped by the test")

    monkeypatch.setattr(estimate, "estimate_poses", fake)
    return seen


@pytest.mark.parametrize("flag", ["--max-frames", "--poses.max-frames"])
def test_build_max_frames_reaches_the_video(tmp_path, clip, monkeypatch, capsys, flag):
    seen = _stop_at_poses(monkeypatch)
    code = main(["build", str(clip), "--out", str(tmp_path / "T"), flag, "5", "--until", "poses", "--no-progress"])
    assert code == 2 and "stopped by the test" in capsys.readouterr().err
    assert seen == [[f"frame_{i:05d}" for i in range(5)]]


def test_build_min_change_and_config_file(tmp_path, clip, monkeypatch):
    """--min-change reaches the extraction (a clip held still 6 frames at each of 4 places: 4 frames by
    default, 12 with 0), and both options come from a config file too."""
    import numpy as np

    rng = np.random.default_rng(0)
    still = tmp_path / "still.mp4"   # grey-level noise: no two frames identical (those are dropped anyway)
    _encode(still, [np.minimum(_board(20 * (i // 6)), 254) + rng.integers(0, 2, (64, 96, 3), dtype=np.uint8)
                    for i in range(24)])
    seen = _stop_at_poses(monkeypatch)
    assert main(["build", str(still), "--out", str(tmp_path / "A"), "--max-frames", "12", "--until", "poses"]) == 2
    assert main(["build", str(still), "--out", str(tmp_path / "B"), "--max-frames", "12", "--min-change", "0",
                 "--until", "poses"]) == 2
    cfg = tmp_path / "twin.yaml"
    cfg.write_text("poses:\n  max_frames: 7\n  min_change: 0\n")
    assert main(["build", str(still), "--out", str(tmp_path / "C"), "--config", str(cfg), "--until", "poses"]) == 2
    assert [len(s) for s in seen] == [4, 12, 7]


def test_max_frames_is_part_of_the_poses_key(tmp_path, clip):
    """Another --max-frames (or --min-change) re-runs the poses stage (and so everything after it)."""
    from splattwin.pipeline.build import stage_keys
    from splattwin.pipeline.options import BuildOptions
    from splattwin.poses.options import PoseOptions

    def keys(**kw):
        return stage_keys(tmp_path / "T", BuildOptions(input=str(clip), poses=PoseOptions(**kw)))

    base = keys()
    assert keys(max_frames=60)["poses"] != base["poses"] and keys(max_frames=60)["splats"] != base["splats"]
    assert keys(min_change=0.0)["poses"] != base["poses"]
    assert keys(max_frames=60)["poses"] != keys(max_frames=61)["poses"]


def test_unknown_build_option_prints_builds_usage(tmp_path, clip, capsys):
    with pytest.raises(SystemExit) as e:
        main(["build", str(clip), "--out", str(tmp_path / "T"), "--max-frams", "60"])
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert "usage: splattwin build" in err and "splattwin build: error: unrecognized arguments: --max-frams 60" in err
    assert not (tmp_path / "T").exists()


@pytest.mark.parametrize("n", ["0", "-2"])
def test_max_frames_below_one_refused_everywhere(tmp_path, clip, capsys, n):
    """0 or a negative --max-frames: exit 2 naming the option, before anything is read or written, on every
    command that takes it (0 was silently replaced by 30 on a video, -2 was an internal error in numpy, and
    0 on an image folder said "dataset has no frames")."""
    import numpy as np

    from splattwin import io

    photos = tmp_path / "photos"
    for i in range(3):
        io.write_image(photos / f"img_{i}.png", np.full((48, 64, 3), 40 * i, np.uint8))
    before = sorted(p.name for p in clip.parent.iterdir())
    runs = [["poses", str(clip), str(tmp_path / "P1")], ["poses", str(photos), str(tmp_path / "P2")],
            ["build", str(clip), "--out", str(tmp_path / "B1"), "--until", "poses"],
            ["build", str(clip), "--out", str(tmp_path / "B2"), "--poses.max-frames"],
            ["train", str(photos), str(tmp_path / "T")],
            ["capture", "info", str(clip)], ["capture", "frames", str(clip), str(tmp_path / "F")]]
    for argv in runs:
        argv = argv + ([n] if argv[-1].startswith("--poses") else ["--max-frames", n])
        assert main(argv) == 2, argv
        assert f"--max-frames must be >= 1, got {n}" in capsys.readouterr().err, argv
    assert not [p for p in tmp_path.iterdir() if p.name not in ("vids", "photos")]
    assert sorted(p.name for p in clip.parent.iterdir()) == before
    cfg = tmp_path / "twin.yaml"
    cfg.write_text(f"poses:\n  max_frames: {n}\n")
    assert main(["build", str(clip), "--out", str(tmp_path / "B3"), "--config", str(cfg)]) == 2
    assert f"--max-frames must be >= 1, got {n}" in capsys.readouterr().err
    assert not (tmp_path / "B3").exists()
    assert main(["build", str(clip), "--out", str(tmp_path / "B4"), "--min-change", "-1"]) == 2
    assert "--min-change must be a number >= 0, got -1" in capsys.readouterr().err


def test_no_progress_silences_the_frame_scoring(tmp_path, clip, monkeypatch, capsys):
    """--no-progress: no 'scoring scan.mp4' lines from build, poses or capture frames (they were printed
    whatever the flag said); without it they are there."""
    _stop_at_poses(monkeypatch)
    assert main(["build", str(clip), "--out", str(tmp_path / "A"), "--until", "poses"]) == 2
    assert "scoring scan.mp4" in capsys.readouterr().err
    assert main(["build", str(clip), "--out", str(tmp_path / "B"), "--until", "poses", "--no-progress"]) == 2
    assert main(["poses", str(clip), str(tmp_path / "P"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "scoring" not in err and err.count("stopped by the test") == 2
    assert main(["capture", "frames", str(clip), str(tmp_path / "F"), "--no-progress"]) == 0
    assert main(["capture", "info", str(clip), "--no-progress"]) == 0
    assert "scoring" not in capsys.readouterr().err


def test_video_beside_a_scene_is_not_that_scene(tmp_path, clip, monkeypatch, capsys):
    """A video saved in a scene folder (beside its scene.json and masks/) is refused by the pre-flight for
    having no 2D masks, before any frame is extracted or SfM runs, as the same video elsewhere is: the
    build took the scene's masks for its own, passed the pre-flight, and failed on them after SfM and
    training ("no mask view matches a dataset image")."""
    seen = _stop_at_poses(monkeypatch)
    scene = tmp_path / "scene_c"
    (scene / "masks" / "noisy").mkdir(parents=True)
    (scene / "scene.json").write_text("{}")
    walk = scene / "walk.mp4"
    walk.write_bytes(clip.read_bytes())
    for video in (clip, walk):
        assert main(["build", str(video), "--out", str(tmp_path / video.stem), "--no-progress"]) == 2
        assert "no 2D masks for the semantics stage" in capsys.readouterr().err
        assert not (tmp_path / video.stem).exists()
    assert seen == []


def _no_data(path, n=20):
    """A clip whose stream declares n frames but whose coded data is zeroed: nothing decodes."""
    _encode(path, [_board(3 * i) for i in range(n)])
    b = bytearray(path.read_bytes())
    i = b.find(b"mdat")
    size = int.from_bytes(b[i - 4:i], "big")
    b[i + 4:i - 4 + size] = bytes(size - 8)
    path.write_bytes(bytes(b))
    return path


def test_video_with_fewer_than_two_frames_stopped_by_the_preflight(tmp_path, monkeypatch, capsys):
    """A 1-frame video, one whose frames do not decode, or --max-frames 1: the pre-flight names the video
    and the problem and the build leaves no folder (it failed in the poses stage with SfM's generic advice
    about intrinsics and overlap, naming no file, and left pipeline.json, the lock and the frames)."""
    seen = _stop_at_poses(monkeypatch)
    one = tmp_path / "one.mp4"
    _encode(one, [_board(0)])
    two = tmp_path / "two.mp4"
    _encode(two, [_board(0), _board(9)])
    cases = [(one, [], "gave 1 frame (the video has 1 decodable frame); structure from motion needs >= 2"),
             (_no_data(tmp_path / "nodata.mp4"), [], "gave no frame: decoding failed at its first frame"),
             (two, ["--max-frames", "1"], "gave 1 frame (--max-frames 1); structure from motion needs >= 2")]
    for video, extra, msg in cases:
        out = tmp_path / f"T_{video.stem}"
        assert main(["build", str(video), "--out", str(out), "--until", "splats", "--no-progress"] + extra) == 2
        err = capsys.readouterr().err
        assert f"{video}: {msg}" in err, err
        assert not out.exists()
    assert seen == []


def test_failed_video_build_removes_the_folder_it_created(tmp_path, clip, monkeypatch, capsys):
    """An input error found in the poses stage, before it wrote anything of its own (here an unknown
    --heldout-views name, after the frames were extracted): the folder the build created goes, as the
    pre-flight's errors already removed it; a folder where SfM has begun (poses/) is kept to resume; a
    folder that existed before is kept."""
    out = tmp_path / "X8"
    assert main(["build", str(clip), "--out", str(out), "--heldout-views", "frame_00003,frame_99999",
                 "--until", "splats", "--no-progress"]) == 2
    assert "no view named 'frame_99999'" in capsys.readouterr().err
    assert not out.exists()
    out.mkdir()
    assert main(["build", str(clip), "--out", str(out), "--heldout-views", "frame_99999", "--until", "splats",
                 "--no-progress"]) == 2
    assert (out / "pipeline.json").is_file()
    import splattwin.poses.estimate as estimate

    def sfm_began(ds, opts=None):
        (opts.work_dir / "database.db").parent.mkdir(parents=True)
        (opts.work_dir / "database.db").write_bytes(b"features")
        raise InputError("SfM registered too few images")

    monkeypatch.setattr(estimate, "estimate_poses", sfm_began)
    assert main(["build", str(clip), "--out", str(tmp_path / "S"), "--until", "splats", "--no-progress"]) == 2
    assert (tmp_path / "S" / "poses" / "sfm" / "database.db").is_file()


def test_video_collapsing_to_one_frame_named_by_the_poses_stage(tmp_path, capsys):
    """A camera that never moved: every frame a near-duplicate of the first, so one frame is kept; the poses
    stage names the video and why, not SfM's advice about intrinsics."""
    import numpy as np

    rng = np.random.default_rng(0)
    still = tmp_path / "still.mp4"
    _encode(still, [np.minimum(_board(0), 254) + rng.integers(0, 2, (64, 96, 3), dtype=np.uint8)
                    for _ in range(12)])
    assert main(["poses", str(still), str(tmp_path / "P"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{still}: gave 1 frame (of 12 decoded frames, the others differ too little from it" in err, err
