"""Pure-torch twin of :func:`warpnerf.ops.composite.composite_rays` (same name and signature).

Vectorised with a dense (rays x longest ray) table for the per-ray cumulative sums; gradients
come from torch autograd, which is what the hand-written Warp backward is tested against.
"""

from __future__ import annotations

from typing import Sequence, Union

import torch

from warpnerf.ops.composite import TRANSMITTANCE_EPS
from warpnerf.ops.raymarch import prefix_rows

__all__ = ["composite_rays", "active_sample_counts"]


def composite_rays(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_offsets: torch.Tensor,
    ray_counts: torch.Tensor,
    background: Union[Sequence[float], torch.Tensor] = (1.0, 1.0, 1.0),
    transmittance_eps: float = TRANSMITTANCE_EPS,
    return_weights: bool = False,
):
    """See :func:`warpnerf.ops.composite.composite_rays`; same outputs, autograd gradients."""
    num_rays, num_samples = ray_offsets.shape[0], sigmas.shape[0]
    ray, idx, s, tau = _optical_depths(sigmas, t_starts, t_ends, ray_offsets, ray_counts)
    trans = torch.exp(-tau)
    w = torch.where(trans >= transmittance_eps, trans * (1.0 - torch.exp(-s)), torch.zeros_like(s))

    opacity = s.new_zeros(num_rays).index_add(0, ray, w)
    depth = s.new_zeros(num_rays).index_add(0, ray, w * (0.5 * (t_starts[idx] + t_ends[idx])))
    color = s.new_zeros(num_rays, 3).index_add(0, ray, w[:, None] * rgbs[idx])
    if isinstance(background, torch.Tensor):
        bg = background.detach()
    else:
        bg = torch.tensor(background, dtype=s.dtype, device=s.device)
    rgb = color + (1.0 - opacity)[:, None] * bg
    if not return_weights:
        return rgb, opacity, depth
    return rgb, opacity, depth, s.new_zeros(num_samples).index_put((idx,), w)


def active_sample_counts(
    sigmas: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_offsets: torch.Tensor,
    ray_counts: torch.Tensor,
    transmittance_eps: float = TRANSMITTANCE_EPS,
) -> torch.Tensor:
    """See :func:`warpnerf.ops.composite.active_sample_counts`; the transmittance from a per-ray
    cumulative sum (equal to the kernel's running product up to rounding)."""
    num_rays = ray_offsets.shape[0]
    ray, _, _, tau = _optical_depths(sigmas.detach(), t_starts, t_ends, ray_offsets, ray_counts)
    active = (torch.exp(-tau) >= transmittance_eps).long()  # a prefix of each ray: tau only grows
    return torch.zeros(num_rays, dtype=torch.long, device=sigmas.device).index_add(0, ray, active).int()


def _optical_depths(sigmas, t_starts, t_ends, ray_offsets, ray_counts):
    """Per packed sample in ray order: its ray, its row, s = sigma * delta, and the exclusive per-ray
    sum of s before it (from a dense rays x longest-ray table)."""
    num_rays = ray_offsets.shape[0]
    ray, idx = prefix_rows(ray_offsets, ray_counts)
    local = idx - ray_offsets.long()[ray]
    s = sigmas[idx] * (t_ends[idx] - t_starts[idx])
    longest = int(ray_counts.max()) if num_rays else 0
    dense = s.new_zeros(num_rays, longest + 1).index_put((ray, local + 1), s)
    return ray, idx, s, torch.cumsum(dense, 1)[:, :-1][ray, local]
