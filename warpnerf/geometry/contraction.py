"""Scene contraction for unbounded (360°) captures: MipNeRF-360's ``contract`` (Barron et al. 2022, eq. 10).

    contract(x) = x                              if |x| <= 1
                  (2 - 1 / |x|) * x / |x|        otherwise

maps all of space into the ball of radius 2, is the identity inside the unit ball, continuous
with a continuous first derivative across |x| = 1, and sends points at distance r to radius
2 - 1/r: equal steps in disparity 1/r beyond the unit ball become equal steps in the contracted
space, which is why samples beyond the ball are spaced linearly in disparity
(:func:`disparity_spaced`). Normalised capture scenes (:mod:`warpnerf.data.normalize`) put the
cameras inside [-1, 1]^3, i.e. near the unit ball, as this assumes.

Used by the ``"contracted"`` ray space (:mod:`warpnerf.geometry.rayspace`, docs/design.md §6):
the renderer maps every marched sample through :func:`contract` before the field, the occupancy
grid covers the contracted box [-2, 2]^3, and the marcher (``march_rays(contract=True)``, the
same formula in ``kernels/raymarch.py``) takes steps of equal length in the contracted space
(world steps ~ ``step * |x|^2`` on rays leaving the scene).
"""

from __future__ import annotations

import torch


def contract(x: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """(..., 3) world points (normalised scene units) -> (..., 3) points in the ball of radius 2."""
    r = x.norm(dim=-1, keepdim=True)
    outside = r > 1.0
    r_safe = torch.where(outside, r, torch.ones_like(r)).clamp_min(eps)
    return torch.where(outside, (2.0 - 1.0 / r_safe) * x / r_safe, x)


def uncontract(y: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """Inverse of :func:`contract` for (..., 3) points with |y| < 2 (|y| -> 2 maps to infinity)."""
    r = y.norm(dim=-1, keepdim=True)
    outside = r > 1.0
    r_safe = torch.where(outside, r, torch.ones_like(r))
    return torch.where(outside, y / (r_safe * (2.0 - r_safe).clamp_min(eps)), y)


def disparity_spaced(t_split: float, far: float, n: int, dtype=torch.float32) -> torch.Tensor:
    """(n + 1,) sample boundaries from ``t_split`` to ``far`` (may be inf) equally spaced in 1 / t.

    Beyond the unit ball this makes samples equally spaced in the contracted space along a ray
    from the centre: 2 - 1/t is linear in 1/t.
    """
    s = torch.linspace(0.0, 1.0, n + 1, dtype=torch.float64)
    inv_far = 0.0 if far == float("inf") else 1.0 / far
    inv = (1.0 - s) / t_split + s * inv_far
    return (1.0 / inv.clamp_min(1e-12)).to(dtype)
