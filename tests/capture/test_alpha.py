"""Fully transparent pixels (alpha 0) become loss masks in every dataset layout, not only image folders
(`capture.images.mask_transparent_pixels`, called once by `load_dataset`)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from splattwin import io
from splattwin.capture import colmap, nerfstudio
from splattwin.capture.dataset import load_dataset, load_image, load_loss_mask
from splattwin.splat.trainer import load_views

W, H = 64, 48


def _make_rgba(ds) -> None:
    """Frame 0: its top 10 rows transparent over black (a render's transparent film); frame 1: its left 16
    columns transparent and a half-transparent edge beside them (an observation, not masked); frame 2: alpha,
    all of it opaque; frame 3 stays RGB."""
    rng = np.random.default_rng(1)
    for i, f in enumerate(ds.frames[:3]):
        rgba = np.concatenate([rng.integers(30, 255, (H, W, 3), dtype=np.uint8), np.full((H, W, 1), 255, np.uint8)], 2)
        if i == 0:
            rgba[:10] = 0
        elif i == 1:
            rgba[:, :16] = 0
            rgba[:, 16:18, 3] = 128
        io.write_image(f.image_path, rgba)


def _keep(frame) -> np.ndarray | None:
    return None if frame.mask_path is None else load_loss_mask(frame.mask_path, (W, H))


def test_rgba_transforms_json_masks_transparent_pixels_and_ands_mask_path(tmp_path, make_dataset):
    # a Blender-style synthetic set (RGBA renders, no mask_path) read through a transforms.json: alpha was
    # dropped and the black under it trained on; frame 1 also has its own half-size mask_path (masks_2/)
    ds = make_dataset(tmp_path / "ds")
    _make_rgba(ds)
    own = np.full((H // 2, W // 2), 255, np.uint8)
    own[-4:] = 0                                   # the bottom 8 rows at full size: people, the rig
    ds.frames[1].mask_path = io.write_image(tmp_path / "ds" / "masks_2" / "img_001.png", own)
    tj = nerfstudio.write(ds, tmp_path / "ds" / "transforms.json")

    back = load_dataset(tj, frames_dir=tmp_path / "frames")
    f0, f1, f2, f3 = back.frames
    assert f2.mask_path is None and f3.mask_path is None   # opaque alpha, no alpha: nothing to mask
    assert f0.mask_path.is_relative_to(tmp_path / "frames")
    k0, k1 = _keep(f0), _keep(f1)
    assert not k0[:10].any() and k0[10:].all()
    # the transparent columns AND the frame's own mask; the half-transparent edge is kept
    assert not k1[:, :16].any() and not k1[-8:].any() and k1[:-8, 16:].all()
    assert f1.mask_path != ds.frames[1].mask_path   # the dataset's own mask file is not touched
    # training and evaluation see the masks (load_views is what both read)
    views = {v.name: v for v in load_views(back.frames)}
    m0 = views["img_000"].mask[..., 0].numpy()
    assert m0[:10].sum() == 0 and m0[10:].min() == 1
    assert views["img_002"].mask is None
    assert load_image(f0.image_path).shape == (H, W, 3)   # the photo itself is read as before

    # read again (pre-flight, poses, ...): the same masks, not rewritten; a mask that already leaves out every
    # transparent pixel (the poses stage's bundled one) is kept as it is
    stamp = f0.mask_path.stat().st_mtime_ns
    again = load_dataset(tj, frames_dir=tmp_path / "frames")
    assert again.frames[0].mask_path == f0.mask_path and f0.mask_path.stat().st_mtime_ns == stamp
    import shutil

    for f, src in zip(ds.frames, (f0, f1)):
        f.mask_path = tmp_path / "ds" / "bundled" / src.mask_path.name
        shutil.copyfile(src.mask_path, f.mask_path.parent.mkdir(exist_ok=True) or f.mask_path)
    tj2 = nerfstudio.write(ds, tmp_path / "ds" / "t2.json")
    covered = load_dataset(tj2)                     # no frames_dir: nothing left to write, no warning needed
    assert [f.mask_path for f in covered.frames[:2]] == [f.mask_path for f in ds.frames[:2]]


def test_train_and_eval_cli_leave_transparent_pixels_out(tmp_path, make_dataset):
    from splattwin.cli import main

    ds = make_dataset(tmp_path / "ds")
    _make_rgba(ds)
    ds.frames[3].split = "train"
    ds.frames[0].split = "heldout"                # the held-out view has transparent pixels too
    tj = nerfstudio.write(ds, tmp_path / "ds" / "transforms.json")
    out = tmp_path / "out"
    assert main(["train", str(tj), str(out), "--iters", "4", "--sh-degree", "0", "--no-progress",
                 "--device", "cpu"]) == 0
    rec = json.loads((out / "train.json").read_text())["loss_masks"]
    assert rec["ignored_share"] == {"img_001": round(16 / 64, 4)}
    assert (out / "capture" / "frames" / "alpha_masks" / "img_001.png").is_file()
    assert main(["eval", str(out), "--dataset", str(tj), "--no-progress", "--device", "cpu"]) == 0
    m = json.loads((out / "eval" / "metrics.json").read_text())
    assert m["loss_masks"]["views"] == ["img_000"]


def test_rgba_colmap_dataset_masks_transparent_pixels(tmp_path, make_dataset, caplog):
    ds = make_dataset(tmp_path)
    _make_rgba(ds)
    colmap.write_text(ds, tmp_path / "sparse" / "0")
    back = load_dataset(tmp_path, frames_dir=tmp_path / "frames")
    assert back.meta["format"] == "colmap"
    by_name = {f.name: f for f in back.frames}
    k0, k1 = _keep(by_name["img_000"]), _keep(by_name["img_001"])
    assert not k0[:10].any() and k0[10:].all()
    assert not k1[:, :16].any() and k1[:, 16:].all()
    assert by_name["img_002"].mask_path is None and by_name["img_003"].mask_path is None
    # nowhere to write the masks: said, naming the photos
    with caplog.at_level(logging.WARNING, logger="splattwin.capture.images"):
        plain = load_dataset(tmp_path)
    assert all(f.mask_path is None for f in plain.frames)
    assert "2 of 4 photos have transparent pixels (img_000.png (21 %), img_001.png (25 %))" in caplog.text


def _alpha_keep(path) -> np.ndarray | None:
    """What the loss mask of the photo at `path` must be: alpha > 0 read straight from the file (PIL), or
    None when the photo has no alpha or no fully transparent pixel."""
    from PIL import Image

    with Image.open(path) as im:
        if im.mode != "RGBA":
            return None
        keep = np.asarray(im)[..., 3] > 0
    return None if keep.all() else keep


def _tree_bytes(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("fmt, own_masks", [("bop", "mask_visib"), ("tum", "masks")])
def test_rgba_robot_capture_masks_transparent_pixels_through_poses_and_training(tmp_path, fmt, own_masks, caplog):
    """A BOP scene and a TUM pose list (`scene generate --robot-capture`: known poses, 16-bit depth, the
    capture's own per-instance masks) whose photos are RGBA with transparent pixels: every frame's loss mask
    is exactly alpha > 0, the depth of those pixels is unknown in training, and the capture's instance masks
    (BOP mask_visib/, TUM masks/: the semantics stage's, no loss masks) are neither read as loss masks nor
    touched. The poses stage bundles the masks; read again, the bundled mask (the frame's own mask_path now)
    ANDed with alpha is that mask, kept as it is."""
    from splattwin.cli import main
    from splattwin.scene import SceneOptions
    from splattwin.scene.robot_capture import RobotCaptureOptions, write_robot_capture

    cap = write_robot_capture(tmp_path / "cap", SceneOptions(seed=0, width=W, height=H, supersample=1),
                              RobotCaptureOptions(views=4, width=W, height=H, format=fmt), progress=False)
    _make_rgba(load_dataset(cap))
    own = _tree_bytes(cap / own_masks)
    with caplog.at_level(logging.INFO, logger="splattwin.capture.images"):
        ds = load_dataset(cap, frames_dir=tmp_path / "frames")
    assert ds.meta["format"] == fmt and ds.has_poses and len(ds.frames) == 4
    expected = {f.name: _alpha_keep(f.image_path) for f in ds.frames}
    assert [k is not None for k in expected.values()] == [True, True, False, False]   # frame 2: opaque alpha
    for f in ds.frames:
        assert f.depth_path is not None                 # the RGB-D pairing is unchanged
        if expected[f.name] is None:
            assert f.mask_path is None
        else:
            assert f.mask_path.parent == tmp_path / "frames" / "alpha_masks"
            np.testing.assert_array_equal(_keep(f), expected[f.name])
    names = [f.image_path.name for f in ds.frames[:2]]
    assert f"2 of 4 photos have transparent pixels ({names[0]} (21 %), {names[1]} (25 %))" in caplog.text
    # training: the photo's transparent pixels are ignored, and the depth under them is unknown (inf)
    views = load_views(ds.frames, depth=True, depth_scale=ds.depth_scale)
    for v in views[:2]:
        keep = expected[v.name]
        np.testing.assert_array_equal(v.mask[..., 0].numpy() > 0, keep)
        assert np.isinf(v.depth.numpy()[~keep]).all() and np.isfinite(v.depth.numpy()[keep]).any()
    assert views[2].mask is None and views[3].mask is None

    # the poses stage (known poses) bundles the loss masks beside its transforms.json
    assert main(["poses", str(cap), str(tmp_path / "posed"), "--no-progress"]) == 0
    posed = load_dataset(tmp_path / "posed" / "transforms.json", frames_dir=tmp_path / "frames2")
    for f in posed.frames:
        if expected[f.name] is None:
            assert f.mask_path is None
        else:
            assert f.mask_path.parent == tmp_path / "posed" / "masks"   # its own mask, not a new alpha mask
            np.testing.assert_array_equal(_keep(f), expected[f.name])
    assert not (tmp_path / "frames2" / "alpha_masks").exists()
    assert _tree_bytes(cap / own_masks) == own


def test_train_and_eval_into_a_locked_folder_refuse_before_writing_masks(tmp_path, make_dataset):
    """Reading an RGBA dataset writes loss masks into OUT/capture/frames: a second `train` into an OUT another
    run holds, or an `eval` into a training folder a `train` still holds, exits 2 before writing them."""
    import fcntl
    import os

    from splattwin.cli import main
    from splattwin.lock import lock_path

    ds = make_dataset(tmp_path / "ds")
    _make_rgba(ds)
    tj = nerfstudio.write(ds, tmp_path / "ds" / "transforms.json")
    out = tmp_path / "out"

    def hold(folder):
        """Lock `folder` as another process would: flock on an open file description of our own."""
        lock_path(folder).parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path(folder), os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return fd

    fd = hold(out)
    try:
        assert main(["train", str(tj), str(out), "--iters", "4", "--sh-degree", "0", "--no-progress",
                     "--device", "cpu"]) == 2
        assert [p.name for p in out.iterdir()] == [".splattwin"]   # no capture/frames/alpha_masks
    finally:
        os.close(fd)
    assert main(["train", str(tj), str(out), "--iters", "4", "--sh-degree", "0", "--no-progress",
                 "--device", "cpu"]) == 0
    assert (out / "capture" / "frames" / "alpha_masks").is_dir()

    fd = hold(out)   # a `train` (say, --resume) running in the training folder
    try:
        assert main(["eval", str(out), "--dataset", str(tj), "--no-progress", "--device", "cpu"]) == 2
        assert not (out / "eval").exists()
    finally:
        os.close(fd)
    assert main(["eval", str(out), "--dataset", str(tj), "--no-progress", "--device", "cpu"]) == 0
    assert (out / "eval" / "capture" / "frames" / "alpha_masks").is_dir()
