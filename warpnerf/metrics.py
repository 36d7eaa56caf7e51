"""Image-quality metrics: PSNR, SSIM and (when its weights are already on disk) LPIPS.

Images are (H, W, C) or (N, H, W, C) float tensors in [0, 1] (the layout of
:class:`warpnerf.data.scene.Views`). For a batch, PSNR and SSIM are computed per image and then
averaged, which is how NeRF papers report them.

SSIM follows Wang et al. 2004 with the settings every NeRF paper quotes: gaussian window 11x11,
sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, per channel then averaged. Two border treatments:

* ``padding="valid"`` (default): only windows fully inside the image, i.e. skimage's
  ``structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1, channel_axis=-1)`` and the JaxNeRF / mip-NeRF ``compute_ssim``;
* ``padding="zero"``: zero padding and a mean over all pixels, i.e. pohsun's ``pytorch-ssim``,
  which BARF's evaluation uses. It reads slightly lower near the borders.
"""

from __future__ import annotations

import math
import os
from typing import Optional

import torch
import torch.nn.functional as F


def _as_batch(x: torch.Tensor) -> torch.Tensor:
    """(H, W, C) or (N, H, W, C) -> (N, C, H, W)."""
    if x.dim() == 3:
        x = x[None]
    if x.dim() != 4:
        raise ValueError(f"expected (H, W, C) or (N, H, W, C) images, got shape {tuple(x.shape)}")
    return x.permute(0, 3, 1, 2)


def psnr_from_mse(mse) -> float:
    """PSNR in dB for a mean squared error of images in [0, 1] (peak 1); ``inf`` for MSE 0."""
    mse = float(mse)
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Peak signal-to-noise ratio, dB, of images in [0, 1]: ``-10 log10(MSE)``.

    pred, gt: (H, W, C) or (N, H, W, C). The MSE is taken in float64 over each image; for a
    batch the per-image PSNRs are averaged. Identical images give ``inf``.
    """
    p = _as_batch(pred.detach()).to(torch.float64)
    g = _as_batch(gt.detach()).to(torch.float64)
    mse = (p - g).square().flatten(1).mean(1)
    return float((-10.0 * torch.log10(mse)).mean())


def gaussian_window_1d(size: int = 11, sigma: float = 1.5, dtype=torch.float64) -> torch.Tensor:
    """Normalised 1-D gaussian taps (size,), centred; the 2-D SSIM window is its outer product."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return (g / g.sum()).to(dtype)


def _blur(x: torch.Tensor, g: torch.Tensor, pad: int) -> torch.Tensor:
    """Separable gaussian filter of x (B, 1, H, W): rows then columns, zero padding ``pad``."""
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k), padding=(0, pad))
    return F.conv2d(x, g.view(1, 1, k, 1), padding=(pad, 0))


def ssim_map(
    pred: torch.Tensor,
    gt: torch.Tensor,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    data_range: float = 1.0,
    padding: str = "valid",
) -> torch.Tensor:
    """Per-pixel SSIM map (N, C, H', W') of pred, gt (H, W, C) or (N, H, W, C).

    H' = H - window + 1 for ``padding="valid"``, H for ``"zero"``. Differentiable; computed in
    the input dtype (use float64 for reference values).
    """
    if padding not in ("valid", "zero"):
        raise ValueError(f"padding must be 'valid' or 'zero', got {padding!r}")
    p, q = _as_batch(pred), _as_batch(gt)
    n, c, h, w = p.shape
    if padding == "valid" and (h < window or w < window):
        raise ValueError(f"image {h}x{w} is smaller than the {window}x{window} SSIM window")
    g = gaussian_window_1d(window, sigma, p.dtype).to(p.device)
    pad = 0 if padding == "valid" else window // 2
    # All five local moments through one filter call: channels are folded into the batch.
    stack = torch.cat([p, q, p * p, q * q, p * q], 0).reshape(5 * n * c, 1, h, w)
    blurred = _blur(stack, g, pad)
    mu_p, mu_q, e_pp, e_qq, e_pq = blurred.reshape(5, n, c, *blurred.shape[-2:]).unbind(0)
    # Population (not sample) covariances, as in the paper and skimage's use_sample_covariance=False.
    var_p = e_pp - mu_p * mu_p
    var_q = e_qq - mu_q * mu_q
    cov = e_pq - mu_p * mu_q
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    num = (2 * mu_p * mu_q + c1) * (2 * cov + c2)
    den = (mu_p * mu_p + mu_q * mu_q + c1) * (var_p + var_q + c2)
    return num / den


def ssim(pred: torch.Tensor, gt: torch.Tensor, padding: str = "valid") -> float:
    """Structural similarity (unitless, 1 = identical) of images in [0, 1].

    pred, gt: (H, W, C) or (N, H, W, C), at least 11x11 for ``padding="valid"``. Gaussian 11x11
    window, sigma 1.5, K1 0.01, K2 0.03, data range 1; mean over pixels and channels per image,
    then over images. Evaluated in float64. See the module docstring for ``padding``.
    """
    m = ssim_map(pred.detach().to(torch.float64), gt.detach().to(torch.float64), padding=padding)
    return float(m.flatten(1).mean(1).mean())


_LPIPS_MODEL = None
_LPIPS_TRIED = False


def _torchvision_alexnet_cached() -> bool:
    """True if torchvision's ImageNet AlexNet checkpoint is already in the torch hub cache
    (lpips' backbone loads it from there and would otherwise download it)."""
    # The exact file name torchvision's AlexNet_Weights.IMAGENET1K_V1 url resolves to; if it is
    # present, torch.hub.load_state_dict_from_url reads it instead of downloading.
    return os.path.isfile(os.path.join(torch.hub.get_dir(), "checkpoints", "alexnet-owt-7be5be79.pth"))


def _load_lpips():
    """The LPIPS(alex) network if the ``lpips`` package, its linear-layer weights and the AlexNet
    backbone weights are all installed locally; None otherwise. Never downloads anything."""
    global _LPIPS_MODEL, _LPIPS_TRIED
    if _LPIPS_TRIED:
        return _LPIPS_MODEL
    _LPIPS_TRIED = True
    try:
        import lpips  # noqa: F401  (optional dependency)
    except Exception:
        return None
    lin = os.path.join(os.path.dirname(lpips.__file__), "weights", "v0.1", "alex.pth")
    if not (os.path.isfile(lin) and _torchvision_alexnet_cached()):
        return None
    try:
        model = lpips.LPIPS(net="alex", verbose=False)
    except Exception:
        return None
    _LPIPS_MODEL = model.eval()
    return _LPIPS_MODEL


def lpips_or_none(pred: torch.Tensor, gt: torch.Tensor) -> Optional[float]:
    """LPIPS (AlexNet, lower is better) of images in [0, 1], or None when its pretrained weights
    are not available offline (the usual case here; results then report LPIPS as null).

    pred, gt: (H, W, 3) or (N, H, W, 3); for a batch the per-image values are averaged.
    """
    model = _load_lpips()
    if model is None:
        return None
    p = _as_batch(pred.detach()).float().cpu() * 2 - 1  # LPIPS expects [-1, 1]
    q = _as_batch(gt.detach()).float().cpu() * 2 - 1
    with torch.no_grad():
        d = model(p, q)
    return float(d.mean())


__all__ = ["psnr", "psnr_from_mse", "ssim", "ssim_map", "gaussian_window_1d", "lpips_or_none"]
