import json

import numpy as np
import pytest

from splattwin.capture.video import extract_frames, select_frames, sharpness
from splattwin.cli import main
from splattwin.errors import InputError


def _write_video(path, n=24, sharp_every=6, w=96, h=64):
    """A clip whose frame i is a sharp checkerboard only when i % sharp_every == 3, blurred otherwise."""
    import av
    import cv2

    yy, xx = np.mgrid[0:h, 0:w]
    board = (((xx // 8) + (yy // 8)) % 2 * 255).astype(np.uint8)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=10, options={"crf": "0", "preset": "ultrafast"})
        s.width, s.height, s.pix_fmt = w, h, "yuv444p"
        sharp = []
        for i in range(n):
            img = np.roll(board, i, axis=1)
            if i % sharp_every != 3:
                img = cv2.GaussianBlur(img, (0, 0), 3)
            else:
                sharp.append(i)
            rgb = np.repeat(img[..., None], 3, axis=2)
            for p in s.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return sharp


def test_select_frames_windows():
    scores = np.array([0, 5, 1, 9, 0, 0, 2, 1])
    assert select_frames(scores, 2) == [3, 6]
    assert select_frames(scores, 100) == list(range(8))


def test_video_extraction_picks_sharpest(tmp_path):
    video = tmp_path / "scan.mp4"
    sharp = _write_video(video)
    frames = extract_frames(video, tmp_path / "frames", max_frames=4)
    assert len(frames) == 4
    index = json.loads((tmp_path / "frames" / "frames.json").read_text())
    assert index["source_indices"] == sharp
    # cached second call returns the same files without re-decoding
    assert extract_frames(video, tmp_path / "frames", max_frames=4) == frames
    from splattwin.capture import load_dataset

    ds = load_dataset(video, max_frames=4)
    assert len(ds.frames) == 4 and not ds.has_poses and ds.meta["format"] == "video"


def test_sharpness_orders_blur():
    import cv2

    img = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)
    assert sharpness(img) > sharpness(cv2.GaussianBlur(img, (0, 0), 2))


def test_bad_video(tmp_path):
    p = tmp_path / "bad.mp4"
    p.write_bytes(b"garbage")
    with pytest.raises(InputError, match="video"):
        extract_frames(p, tmp_path / "out")


def test_cli_convert_and_info(tmp_path, capsys, make_dataset):
    ds = make_dataset(tmp_path, with_points=False)
    from splattwin.capture import nerfstudio

    nerfstudio.write(ds, tmp_path / "transforms.json")
    assert main(["capture", "info", str(tmp_path)]) == 0
    assert "4 frames" in capsys.readouterr().out
    assert main(["capture", "convert", str(tmp_path), str(tmp_path / "colmap"), "--format", "colmap"]) == 0
    assert (tmp_path / "colmap" / "images.txt").is_file()
    assert main(["capture", "info", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["capture", "convert", str(tmp_path / "images"), str(tmp_path / "x"), "--format", "nerfstudio"]) == 2


def test_info_on_a_video_writes_nothing_beside_it(tmp_path, capsys):
    from splattwin.cli import main

    video = tmp_path / "scan.mp4"
    _write_video(video)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["capture", "info", str(video)]) == 0
    assert "frames" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def _encode(path, frames, rate=10, turn_cw=False):
    """Lossless H.264 clip of these RGB frames. turn_cw: an MP4 display matrix saying "turn 90 degrees
    clockwise to show" (what a phone filming in portrait writes into the track header, `tkhd`)."""
    import struct

    import av

    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=rate, options={"crf": "0", "preset": "ultrafast"})
        s.height, s.width = frames[0].shape[:2]
        s.pix_fmt = "yuv444p"
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    if turn_cw:   # PyAV cannot set it: patch the tkhd matrix (version 0 header) in place
        b = bytearray(path.read_bytes())
        i = b.find(b"tkhd")
        assert i > 0 and b[i + 4] == 0
        off = i + 4 + 4 + 20 + 8 + 8
        b[off:off + 36] = struct.pack(">9i", 0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000)
        path.write_bytes(bytes(b))


def _board(shift, w=96, h=64):
    """A random 8-pixel block texture panned by `shift` pixels (no two shifts below 96 look alike)."""
    blocks = np.random.default_rng(0).integers(0, 256, (h // 8, w // 8), dtype=np.uint8)
    img = np.roll(np.kron(blocks, np.ones((8, 8), np.uint8)), shift, axis=1)
    return np.repeat(img[..., None], 3, axis=2)


def _frame_files(folder):
    return sorted(p.name for p in folder.glob("frame_*.png"))


def test_reextraction_leaves_no_stale_frames(tmp_path):
    """A changed --max-frames or a re-recorded video under the same name: the old frames go, and only the
    frames of the new extraction are read (they were mixed in: 10 frames for --max-frames 5)."""
    from splattwin.capture import load_dataset

    video, out = tmp_path / "scan.mp4", tmp_path / "frames"
    _encode(video, [_board(3 * i) for i in range(24)])
    assert len(extract_frames(video, out, max_frames=12)) == 12
    (out / "notes.png").write_bytes(b"not ours")          # a file this code did not write stays
    assert len(extract_frames(video, out, max_frames=5)) == 5
    assert _frame_files(out) == [f"frame_{i:05d}.png" for i in range(5)]
    assert (out / "notes.png").is_file()
    assert len(load_dataset(video, max_frames=5, frames_dir=out).frames) == 5
    # re-recorded: another scene, fewer frames, portrait
    _encode(video, [np.ascontiguousarray(np.rot90(_board(5 * i), 1)) for i in range(3)])
    ds = load_dataset(video, max_frames=5, frames_dir=out)
    assert len(ds.frames) == 3 and {(f.camera.width, f.camera.height) for f in ds.frames} == {(64, 96)}
    assert _frame_files(out) == [f"frame_{i:05d}.png" for i in range(3)]


def test_rotated_video_frames_are_upright(tmp_path):
    """A phone video stored sideways with a display rotation comes out as a player shows it."""
    from PIL import Image

    upright = np.zeros((48, 80, 3), np.uint8)
    upright[:16, :24] = (255, 0, 0)       # a red block top-left: any turn or mirror moves it
    upright[30:, 50:] = (0, 0, 255)
    stored = np.rot90(upright, 1)         # sensor data turned 90 degrees counter-clockwise ...
    video = tmp_path / "phone.mp4"
    _encode(video, [stored] * 2 + [np.roll(stored, 9, axis=0)] * 2, turn_cw=True)  # ... and tagged to be turned back
    frames = extract_frames(video, tmp_path / "f", max_frames=4)
    first = np.asarray(Image.open(frames[0]).convert("RGB"))
    assert first.shape == upright.shape
    assert np.abs(first.astype(int) - upright).mean() < 3
    assert json.loads((tmp_path / "f" / "frames.json").read_text())["turned_ccw_deg"] == 270


def test_select_frames_skips_near_duplicates():
    thumbs = [np.full((4, 4), v, np.uint8) for v in (0, 0, 0, 10, 10, 10.5, 30)]
    scores = np.array([1, 5, 1, 1, 9, 1, 1.0])
    assert select_frames(scores, 7) == list(range(7))                      # without thumbnails: every window
    assert select_frames(scores, 7, thumbs, min_change=1.0) == [0, 3, 6]
    assert select_frames(scores, 7, thumbs, min_change=0) == list(range(7))
    # a window's sharpest frame is a copy of the last kept one: its sharpest new view is taken instead
    z = np.zeros((4, 4), np.uint8)
    assert select_frames(np.array([9, 1, 8, 2.0]), 2, [z, z, z, z + 50]) == [0, 3]


def test_paused_camera_gives_one_frame_per_pause(tmp_path):
    """Held-out video frames had near-copies in training: a camera resting at 4 places, 5 frames each."""
    video = tmp_path / "pauses.mp4"
    _encode(video, [_board(7 * k) for k in range(4) for _ in range(5)])
    frames = extract_frames(video, tmp_path / "f", max_frames=20)
    assert len(frames) == 4
    assert json.loads((tmp_path / "f" / "frames.json").read_text())["source_indices"][0] == 0
    # a moving camera keeps its frames (a 2-pixel pan per frame)
    moving = tmp_path / "pan.mp4"
    _encode(moving, [_board(2 * i) for i in range(20)])
    assert len(extract_frames(moving, tmp_path / "g", max_frames=20)) == 20


def test_paused_camera_with_blurred_frames_gives_its_sharp_frame_once(tmp_path):
    """A robot arm settling at 4 waypoints: 6 frames held at each, 3 of them motion-blurred (a 9-px blur of
    a 128-px frame). The blurred copies passed the near-duplicate test against the sharp frame, and the next
    sharp copy passed against a blurred one: 20 of 24 frames were kept, 12 of them blurred."""
    import cv2

    def place(seed, w=128, h=96):   # a smooth random texture, photo-like contrast
        noise = np.random.default_rng(seed).integers(0, 256, (h, w)).astype(np.float32)
        img = np.clip((cv2.GaussianBlur(noise, (0, 0), 2) - 128) * 1.5 + 128, 0, 255).astype(np.uint8)
        return np.repeat(img[..., None], 3, axis=2)

    kernel = np.zeros((9, 9), np.float32)
    kernel[4, :] = 1 / 9   # horizontal motion blur
    hold = "BSBSSB"        # each waypoint starts blurred: its sharp frame must replace that one
    frames = [cv2.filter2D(place(p), -1, kernel) if c == "B" else place(p) for p in range(4) for c in hold]
    video = tmp_path / "waypoints.mp4"
    _encode(video, frames)
    extract_frames(video, tmp_path / "f", max_frames=24)
    kept = json.loads((tmp_path / "f" / "frames.json").read_text())["source_indices"]
    assert kept == [6 * p + hold.index("S") for p in range(4)]
    # a copy of the kept frame before the last (the camera back after a jolt) is no new view either
    z = np.zeros((4, 4), np.uint8)
    assert select_frames(np.ones(3), 3, [z, z + 50, z]) == [0, 1]


def test_video_suffix_any_case(tmp_path, capsys):
    video = tmp_path / "SCAN.Mp4"
    _encode(video, [_board(3 * i) for i in range(6)])
    assert main(["capture", "info", str(video)]) == 0
    assert "video dataset, 6 frames" in capsys.readouterr().out


def test_train_and_convert_of_a_video_write_nothing_beside_it(tmp_path, capsys):
    """Both extracted the frames into <stem>_frames/ beside the video, outside any output folder."""
    video = tmp_path / "scan.MOV"
    _encode(video, [_board(3 * i) for i in range(6)])
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["train", str(video), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "scan.MOV" in err and "splattwin poses" in err
    assert main(["capture", "convert", str(video), str(tmp_path / "conv"), "--format", "nerfstudio"]) == 2
    assert "no camera poses" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_cameras_json_of_distorted_cameras_says_how(tmp_path, make_dataset, capsys):
    from splattwin.capture import nerfstudio

    ds = make_dataset(tmp_path, with_points=False, dist=np.array([-0.07, 0.0, 0.0, 0.0]))
    for f in ds.frames:   # centred: only the distortion stands in the way
        f.camera.K[0, 2], f.camera.K[1, 2] = f.camera.width / 2, f.camera.height / 2
    nerfstudio.write(ds, tmp_path / "transforms.json")
    assert main(["capture", "convert", str(tmp_path), str(tmp_path / "c"), "--format", "cameras-json"]) == 2
    err = capsys.readouterr().err
    assert "undistort the images first" in err and "image_undistorter" in err and "--format nerfstudio" in err


def test_eval_fuse_segment_refuse_a_video_before_extracting(tmp_path, capsys):
    """eval, fuse and segment given a video stop (exit 2, naming it) before extracting anything: they
    extracted 30 frames into <stem>_frames/ beside the video, outside --out, and only then failed
    ("vids/scan_frames: dataset has no camera poses"), as train already refused it."""
    from splattwin.splat.gaussians import Gaussians

    vids = tmp_path / "vids"
    vids.mkdir()
    video = vids / "scan.mp4"
    _encode(video, [_board(3 * i) for i in range(12)])
    n = 10
    ply = Gaussians(means=np.random.default_rng(0).normal(size=(n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                    scales=np.full((n, 3), 0.01), opacities=np.full(n, 0.9),
                    sh=np.zeros((n, 1, 3))).save_ply(tmp_path / "splat" / "point_cloud.ply")
    masks = tmp_path / "masks"
    masks.mkdir()
    runs = {"eval": ["eval", str(ply), "--dataset", str(video), "--out", str(tmp_path / "EV")],
            "fuse": ["fuse", "--splats", str(ply), "--dataset", str(video), "--masks", str(masks),
                     "--out", str(tmp_path / "FV")],
            "segment": ["segment", str(video), "--masks", str(masks), "--out", str(tmp_path / "SG")]}
    for name, argv in runs.items():
        assert main(argv) == 2, name
        err = capsys.readouterr().err
        assert str(video) in err and ("no camera poses" in err if name != "segment" else "not a video" in err), err
        assert sorted(p.name for p in vids.iterdir()) == ["scan.mp4"], name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["masks", "splat", "vids"]


def test_pose_errors_about_a_video_name_it_and_both_commands_flags(tmp_path, monkeypatch):
    """`build VIDEO --poses known` said 'OUT/capture/frames: --known: ... (use --sfm or --robot-poses)':
    the internal frames folder, and flags `build` does not have; an SfM failure named the frames folder too
    (audit 9 F13). The video is named, and each command's spelling."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.poses import sfm

    video = tmp_path / "scan.mp4"
    _encode(video, [_board(5 * i) for i in range(6)])
    ds = load_dataset(video, frames_dir=tmp_path / "twin" / "capture" / "frames")
    with pytest.raises(InputError) as e:
        estimate_poses(ds, PoseOptions(method="known", progress=False))
    assert e.value.path == video and "a video has no camera poses" in e.value.problem
    assert "build: --poses sfm" in e.value.problem and "splattwin poses: --sfm" in e.value.problem

    def failing(paths, work, opts, progress=True, masks=None):
        raise InputError("structure from motion registered only 1/6 images", sfm.image_layout(paths)[0])

    monkeypatch.setattr(sfm, "run_sfm", failing)
    with pytest.raises(InputError) as e:
        estimate_poses(ds, PoseOptions(method="sfm", progress=False))
    assert e.value.path == video and "registered only 1/6" in e.value.problem
    assert str(tmp_path / "twin" / "capture" / "frames") in e.value.problem   # where its frames are, as a note


def test_capture_help_describes_every_argument_and_option_with_its_default(capsys):
    """`capture frames --help` showed `video` and `--max-frames MAX_FRAMES` with no word (its default is
    30), `capture info --max-frames` no default, `capture convert --format` nothing (audit 9 F15)."""
    import argparse

    from splattwin.cli import build_parser

    capture = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["capture"]
    actions = next(a for a in capture._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert {"frames", "info", "convert"} <= set(actions)
    for name, parser in actions.items():
        for a in parser._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            where = f"capture {name} {a.option_strings or a.dest}"
            assert a.help, where
            if a.option_strings and a.nargs != 0:   # an option that takes a value: its default, or that it has none
                assert "default" in a.help, where
    with pytest.raises(SystemExit):
        main(["capture", "frames", "--help"])
    out = capsys.readouterr().out
    assert "default 30" in out and "video file" in out
    assert "(default none)" not in out   # the help of an option decided per input says its defaults itself


@pytest.mark.parametrize("suffix", [".mp4", ".mkv"])   # an MKV declares no frame count: caught while decoding
def test_video_with_more_frames_than_the_limit_is_refused(tmp_path, monkeypatch, suffix):
    """A still scene compresses to ~20 bytes a frame, so a few MB can hold hours that the scoring pass would decode;
    the frames of a video are bounded by SPLATTWIN_MAX_VIDEO_FRAMES (here lowered to 10 for a 24-frame clip)."""
    from splattwin import limits

    monkeypatch.setattr(limits, "MAX_VIDEO_FRAMES", 10, raising=False)
    video = tmp_path / f"clip{suffix}"
    _write_video(video)
    with pytest.raises(InputError, match="(24 frames \\(its header says\\)|more than 10 frames); a capture may have at "
                                         "most 10") as e:
        extract_frames(video, tmp_path / "frames")
    assert e.value.path == video
    assert not list(tmp_path.glob("frames/*.png"))   # refused before any frame is written


def test_a_long_video_is_scored_on_every_nth_frame_within_the_thumbnail_bound(tmp_path, monkeypatch):
    """The scoring pass kept a thumbnail of every frame with no bound (a 200 000-frame clip: 3.4 GB, then a
    MemoryError); a longer video than `MAX_SCORED` scored frames is now scored on every 2nd, 4th, ... frame and
    still extracted (here 8 for a 24-frame clip: every 4th frame), the frames' source indices those scored."""
    import json

    from splattwin.capture import video as video_mod

    monkeypatch.setattr(video_mod, "MAX_SCORED", 8)
    kept = []
    real = video_mod.thumbnail
    monkeypatch.setattr(video_mod, "thumbnail", lambda rgb, *a: kept.append(1) or real(rgb, *a))
    clip = tmp_path / "clip.mp4"
    _write_video(clip)
    frames = extract_frames(clip, tmp_path / "frames", max_frames=4, min_change=0.0)
    rec = json.loads((tmp_path / "frames" / "frames.json").read_text())
    assert rec["frames_decoded"] == 24 and rec["scored_every"] == 4
    assert len(frames) == 4 and all(i % 4 == 0 for i in rec["source_indices"])
    assert len(kept) < 24   # frames between the stride were never scored
