"""Photos stored rotated with an EXIF Orientation tag: read upright (copies), cameras upright, SfM upright."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splattwin.capture import load_dataset
from splattwin.capture.orientation import displayed_size, exif_orientation
from splattwin.errors import InputError

# what a viewer does to the stored pixels for each tag (numpy on an HxWxC array)
SHOW = {1: lambda a: a, 3: lambda a: np.rot90(a, 2), 6: lambda a: np.rot90(a, -1), 8: lambda a: np.rot90(a, 1),
        2: lambda a: a[:, ::-1], 5: lambda a: np.transpose(a, (1, 0, 2))}
# the inverse: how a camera stores an upright picture under that tag
STORE = {1: lambda a: a, 3: lambda a: np.rot90(a, 2), 6: lambda a: np.rot90(a, 1), 8: lambda a: np.rot90(a, -1),
         2: lambda a: a[:, ::-1], 5: lambda a: np.transpose(a, (1, 0, 2))}


def save_stored(path: Path, upright: np.ndarray, tag: int | None) -> None:
    """Write `upright` as a camera would with EXIF Orientation `tag` (PNG, lossless)."""
    kw = {}
    if tag is not None:
        ex = Image.Exif()
        ex[0x0112] = tag
        kw["exif"] = ex
    Image.fromarray(np.ascontiguousarray(STORE[tag or 1](upright))).save(path, **kw)


def test_store_and_show_are_inverse():
    a = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    for t in SHOW:
        np.testing.assert_array_equal(SHOW[t](STORE[t](a)), a)


def test_orientation_tag_and_displayed_size(tmp_path):
    img = np.zeros((4, 6, 3), np.uint8)
    for tag in (None, 1, 3, 6, 8):
        save_stored(tmp_path / f"t{tag}.png", img, tag)
        assert exif_orientation(tmp_path / f"t{tag}.png") == (tag or 1)
    save_stored(tmp_path / "bad.png", img, 1)
    ex = Image.Exif()
    ex[0x0112] = 42                                   # not an orientation: the pixels as stored
    Image.fromarray(img).save(tmp_path / "bad.png", exif=ex)
    assert exif_orientation(tmp_path / "bad.png") == 1
    assert displayed_size(6, 4, 6) == (4, 6) and displayed_size(6, 4, 3) == (6, 4)


def test_image_folder_reads_rotated_photos_upright(tmp_path, caplog):
    rng = np.random.default_rng(0)
    src = tmp_path / "photos"
    src.mkdir()
    upright = {}
    tags = {"a": None, "b": 6, "c": 8, "d": 3, "e": 5}
    for name, tag in tags.items():
        upright[name] = rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)   # as the photographer saw it
        save_stored(src / f"{name}.png", upright[name], tag)
    frames_dir = tmp_path / "twin" / "capture" / "frames"
    ds = load_dataset(src, frames_dir=frames_dir)
    assert [f.name for f in ds.frames] == list(tags)          # view names are the photos' names
    for f in ds.frames:
        assert (f.camera.width, f.camera.height) == (40, 30)  # the displayed size for every tag
        from splattwin.capture.dataset import load_image

        got = (load_image(f.image_path) * 255 + 0.5).astype(np.uint8)
        np.testing.assert_array_equal(got, upright[f.name])
        rotated = tags[f.name] not in (None, 1)
        assert (f.image_path.parent == frames_dir / "upright") == rotated
        assert f.image_path == (frames_dir / "upright" / f"{f.name}.png" if rotated else src / f"{f.name}.png")
    assert ds.meta["exif_rotated"] == ["b.png", "c.png", "d.png", "e.png"]
    # reused while the photos are unchanged (and said once: pre-flight, scene and poses each read the folder);
    # rewritten when one changes
    copy_b = frames_dir / "upright" / "b.png"
    before = copy_b.stat().st_mtime_ns
    import logging

    with caplog.at_level(logging.INFO, logger="splattwin.capture.orientation"):
        load_dataset(src, frames_dir=frames_dir)
        load_dataset(src, frames_dir=frames_dir)
    assert copy_b.stat().st_mtime_ns == before
    assert caplog.text.count("photos are stored rotated") == 0   # announced by the first read above
    new_b = rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)
    save_stored(src / "b.png", new_b, 6)
    os.utime(src / "b.png", ns=(before + 10**9, before + 10**9))
    ds = load_dataset(src, frames_dir=frames_dir)
    f = next(f for f in ds.frames if f.name == "b")
    from splattwin.capture.dataset import load_image

    np.testing.assert_array_equal((load_image(f.image_path) * 255 + 0.5).astype(np.uint8), new_b)


def test_rotated_photos_without_a_folder_for_copies_are_refused(tmp_path):
    save_stored(tmp_path / "a.png", np.zeros((4, 6, 3), np.uint8), 6)
    save_stored(tmp_path / "b.png", np.zeros((4, 6, 3), np.uint8), None)
    with pytest.raises(InputError, match="1 of 2 photos are stored rotated.*a.png: 6"):
        load_dataset(tmp_path)


def test_sfm_on_phone_style_rotated_photos_gives_upright_cameras(scene_small, tmp_path):
    """The embedded scene's photos stored as a phone stores portrait shots (pixels turned, tag 6 or 8):
    SfM through the upright copies registers the same photos as from the same pixels stored upright, and
    its cameras agree with the ground truth after a similarity transform within 1 degree (a reconstruction
    of the stored, sideways pixels would be 90 degrees off)."""
    from splattwin.capture.dataset import load_image
    from splattwin.poses import PoseOptions, estimate_poses
    from splattwin.poses.align import umeyama

    gt = load_dataset(scene_small)
    runs = {}
    for kind in ("upright", "rotated"):
        photos = tmp_path / kind
        photos.mkdir()
        for i, f in enumerate(gt.train()):
            rgb = (load_image(f.image_path) * 255 + 0.5).astype(np.uint8)
            save_stored(photos / f"{f.name}.png", rgb, None if kind == "upright" else (6 if i % 2 == 0 else 8))
        ds = load_dataset(photos, frames_dir=tmp_path / f"frames_{kind}")
        runs[kind] = estimate_poses(ds, PoseOptions(method="sfm", work_dir=tmp_path / f"sfm_{kind}", progress=False))
    assert sorted(f.name for f in runs["rotated"].frames) == sorted(f.name for f in runs["upright"].frames)
    assert len(runs["rotated"].frames) >= len(gt.train()) - 1
    g = {f.name: f.camera for f in gt.frames}

    def angles(res) -> dict:
        """Each camera's rotation error against the ground truth (deg) after a similarity transform."""
        fit = umeyama(np.array([f.camera.center for f in res.frames]), np.array([g[f.name].center for f in res.frames]))
        R = fit.S[:3, :3] / fit.scale
        out = {}
        for f in res.frames:
            assert (f.camera.width, f.camera.height) == (g[f.name].width, g[f.name].height)
            Rg = g[f.name].T_world_cam[:3, :3]
            c = (np.trace(Rg.T @ R @ f.camera.T_world_cam[:3, :3]) - 1) / 2
            out[f.name] = float(np.degrees(np.arccos(np.clip(c, -1, 1))))
        return out

    a_up, a_rot = angles(runs["upright"]), angles(runs["rotated"])
    # 160x120 photos: SfM itself is within ~2 degrees; sideways cameras would be ~90 degrees off
    assert max(a_rot.values()) < 3.0, a_rot
    assert all(abs(a_rot[n] - a_up[n]) < 0.5 for n in a_up), (a_up, a_rot)


def test_heic_photos_are_read_through_png_copies(tmp_path):
    """HEIC (an iPhone's default format): found in the folder (any suffix case), decoded through pillow-heif,
    and given a PNG copy COLMAP can read."""
    pytest.importorskip("pillow_heif")   # a declared dependency; the skip only guards a broken install
    import pillow_heif

    from splattwin.capture.dataset import load_image

    pillow_heif.register_heif_opener()
    src = tmp_path / "iphone"
    src.mkdir()
    yy, xx = np.mgrid[0:48, 0:64]
    upright = np.stack([xx * 4, yy * 5, (xx + yy) * 2], -1).astype(np.uint8)   # smooth: HEVC keeps it close
    # (an iPhone records a portrait shot's turn as a HEIF container transform, which libheif applies on
    # decoding; pillow-heif cannot write one, so this file is stored upright)
    Image.fromarray(upright).save(src / "IMG_0001.HEIC", quality=95)
    Image.fromarray(upright).save(src / "IMG_0002.Jpg", quality=95)
    ds = load_dataset(src, frames_dir=tmp_path / "frames")
    assert [f.name for f in ds.frames] == ["IMG_0001", "IMG_0002"]
    heic, jpg = ds.frames
    assert heic.image_path == tmp_path / "frames" / "upright" / "IMG_0001.png" and jpg.image_path == src / "IMG_0002.Jpg"
    assert (heic.camera.width, heic.camera.height) == (64, 48)
    got = (load_image(heic.image_path) * 255 + 0.5).astype(np.uint8)
    direct = (load_image(src / "IMG_0001.HEIC") * 255 + 0.5).astype(np.uint8)   # our reader, through pillow-heif
    np.testing.assert_array_equal(got, direct)
    assert np.abs(got.astype(int) - upright).mean() < 4   # the photo (HEVC is lossy)
    assert ds.meta["exif_rotated"] == ["IMG_0001.HEIC"]
