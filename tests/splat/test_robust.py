"""Transient masks (splattwin.splat.robust) and their place in the trainer's loss."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from splattwin.splat.config import TrainConfig
from splattwin.splat.losses import photometric_loss
from splattwin.splat.robust import _box_mean, masked_target, outlier_mask


def _residual(seed: int = 0) -> torch.Tensor:
    """Noise, thin high-residual lines every 7th column (a scene's edges) and one 40x50 blob (a passer-by)."""
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(120, 160, generator=g) * 0.1
    r[:, ::7] += 0.5
    r[40:80, 60:110] += 0.6
    return r


def test_blobs_are_masked_scattered_edges_are_not():
    m = outlier_mask(_residual())
    assert m.dtype == torch.bool and m.shape == (120, 160)
    assert m[40:80, 60:110].float().mean() > 0.9        # the blob
    assert m[44:76, 64:106].all()                        # its inside entirely
    assert not m[:, :50].any() and not m[:, 120:].any()  # the lines away from it
    assert not m[:30].any()


def test_quantile_sets_how_much_can_be_candidates():
    r = _residual()
    # with the 0.99 quantile only the top 1 % are candidates: too few to fill a 16x16 patch anywhere
    assert outlier_mask(r, quantile=0.99).float().mean() < outlier_mask(r, quantile=0.8).float().mean()
    flat = torch.rand(64, 64, generator=torch.Generator().manual_seed(1))  # no structure: nothing masked
    assert outlier_mask(flat).float().mean() < 0.02


@pytest.mark.parametrize("bad", [0.0, 1.0, 1.5])
def test_quantile_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="quantile"):
        outlier_mask(_residual(), quantile=bad)


def test_masked_target_removes_the_outliers_from_l1():
    """Where the mask is set the target is the (detached) render: L1 sends no gradient from there, and the
    rest of the image keeps its gradient."""
    g = torch.Generator().manual_seed(2)
    gt = torch.rand(120, 160, 3, generator=g) * 0.2 + 0.4
    img = (gt + 0.02 * torch.randn(120, 160, 3, generator=g)).requires_grad_(True)
    with torch.no_grad():
        gt_moved = gt.clone()
        gt_moved[40:80, 60:110] = 1.0            # something in this photo only
    target, out = masked_target(img, gt_moved)
    assert out[44:76, 64:106].all() and out.float().mean() < 0.15
    assert torch.equal(target[out], img.detach()[out]) and torch.equal(target[~out], gt_moved[~out])
    photometric_loss(img, target, ssim_lambda=0.0).backward()
    grad = img.grad.abs().sum(-1)
    assert (grad[out] == 0).all() and (grad[~out] > 0).float().mean() > 0.99


@pytest.mark.parametrize("k", [3, 16])
def test_box_mean_matches_avg_pool(k):
    """The summed-area box mean equals torch's average pooling with the pixels outside the image left out."""
    x = torch.rand(50, 70, generator=torch.Generator().manual_seed(3))
    ref = torch.nn.functional.avg_pool2d(x[None, None], k, stride=1, padding=k // 2,
                                         count_include_pad=False)[0, 0, :50, :70]
    torch.testing.assert_close(_box_mean(x, k), ref, atol=1e-6, rtol=0)


def test_contrast_spares_a_photo_with_nothing_in_it():
    """A clean photo's worst-fitted region (residual 2x the rest) is not a distractor: left in at the default
    contrast, taken out without it."""
    g = torch.Generator().manual_seed(4)
    r = 0.02 + 0.01 * torch.rand(120, 160, generator=g)
    r[30:90, 40:120] *= 2.0
    assert not outlier_mask(r).any()
    assert outlier_mask(r, contrast=0.0)[35:85, 45:115].float().mean() > 0.9


@pytest.mark.parametrize("field,value", [("robust_quantile", 0.3), ("robust_quantile", 1.0), ("robust_quantile", -1.0),
                                         ("robust_start", 1.0), ("robust_start", -0.1)])
def test_bad_robust_options_are_refused(field, value):
    from splattwin.errors import InputError

    with pytest.raises(InputError, match=field.replace("_", "-")):
        TrainConfig(**{field: value}).check()


def test_trainer_leaves_a_distractor_out(tmp_path, monkeypatch):
    """One training photo shows a magenta square no other photo has. With the masks (from 30 % of the run)
    the steps on that photo leave most of the square out of the loss while the clean photos keep almost every
    pixel, and the model paints less of the square into that view than with the plain loss."""
    from splattwin.capture import load_dataset, load_image
    from splattwin.io import write_image
    from splattwin.splat import trainer as trainer_mod
    from splattwin.splat.trainer import Trainer
    from tests.splat.test_trainer import make_dataset, tiny_config

    root = make_dataset(tmp_path / "ds", n_train=8, n_heldout=1, width=96, height=72)
    f0 = load_dataset(root).train()[0]
    img = load_image(f0.image_path)
    img[20:52, 30:62] = [1.0, 0.0, 1.0]
    write_image(f0.image_path, (img * 255 + 0.5).astype(np.uint8))
    ds = load_dataset(root)
    square = torch.zeros(72, 96, dtype=torch.bool)
    square[20:52, 30:62] = True
    magenta = torch.tensor([1.0, 0.0, 1.0])

    calls: list[tuple[int, torch.Tensor]] = []

    def recording(img, gt, *a):
        target, out = masked_target(img, gt, *a)
        calls.append((next(i for i, v in enumerate(t.views) if v.image is gt), out))
        return target, out

    monkeypatch.setattr(trainer_mod, "masked_target", recording)
    to_magenta = {}
    for q in (0.0, 0.8):
        calls.clear()
        t = Trainer(ds, tmp_path / f"q{q}", tiny_config(iters=300, robust_quantile=q, robust_start=0.3))
        t._fresh_state()
        masked = []
        while t.step < t.cfg.iters:
            info = t.train_step()
            masked.append(info.get("masked"))
        with torch.no_grad():
            render, _, _ = t.render(0)
        to_magenta[q] = float((render[square] - magenta).abs().mean())
        if q == 0:
            plain = t
            assert not calls and masked == [None] * 300
            continue
        assert len(calls) == 210 and masked[:90] == [0.0] * 90          # from step 90 on, every step
        on_square = [float(out[square].float().mean()) for i, out in calls if i == 0]
        elsewhere = [float(out[~square].float().mean()) for i, out in calls if i == 0]
        clean = [float(out.float().mean()) for i, out in calls if i != 0]
        assert len(on_square) > 10
        assert np.median(on_square) > 0.8 and np.median(elsewhere) < 0.02, (on_square, elsewhere)
        assert np.median(clean) < 0.01
    assert to_magenta[0.8] > to_magenta[0.0] + 0.02, to_magenta
    # the record: a picture and the share per view; the painted view the most
    t._write_outputs(1.0, 0.0, 0.0)
    rec = json.loads((tmp_path / "q0.8" / "train.json").read_text())["transients"]
    from PIL import Image

    assert Image.open(tmp_path / "q0.8" / rec["image"]).size[0] == 4 * 256
    shares = rec["masked_share"]
    assert max(shares, key=shares.get) == t.views[0].name and shares[t.views[0].name] > 0.1
    (tmp_path / "q0.0").mkdir(exist_ok=True)
    (tmp_path / "q0.0" / "transients.png").write_bytes(b"stale")   # from an earlier run with the masks
    plain._write_outputs(1.0, 0.0, 0.0)
    assert json.loads((tmp_path / "q0.0" / "train.json").read_text())["transients"] is None
    assert not (tmp_path / "q0.0" / "transients.png").exists()
