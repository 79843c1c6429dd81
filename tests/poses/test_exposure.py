"""Exposure / white-balance check (`splattwin.poses.exposure`): known per-image gains recovered from
shared points, ~1 on unperturbed images, the poses stage's record and warning, and input it cannot use."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from splattwin.capture import load_dataset, load_image
from splattwin.io import write_image
from splattwin.poses import PoseOptions, estimate_poses
from splattwin.poses.exposure import THRESHOLD_PCT, fit_log_gains, measure_exposure


def _log_colours(gains: np.ndarray, n: int = 2000, seed: int = 0, seen_frac: float = 0.6,
                 outlier_frac: float = 0.05) -> np.ndarray:
    """[V,N,3] log colours of N points of random albedo under per-image gains [V,3], each point seen in a
    random subset of the images, with noise and a share of wrong samples (occlusion misses)."""
    rng = np.random.default_rng(seed)
    V = len(gains)
    albedo = rng.uniform(0.1, 0.7, (n, 3))
    c = gains[:, None, :] * albedo[None] * np.exp(rng.normal(0, 0.02, (V, n, 3)))
    wrong = rng.random((V, n)) < outlier_frac
    c[wrong] = rng.uniform(0.05, 0.95, (int(wrong.sum()), 3))
    L = np.log(c)
    L[rng.random((V, n)) > seen_frac] = np.nan
    return L


def _relative(g: np.ndarray) -> np.ndarray:
    return g - np.median(g, axis=0)


def test_fit_recovers_known_per_channel_gains():
    rng = np.random.default_rng(1)
    gains = rng.uniform(0.7, 1.3, (12, 1)) * rng.uniform(0.9, 1.1, (12, 3))
    g, samples = fit_log_gains(_log_colours(gains))
    assert (samples > 500).all()
    err = np.abs(g - _relative(np.log(gains)))
    assert err.max() < 0.01, err.max()                 # within 1 % of the applied gains
    assert np.abs(np.median(g, axis=0)).max() < 1e-9   # relative to the median image


def test_fit_reads_one_on_unperturbed_images():
    g, _ = fit_log_gains(_log_colours(np.ones((10, 3))))
    assert np.abs(g).max() < 0.005


def test_fit_without_shared_points_measures_nothing():
    # each image sees its own points only: no ratio between images exists
    L = np.full((4, 400, 3), np.nan)
    for v in range(4):
        L[v, v * 100:(v + 1) * 100] = np.log(0.5)
    g, samples = fit_log_gains(L)
    assert np.isnan(g).all() and (samples == 0).all()
    with pytest.raises(ValueError, match=r"\[V,N,3\]"):
        fit_log_gains(np.zeros((4, 10)))


def _perturbed_copy(src: Path, dst: Path, gains: dict[str, np.ndarray]) -> Path:
    shutil.copytree(src, dst)
    ds = load_dataset(dst)
    for f in ds.frames:
        if f.name in gains:
            write_image(f.image_path, np.round(np.clip(load_image(f.image_path) * gains[f.name], 0, 1) * 255)
                        .astype(np.uint8))
    return dst


def test_measure_on_posed_images(scene_small, tmp_path):
    ds = load_dataset(scene_small)
    rng = np.random.default_rng(2)
    gains = {f.name: rng.uniform(0.75, 1.25) * rng.uniform(0.92, 1.08, 3) for f in ds.frames}
    pert = load_dataset(_perturbed_copy(scene_small, tmp_path / "pert", gains))
    # the scene's surface points, from its depth: the poses stage's back-projection
    from splattwin.poses.depth import backproject_frames

    xyz, _ = backproject_frames(ds.frames, stride=4, depth_scale=ds.depth_scale, seed=0)
    names = [f.name for f in ds.frames]
    cams = [f.camera for f in ds.frames]
    clean = measure_exposure(cams, [f.image_path for f in ds.frames], names, xyz)
    assert not clean.get("error") and clean["varies"] is False and clean["images_off"] == []
    assert clean["spread_pct"] < 2.0
    for rec in clean["images"].values():
        assert abs(rec["gain"] - 1.0) < 0.02

    rec = measure_exposure(cams, [f.image_path for f in pert.frames], names, xyz)
    assert rec["varies"] is True and rec["spread_pct"] > THRESHOLD_PCT
    got = np.log([rec["images"][n]["rgb_gain"] for n in names])
    want = _relative(np.log([gains[n] for n in names]))
    assert np.abs(got - want).max() < 0.03, np.abs(got - want).max()
    off = {n for n in names if 100 * np.expm1(np.abs(want[names.index(n)]).max()) > THRESHOLD_PCT + 3}
    assert off <= set(rec["images_off"])
    # the same photos as JPEGs (decoded at a reduced scale: the path real photos take)
    from PIL import Image

    jpgs = []
    for f in pert.frames:
        jpgs.append(tmp_path / f"{f.name}.jpg")
        Image.open(f.image_path).convert("RGB").save(jpgs[-1], quality=95)
    rec = measure_exposure(cams, jpgs, names, xyz, max_side=80)
    got = np.log([rec["images"][n]["rgb_gain"] for n in names])
    assert np.abs(got - want).max() < 0.03, np.abs(got - want).max()


def test_measure_bad_input(scene_small):
    ds = load_dataset(scene_small)
    cams = [f.camera for f in ds.frames]
    paths = [f.image_path for f in ds.frames]
    names = [f.name for f in ds.frames]
    assert "no sparse points" in measure_exposure(cams, paths, names, None)["error"]
    assert "no sparse points" in measure_exposure(cams, paths, names, np.zeros((0, 3)))["error"]
    # points behind every camera: no image sees any of them
    behind = np.array([c.center - 5.0 * c.T_world_cam[:3, 2] for c in cams])
    rec = measure_exposure(cams, paths, names, np.repeat(behind, 50, axis=0))
    assert "fewer than two images share" in rec["error"] and set(rec["unmeasured"]) == set(names)
    assert "fewer than two posed images" in measure_exposure(cams[:1], paths[:1], names[:1], np.zeros((5, 3)))["error"]
    with pytest.raises(ValueError, match="same length"):
        measure_exposure(cams, paths[:2], names, np.zeros((5, 3)))


def test_poses_stage_records_and_logs(scene_small, tmp_path, caplog):
    ds = load_dataset(scene_small)
    rng = np.random.default_rng(3)
    gains = {f.name: np.full(3, g) for f, g in zip(ds.frames, rng.uniform(0.7, 1.3, len(ds.frames)))}
    gains[ds.frames[0].name] = np.array([1.35, 1.0, 0.8])    # one clearly off, by name
    pert = _perturbed_copy(scene_small, tmp_path / "pert", gains)
    with caplog.at_level(logging.INFO, logger="splattwin.poses.estimate"):
        res = estimate_poses(load_dataset(pert), PoseOptions(method="known", progress=False))
    rec = res.stats["exposure"]
    assert rec["varies"] is True and ds.frames[0].name in rec["images_off"]
    said = [r for r in caplog.records if "exposure check" in r.getMessage()]
    # the measurement, with the gains; an info line: the splats stage holds the warning (see below)
    assert len(said) == 1 and said[0].levelno == logging.INFO
    assert f"{ds.frames[0].name} (x" in said[0].getMessage() and "--splat.appearance" in said[0].getMessage()
    out = res.save(tmp_path / "poses")
    from splattwin.limits import read_json

    assert read_json(tmp_path / "poses" / "poses_report.json", "report")["exposure"]["varies"] is True
    assert out.is_file()


def test_differing_exposures_warn_once_over_poses_and_splats(scene_small, tmp_path, caplog):
    """On photos whose exposures differ (an internet photo set) the poses stage warned "exposure check: images
    differ ..." and the splats stage "appearance: the photos differ in exposure ...": the same thing twice. Now
    one warning, the splats stage's, which says whether a correction is trained and refers to the check."""
    from splattwin.splat.appearance import decide, exposure_record

    ds = load_dataset(scene_small)
    gains = {f.name: np.full(3, 1.0) for f in ds.frames}
    gains[ds.frames[1].name] = np.array([1.4, 1.3, 1.2])
    pert = _perturbed_copy(scene_small, tmp_path / "pert", gains)
    for requested in ("off", "auto"):   # the default, and auto
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="splattwin"):
            res = estimate_poses(load_dataset(pert), PoseOptions(method="known", progress=False))
            res.save(tmp_path / requested)
            exposure, where = exposure_record(load_dataset(tmp_path / requested))
            decide(requested, exposure, where)
        warned = [r.getMessage() for r in caplog.records if "expos" in r.getMessage()]
        assert len(warned) == 1, warned
        assert ds.frames[1].name in warned[0] and "exposure check" in warned[0] and str(where) in warned[0]
