from __future__ import annotations

import importlib.util
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from splattwin.errors import InputError
from splattwin.splat.eval import evaluate

_spec = importlib.util.spec_from_file_location("_splat_trainer_helpers", Path(__file__).with_name("test_trainer.py"))
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def test_eval_ground_truth_vs_degraded(tmp_path):
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    g = helpers.gt_gaussians()
    ply = g.save_ply(tmp_path / "gt.ply")
    res = evaluate(ply, ds_root, tmp_path / "eval", progress=False)
    assert res.split == "heldout" and len(res.views) == 2
    assert res.mean_psnr > 40 and res.mean_ssim > 0.99  # only PNG quantisation differs
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["mean_psnr"] == pytest.approx(res.mean_psnr) and len(m["views"]) == 2
    im = np.asarray(Image.open(tmp_path / "eval" / m["views"][0]["image"]))
    assert im.shape == (helpers.H, 3 * helpers.W + 8, 3)
    bad = g.subset(np.arange(len(g)) % 2 == 0)
    res2 = evaluate(bad, ds_root, None, progress=False)
    assert res2.mean_psnr < res.mean_psnr - 5 and res2.mean_ssim < res.mean_ssim


def test_eval_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        evaluate(tmp_path / "nope.ply", tmp_path, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="point_cloud.ply"):
        evaluate(tmp_path / "empty", tmp_path, progress=False)


def test_eval_of_a_twin_folder_or_plain_photos_says_what_to_give(tmp_path):
    """A new user ran `splattwin eval TWIN --dataset PHOTOS` (README: `eval OUT --dataset DATASET`) on the
    folder `build --out TWIN` wrote: "no point_cloud.ply in this folder (train first: splattwin train)",
    though the build had trained; then, on TWIN/splat, "dataset has no camera poses to render from" for the
    photos. Each message now names what to give: TWIN/splat and TWIN/poses."""
    twin = tmp_path / "twin"
    helpers.gt_gaussians().save_ply(twin / "splat" / "point_cloud.ply")
    with pytest.raises(InputError, match="twin folder") as e:
        evaluate(twin, tmp_path, progress=False)
    assert f"splattwin eval {twin / 'splat'} --dataset {twin / 'poses'}" in str(e.value)
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.fromarray(np.full((helpers.H, helpers.W, 3), 40 * i, np.uint8)).save(photos / f"{i}.png")
    with pytest.raises(InputError, match="no camera poses") as e:
        evaluate(twin / "splat", photos, progress=False)
    assert "poses/ folder" in str(e.value) and "splattwin poses" in str(e.value)


def test_eval_align_poses_fits_held_out_cameras_that_are_off(tmp_path):
    # The splat is the ground truth but the dataset's held-out cameras are 1 deg / 1 cm off (as after
    # training with refined poses): as given the metrics measure the offset; aligned they are near-perfect.
    import dataclasses

    from splattwin.capture import load_dataset
    from splattwin.splat.pose_refine import perturb_poses

    ds = load_dataset(helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2))
    for i, f in enumerate(ds.heldout()):
        T = perturb_poses(f.camera.T_cam_world[None], 1.0, 0.01, seed=i)[0]
        f.camera = dataclasses.replace(f.camera, T_world_cam=np.linalg.inv(T))
    g = helpers.gt_gaussians()
    raw = evaluate(g, ds, None, progress=False)
    out = tmp_path / "eval"
    al = evaluate(g, ds, out, progress=False, align_poses=True)
    assert al.mean_psnr > raw.mean_psnr + 10 and al.mean_ssim > 0.98, (raw.mean_psnr, al.mean_psnr)
    for v in al.views:
        assert v["pose_correction_deg"] == pytest.approx(1.0, abs=0.2)
    m = json.loads((out / "metrics.json").read_text())
    assert m["poses"].startswith("aligned") and "pose_correction_m" in m["views"][0]


def test_training_coverage_analytic_frustum_overlap():
    """A fronto-parallel plane 2 m ahead; a training camera 1 m to the right (same orientation) sees the
    held-out pixels whose x on the plane is >= -1 m: columns 50..199 of 200 (fx 100, cx 100) -> 0.75."""
    from splattwin.capture.camera import Camera
    from splattwin.splat.eval import training_coverage

    K = [[100.0, 0, 100.0], [0, 100.0, 50.0], [0, 0, 1]]
    held = Camera(K, 200, 100)
    right = np.eye(4)
    right[0, 3] = 1.0
    behind = np.diag([-1.0, 1.0, -1.0, 1.0])       # turned around: the plane is behind it
    depth, alpha = np.full((100, 200), 2.0), np.ones((100, 200))
    seen = training_coverage(depth, alpha, held, [Camera(K, 200, 100, right)])
    assert seen[:, 50:].all() and not seen[:, :50].any() and seen.mean() == 0.75
    assert not training_coverage(depth, alpha, held, [Camera(K, 200, 100, behind)]).any()
    alpha[:, 150:] = 0.2                             # nothing drawn there: not covered
    assert training_coverage(depth, alpha, held, [Camera(K, 200, 100, right)]).mean() == 0.5
    # training cameras at another image size (the held-out K is at the render's size): the same
    K2 = [[200.0, 0, 200.0], [0, 200.0, 100.0], [0, 0, 1]]
    alpha[:] = 1.0
    assert training_coverage(depth, alpha, held, [Camera(K2, 400, 200, right)]).mean() == 0.75


def test_eval_reports_psnr_over_pixels_the_training_views_saw(tmp_path):
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    res = evaluate(helpers.gt_gaussians(), ds_root, tmp_path / "eval", progress=False)
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert 0.0 < res.mean_covered_frac <= 1.0 and m["mean_covered_frac"] == pytest.approx(res.mean_covered_frac)
    for v in res.views:
        assert 0.0 < v["covered_frac"] <= 1.0 and v["psnr_covered"] > 40
    assert m["mean_psnr_covered"] > 40 and "coverage_protocol" in m


def test_side_by_side_tints_unseen_pixels_of_the_error_map_only():
    from splattwin.splat.eval import UNSEEN_TINT, side_by_side

    gt = np.zeros((6, 5, 3))
    render = np.zeros((6, 5, 3))
    unseen = np.zeros((6, 5), bool)
    unseen[:, 3:] = True
    plain, tinted = side_by_side(gt, render), side_by_side(gt, render, unseen)
    assert plain.shape == tinted.shape == (6, 3 * 5 + 8, 3)
    err = slice(2 * 5 + 8, None)
    np.testing.assert_array_equal(tinted[:, :2 * 5 + 8], plain[:, :2 * 5 + 8])   # photo and render untouched
    np.testing.assert_array_equal(tinted[:, err][:, :3], plain[:, err][:, :3])
    np.testing.assert_array_equal(tinted[:, err][:, 3:], (plain[:, err][:, 3:].astype(np.uint16) + UNSEEN_TINT) // 2)


def test_eval_renders_with_the_low_pass_the_splats_were_trained_with(tmp_path):
    """train.json's config names the mode and low-pass (eps2d; 0: the mode's default, 0.1 antialiased);
    a config from before the option recorded it was trained with 0.3; a bad value is an error naming
    train.json. Bare Gaussians with a mode: the mode's default."""
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    g = helpers.gt_gaussians()

    def folder(name, cfg):
        d = tmp_path / name
        d.mkdir()
        g.save_ply(d / "point_cloud.ply")
        (d / "train.json").write_text(json.dumps({"config": cfg}))
        return d

    auto = evaluate(folder("auto", {"rasterize_mode": "antialiased", "eps2d": 0.0}), ds_root, None, progress=False)
    legacy = evaluate(folder("legacy", {"rasterize_mode": "antialiased"}), ds_root, None, progress=False)
    explicit = evaluate(folder("explicit", {"rasterize_mode": "antialiased", "eps2d": 0.3}), ds_root, None,
                        progress=False)
    bare = evaluate(g, ds_root, None, progress=False, rasterize_mode="antialiased")
    assert legacy.mean_psnr == explicit.mean_psnr
    assert auto.mean_psnr == pytest.approx(bare.mean_psnr, abs=1e-4)  # (the PLY stores float32)
    assert abs(auto.mean_psnr - legacy.mean_psnr) > 0.01  # the two low-passes differ here: the test can fail
    given = evaluate(g, ds_root, None, progress=False, rasterize_mode="antialiased", eps2d=0.3)
    assert given.mean_psnr == pytest.approx(legacy.mean_psnr, abs=1e-4)   # an explicit low-pass wins
    with pytest.raises(InputError, match="eps2d") as e:
        evaluate(folder("bad", {"rasterize_mode": "antialiased", "eps2d": "wide"}), ds_root, None, progress=False)
    assert "train.json" in str(e.value)


def test_eval_compares_distorted_photos_undistorted(tmp_path):
    """Held-out photos with lens distortion (as SfM's SIMPLE_RADIAL estimates it): the true splats score as
    on pinhole photos (the photo is undistorted to its pinhole camera before the comparison), and
    metrics.json names the views so compared."""
    import dataclasses

    from splattwin.capture import Dataset, Frame
    from splattwin.capture.undistort import distort_image, pinhole_for
    from splattwin.io import write_image

    g = helpers.gt_gaussians()
    cams = helpers.ring_cameras(4, 160, 120)
    frames = []
    for i, cam in enumerate(cams):
        cam = dataclasses.replace(cam, dist=np.array([0.1, 0.0, 0.0, 0.0]), name=f"v{i}")
        fine = pinhole_for(cam).scaled(2.0)
        photo = distort_image(helpers.render_gaussians(g, fine), fine, cam)
        p = write_image(tmp_path / f"v{i}.png", (np.clip(photo, 0, 1) * 255 + 0.5).astype(np.uint8))
        frames.append(Frame(image_path=p, camera=cam, split="heldout" if i == 3 else "train"))
    ds = Dataset(root=tmp_path, frames=frames, has_poses=True)
    res = evaluate(g, ds, tmp_path / "eval", progress=False)
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["undistorted_views"] == ["v3"]
    assert res.mean_psnr > 38, res.mean_psnr
    # the same photo read as if it were a pinhole image
    for f in frames:
        f.camera = dataclasses.replace(f.camera, dist=None)
    naive = evaluate(g, ds, None, progress=False)
    assert naive.mean_psnr < res.mean_psnr - 8, (naive.mean_psnr, res.mean_psnr)


def test_eval_holds_out_what_training_held_out_and_never_a_training_view(tmp_path, caplog):
    """`splattwin train --heldout-views` splits the dataset in memory: the dataset's own split (here
    heldout_003/004) then names views the splat was trained on. Evaluation follows train.json."""
    caplog.set_level(logging.INFO, logger="splattwin.splat.eval")
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=2)
    run = tmp_path / "run"
    helpers.gt_gaussians().save_ply(run / "point_cloud.ply")
    trained = ["train_000", "train_002", "heldout_003", "heldout_004"]
    record = {"source": "option", "rule": "listed views (--heldout-views 1)", "views": ["train_001"]}
    (run / "train.json").write_text(json.dumps({"views": [{"name": n} for n in trained], "heldout": record}))
    res = evaluate(run, ds_root, tmp_path / "eval", progress=False)
    assert res.split == "heldout" and [v["name"] for v in res.views] == ["train_001"]
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["heldout"]["views"] == ["train_001"] and m["heldout"]["rule"] == record["rule"]
    assert "not the dataset's split" in caplog.text
    # trained without a hold-out (`--heldout-every 0`): the dataset's held-out views were training views
    (run / "train.json").write_text(json.dumps({"views": [{"name": n} for n in trained + ["train_001"]],
                                                "heldout": {"source": "option", "rule": "none", "views": []}}))
    caplog.clear()
    res = evaluate(run, ds_root, None, progress=False)
    assert res.split == "train" and "heldout_003, heldout_004: trained on by this splat" in caplog.text
    # a malformed record (untrusted file) is refused, naming the file, not silently replaced by another split
    for bad in ({"views": "x"}, {"views": [{"name": 3}]}, {"heldout": {"views": 3}}, {"heldout": {"views": [1]}},
                {"heldout": []}):
        (run / "train.json").write_text(json.dumps(bad))
        with pytest.raises(InputError, match="malformed training record") as e:
            evaluate(run, ds_root, None, progress=False)
        assert e.value.path == run / "train.json"
    # trained on another capture (no name in common): the dataset's split, its training views for coverage
    (run / "train.json").write_text(json.dumps({"views": [{"name": "other_000"}]}))
    res = evaluate(run, ds_root, None, progress=False)
    assert [v["name"] for v in res.views] == ["heldout_003", "heldout_004"] and res.mean_covered_frac > 0.5


def test_dataset_units_come_from_the_frame_json_beside_the_poses(tmp_path):
    from splattwin.capture import load_dataset
    from splattwin.poses.twin_frame import TwinFrame
    from splattwin.splat.eval import dataset_units

    root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=1)
    assert dataset_units(load_dataset(root)) == "m"  # known poses without a frame.json: metres, as the poses stage
    (root / "frame.json").write_text(json.dumps(vars(TwinFrame(source="unscaled", scaled=False))))
    assert dataset_units(load_dataset(root)) == "unscaled"


@pytest.mark.parametrize("text, needle", [
    # a target width of 100000 px upsampled every view to gigapixels (23 GB, OOM-killed)
    (json.dumps({"resolution": {"resolution": 100000, "max_side": 10**6}}), "target width of 16 to 65535"),
    (json.dumps({"resolution": {"resolution": 1, "max_side": 10**9}}), "max_side"),
    (json.dumps({"resolution": {"resolution": True}}), "whole number"),
    (json.dumps({"config": {"resolution": -5}}), "config resolution"),
    (json.dumps({"config": {"cpu_max_side": "big"}}), "cpu_max_side"),
    (json.dumps({"config": {"background": [0, "x", 0]}}), "background"),
    (json.dumps({"config": {"rasterize_mode": ["x"]}}), "rasterize_mode"),
    (json.dumps({"resolution": 7}), "resolution must be a JSON object"),
    ("[1, 2]", "expected a JSON object"),   # was AttributeError (exit 1)
    ("{'a': 1}", "not valid JSON"),          # was a JSONDecodeError (exit 1)
    ('{"n": ' + "7" * 5000 + "}", "number too long"),
])
def test_eval_checks_the_training_record_before_sizing_views(tmp_path, text, needle):
    d = tmp_path / "run"
    d.mkdir()
    helpers.gt_gaussians().save_ply(d / "point_cloud.ply")
    (d / "train.json").write_text(text)
    with pytest.raises(InputError, match=needle) as e:
        evaluate(d, tmp_path / "no-dataset", None, progress=False)
    assert e.value.path == d / "train.json"


def test_eval_never_upsamples_held_out_photos_beyond_their_size(tmp_path):
    # a received train.json's target width (here 20000 px for 64 px photos) is capped at the photo's size:
    # an upsampled held-out photo holds nothing more, and the views would be sized up to the pixel limit
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=2, n_heldout=1)
    d = tmp_path / "run"
    d.mkdir()
    helpers.gt_gaussians().save_ply(d / "point_cloud.ply")
    for r, want in ((20000, "full"), (2, "half")):
        (d / "train.json").write_text(json.dumps({"resolution": {"resolution": r, "max_side": None, "how": "x"}}))
        res = evaluate(d, ds_root, None, progress=False)
        er = res.eval_resolution
        assert er["mode"] == "training"
        if want == "full":
            assert er["sizes"] == er["full_sizes"]
        else:
            assert er["sizes"] != er["full_sizes"]


def test_views_are_never_upsampled_beyond_the_pixel_limit(tmp_path, monkeypatch):
    from splattwin import limits
    from splattwin.capture import load_dataset
    from splattwin.splat.resolution import Resolution
    from splattwin.splat.trainer import load_views

    ds = load_dataset(helpers.make_dataset(tmp_path / "ds", n_train=1, n_heldout=0))
    monkeypatch.setattr(limits, "MAX_IMAGE_PIXELS", 100_000)
    with pytest.raises(InputError, match="megapixels") as e:
        load_views(ds.frames, Resolution(1000))   # 1000 px wide from a small image: over the (lowered) limit
    assert e.value.path == ds.frames[0].image_path


def test_a_view_no_longer_held_out_loses_its_old_comparison_image(tmp_path):
    """After `--heldout-views` changed, eval/ kept the old held-out view's picture beside the new ones; only
    the pictures the earlier metrics.json listed go (a user's own files in --out stay)."""
    ds_root = helpers.make_dataset(tmp_path / "ds", n_train=3, n_heldout=1)
    run = tmp_path / "run"
    helpers.gt_gaussians().save_ply(run / "point_cloud.ply")
    out = tmp_path / "eval"
    names = ["train_000", "train_001", "train_002", "heldout_003"]

    def held_out(view: str) -> list[str]:
        record = {"source": "option", "rule": f"listed views ({view})", "views": [view]}
        (run / "train.json").write_text(json.dumps({"views": [{"name": n} for n in names if n != view],
                                                    "heldout": record}))
        evaluate(run, ds_root, out, progress=False)
        return sorted(p.name for p in out.glob("*.png"))

    assert held_out("heldout_003") == ["heldout_003.png"]
    (out / "notes.png").write_bytes(b"a user's own file")
    assert held_out("train_001") == ["notes.png", "train_001.png"]
