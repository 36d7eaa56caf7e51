"""Tests for warpnerf.train.metrics: PSNR, SSIM (against a float64 direct-sum reference), LPIPS fallback."""

import importlib.util
import math

import numpy as np
import pytest
import torch

from warpnerf.train import metrics as M


def _image(h=24, w=29, seed=0, dtype=torch.float32):
    """A smooth image plus texture, in [0, 1], (H, W, 3)."""
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([x, y, 0.5 * (x + y)], -1)
    return (0.7 * base + 0.3 * torch.rand(h, w, 3, generator=g)).to(dtype)


def test_psnr_of_known_mse():
    gt = torch.zeros(8, 8, 3, dtype=torch.float64)  # 0.1 is not exact in float32
    assert abs(M.psnr(torch.full_like(gt, 0.1), gt) - 20.0) < 1e-9  # MSE 1e-2 -> 20 dB
    assert abs(M.psnr(torch.full_like(gt, 0.01), gt) - 40.0) < 1e-9
    assert abs(M.psnr_from_mse(1e-3) - 30.0) < 1e-12
    assert math.isinf(M.psnr_from_mse(0.0))
    # A batch averages per-image PSNRs (20 and 40 dB), not the PSNR of the pooled MSE.
    batch = torch.stack([torch.full_like(gt, 0.1), torch.full_like(gt, 0.01)])
    assert abs(M.psnr(batch, torch.zeros_like(batch)) - 30.0) < 1e-9
    assert math.isinf(M.psnr(gt, gt))


def test_gaussian_window():
    g = M.gaussian_window_1d(11, 1.5)
    assert g.shape == (11,)
    assert abs(g.sum().item() - 1) < 1e-15
    assert torch.equal(g, g.flip(0))
    assert abs((g[5] / g[6]).item() - math.exp(1 / (2 * 1.5**2))) < 1e-12


def test_ssim_identity_and_monotone_in_noise():
    x = _image()
    assert abs(M.ssim(x, x) - 1.0) < 1e-12
    assert abs(M.ssim(x, x, padding="zero") - 1.0) < 1e-12
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(x.shape, generator=g)
    values = [M.ssim((x + s * noise).clamp(0, 1), x) for s in (0.01, 0.05, 0.1, 0.3)]
    assert all(a > b for a, b in zip(values, values[1:]))
    assert values[0] < 1.0 and values[-1] < 0.5


def _ssim_reference(a: np.ndarray, b: np.ndarray, pad_zero: bool) -> float:
    """Direct float64 evaluation of the SSIM formula with an explicit 2-D 11x11 gaussian window
    (no separability, no conv): mean over pixels and channels."""
    r = np.arange(11) - 5.0
    g1 = np.exp(-r**2 / (2 * 1.5**2))
    win = np.outer(g1, g1)
    win /= win.sum()
    c1, c2 = 0.01**2, 0.03**2
    h, w, ch = a.shape
    if pad_zero:
        a = np.pad(a, ((5, 5), (5, 5), (0, 0)))
        b = np.pad(b, ((5, 5), (5, 5), (0, 0)))
        out_h, out_w = h, w
    else:
        out_h, out_w = h - 10, w - 10
    vals = []
    for c in range(ch):
        for i in range(out_h):
            for j in range(out_w):
                pa = a[i:i + 11, j:j + 11, c]
                pb = b[i:i + 11, j:j + 11, c]
                ma, mb = (win * pa).sum(), (win * pb).sum()
                va = (win * pa * pa).sum() - ma * ma
                vb = (win * pb * pb).sum() - mb * mb
                cov = (win * pa * pb).sum() - ma * mb
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma * ma + mb * mb + c1) * (va + vb + c2)))
    return float(np.mean(vals))


@pytest.mark.parametrize("padding", ["valid", "zero"])
def test_ssim_matches_float64_reference(padding):
    x = _image(20, 23, seed=2)
    g = torch.Generator().manual_seed(3)
    y = (x + 0.08 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    ref = _ssim_reference(x.double().numpy(), y.double().numpy(), pad_zero=padding == "zero")
    got = M.ssim(x, y, padding=padding)
    # ssim() evaluates in float64 with separable convolutions; measured difference 3e-16.
    assert abs(got - ref) < 1e-12
    assert 0.3 < got < 0.99  # a genuinely degraded image, not a trivial case


def test_ssim_batch_and_map_shapes():
    x = torch.stack([_image(seed=4), _image(seed=5)])
    y = x.flip(0)
    m = M.ssim_map(x, y)
    assert m.shape == (2, 3, 24 - 10, 29 - 10)
    assert M.ssim_map(x, y, padding="zero").shape == (2, 3, 24, 29)
    per_image = [M.ssim(x[i], y[i]) for i in range(2)]
    assert abs(M.ssim(x, y) - sum(per_image) / 2) < 1e-12
    with pytest.raises(ValueError):
        M.ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3))  # smaller than the 11x11 window


def test_ssim_map_is_differentiable():
    x = _image(16, 16, dtype=torch.float64)
    y = (x * 0.9).requires_grad_()
    M.ssim_map(x, y).mean().backward()
    assert torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0


def test_lpips_is_none_without_offline_weights():
    x = _image()
    out = M.lpips_or_none(x, x)
    if importlib.util.find_spec("lpips") is None:
        assert out is None
    else:  # package present: a number if its weights are cached, never a download
        assert out is None or out < 1e-3
