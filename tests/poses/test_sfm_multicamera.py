"""Photos of several sizes (several cameras): accepted by the capture reader, one COLMAP camera per size in
SfM, per-image intrinsics downstream, and the trainer trains on the per-frame cameras."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splattwin.capture import load_dataset


@pytest.fixture(scope="module")
def mixed_sizes(scene_default: Path, tmp_path_factory: pytest.TempPathFactory):
    """scene_default's 15 training views, every other one downscaled to 240x180 (another 'camera'),
    and the posed SfM result of the folder."""
    from splattwin.poses import PoseOptions, estimate_poses

    folder = tmp_path_factory.mktemp("mixed") / "images"
    folder.mkdir()
    gt = load_dataset(scene_default)
    small = set()
    for i, f in enumerate(gt.train()):
        if i % 2:
            with Image.open(f.image_path) as im:
                im.convert("RGB").resize((240, 180), Image.BOX).save(folder / f.image_path.name)
            small.add(f.image_path.name)
        else:
            shutil.copy(f.image_path, folder / f.image_path.name)
    ds = load_dataset(folder)
    res = estimate_poses(ds, PoseOptions(method="sfm", work_dir=folder.parent / "work", progress=False))
    return gt, ds, res, small


def test_reader_keeps_each_size(mixed_sizes):
    _, ds, _, small = mixed_sizes
    sizes = {f.image_path.name: (f.camera.width, f.camera.height) for f in ds.frames}
    assert {sizes[n] for n in small} == {(240, 180)} and {v for k, v in sizes.items() if k not in small} == {(320, 240)}


def test_sfm_one_camera_per_size_and_per_image_intrinsics(mixed_sizes):
    gt, ds, res, small = mixed_sizes
    assert res.stats["registered"] >= 14
    groups = res.stats["camera_groups"]
    assert sorted(tuple(g["size"]) for g in groups) == [(240, 180), (320, 240)]
    f_true = gt.frames[0].camera.fx
    for fr in res.frames:
        w, h = (240, 180) if fr.image_path.name in small else (320, 240)
        assert (fr.camera.width, fr.camera.height) == (w, h)
        assert fr.camera.fx == pytest.approx(f_true * w / 320, rel=0.03)  # each camera's own focal length
    # both kinds are written per frame and read back with their own sizes
    out = res.save(Path(res.frames[0].image_path).parents[1] / "posed")
    back = load_dataset(out)
    back.validate()
    assert {(f.camera.width, f.camera.height) for f in back.frames} == {(240, 180), (320, 240)}


def test_trainer_trains_on_per_frame_cameras(mixed_sizes, tmp_path: Path):
    from splattwin.splat.trainer import TrainConfig, Trainer

    _, _, res, _ = mixed_sizes
    ds = res.to_dataset(tmp_path)
    tr = Trainer(ds, tmp_path / "train", TrainConfig(iters=6, checkpoint_every=0, progress=False, densify=False,
                                                     init_points=2000))
    assert {(v.camera.width, v.camera.height) for v in tr.views} == {(240, 180), (320, 240)}
    assert {tuple(v.image.shape[:2]) for v in tr.views} == {(180, 240), (240, 320)}
    out = tr.run()
    assert out.steps == 6 and np.isfinite(out.final_loss)
