"""The poses stage used from Python (audit 8A): what `save` writes loads back, the caller's dataset is
left alone, and a mode that would write an unreadable file says so."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import load_dataset
from splattwin.errors import InputError


def _known(ds, **kw):
    from splattwin.poses import PoseOptions, estimate_poses

    return estimate_poses(ds, PoseOptions(method="known", depth_points=False, progress=False, **kw))


def test_save_without_bundle_outside_the_capture_is_refused_before_writing(scene_small: Path, tmp_path: Path):
    """bundle=False used to write '../scene/images/...' paths that load_dataset always refused (H1)."""
    res = _known(load_dataset(scene_small))
    out = tmp_path / "poses"
    with pytest.raises(InputError, match="bundle=True"):
        res.save(out, bundle=False)
    assert not (out / "transforms.json").exists() and not (out / "frame.json").exists()


def test_save_without_bundle_inside_the_capture_loads_back(scene_small: Path, tmp_path: Path):
    """bundle=False with OUT holding the images: relative paths inside OUT, which load_dataset reads."""
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(scene_small, cap)
    res = _known(load_dataset(cap))
    p = res.save(cap, bundle=False)
    back = load_dataset(p)
    assert len(back) == len(res.frames)
    assert all(not fr["file_path"].startswith("..") for fr in json.loads(p.read_text())["frames"])


def test_nerfstudio_write_confined_refuses_outside_paths(scene_small: Path, tmp_path: Path):
    from splattwin.capture import nerfstudio

    ds = load_dataset(scene_small)
    with pytest.raises(InputError, match="outside"):
        nerfstudio.write(ds, tmp_path / "x" / "transforms.json", confine=True)
    assert not (tmp_path / "x" / "transforms.json").exists()


def test_estimate_poses_leaves_the_callers_dataset_alone(scene_small: Path):
    """apply_holdout set splits and meta on the caller's Dataset (M2); the result carries them instead."""
    from splattwin.poses.options import HoldoutOptions

    ds = load_dataset(scene_small)
    splits0, meta0 = [f.split for f in ds.frames], copy.deepcopy(ds.meta)
    res = _known(ds, holdout=HoldoutOptions(heldout_every=2))
    assert [f.split for f in ds.frames] == splits0 and ds.meta == meta0
    assert [f.split for f in res.frames] != splits0   # the new split is in the result
    assert not any(r is f for r in res.frames for f in ds.frames)


def test_estimate_poses_refuses_a_non_dataset():
    from splattwin.poses import estimate_poses

    with pytest.raises(InputError, match="Dataset"):
        estimate_poses(["a.png"])


def test_to_dataset_root_is_never_the_cwd(scene_small: Path):
    """to_dataset() used Path('.') (L10): now the folder holding the images."""
    res = _known(load_dataset(scene_small))
    ds = res.to_dataset()
    assert ds.root != Path(".") and ds.root.is_absolute()
    assert all(f.image_path.absolute().is_relative_to(ds.root) for f in ds.frames)
    with pytest.raises(ValueError, match="root"):
        dataclasses.replace(res, frames=[]).to_dataset()


def test_pose_result_round_trips(scene_small: Path, tmp_path: Path):
    from splattwin.poses import PoseResult

    res = _known(load_dataset(scene_small))
    res.save(tmp_path / "p")
    back = PoseResult.load(tmp_path / "p")
    assert back.frame == res.frame and back.unregistered == res.unregistered
    assert [f.name for f in back.frames] == [f.name for f in res.frames]
    assert [f.split for f in back.frames] == [f.split for f in res.frames]
    for a, b in zip(back.frames, res.frames):
        np.testing.assert_allclose(a.camera.T_world_cam, b.camera.T_world_cam, atol=1e-9)
        np.testing.assert_allclose(a.camera.K, b.camera.K)
    np.testing.assert_allclose(back.T_out_in, res.T_out_in)
    assert back.stats["method"] == res.stats["method"] and back.stats["registered"] == res.stats["registered"]
    assert back.label_objects == res.label_objects
    assert copy.deepcopy(back) == back   # by value (audit 10A L1: raised ValueError)
    assert PoseResult.load(tmp_path / "p" / "transforms.json").frame == res.frame
    with pytest.raises(InputError, match="transforms.json"):
        PoseResult.load(tmp_path / "nothing")


def test_twin_frame_save_round_trips(tmp_path: Path):
    from splattwin.poses import TwinFrame, load_frame

    f = TwinFrame(source="marker", scaled=True, scale_uncertainty_rel=0.01, description="d", up_check={"a": 1})
    p = f.save(tmp_path / "frame.json")
    assert load_frame(p) == f and TwinFrame.load(tmp_path) == f
    tmp_path.joinpath("d").mkdir()
    assert f.save(tmp_path / "d").name == "frame.json"


def test_save_again_with_fewer_views_removes_the_files_of_the_views_gone(scene_small: Path, tmp_path: Path):
    """A rebuild from a capture with fewer views left the old views' photos (and depth, labels) in
    OUT/images/...: a twin handed on carried photos of a capture it was not built from (audit 9 F12).
    Files this save did not bundle are left alone: a capture saved into its own folder keeps every photo."""
    import shutil

    ds = load_dataset(scene_small)
    out = tmp_path / "poses"
    _known(ds).save(out)
    bundled = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.parent != out}
    assert any(b.startswith("images/") for b in bundled)
    fewer = load_dataset(scene_small)
    gone = {f.name for f in fewer.frames[5:]}
    fewer.frames = fewer.frames[:5]
    res = _known(fewer)
    (out / "images" / "mine.txt").write_text("a file the bundle did not write")
    load_dataset(res.save(out))   # loads back
    left = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.parent != out}
    assert left == {b for b in bundled if Path(b).stem not in gone} | {"images/mine.txt"}
    # OUT holding the capture: its own photos are inputs, never removed
    cap = tmp_path / "cap"
    shutil.copytree(scene_small, cap)
    before = sorted(p.name for p in (cap / "images").iterdir())
    _known(load_dataset(cap)).save(cap)
    less = load_dataset(cap)
    less.frames = less.frames[:3]
    _known(less).save(cap)
    assert sorted(p.name for p in (cap / "images").iterdir()) == before


def test_the_camera_plot_leaves_the_callers_matplotlib_backend(scene_small: Path, tmp_path: Path):
    """plot_cameras (PoseResult.save's cameras.png) called matplotlib.use("Agg"), switching a notebook's
    backend (audit 10A L11)."""
    import matplotlib
    from PIL import Image

    from splattwin.poses.estimate import plot_cameras

    before = matplotlib.get_backend()
    matplotlib.use("svg")   # stands for the caller's own (a notebook's inline) backend
    try:
        out = plot_cameras(_known(load_dataset(scene_small)), tmp_path / "cameras.png")
        assert matplotlib.get_backend() == "svg"
        assert Image.open(out).format == "PNG"
    finally:
        matplotlib.use(before)


def test_the_camera_plot_frames_the_cameras_not_a_few_stray_points(scene_small: Path, tmp_path: Path):
    """The real cake's cameras.png (report: "camera poses and sparse points") fitted a few stray SfM points
    tens of scene sizes away: the cameras and the scene were a dot in the middle of each view."""
    import numpy as np
    from PIL import Image

    from splattwin.poses.estimate import plot_cameras

    res = _known(load_dataset(scene_small))
    C = np.array([c.center for c in res.cameras])
    size = float(np.ptp(C, axis=0).max())
    stray = C.mean(axis=0) + size * np.array([[-40.0, 30.0, -20.0], [25.0, -45.0, 15.0]])
    res.points_xyz = np.concatenate([res.points_xyz, stray])
    if res.points_rgb is not None:
        res.points_rgb = np.concatenate([res.points_rgb, np.zeros((2, 3), res.points_rgb.dtype)])
    img = np.asarray(Image.open(plot_cameras(res, tmp_path / "cameras.png")).convert("RGB")).astype(int)
    red = (img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)
    left = red[:, : img.shape[1] // 2]   # the top view
    cols = np.flatnonzero(left.any(axis=0))
    assert cols.size and cols.max() - cols.min() > 0.25 * left.shape[1]


def test_the_camera_plot_logs_no_matplotlib_warning(scene_small: Path, tmp_path: Path, caplog):
    """Every SfM build's log held four lines of matplotlib noise from cameras.png ("Ignoring fixed y limits
    to fulfill fixed data aspect with adjustable data limits."): the view's limits were fixed and then
    grown for the equal aspect. The stray points stay out of the view (test above)."""
    import logging

    from splattwin.poses.estimate import plot_cameras

    with caplog.at_level(logging.WARNING):
        plot_cameras(_known(load_dataset(scene_small)), tmp_path / "cameras.png")
    assert not [r.getMessage() for r in caplog.records if r.name.startswith("matplotlib")]
