"""SfM on the embedded scene with its poses stripped (pycolmap, CPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from splattwin.errors import InputError
from splattwin.poses.align import umeyama


def _scene_size(gt) -> float:
    import json

    ext = json.loads((gt.root / "scene.json").read_text())["table"]["extent"]
    return float(np.hypot(ext[1] - ext[0], ext[3] - ext[2]))


def test_all_training_views_register(default_unscaled):
    gt, res = default_unscaled
    train = [f.image_path.name for f in gt.train()]
    posed = {f.image_path.name for f in res.frames}
    assert len(train) == 15
    assert set(train) <= posed
    assert res.stats["registered"] == len(res.frames) and res.stats["total"] == len(gt.frames)
    assert 0 < res.stats["mean_reproj_error"] < 1.5
    # splits survive
    assert {f.image_path.name for f in res.frames if f.split == "heldout"} <= {f.image_path.name for f in gt.heldout()}


def test_camera_centres_match_ground_truth_after_sim3(default_unscaled):
    gt, res = default_unscaled
    g = {f.image_path.name: f.camera for f in gt.frames}
    src = np.array([f.camera.center for f in res.frames])
    tgt = np.array([g[f.image_path.name].center for f in res.frames])
    fit = umeyama(src, tgt)
    assert fit.residuals.max() < 0.01 * _scene_size(gt)
    # rotations agree too after the alignment
    R = fit.S[:3, :3] / fit.scale
    for f in res.frames:
        Rg = g[f.image_path.name].T_world_cam[:3, :3]
        ang = np.degrees(np.arccos(np.clip((np.trace(Rg.T @ R @ f.camera.T_world_cam[:3, :3]) - 1) / 2, -1, 1)))
        assert ang < 1.0


def test_focal_length_estimated_within_one_percent(default_unscaled):
    gt, res = default_unscaled
    f_gt = gt.frames[0].camera.fx
    for f in res.frames:
        assert abs(f.camera.fx - f_gt) / f_gt < 0.01
        assert abs(f.camera.fy - f_gt) / f_gt < 0.01


def test_sparse_points_have_colours_and_lie_in_the_scene(default_unscaled):
    gt, res = default_unscaled
    assert res.points_xyz.shape[0] > 200 and res.points_xyz.shape == res.points_rgb.shape
    assert res.points_rgb.dtype == np.uint8 and res.points_rgb.std() > 5
    # unscaled table frame: most points on or above the table plane z = 0
    z = res.points_xyz[:, 2]
    spread = np.ptp(res.points_xyz[:, :2], axis=0).max()
    assert np.mean(z > -0.02 * spread) > 0.9


def test_unscaled_frame_is_flagged(default_unscaled):
    gt, res = default_unscaled
    assert res.frame.source == "unscaled" and res.frame.scaled is False
    # cameras look down on the table from above: z up towards the cameras
    assert all(f.camera.center[2] > 0 for f in res.frames)
    assert res.depth_xyz is None  # metric depth must not be mixed with an unscaled frame


def test_resume_reuses_finished_model(default_unscaled, sfm_default_dir):
    from tests.poses.conftest import stripped
    from splattwin.poses import PoseOptions, estimate_poses

    gt, res = default_unscaled
    assert (sfm_default_dir / "sparse" / "done").is_file()
    again = estimate_poses(stripped(gt), PoseOptions(method="sfm", work_dir=sfm_default_dir, progress=False))
    assert again.stats["timings"] == {}  # nothing re-computed
    np.testing.assert_allclose(again.cameras[0].T_world_cam, res.cameras[0].T_world_cam, atol=1e-9)


def test_the_unscaled_warning_claims_no_twin(default_unscaled, sfm_default_dir, caplog):
    """`build --until splats` (and `splattwin poses`) logged "the twin is built but robot planning will refuse it":
    the poses stage builds no twin and does not know whether one follows. The warning says what holds either way."""
    import logging

    from tests.poses.conftest import stripped
    from splattwin.poses import PoseOptions, estimate_poses

    gt, _ = default_unscaled
    with caplog.at_level(logging.WARNING, logger="splattwin.poses.estimate"):
        estimate_poses(stripped(gt), PoseOptions(method="sfm", work_dir=sfm_default_dir, progress=False))
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("no metric scale")]
    assert len(warned) == 1 and "the twin is built" not in warned[0]
    assert "a twin built on these poses is unscaled too" in warned[0] and "planning refuses" in warned[0]


def test_textureless_images_fail_with_advice(tmp_path: Path):
    from splattwin import io
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses

    rng = np.random.default_rng(0)
    for i in range(3):
        img = np.full((120, 160, 3), 128, np.uint8) + rng.integers(0, 2, (120, 160, 3), dtype=np.uint8)
        io.write_image(tmp_path / "imgs" / f"im_{i}.png", img)
    ds = load_dataset(tmp_path / "imgs")
    with pytest.raises(InputError) as e:
        estimate_poses(ds, PoseOptions(method="sfm", work_dir=tmp_path / "work", progress=False))
    msg = str(e.value)
    assert "overlap" in msg and "intrinsics" in msg


def test_min_registered_names_missing_images(tmp_path: Path, scene_default: Path):
    """Two scene views plus one unrelated noise image: the noise image is named as unregistered."""
    import shutil

    from splattwin import io
    from splattwin.capture import load_dataset
    from splattwin.poses.sfm import SfmOptions, run_sfm

    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for n in ("train_000.png", "train_001.png", "train_002.png"):
        shutil.copy(scene_default / "images" / n, imgs / n)
    io.write_image(imgs / "zz_noise.png", np.random.default_rng(1).integers(0, 255, (240, 320, 3), dtype=np.uint8))
    paths = [f.image_path for f in load_dataset(imgs).frames]
    with pytest.raises(InputError) as e:
        run_sfm(paths, tmp_path / "w", SfmOptions(min_registered=4), progress=False)
    assert "zz_noise.png" in str(e.value) and "min-registered" in str(e.value)


def test_sequential_matching_with_known_intrinsics(scene_small: Path, tmp_path: Path):
    """Video-style capture: sequential matching; known intrinsics stay fixed; unregistered views are named."""
    from splattwin.capture import load_dataset
    from splattwin.poses import PoseOptions, estimate_poses
    from tests.poses.conftest import stripped

    gt = load_dataset(scene_small)
    c = gt.frames[0].camera
    ds = stripped(gt)
    ds.meta["sequential"] = True
    res = estimate_poses(ds, PoseOptions(method="sfm", intrinsics=(c.fx, c.fy, c.cx, c.cy), min_registered=6,
                                         matcher="sequential", work_dir=tmp_path / "w", progress=False))
    assert res.stats["matcher"] == "sequential"  # (auto: exhaustive for a set this small, video or not)
    assert res.stats["registered"] >= 6
    for f in res.frames:
        np.testing.assert_allclose(f.camera.K, c.K, atol=1e-9)
    assert len(res.unregistered) == len(gt.frames) - len(res.frames)
    assert all(Path(u).name.endswith(".png") for u in res.unregistered)


def json_load(p: Path):
    import json

    return json.loads(p.read_text())


def test_unregistered_image_named_with_reason_in_report_and_cli(tmp_path: Path, scene_default: Path, capsys):
    """Four scene views plus an unrelated noise image: the retries cannot register it; poses_report.json
    and the CLI output name it and say why."""
    import shutil

    from splattwin import io
    from splattwin.cli import main

    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for n in ("train_000.png", "train_001.png", "train_002.png", "train_003.png"):
        shutil.copy(scene_default / "images" / n, imgs / n)
    io.write_image(imgs / "zz_noise.png", np.random.default_rng(1).integers(0, 255, (240, 320, 3), dtype=np.uint8))
    rc = main(["poses", str(imgs), str(tmp_path / "out"), "--min-registered", "3"])
    out = capsys.readouterr().out
    assert rc == 0
    rep = json_load(tmp_path / "out" / "poses_report.json")
    assert rep["registered"] == 4 and list(rep["failures"]) == ["zz_noise.png"]
    assert "no verified matches" in rep["failures"]["zz_noise.png"]
    assert [a["name"] for a in rep["attempts"]][:2] == ["default", "relaxed"]  # retried, to no avail
    assert "zz_noise.png: no verified matches" in out and "SfM attempts:" in out


def _pairs(db: Path) -> list[tuple[int, int]]:
    import sqlite3

    con = sqlite3.connect(db)
    try:
        return [divmod(p, 2147483647) for (p,) in con.execute("SELECT pair_id FROM two_view_geometries")]
    finally:
        con.close()


def test_ordered_frames_match_sequentially_with_loop_closure(scene_default: Path, tmp_path: Path):
    from splattwin.poses.sfm import SfmOptions, run_sfm

    paths = sorted((scene_default / "images").glob("train_*.png"))
    res = run_sfm(paths, tmp_path / "w", SfmOptions(ordered=True, matcher="sequential", sequential_overlap=3), progress=False)
    assert res.matcher == "sequential" and res.num_registered == len(paths) == 15
    assert (tmp_path / "w" / "visual_index.bin").is_file()  # built from this capture's descriptors
    pairs = _pairs(tmp_path / "w" / "database.db")
    assert len(pairs) < 15 * 14 // 2                       # not all pairs
    assert any(b - a > 3 for a, b in pairs)                # loop closure found pairs beyond the overlap


def test_large_unordered_sets_match_retrieved_pairs(scene_default: Path, tmp_path: Path):
    from splattwin.poses.sfm import SfmOptions, run_sfm

    paths = sorted((scene_default / "images").glob("train_*.png"))
    res = run_sfm(paths, tmp_path / "w", SfmOptions(exhaustive_max_images=5, retrieval_neighbours=6), progress=False)
    assert res.matcher == "retrieval" and res.num_registered == 15
    pairs = _pairs(tmp_path / "w" / "database.db")
    assert 15 * 3 <= len(pairs) < 15 * 14 // 2


def test_feature_masks_keep_sift_out_of_transparent_pixels(tmp_path):
    """A photo's transparent pixels (its alpha loss mask, `capture.images`) reach COLMAP's feature extraction
    as its mask_path (<root>/<image name>.png): no keypoint there. Without it SIFT found corners on the edge of
    the black under a removed background, the same in every photo, and SfM registered 3 of 8 cake photos."""
    import pycolmap

    from splattwin import io
    from splattwin.poses.colmap_worker import step_extract
    from splattwin.poses.sfm import SfmOptions, _extraction_options, _feature_mask_names, _write_feature_masks

    rng = np.random.default_rng(0)
    img = (rng.random((30, 40)) > 0.5).astype(np.uint8) * 255
    img = np.kron(img, np.ones((6, 6), np.uint8))                      # 240x180 checker-like texture
    photo = tmp_path / "photos" / "sub dir" / "a.png"
    io.write_image(photo, np.repeat(img[..., None], 3, axis=2))
    io.write_image(tmp_path / "photos" / "b.png", np.repeat(img[..., None], 3, axis=2)[::-1])   # no mask
    keep = np.full(img.shape, 255, np.uint8)
    keep[:90] = 0                                                     # the top half is transparent
    mask = io.write_image(tmp_path / "alpha" / "a.png", keep)
    names = _feature_mask_names([photo], tmp_path / "photos", {photo: mask})
    assert names == {"sub dir/a.png": mask}
    all_names = ["b.png", "sub dir/a.png"]
    root = _write_feature_masks(tmp_path / "work", names, tmp_path / "photos", all_names)
    assert (root / "sub dir" / "a.png.png").is_file() and (root / "b.png.png").is_file()

    def keypoints(mask_root, name):
        db = tmp_path / f"{mask_root is not None}.db"
        job = {"db": str(db), "image_root": str(tmp_path / "photos"), "names": all_names,
               "groups": [{"names": all_names, "camera_model": "SIMPLE_RADIAL", "per_image": False}],
               "extraction": _extraction_options(SfmOptions(), "base", 1, 240)}
        if mask_root is not None:
            job["mask_root"] = str(mask_root)
        step_extract(job)
        with pycolmap.Database.open(str(db)) as d:
            return d.read_keypoints(d.read_image_with_name(name).image_id)[:, :2]

    free, masked = keypoints(None, "sub dir/a.png"), keypoints(root, "sub dir/a.png")
    assert (free[:, 1] < 90).sum() > 20 and len(masked) > 20
    assert (masked[:, 1] < 90).sum() == 0
    # a photo without transparent pixels keeps all its features (COLMAP extracts none from an image without a mask)
    assert len(keypoints(root, "b.png")) == len(keypoints(None, "b.png")) > 40
