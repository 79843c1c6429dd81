from __future__ import annotations

import numpy as np
import pytest
import torch

from splattwin.splat import metrics
from splattwin.splat.losses import photometric_loss, ssim, ssim_map


def numpy_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Straightforward float64 SSIM: explicit 11x11 Gaussian windows, valid positions only."""
    r = np.arange(11) - 5.0
    g = np.exp(-(r**2) / (2 * 1.5**2))
    w = np.outer(g, g)
    w /= w.sum()
    c1, c2 = 0.01**2, 0.03**2
    h, wd, ch = x.shape
    vals = []
    for c in range(ch):
        for i in range(h - 10):
            for j in range(wd - 10):
                a, b = x[i:i + 11, j:j + 11, c], y[i:i + 11, j:j + 11, c]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * a * a).sum() - ma**2, (w * b * b).sum() - mb**2
                cab = (w * a * b).sum() - ma * mb
                vals.append((2 * ma * mb + c1) * (2 * cab + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_psnr_known_values():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.2, 0.8, size=(16, 20, 3))
    assert metrics.psnr(ref, ref) == float("inf")
    assert metrics.psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-9)   # MSE 0.01
    assert metrics.psnr(ref - 0.01, ref) == pytest.approx(40.0, abs=1e-9)
    assert metrics.psnr(torch.tensor(ref + 0.1), torch.tensor(ref)) == pytest.approx(20.0, abs=1e-9)


def test_ssim_matches_numpy_reference():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0, 1, size=(18, 21, 3))
    img = np.clip(ref + rng.normal(0, 0.1, size=ref.shape), 0, 1)
    assert metrics.ssim(ref, ref) == pytest.approx(1.0, abs=1e-12)
    s = metrics.ssim(img, ref)
    assert s == pytest.approx(numpy_ssim(img, ref), abs=1e-10)
    assert 0.0 < s < 0.99
    with pytest.raises(ValueError):
        metrics.ssim(ref[:5], ref[:5])


def test_ssim_same_padding_shape_and_gradient():
    torch.manual_seed(0)
    x = torch.rand(1, 12, 13, 3, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 12, 13, 3, dtype=torch.float64)
    assert ssim_map(x, y, padding="same").shape == (1, 3, 12, 13)
    assert ssim_map(x, y, padding="valid").shape == (1, 3, 2, 3)
    assert torch.autograd.gradcheck(lambda a: ssim(a, y), (x,))


def test_photometric_loss_mix():
    torch.manual_seed(0)
    x, y = torch.rand(16, 16, 3), torch.rand(16, 16, 3)
    l1 = (x - y).abs().mean()
    expected = 0.8 * l1 + 0.2 * (1 - ssim(x, y))
    assert torch.allclose(photometric_loss(x, y, 0.2), expected)
    assert float(photometric_loss(y, y)) == pytest.approx(0.0, abs=1e-6)


def test_error_heatmap():
    ref = np.zeros((4, 5, 3))
    img = ref.copy()
    img[0, 0] = 1.0
    hm = metrics.error_heatmap(img, ref)
    assert hm.shape == (4, 5, 3) and hm.dtype == np.uint8
    assert tuple(hm[0, 0]) == (255, 255, 255) and tuple(hm[1, 1]) == (0, 0, 0)


@pytest.mark.parametrize("h,w", [(23, 31), (131, 67)])  # the second spans several row bands of the kernels
def test_fused_ssim_matches_torch_reference_and_gradient(h, w):
    from splattwin.splat.losses import fused_ssim
    torch.manual_seed(0)
    ref = torch.rand(h, w, 3)
    img = (ref + 0.15 * torch.randn(h, w, 3)).clamp(0, 1).requires_grad_(True)
    s = fused_ssim(img, ref)
    s.backward()
    img64 = img.detach().double().requires_grad_(True)
    s64 = ssim(img64, ref.double())
    s64.backward()
    assert float(s.detach()) == pytest.approx(float(s64.detach()), abs=1e-5)
    torch.testing.assert_close(img.grad.double(), img64.grad, atol=1e-6, rtol=1e-3)
    # finite difference on one pixel
    e = 1e-2
    p, m = img.detach().clone(), img.detach().clone()
    p[5, 7, 1] += e
    m[5, 7, 1] -= e
    fd = (float(ssim(p.double(), ref.double())) - float(ssim(m.double(), ref.double()))) / (2 * e)
    assert float(img.grad[5, 7, 1]) == pytest.approx(fd, rel=1e-2, abs=1e-6)


def test_masked_psnr_known_answers():
    from splattwin.splat.metrics import masked_psnr

    ref = np.zeros((4, 4, 3))
    img = ref.copy()
    img[:2] = 0.1                                  # error 0.1 on the top half only
    top = np.zeros((4, 4), bool)
    top[:2] = True
    assert masked_psnr(img, ref, top) == pytest.approx(20.0)
    assert masked_psnr(img, ref, ~top) == float("inf")
    assert np.isnan(masked_psnr(img, ref, np.zeros((4, 4), bool)))
    assert masked_psnr(img, ref, np.ones((4, 4), bool)) == pytest.approx(metrics.psnr(img, ref))


def test_an_8bit_photo_against_a_float_render_is_refused_not_scored():
    """psnr(render in [0,1], np.asarray(Image.open(photo))) read -41 dB and ssim 0.00007, silently, with a torch
    warning about the PIL array being read-only (api13 B2). Mixed integer / float images are a ValueError saying
    to divide by 255; two 8-bit images with max_val 255 still give their PSNR; SSIM takes floats only."""
    import warnings

    rng = np.random.default_rng(0)
    photo = rng.integers(0, 256, size=(16, 20, 3), dtype=np.uint8)
    photo.flags.writeable = False   # as np.asarray(PIL image)
    render = photo / 255.0
    for f in (metrics.psnr, metrics.ssim, lambda a, b: metrics.masked_psnr(a, b, np.ones((16, 20), bool)),
              lambda a, b: metrics.masked_ssim(a, b, np.ones((16, 20), bool))):
        with pytest.raises(ValueError, match=r"divide by 255"):
            f(render, photo)
        with pytest.raises(ValueError, match=r"^(masked_)?(psnr|ssim) .*img holds integers"):
            f(torch.as_tensor(photo.copy()), render)
    with pytest.raises(ValueError, match="ssim"):
        metrics.ssim(photo, photo)
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # no "non-writable" UserWarning from torch
        assert metrics.psnr(render, photo / 255.0) == float("inf")
        assert metrics.psnr(photo, np.clip(photo.astype(np.int64) + 1, 0, 255), max_val=255) > 40
        assert metrics.ssim(render, photo / 255.0) == pytest.approx(1.0)
