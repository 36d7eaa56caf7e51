"""Pure-torch twins of :func:`warpnerf.ops.raymarch.march_rays` and ``march_rays_within_budget``
(same names, signatures, results).

Vectorised over a dense (rays x candidate steps) table, so memory grows with the longest ray;
meant for tests and the kernel-vs-torch benchmark, not for training. Every float32 operation
is done in the kernel's order so that sample counts match the kernel exactly.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from ..launch import aabb_floats
from ..raymarch import MAX_STEPS_PER_RAY, PackedSamples, rays_within_budget

__all__ = ["march_rays", "march_rays_within_budget"]


def march_rays(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb: Sequence[float],
    occ_bitfield: Optional[torch.Tensor],
    occ_resolution: int,
    near: float,
    far: float,
    step_size: float,
    max_samples_per_ray: int = 1024,
    jitter: Optional[torch.Tensor] = None,
) -> PackedSamples:
    """See :func:`warpnerf.ops.raymarch.march_rays`; results are identical."""
    lo, hi = aabb_floats(aabb)
    device = rays_o.device
    f32 = dict(dtype=torch.float32, device=device)
    res = int(occ_resolution)
    if occ_bitfield is None:
        res = 1
        occ_bitfield = torch.ones(1, dtype=torch.uint8, device=device)
    # scalars as float32 tensors: the kernel receives them rounded to float32
    box_min, box_max = torch.tensor(lo, **f32), torch.tensor(hi, **f32)
    grid_scale = torch.tensor([res / (h - l) for l, h in zip(lo, hi)], **f32)
    near_t, far_t, step = (torch.tensor(float(v), **f32) for v in (near, far, step_size))
    num_rays = rays_o.shape[0]

    t0 = near_t.expand(num_rays).clone()
    t1 = far_t.expand(num_rays).clone()
    for a in range(3):
        o, d = rays_o[:, a], rays_d[:, a]
        flat = d == 0.0
        safe_d = torch.where(flat, torch.ones_like(d), d)
        ta = (box_min[a] - o) / safe_d
        tb = (box_max[a] - o) / safe_d
        t0 = torch.where(flat, t0, torch.maximum(t0, torch.minimum(ta, tb)))
        t1 = torch.where(flat, t1, torch.minimum(t1, torch.maximum(ta, tb)))
        t1 = torch.where(flat & ((o < box_min[a]) | (o > box_max[a])), t0, t1)
    hit = (t1 > t0) & (rays_d != 0.0).any(1)
    # the kernel's guards: non-finite rays or intervals are misses, at most MAX_STEPS_PER_RAY steps
    hit &= torch.isfinite(rays_o).all(1) & torch.isfinite(rays_d).all(1) & torch.isfinite(t0) & torch.isfinite(t1)

    u = jitter if jitter is not None else torch.zeros(num_rays, **f32)
    span = ((t1 - t0) / step)[hit]
    n_steps = min(int(torch.ceil(span.max()).item()) + 1, MAX_STEPS_PER_RAY) if span.numel() else 0
    k = torch.arange(n_steps, **f32)
    ts = t0[:, None] + (k[None, :] + u[:, None]) * step
    te = torch.minimum(ts + step, t1[:, None])
    mid = 0.5 * (ts + te)
    g = (rays_o[:, None, :] + rays_d[:, None, :] * mid[..., None] - box_min) * grid_scale
    inside = ((g >= 0.0) & (g < float(res))).all(-1)
    cell = torch.floor(torch.where(inside[..., None], g, torch.zeros_like(g))).long()
    flat_cell = (cell[..., 0] * res + cell[..., 1]) * res + cell[..., 2]
    keep = hit[:, None] & (ts < t1[:, None]) & inside & (occ_bitfield[flat_cell] != 0)
    keep &= torch.cumsum(keep.int(), 1) <= int(max_samples_per_ray)

    counts = keep.sum(1, dtype=torch.int32)
    offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).int()
    ray_ids, step_ids = keep.nonzero(as_tuple=True)
    return PackedSamples(ray_ids.int(), ts[ray_ids, step_ids], te[ray_ids, step_ids], offsets, counts)


def march_rays_within_budget(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb: Sequence[float],
    occ_bitfield: Optional[torch.Tensor],
    occ_resolution: int,
    near: float,
    far: float,
    step_size: float,
    max_samples_per_ray: int = 1024,
    jitter: Optional[torch.Tensor] = None,
    max_total_samples: Optional[int] = None,
) -> tuple[PackedSamples, int]:
    """See :func:`warpnerf.ops.raymarch.march_rays_within_budget`; results are identical."""
    packed = march_rays(rays_o, rays_d, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                        max_samples_per_ray, jitter)
    if max_total_samples is None:
        return packed, rays_o.shape[0]
    if int(max_total_samples) < 1:
        raise ValueError(f"march_rays: max_total_samples must be >= 1, got {max_total_samples}")
    # samples are packed in ray order: the kept prefix of rays owns a prefix of the samples
    keep = rays_within_budget(packed.ray_counts, int(max_total_samples))
    counts = packed.ray_counts.clone()
    counts[keep:] = 0
    total = int(counts.sum(dtype=torch.int64))
    offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).int()
    return PackedSamples(packed.ray_indices[:total], packed.t_starts[:total], packed.t_ends[:total], offsets,
                         counts), keep
