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
