"""Held-out label quality against the user's own 2D masks (splattwin.semantics.lift.heldout_mask_miou)."""

from types import SimpleNamespace

import numpy as np
import pytest

from splattwin import io
from splattwin.semantics.lift import heldout_mask_miou
from splattwin.semantics.masks import MaskSet


def _frame(name: str, split: str):
    return SimpleNamespace(name=name, split=split)


def test_heldout_mask_miou_scores_only_the_views_the_fusion_did_not_use(tmp_path):
    """Two objects; the held-out view's rendered labels overlap its masks by known areas: object 1 IoU
    1/2 (4x8 rendered vs 4x4 mask inside it), object 2 IoU 1 -> mIoU 0.75. The training view, whose masks
    the fusion used, is not scored even though its labels are wrong; without held-out masks: nothing."""
    h, w = 12, 16
    ms = MaskSet()
    m1 = np.zeros((h, w), bool)
    m1[0:4, 0:4] = True
    m2 = np.zeros((h, w), bool)
    m2[8:12, 8:16] = True
    for view in ("train0", "held0"):
        ms.add(view, 1, m1, name="box")
        ms.add(view, 2, m2, name="cube")
    raw = tmp_path / "label_maps" / "raw"
    fused = np.zeros((h, w), np.uint8)
    fused[0:4, 0:8] = 1
    fused[8:12, 8:16] = 2
    io.write_image(raw / "held0.png", fused)
    io.write_image(raw / "train0.png", np.zeros((h, w), np.uint8))  # all wrong, but a fused view
    ds = SimpleNamespace(frames=[_frame("train0", "train"), _frame("held0", "heldout")])
    out = heldout_mask_miou(ms, ds, tmp_path, [1, 2])
    assert out["miou_heldout_masks_views"] == ["held0"]
    assert np.isclose(out["miou_heldout_masks"], 0.75)
    assert heldout_mask_miou(ms, SimpleNamespace(frames=[_frame("train0", "train")]), tmp_path, [1, 2]) == {}


def test_dataset_objects_finds_the_scene_of_a_twins_poses_folder(tmp_path):
    """A twin's poses/ holds the scene's ground-truth label images, whose ids are the scene's: `fuse
    --dataset TWIN/poses/transforms.json` must read them from TWIN/scene/scene.json (it numbered the mask
    objects by name instead, and scored mIoU 0.19 for labels that score 0.92)."""
    from splattwin.semantics.lift import dataset_objects

    twin = tmp_path / "twin"
    (twin / "poses").mkdir(parents=True)
    (twin / "scene").mkdir()
    io.write_json(twin / "scene" / "scene.json", {"objects": [{"name": "table", "label": 0},
                                                             {"name": "yellow_cube", "label": 1},
                                                             {"name": "blue_box", "label": 2}]})
    (twin / "poses" / "transforms.json").write_text("{}")
    assert dataset_objects(twin / "poses" / "transforms.json") == {"yellow_cube": 1, "blue_box": 2}
    assert dataset_objects(twin / "scene") == {"yellow_cube": 1, "blue_box": 2}
    assert dataset_objects(tmp_path / "elsewhere") is None


def test_splat_depth_and_label_maps_draw_the_splats_as_trained():
    """`raster` = the splats' trained (mode, eps2d): SplatDepth's depth and the label maps use it. Sub-pixel
    Gaussians drawn classic (0.3 dilation, no opacity compensation) cover far more pixels than the same
    splats drawn antialiased with 0.1, as they were trained."""
    from splattwin.capture import Camera
    from splattwin.semantics.label_render import SplatDepth, render_label_maps
    from splattwin.splat.gaussians import Gaussians
    from splattwin.splat.rendering import render

    rng = np.random.default_rng(0)
    n = 60
    means = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), np.full(n, 2.0)]   # ~0.4 px std each, apart
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.008),
                  opacities=np.full(n, 0.95), sh=np.zeros((n, 1, 3)))
    cam = Camera.from_fov(0.6, 64, 64)
    aa = ("antialiased", 0.1)
    d_aa = SplatDepth(g, raster=aa, min_alpha=0.3)(None, [cam])[0]
    d_cl = SplatDepth(g, min_alpha=0.3)(None, [cam])[0]
    ref, alpha = render(g, cam, mode="ED", rasterize_mode="antialiased", eps2d=0.1)
    np.testing.assert_array_equal(np.isfinite(d_aa), alpha >= 0.3)
    assert np.isfinite(d_cl).sum() > 1.5 * np.isfinite(d_aa).sum() > 0
    labels = np.ones(n, np.int64)
    lab_aa = render_label_maps(g, labels, [cam], 1, raster=aa, threshold=0.3)[0]
    lab_cl = render_label_maps(g, labels, [cam], 1, threshold=0.3)[0]
    np.testing.assert_array_equal(lab_aa > 0, alpha >= 0.3)
    assert (lab_cl > 0).sum() > 1.5 * (lab_aa > 0).sum()


def test_fuse_to_dir_reads_the_trained_filter_beside_the_splats(tmp_path, monkeypatch, test_module):
    """A splat file beside its training record (train.json) is fused with the mode and low-pass it was
    trained with; bare Gaussians or a PLY without a record: classic 0.3; a bad record names train.json."""
    import json

    import pytest

    from splattwin.capture import load_dataset
    from splattwin.errors import InputError
    from splattwin.semantics import lift

    h = test_module("splat/test_trainer.py")
    ds = load_dataset(h.make_dataset(tmp_path / "ds", n_train=3, n_heldout=1))
    g = h.gt_gaussians()
    ms = h.half_image_masks(ds.frames)
    seen = []
    real = lift.make_depth_renderer
    monkeypatch.setattr(lift, "make_depth_renderer", lambda gs, r="auto", raster=("classic", None):
                        seen.append(raster) or real(gs, r, raster))

    def fuse(splats, name):
        return lift.fuse_to_dir(splats, ds, ms, tmp_path / name, label_maps=False, progress=False)

    run = tmp_path / "run"
    run.mkdir()
    g.save_ply(run / "point_cloud.ply")
    fuse(run / "point_cloud.ply", "no_record")
    (run / "train.json").write_text(json.dumps({"config": {"rasterize_mode": "antialiased", "eps2d": 0.0}}))
    fuse(run / "point_cloud.ply", "with_record")
    fuse(g, "bare")
    assert seen == [("classic", 0.3), ("antialiased", 0.1), ("classic", 0.3)]
    (run / "train.json").write_text(json.dumps({"config": {"rasterize_mode": "antialiased", "eps2d": -2}}))
    with pytest.raises(InputError, match="eps2d") as e:
        fuse(run / "point_cloud.ply", "bad")
    assert "train.json" in str(e.value)


def test_splat_depth_and_label_maps_land_where_a_distorted_camera_sees_the_splats():
    """A photo with lens distortion (SfM's SIMPLE_RADIAL): the fusion projects centres through the lens
    model (`project_to_pixels`), so the depth and label maps it compares them with must be in the photo's
    pixel grid too. Small splats near the corners (displaced ~9 px by k1 = 0.1) are found at their distorted
    pixels with their depth; drawn as a pinhole they were not."""
    import dataclasses

    from splattwin.capture import Camera
    from splattwin.semantics.label_render import SplatDepth, project_to_pixels, render_label_maps
    from splattwin.splat.gaussians import Gaussians

    cam = Camera(K=np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), width=320, height=240,
                 dist=[0.1, 0.0, 0.0, 0.0])
    xy = np.array([[-0.45, -0.32], [0.45, -0.3], [-0.44, 0.31], [0.42, 0.33], [0.0, 0.0]])
    z = np.array([1.0, 1.2, 1.4, 1.1, 1.3])
    means = np.c_[xy * z[:, None], z]
    n = len(means)
    g = Gaussians(means=means, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.004),
                  opacities=np.full(n, 0.99), sh=np.zeros((n, 1, 3)))
    pix, zz = project_to_pixels(means, cam)
    assert np.all(pix >= 0)
    v, u = np.divmod(pix, cam.width)
    d = SplatDepth(g, min_alpha=0.3)(None, [cam])[0]
    assert d.shape == (240, 320)
    np.testing.assert_allclose(d[v, u], zz, rtol=1e-3)
    half = SplatDepth(g, min_alpha=0.3, scale=0.5)(None, [cam])[0]  # drawn at half size, in the photo's grid
    assert half.shape == (240, 320)
    np.testing.assert_allclose(half[v, u], zz, rtol=1e-3)
    labels = np.arange(1, n + 1)
    lab = render_label_maps(g, labels, [cam], n, threshold=0.3)[0]
    np.testing.assert_array_equal(lab[v, u], labels)
    # the same splats drawn as if the lens were ideal miss their corner pixels
    pinhole = dataclasses.replace(cam, dist=None)
    d_pin = SplatDepth(g, min_alpha=0.3)(None, [pinhole])[0]
    assert np.isinf(d_pin[v[:4], u[:4]]).all() and np.isfinite(d_pin[v[4], u[4]])


def test_masks_for_only_some_training_views_are_warned_about():
    """Masks for 1 of 7 training views were fused silently (mIoU 0.05): the views without masks are named."""
    import warnings as w
    from types import SimpleNamespace

    from splattwin.semantics.lift import views_for
    from splattwin.semantics.masks import MaskSet, MaskWarning

    frames = [SimpleNamespace(name=f"v{i}", camera=None) for i in range(4)]
    ms = MaskSet(objects={1: "cube"})
    ms.add("v0", 1, np.ones((4, 4), bool))
    with pytest.warns(MaskWarning, match=r"masks cover 1 of 4 training views.*v1, v2, v3"):
        assert [v.name for v in views_for(frames, ms)] == ["v0"]
    for i in (1, 2, 3):
        ms.add(f"v{i}", 1, np.ones((4, 4), bool))
    with w.catch_warnings():
        w.simplefilter("error")
        assert len(views_for(frames, ms)) == 4


def test_fusion_of_fewer_views_removes_the_pictures_of_the_views_gone(tmp_path, test_module):
    """A rebuild from fewer views left the old views' label maps (and 2D masks | labels pictures) beside
    the new ones, and the report globbed them as this twin's (audit 9 F12). fusion.json lists the views
    its pictures are of; other files in the folders are left alone."""
    import json

    from splattwin.capture import load_dataset
    from splattwin.semantics import lift

    h = test_module("splat/test_trainer.py")
    ds = load_dataset(h.make_dataset(tmp_path / "ds", n_train=4, n_heldout=1))
    g, ms = h.gt_gaussians(), h.half_image_masks(ds.frames)
    out = tmp_path / "sem"

    def pictures(sub):
        return sorted(p.stem for p in (out / sub).glob("*.png"))

    lift.fuse_to_dir(g, ds, ms, out, progress=False, metrics=True, maps_renderer="points")
    assert pictures("label_maps") == sorted(f.name for f in ds.frames)
    (out / "label_maps" / "notes.txt").write_text("not a picture of the fusion")
    gone = ds.frames[2].name
    ds.frames = [f for f in ds.frames if f.name != gone]
    ms = h.half_image_masks(ds.frames)
    lift.fuse_to_dir(g, ds, ms, out, progress=False, metrics=True, maps_renderer="points")
    names = sorted(f.name for f in ds.frames)
    assert pictures("label_maps") == pictures("label_maps/raw") == names
    assert gone not in pictures("masks_vs_labels") and pictures("masks_vs_labels")
    assert (out / "label_maps" / "notes.txt").is_file()
    assert sorted(json.loads((out / "fusion.json").read_text())["label_map_views"]) == names
    lift.fuse_to_dir(g, ds, ms, out, progress=False, label_maps=False)   # no maps: none of an earlier run
    assert pictures("label_maps") == pictures("label_maps/raw") == pictures("masks_vs_labels") == []
