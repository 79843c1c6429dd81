"""nerfstudio loss masks (a frame's `mask_path`, 0 = ignore the pixel) in training and evaluation."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from splattwin.capture import load_dataset, load_image
from splattwin.errors import InputError
from splattwin.io import write_image
from splattwin.splat.gaussians import Gaussians, rgb_to_sh0
from splattwin.splat.losses import photometric_loss, ssim
from splattwin.splat.trainer import TrainConfig, Trainer, TrainView, load_views
from tests.splat.test_trainer import make_dataset, tiny_config


def add_masks(root: Path, masks: dict[str, np.ndarray]) -> Path:
    """Give the frames of root/transforms.json named in `masks` (view name -> bool [h,w], True = keep) a
    nerfstudio loss mask (masks/<name>.png, 0 / 255)."""
    meta = json.loads((root / "transforms.json").read_text())
    for fr in meta["frames"]:
        name = Path(fr["file_path"]).stem
        if name in masks:
            write_image(root / "masks" / f"{name}.png", np.where(masks[name], 255, 0).astype(np.uint8))
            fr["mask_path"] = f"masks/{name}.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def square(h: int, w: int, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
    """bool [h,w] mask keeping everything but rows y0:y1, columns x0:x1."""
    m = np.ones((h, w), bool)
    m[y0:y1, x0:x1] = False
    return m


# -- the loss -------------------------------------------------------------------------------------------
def reference_loss(img: torch.Tensor, gt: torch.Tensor, keep: torch.Tensor, lam: float) -> torch.Tensor:
    """splatfacto's masked loss in plain torch: both images times the mask, then L1 and D-SSIM (conv2d)."""
    m = keep[..., None].to(img.dtype)
    a, b = img * m, gt * m
    return (1 - lam) * (a - b).abs().mean() + lam * (1 - ssim(a, b))


def test_a_masked_pixels_colour_changes_neither_the_loss_nor_its_gradient():
    rng = np.random.default_rng(0)
    h, w, lam = 40, 52, 0.2
    gt = torch.tensor(rng.uniform(0, 1, (h, w, 3)), dtype=torch.float32)
    keep = torch.tensor(square(h, w, 10, 25, 14, 30))
    view = TrainView("v", gt, None, mask=keep[..., None].float())
    render = torch.tensor(rng.uniform(0, 1, (h, w, 3)), dtype=torch.float32)

    def loss_and_grad(photo: torch.Tensor, rendered: torch.Tensor) -> tuple[float, torch.Tensor]:
        x = rendered.clone().requires_grad_(True)
        v = TrainView("v", photo, None, mask=view.mask)
        loss = photometric_loss(*v.masked(x), lam)   # the trainer's path (fused numba SSIM on the CPU)
        loss.backward()
        return float(loss.detach()), x.grad

    loss, grad = loss_and_grad(gt, render)
    x = render.clone().requires_grad_(True)
    ref = reference_loss(x, gt, keep, lam)
    ref.backward()
    assert loss == pytest.approx(float(ref.detach()), rel=1e-5)
    torch.testing.assert_close(grad, x.grad, atol=2e-7, rtol=1e-3)
    assert float(grad[~keep].abs().max()) == 0.0 and float(grad[keep].abs().max()) > 0
    # other colours in the ignored pixels, of the photo and of the render: the same loss and gradient
    gt2, render2 = gt.clone(), render.clone()
    gt2[~keep] = torch.tensor([1.0, 0.0, 1.0])
    render2[~keep] = 0.5
    loss2, grad2 = loss_and_grad(gt2, render2)
    assert loss2 == loss
    torch.testing.assert_close(grad2, grad, atol=0, rtol=0)
    # without the mask the photo's colour there matters (the test would see a missing mask)
    nomask = TrainView("v", gt2, None)
    assert float(photometric_loss(*nomask.masked(render), lam)) != pytest.approx(loss)


def test_training_ignores_the_colours_of_masked_pixels(tmp_path):
    """Two captures that differ only in the masked pixels' colours train to the same Gaussians, bit for bit:
    the ignored pixels add nothing to the loss, its gradient or the densification statistics."""
    clean = make_dataset(tmp_path / "clean")
    corrupt = tmp_path / "corrupt"
    shutil.copytree(clean, corrupt)
    ds = load_dataset(clean)
    h, w = ds.frames[0].camera.height, ds.frames[0].camera.width
    keep = square(h, w, 8, 24, 10, 30)
    for f in ds.train():
        p = corrupt / "images" / f.image_path.name
        img = (load_image(p) * 255 + 0.5).astype(np.uint8)
        img[~keep] = (255, 0, 255)
        write_image(p, img)
    masks = {f.name: keep for f in ds.train()}
    add_masks(clean, masks)
    add_masks(corrupt, masks)
    cfg = tiny_config(iters=60)   # densifies at steps 10, 20, 30
    a = Trainer(load_dataset(clean), tmp_path / "a", cfg).run()
    b = Trainer(load_dataset(corrupt), tmp_path / "b", cfg).run()
    assert len(a.gaussians) == len(b.gaussians)
    for k in ("means", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(a.gaussians, k), getattr(b.gaussians, k))
    rec = json.loads((tmp_path / "b" / "train.json").read_text())["loss_masks"]
    assert rec["applied"] and rec["views"] == len(ds.train())
    assert rec["ignored_share"][ds.train()[0].name] == pytest.approx(1 - keep.mean(), abs=1e-4)


def test_a_view_whose_mask_ignores_every_pixel_leaves_the_psnr_curve_finite(tmp_path):
    """Such a view measures no pixel: its step PSNR was +inf (mse 0), and the moving average kept +inf for the
    rest of the run (history psnr inf, train.json's train_psnr null). It is now not measured (NaN) and the
    average skips it."""
    root = make_dataset(tmp_path / "ds")
    ds = load_dataset(root)
    f = ds.train()[0]
    add_masks(root, {f.name: np.zeros((f.camera.height, f.camera.width), bool)})
    res = Trainer(load_dataset(root), tmp_path / "out", tiny_config(iters=40)).run()
    psnrs = [h["psnr"] for h in res.history]
    assert len(psnrs) == 4 and all(np.isfinite(psnrs)) and min(psnrs) > 10, psnrs
    assert res.final_psnr is not None and 10 < res.final_psnr < 60
    rec = json.loads((tmp_path / "out" / "train.json").read_text())
    assert rec["train_psnr"] == pytest.approx(res.final_psnr) and rec["loss_masks"]["ignored_share"][f.name] == 1.0


# -- the mask file ----------------------------------------------------------------------------------------
def test_a_mask_of_the_wrong_size_is_refused_naming_it(tmp_path):
    root = make_dataset(tmp_path / "ds", n_train=2, n_heldout=1)
    ds = load_dataset(root)
    h, w = ds.frames[0].camera.height, ds.frames[0].camera.width
    name = ds.frames[0].name
    add_masks(root, {name: np.ones((h - 5, w), bool)})
    with pytest.raises(InputError) as e:
        load_dataset(root)
    assert e.value.path.name == f"{name}.png" and "loss mask" in str(e.value)
    assert f"{w}x{h - 5}" in str(e.value) and f"{w}x{h}" in str(e.value)


def test_a_downscaled_mask_is_enlarged_and_follows_the_training_resolution(tmp_path):
    """nerfstudio's masks_2/: a mask at half the image size is accepted, enlarged by nearest pixel and, like
    the photo, brought to the training size by nearest pixel."""
    root = make_dataset(tmp_path / "ds", n_train=2, n_heldout=1, width=48, height=36)
    ds = load_dataset(root)
    name = ds.frames[0].name
    half = np.ones((18, 24), bool)
    half[4:10, 6:12] = False     # image rows 8:20, columns 12:24
    add_masks(root, {name: half})
    views = load_views(load_dataset(root).frames, 1)
    full = views[0].mask[..., 0].numpy() > 0.5
    assert full.shape == (36, 48) and (~full).sum() == 12 * 12 and not full[8:20, 12:24].any()
    assert views[1].mask is None
    small = load_views(load_dataset(root).frames, 2)[0].mask[..., 0].numpy() > 0.5
    assert small.shape == (18, 24)
    np.testing.assert_array_equal(small, half)


# -- evaluation -----------------------------------------------------------------------------------------
def test_eval_measures_only_the_kept_pixels(tmp_path):
    """A splat that renders the black background everywhere, held-out photos that are black but for a
    white masked square and a grey kept patch: PSNR over the kept pixels only (analytic), and infinite
    (JSON null) when the kept pixels are perfect; metrics.json records the masks."""
    from splattwin.splat.eval import evaluate

    root = make_dataset(tmp_path / "ds", n_train=2, n_heldout=2, width=48, height=36)
    ds = load_dataset(root)
    held = ds.heldout()
    h, w = 36, 48
    keep = square(h, w, 5, 20, 5, 25)
    for i, f in enumerate(held):
        img = np.zeros((h, w, 3), np.uint8)
        img[~keep] = 255
        if i == 1:
            img[30:34, 40:46] = 51       # kept, 0.2 off the render
        write_image(f.image_path, img)
    add_masks(root, {f.name: keep for f in held})
    # one Gaussian behind every camera: the render is exactly the background
    g = Gaussians(np.array([[0.0, 0.0, 50.0]]), np.array([[1.0, 0, 0, 0]]), np.full((1, 3), 1e-3),
                  np.array([0.9]), rgb_to_sh0(np.array([[0.5, 0.5, 0.5]]))[:, None, :])
    res = evaluate(g, root, out_dir=tmp_path / "eval", background=(0.0, 0.0, 0.0), progress=False)
    by = {r["name"]: r for r in res.views}
    assert by[held[0].name]["psnr"] == float("inf") and by[held[0].name]["ssim"] == pytest.approx(1.0)
    mse = 24 * float(np.float32(51) / np.float32(255)) ** 2 / keep.sum()   # 0.2 as the photo loads
    assert by[held[1].name]["psnr"] == pytest.approx(-10 * np.log10(mse), abs=1e-9)
    assert by[held[1].name]["ignored_frac"] == pytest.approx(1 - keep.mean())
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert m["loss_masks"]["applied"] and m["loss_masks"]["views"] == [f.name for f in held]
    assert m["views"][0]["psnr"] is None       # inf: strict JSON writes null
    assert m["views"][1]["psnr"] == pytest.approx(-10 * np.log10(mse), abs=1e-9)


def test_masked_ssim_is_ssim_for_a_full_mask_and_ignores_masked_colours():
    from splattwin.splat import metrics

    rng = np.random.default_rng(1)
    a, b = rng.uniform(0, 1, (30, 40, 3)), rng.uniform(0, 1, (30, 40, 3))
    assert metrics.masked_ssim(a, b, np.ones((30, 40), bool)) == pytest.approx(metrics.ssim(a, b), abs=1e-12)
    keep = square(30, 40, 0, 30, 20, 40)
    b2 = b.copy()
    b2[~keep] = 0.7
    assert metrics.masked_ssim(a, b2, keep) == metrics.masked_ssim(a, b, keep)
    assert np.isnan(metrics.masked_ssim(a, b, np.zeros((30, 40), bool)))


# -- end to end -----------------------------------------------------------------------------------------
def test_masked_training_does_not_fit_a_masked_corruption(scene_small, tmp_path):
    """A generated scene whose training photos have a magenta square at the same place, masked: trained
    with the masks the splat renders the scene there, without them it paints the square in."""
    from splattwin.capture import resize_nearest

    root = tmp_path / "scene"
    shutil.copytree(scene_small, root)
    ds = load_dataset(root)
    h, w = ds.frames[0].camera.height, ds.frames[0].camera.width
    keep = square(h, w, h // 4, h // 4 + 40, w // 3, w // 3 + 50)
    for f in ds.train():
        img = (load_image(f.image_path) * 255 + 0.5).astype(np.uint8)
        img[~keep] = (255, 0, 255)
        write_image(f.image_path, img)
    cfg = tiny_config(iters=300, resolution=2, sh_degree=0)
    clean = {v.name: v.image.numpy() for v in load_views(load_dataset(scene_small).train(), 2)}
    err = {}
    for masked in (False, True):
        if masked:
            add_masks(root, {f.name: keep for f in ds.train()})
        tr = Trainer(load_dataset(root), tmp_path / f"out_{masked}", cfg)
        assert all((v.mask is not None) == masked for v in tr.views)
        tr.run()
        e = []
        with torch.no_grad():
            for i, v in enumerate(tr.views):
                img = tr.render(i)[0].clamp(0, 1).numpy()
                hole = resize_nearest(~keep, v.camera.width, v.camera.height)
                e.append(np.abs(img - clean[v.name])[hole].mean())
        err[masked] = float(np.mean(e))
    print("mean |render - clean photo| in the masked square:", err)
    assert err[True] < 0.5 * err[False], err
