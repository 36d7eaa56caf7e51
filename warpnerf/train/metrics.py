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

import importlib.util
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


# ---- LPIPS (AlexNet, v0.1) -----------------------------------------------------------------------
#
# The ``lpips`` package builds its AlexNet trunk with torchvision, and PyPI's torchvision does not
# import beside every torch build (torch 2.13.0+cpu here). So the computation lives here in plain
# torch, with the same layers, layer names and formula as ``lpips.LPIPS(net="alex", version="0.1")``
# (checked in tests/train/test_lpips.py against the lpips package's own forward, on random trunk weights),
# and only the *weights* come from outside. Nothing is ever downloaded.
#
# Weights (both are needed; see docs/outputs.md):
#   trunk: torchvision's ImageNet AlexNet checkpoint ``alexnet-owt-7be5be79.pth`` (keys features.N.*)
#   lin:   lpips' calibrated 1x1 layers ``lpips/weights/v0.1/alex.pth`` (keys linK.model.1.weight),
#          shipped inside the lpips wheel (``pip install 'warpnerf[metrics]'`` or ``pip install --no-deps lpips``)
# or one file with a full ``lpips.LPIPS(net="alex").state_dict()`` (keys net.sliceK.N.*, linK.model.1.weight).

ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"  # torchvision's AlexNet_Weights.IMAGENET1K_V1 file name
_ALEX_CONVS = {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1), 8: (384, 256, 3, 1, 1),
               10: (256, 256, 3, 1, 1)}  # index in torchvision's alexnet.features -> (in, out, kernel, stride, pad)
_ALEX_TAPS = (1, 4, 7, 9, 11)  # the ReLUs whose outputs LPIPS compares (lpips' slice1..slice5 ends)


class AlexNetTrunk(torch.nn.Module):
    """torchvision's ``alexnet().features`` up to relu5 (same indices, so its state dict loads);
    ``forward`` returns the five ReLU outputs LPIPS compares."""

    def __init__(self):
        super().__init__()
        layers = []
        for i in range(12):
            if i in _ALEX_CONVS:
                cin, cout, k, st, pad = _ALEX_CONVS[i]
                layers.append(torch.nn.Conv2d(cin, cout, k, st, pad))
            elif i in (2, 5):
                layers.append(torch.nn.MaxPool2d(3, 2))
            else:
                layers.append(torch.nn.ReLU(inplace=False))
        self.features = torch.nn.Sequential(*layers)
        self.channels = (64, 192, 384, 256, 256)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _ALEX_TAPS:
                out.append(x)
        return out


class LPIPSNet(torch.nn.Module):
    """LPIPS v0.1: a trunk's feature maps, unit-normalised over channels, squared differences
    weighted by one 1x1 conv per tap, averaged over pixels and summed over taps.

    Args:
        trunk: module mapping (N, 3, H, W) scaled images to a list of (N, C_k, H_k, W_k) maps and
            with a ``channels`` tuple (default :class:`AlexNetTrunk`; tests pass a tiny stand-in).
    """

    def __init__(self, trunk: Optional[torch.nn.Module] = None):
        super().__init__()
        self.trunk = trunk if trunk is not None else AlexNetTrunk()
        self.lins = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in self.trunk.channels)
        # lpips' ScalingLayer: ImageNet statistics in the [-1, 1] input range
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) images in [-1, 1] -> (N,) distances."""
        f0 = self.trunk((x0 - self.shift) / self.scale)
        f1 = self.trunk((x1 - self.shift) / self.scale)
        total = 0.0
        for a, b, lin in zip(f0, f1, self.lins):
            a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((a - b) ** 2).mean((2, 3))
        return total[:, 0]

    def load_lpips_state(self, state: dict) -> None:
        """Load trunk and/or linear weights from torchvision (``features.N.*``), lpips
        (``net.sliceK.N.*``, ``linK.model.1.weight``) or this class's own key names."""
        own = {}
        for key, value in state.items():
            parts = key.split(".")
            if parts[0] == "features" and len(parts) == 3:
                own[f"trunk.features.{parts[1]}.{parts[2]}"] = value
            elif parts[0] == "net" and len(parts) == 4 and parts[1].startswith("slice"):
                own[f"trunk.features.{parts[2]}.{parts[3]}"] = value
            elif parts[0].startswith("lin") and parts[0][3:].isdigit() and parts[-1] == "weight":
                own[f"lins.{parts[0][3:]}.weight"] = value
            elif key in self.state_dict():  # our own names (lpips' duplicate lins.K.model.1.* never match)
                own[key] = value
        missing = set(self.state_dict()) - {"shift", "scale"} - set(own)
        self.load_state_dict({**self.state_dict(), **own})
        if len(missing) == len(self.state_dict()) - 2:
            raise ValueError("no LPIPS trunk or linear weights among the keys of this state dict")


def _trunk_keys(state: dict) -> bool:
    return any(k.startswith(("features.0.", "net.slice1.0.", "trunk.features.0.")) for k in state)


def _lin_keys(state: dict) -> bool:
    return any(k.startswith(("lin0.", "lins.0.")) for k in state)


def lpips_default_locations() -> tuple[str, Optional[str]]:
    """Where LPIPS(alex) looks without ``--lpips-weights``: (the trunk's path in torch hub's checkpoint
    folder, which may not exist; lpips' ``alex.pth`` if the lpips package is installed with it, else None).
    lpips is located, never imported; ``warpnerf doctor`` reports both."""
    lin = None
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin:
        cand = os.path.join(os.path.dirname(spec.origin), "weights", "v0.1", "alex.pth")
        lin = cand if os.path.isfile(cand) else None
    return os.path.join(torch.hub.get_dir(), "checkpoints", ALEXNET_CHECKPOINT), lin


def lpips_weight_files(path: str = "") -> Optional[list[str]]:
    """The weight files LPIPS(alex) would load, or None when they are not all on disk.

    ``path``: "" = look in the usual places (:func:`lpips_default_locations`: torch hub's checkpoint
    folder for the trunk, the installed lpips package for the linear layers); a file =
    a full LPIPS state dict, or a torchvision AlexNet checkpoint (linear layers then from lpips);
    a folder = holding ``alexnet-owt-7be5be79.pth`` and ``alex.pth``."""
    trunk, lin = lpips_default_locations()
    if not path:
        return [trunk, lin] if lin and os.path.isfile(trunk) else None
    if os.path.isdir(path):
        trunk, lin_here = os.path.join(path, ALEXNET_CHECKPOINT), os.path.join(path, "alex.pth")
        lin = lin_here if os.path.isfile(lin_here) else lin
        return [trunk, lin] if lin and os.path.isfile(trunk) else None
    if os.path.isfile(path):
        return [path] if lin is None else [path, lin]
    return None


def load_lpips_net(path: str = "") -> Optional[LPIPSNet]:
    """LPIPSNet(alex) with local weights (see :func:`lpips_weight_files`), or None if any are missing."""
    files = lpips_weight_files(path)
    if files is None:
        return None
    states = [torch.load(f, map_location="cpu", weights_only=True) for f in files]
    if not any(_trunk_keys(s) for s in states) or not any(_lin_keys(s) for s in states):
        return None
    net = LPIPSNet()
    for s in reversed(states):  # the explicit file last, so its keys win
        if _trunk_keys(s) or _lin_keys(s):
            net.load_lpips_state(s)
    return net.eval()


_LPIPS = {"path": "", "net": None, "loaded": False}


def configure_lpips(path: str = "", net: Optional[torch.nn.Module] = None) -> bool:
    """Choose LPIPS weights for :func:`lpips_or_none` (``path`` as in :func:`lpips_weight_files`),
    or a ready network ``net`` (tests use a stand-in). A ``path`` given but unusable is an error.
    Returns True when LPIPS will be computed."""
    _LPIPS.update(path=path, net=net, loaded=net is not None)
    if net is None and path:
        if load_lpips_net_cached() is None:
            raise ValueError(f"no usable LPIPS(alex) weights at '{path}': need torchvision's {ALEXNET_CHECKPOINT} "
                             "and lpips' alex.pth, or one full LPIPS state dict (see docs/outputs.md)")
    return load_lpips_net_cached() is not None


def load_lpips_net_cached() -> Optional[torch.nn.Module]:
    if not _LPIPS["loaded"]:
        _LPIPS["net"] = load_lpips_net(_LPIPS["path"])
        _LPIPS["loaded"] = True
    return _LPIPS["net"]


def lpips_or_none(pred: torch.Tensor, gt: torch.Tensor) -> Optional[float]:
    """LPIPS (AlexNet, v0.1, lower is better) of images in [0, 1], or None when its weights are
    not on disk (then results report LPIPS as null). Never downloads.

    pred, gt: (H, W, 3) or (N, H, W, 3); for a batch the per-image values are averaged.
    """
    net = load_lpips_net_cached()
    if net is None:
        return None
    p = _as_batch(pred.detach()).float().cpu() * 2 - 1  # LPIPS expects [-1, 1]
    q = _as_batch(gt.detach()).float().cpu() * 2 - 1
    with torch.no_grad():
        d = net(p, q)
    return float(d.mean())


__all__ = ["psnr", "psnr_from_mse", "ssim", "ssim_map", "gaussian_window_1d", "lpips_or_none", "configure_lpips",
           "LPIPSNet", "AlexNetTrunk", "load_lpips_net", "lpips_weight_files", "lpips_default_locations"]
