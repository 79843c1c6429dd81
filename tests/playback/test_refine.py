"""Object-focused refinement (`splattwin.playback.refine`): a blurred object sharpens towards its photos, the
rest of the scene is left bit for bit, and the twin folder stays consistent for the playback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from .conftest import OBJ_CENTRE, OBJ_HALF, make_object, make_table, write_twin

from splattwin import io
from splattwin.capture.camera import Camera, look_at
from splattwin.capture.dataset import Frame
from splattwin.errors import InputError
from splattwin.playback.scene import DynamicScene, concat
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.splat.rendering import render_rgb
from splattwin.twin.manifest import Manifest
from splattwin.playback.refine import RefineOptions, _labels_of, refine_objects


def sharp_object() -> Gaussians:
    """The object as the photos show it: the same box, a fine two-colour stripe print (period 1 cm)."""
    g = make_object(n=4000, seed=3)
    stripe = (np.floor((g.means[:, 0] + g.means[:, 1] + g.means[:, 2]) / 0.005) % 2).astype(bool)
    rgb = np.where(stripe[:, None], [0.9, 0.9, 0.95], [0.1, 0.2, 0.7])
    sh = np.zeros((len(g), 16, 3))
    sh[:, 0] = rgb_to_sh0(rgb)
    return Gaussians(g.means, g.quats, np.full((len(g), 3), 0.0015), np.full(len(g), 0.95), sh)


def cameras(n: int = 6, width: int = 96, height: int = 72) -> list[Camera]:
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = OBJ_CENTRE + np.array([0.22 * np.cos(a), 0.22 * np.sin(a), 0.18])
        out.append(Camera.from_fov(np.radians(50), width, height, look_at(eye, OBJ_CENTRE), name=f"train_{i:03d}"))
    return out


@pytest.fixture()
def twin_and_photos(tmp_path):
    twin = write_twin(tmp_path / "twin")
    truth = concat([make_table(), sharp_object()], 3)
    frames = []
    for c in cameras():
        p = tmp_path / "photos" / f"{c.name}.png"
        io.write_image(p, (render_rgb(truth, c) * 255 + 0.5).astype(np.uint8))
        frames.append(Frame(image_path=p, camera=c))
    return twin, frames


def object_psnr(twin: Path, frames: list[Frame]) -> float:
    """PSNR over the pixels the object covers in the photos (its projected bounding box, inner part)."""
    from splattwin.capture.dataset import load_image

    sc = DynamicScene.load(twin)
    g = sc.gaussians()
    err = []
    for f in frames:
        c = f.camera
        corners = OBJ_CENTRE + OBJ_HALF * 0.7 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
        pc = corners @ c.T_cam_world[:3, :3].T + c.T_cam_world[:3, 3]
        uv = (pc @ c.K.T)[:, :2] / pc[:, 2:]
        u0, v0 = np.floor(uv.min(0)).astype(int)
        u1, v1 = np.ceil(uv.max(0)).astype(int)
        img = render_rgb(g, c)[v0:v1, u0:u1]
        ref = load_image(f.image_path)[v0:v1, u0:u1]
        err.append(np.mean((img - ref) ** 2))
    return float(10 * np.log10(1 / np.mean(err)))


def test_refine_sharpens_the_object_and_keeps_the_rest(twin_and_photos):
    twin, frames = twin_and_photos
    before = DynamicScene.load(twin, fill_holes=False)
    p0 = object_psnr(twin, frames)
    stats = refine_objects(twin, frames, RefineOptions(iters=240, refine_every=40, max_factor=2.0, seed=0))
    p1 = object_psnr(twin, frames)
    assert p1 > p0 + 3.0, (p0, p1)
    n0, n1 = stats["objects"]["blue_box"]["before"], stats["objects"]["blue_box"]["after"]
    assert n0 == len(before.objects["blue_box"]) and n0 < n1 <= 2 * n0
    # the twin now points to the refined files and loads as before: same background, refined object
    man = Manifest.load(twin)
    assert man.splats == "refined/point_cloud.ply" and man.labels == "refined/labels.npy"
    after = DynamicScene.load(twin, fill_holes=False)
    assert len(after.objects["blue_box"]) == n1
    np.testing.assert_array_equal(after.background.means, before.background.means)
    np.testing.assert_array_equal(after.background.sh, before.background.sh)
    labels = np.load(twin / man.labels)
    assert len(labels) == len(Gaussians.load_ply(twin / man.splats)) and (labels == 1).sum() == n1
    # the splat stage's own output is untouched
    assert len(Gaussians.load_ply(twin / "splat" / "point_cloud.ply")) == len(make_table()) + len(make_object())


def test_refine_dc_only_leaves_no_view_dependence(twin_and_photos):
    twin, frames = twin_and_photos
    refine_objects(twin, frames, RefineOptions(iters=30, refine_every=10, dc_only=True))
    g = DynamicScene.load(twin).objects["blue_box"]
    assert np.all(g.sh[:, 1:] == 0) and np.any(g.sh[:, 0] != 0)


def test_refine_needs_frames(tmp_path):
    twin = write_twin(tmp_path / "twin")
    with pytest.raises(InputError, match="no training frames"):
        refine_objects(twin, [])


def test_labels_of_takes_labels_by_position_and_rejects_strangers():
    full = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    lab = np.array([0, 5, 7])
    np.testing.assert_array_equal(_labels_of(full[[2, 0]], full, lab), [7, 0])
    np.testing.assert_array_equal(_labels_of(full[[1]], full, None), [0])
    with pytest.raises(ValueError, match="do not coincide"):
        _labels_of(full[[1]] + 1e-4, full, lab)


def _coverage(g: Gaussians, cam: Camera) -> np.ndarray:
    """[H,W] accumulated alpha of `g` alone as seen by `cam`."""
    import torch

    from splattwin.splat.rasterize import rasterization

    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    _, alpha, _ = rasterization(t(g.means), t(g.quats), t(g.scales), t(g.opacities), torch.ones(len(g), 1),
                                t(cam.T_cam_world)[None], t(cam.K)[None], cam.width, cam.height, backend="cpu")
    return alpha[0, ..., 0].numpy()


def _mask_error(twin: Path, frames: list[Frame], ms) -> float:
    """Mean |object coverage - mask| over the pixels of the views that have a mask."""
    from splattwin.twin.splats import transform_gaussians

    sc = DynamicScene.load(twin, fill_holes=False)
    g = transform_gaussians(sc.objects["blue_box"], sc.T_world_obj0["blue_box"])
    return float(np.mean([np.abs(_coverage(g, f.camera) - ms.get(f.name, 1)).mean() for f in frames]))


def test_silhouette_loss_pulls_the_object_to_its_masks_and_ignores_a_false_one(twin_and_photos):
    import shutil

    from splattwin.semantics.masks import MaskSet

    twin, frames = twin_and_photos
    truth = sharp_object()
    ms = MaskSet(objects={1: "blue_box"})
    for f in frames:
        ms.add(f.name, 1, _coverage(truth, f.camera) > 0.5)
    # a seventh view whose mask is a false detection in the image corner: it must not be painted in
    c0 = frames[0].camera
    odd = Frame(image_path=frames[0].image_path,
                camera=Camera.from_fov(np.radians(50), c0.width, c0.height, c0.T_world_cam, name="train_odd"))
    wrong = np.zeros((c0.height, c0.width), bool)
    wrong[:12, :12] = True
    ms.add("train_odd", 1, wrong)
    plain = twin.parent / "plain"
    shutil.copytree(twin, plain)
    e0 = _mask_error(twin, frames, ms)
    opts = dict(iters=160, refine_every=40, max_factor=2.0, seed=0)
    refine_objects(plain, frames + [odd], RefineOptions(mask_lambda=0.0, **opts), masks=ms)
    stats = refine_objects(twin, frames + [odd], RefineOptions(mask_lambda=0.05, **opts), masks=ms)
    assert stats["silhouette"] == {"masks": 7, "used": 6}
    assert "silhouette" not in json.loads((plain / "refined" / "refine.json").read_text())
    e_plain, e_masks = _mask_error(plain, frames, ms), _mask_error(twin, frames, ms)
    assert e_masks < 0.8 * e_plain, (e0, e_plain, e_masks)
    from splattwin.twin.splats import transform_gaussians

    sc = DynamicScene.load(twin, fill_holes=False)
    corner = _coverage(transform_gaussians(sc.objects["blue_box"], sc.T_world_obj0["blue_box"]), odd.camera)[:12, :12]
    assert corner.max() < 0.05


def test_silhouette_loss_is_the_area_normalised_l1():
    import torch

    from splattwin.playback.refine import silhouette_loss

    t = torch.zeros(8, 8, 2)
    t[:2, :2, 0] = 1.0                          # areas 4 and 16
    t[4:, 4:, 1] = 1.0
    assert float(silhouette_loss(t.clone(), t)) == 0.0
    c = t.clone()
    c[..., 0] = 0.0                              # first object missing: 4/4 = 1; second perfect: 0
    assert float(silhouette_loss(c, t)) == pytest.approx(0.5)
    c = t.clone()
    c[0, 7, 1] = 1.0                             # one stray pixel of the large object: 1/16
    assert float(silhouette_loss(c, t)) == pytest.approx(0.5 / 16)


def test_masks_that_all_disagree_leave_the_refinement_as_without_masks(twin_and_photos):
    import shutil

    from splattwin.semantics.masks import MaskSet

    twin, frames = twin_and_photos
    ms = MaskSet(objects={1: "blue_box"})
    for f in frames:                                 # every mask a false detection in the image corner
        wrong = np.zeros((f.camera.height, f.camera.width), bool)
        wrong[:8, :8] = True
        ms.add(f.name, 1, wrong)
    plain = twin.parent / "plain"
    shutil.copytree(twin, plain)
    opts = dict(iters=40, refine_every=20, max_factor=2.0, seed=0)
    refine_objects(plain, frames, RefineOptions(mask_lambda=0.0, **opts))
    stats = refine_objects(twin, frames, RefineOptions(mask_lambda=0.05, **opts), masks=ms)
    assert stats["silhouette"] == {"masks": 6, "used": 0}
    a = Gaussians.load_ply(twin / "refined" / "point_cloud.ply")
    b = Gaussians.load_ply(plain / "refined" / "point_cloud.ply")
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.sh, b.sh)
