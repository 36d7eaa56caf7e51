"""Pure-torch twin of :func:`warpnerf.ops.composite.composite_rays` (same name and signature).

Vectorised with a dense (rays x longest ray) table for the per-ray cumulative sums; gradients
come from torch autograd, which is what the hand-written Warp backward is tested against.
"""

from __future__ import annotations

from typing import Sequence, Union

import torch

from ..composite import TRANSMITTANCE_EPS

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
    counts = ray_counts.long()
    ray = torch.repeat_interleave(torch.arange(num_rays, device=sigmas.device), counts)
    local = torch.arange(ray.shape[0], device=sigmas.device) - (torch.cumsum(counts, 0) - counts)[ray]
    idx = ray_offsets.long()[ray] + local

    delta = t_ends[idx] - t_starts[idx]
    s = sigmas[idx] * delta
    longest = int(counts.max()) if num_rays else 0
    dense = s.new_zeros(num_rays, longest + 1).index_put((ray, local + 1), s)
    tau = torch.cumsum(dense, 1)[:, :-1][ray, local]  # exclusive per-ray sum of s
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
    counts = ray_counts.long()
    ray = torch.repeat_interleave(torch.arange(num_rays, device=sigmas.device), counts)
    local = torch.arange(ray.shape[0], device=sigmas.device) - (torch.cumsum(counts, 0) - counts)[ray]
    idx = ray_offsets.long()[ray] + local
    s = (sigmas[idx] * (t_ends[idx] - t_starts[idx])).detach()
    longest = int(counts.max()) if num_rays else 0
    dense = s.new_zeros(num_rays, longest + 1).index_put((ray, local + 1), s)
    tau = torch.cumsum(dense, 1)[:, :-1][ray, local]  # exclusive per-ray sum of s
    active = (torch.exp(-tau) >= transmittance_eps).long()  # a prefix of each ray: tau only grows
    return torch.zeros(num_rays, dtype=torch.long, device=sigmas.device).index_add(0, ray, active).int()
