"""Pure-torch twins of :func:`warpnerf.ops.raymarch.march_rays` and ``march_rays_within_budget``
(same names, signatures, results).

Vectorised over a dense (rays x candidate steps) table, so memory grows with the longest ray;
meant for tests and the kernel-vs-torch benchmark, not for training. Every float32 operation
is done in the kernel's order so that sample counts match the kernel exactly.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from warpnerf.ops.launch import aabb_floats
from warpnerf.ops.raymarch import MAX_STEPS_PER_RAY, MarchState, PackedSamples, _padded_box, rays_within_budget

__all__ = ["march_rays", "march_rays_within_budget", "march_rays_window"]


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
    contract: bool = False,
    occupied_box: Optional[Sequence[float]] = None,
    occupied_blocks: Optional[tuple] = None,
) -> PackedSamples:
    """See :func:`warpnerf.ops.raymarch.march_rays`; results are identical. ``occupied_box`` and
    ``occupied_blocks`` only let the Warp march skip candidates that are never samples: the twin
    marches them all."""
    if contract:
        return _march_rays_contracted(rays_o, rays_d, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                                      max_samples_per_ray, jitter)
    device = rays_o.device
    f32 = dict(dtype=torch.float32, device=device)
    res, occ_bitfield, box_min, box_max, grid_scale, near_t, far_t, step = _kernel_scalars(
        aabb, occ_bitfield, occ_resolution, near, far, step_size, device)
    num_rays = rays_o.shape[0]

    t0, t1, hit = _box_interval(rays_o, rays_d, box_min, box_max, near_t, far_t)

    u = jitter if jitter is not None else torch.zeros(num_rays, **f32)
    span = ((t1 - t0) / step)[hit]
    n_steps = min(int(torch.ceil(span.max()).item()) + 1, MAX_STEPS_PER_RAY) if span.numel() else 0
    k = torch.arange(n_steps, **f32)
    ts = t0[:, None] + (k[None, :] + u[:, None]) * step
    te = torch.minimum(ts + step, t1[:, None])
    mid = 0.5 * (ts + te)
    g = (rays_o[:, None, :] + rays_d[:, None, :] * mid[..., None] - box_min) * grid_scale
    keep = hit[:, None] & (ts < t1[:, None]) & _occupied(g, res, occ_bitfield)
    keep &= torch.cumsum(keep.int(), 1) <= int(max_samples_per_ray)

    counts = keep.sum(1, dtype=torch.int32)
    offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).int()
    ray_ids, step_ids = keep.nonzero(as_tuple=True)
    return PackedSamples(ray_ids.int(), ts[ray_ids, step_ids], te[ray_ids, step_ids], offsets, counts)


def _box_interval(rays_o, rays_d, box_min, box_max, near_t, far_t):
    """kernels/raymarch.py ``ray_aabb_interval`` and the kernel's guards: (t0, t1, hit), where
    non-finite rays or intervals are misses."""
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
    hit &= torch.isfinite(rays_o).all(1) & torch.isfinite(rays_d).all(1) & torch.isfinite(t0) & torch.isfinite(t1)
    return t0, t1, hit


def march_rays_window(rays_o, rays_d, state: MarchState, window: int, aabb, occ_bitfield, occ_resolution, near, far,
                      step_size, max_samples_per_ray: int = 1024, contract: bool = False, occupied_box=None,
                      occupied_blocks=None):
    """See :func:`warpnerf.ops.raymarch.march_rays_window`; same results and state updates
    (rows past ``counts[r]`` are zero here). One candidate step of every ray at a time."""
    device = rays_o.device
    f32 = dict(dtype=torch.float32, device=device)
    res, occ_bitfield, box_min, box_max, grid_scale, near_t, far_t, step = _kernel_scalars(
        aabb, occ_bitfield, occ_resolution, near, far, step_size, device)
    num_rays, window, cap = rays_o.shape[0], int(window), int(max_samples_per_ray)
    if contract:
        t0, t1 = near_t.expand(num_rays), far_t.expand(num_rays)
        ok = (torch.isfinite(rays_o).all(1) & torch.isfinite(rays_d).all(1) & (rays_d != 0.0).any(1)
              & torch.isfinite(t0) & torch.isfinite(t1) & (t1 > t0))
    else:
        t0, t1, ok = _box_interval(rays_o, rays_d, box_min, box_max, near_t, far_t)
    k = state.k.long()
    if not contract:
        f32b = lambda v: torch.tensor(v, dtype=torch.float32, device=device)
        tight_lo, tight_hi = _padded_box(occupied_box, *aabb_floats(aabb))
        tt0, tt1, _ = _box_interval(rays_o, rays_d, f32b(tight_lo), f32b(tight_hi), near_t, far_t)
        usable = ok & torch.isfinite(t0) & torch.isfinite(t1)
        t1 = torch.where(usable & (tt1 > tt0), torch.minimum(t1, tt1 + step), t1)
        start = torch.clamp_min(torch.floor((tt0 - t0) / step - 0.5).long() - 1, 0)
        k = torch.where(usable & (tt1 > tt0) & (k == 0), start, k)
        ok = ok & (tt1 > tt0)
    k = torch.where(ok, k, torch.full_like(k, -1))
    taken = state.taken.long()
    ts = state.t.clone()
    limit = torch.clamp_max(cap - taken, window)
    n = torch.zeros(num_rays, dtype=torch.int64, device=device)
    t_starts = torch.zeros(num_rays, window, **f32)
    t_ends = torch.zeros(num_rays, window, **f32)
    rows = torch.arange(num_rays, device=device)
    while True:
        active = (k >= 0) & (n < limit)
        if not contract:
            ts = torch.where(active, t0 + k.float() * step, ts)
        done = active & ((k >= MAX_STEPS_PER_RAY) | (ts >= t1))
        k = torch.where(done, torch.full_like(k, -1), k)
        active &= ~done
        if not bool(active.any()):
            break
        if contract:
            te = torch.minimum(ts + _contracted_step(rays_o, rays_d, ts, step), t1)
            p = _contract_point(rays_o + rays_d * (0.5 * (ts + te))[:, None])
        else:
            te = torch.minimum(ts + step, t1)
            p = rays_o + rays_d * (0.5 * (ts + te))[:, None]
        keep = active & _occupied((p - box_min) * grid_scale, res, occ_bitfield)
        idx = keep.nonzero().squeeze(1)
        t_starts[rows[idx], n[idx]] = ts[idx]
        t_ends[rows[idx], n[idx]] = te[idx]
        n += keep.long()
        ts = torch.where(active, te, ts)
        k = torch.where(active, k + 1, k)
    live = state.k >= 0
    k = torch.where(live & ok & (taken + n >= cap), torch.full_like(k, -1), k)
    state.k.copy_(torch.where(live, k, state.k.long()).int())
    state.t.copy_(torch.where(live & ok, ts, state.t))
    state.taken.copy_(torch.where(live & ok, taken + n, taken).int())
    return t_starts, t_ends, n.int()


def _kernel_scalars(aabb, occ_bitfield, occ_resolution, near, far, step_size, device):
    """The kernels' scalar inputs as float32 tensors (the kernel receives them rounded to float32),
    and the one always-occupied cell standing in for a missing grid:
    (res, bitfield, box_min, box_max, grid_scale, near, far, step)."""
    lo, hi = aabb_floats(aabb)
    f32 = dict(dtype=torch.float32, device=device)
    res = int(occ_resolution)
    if occ_bitfield is None:
        res = 1
        occ_bitfield = torch.ones(1, dtype=torch.uint8, device=device)
    box_min, box_max = torch.tensor(lo, **f32), torch.tensor(hi, **f32)
    grid_scale = torch.tensor([res / (h - l) for l, h in zip(lo, hi)], **f32)
    near_t, far_t, step = (torch.tensor(float(v), **f32) for v in (near, far, step_size))
    return res, occ_bitfield, box_min, box_max, grid_scale, near_t, far_t, step


def _occupied(g: torch.Tensor, res: int, occ_bitfield: torch.Tensor) -> torch.Tensor:
    """(...) bool: grid coordinates ``g`` (..., 3) lie in [0, res)^3 and in an occupied cell
    (kernels/occupancy.py ``cell_index``)."""
    inside = ((g >= 0.0) & (g < float(res))).all(-1)
    cell = torch.floor(torch.where(inside[..., None], g, torch.zeros_like(g))).long()
    flat = (cell[..., 0] * res + cell[..., 1]) * res + cell[..., 2]
    return inside & (occ_bitfield[flat] != 0)


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
    contract: bool = False,
    occupied_box: Optional[Sequence[float]] = None,
    occupied_blocks: Optional[tuple] = None,
) -> tuple[PackedSamples, int]:
    """See :func:`warpnerf.ops.raymarch.march_rays_within_budget`; results are identical."""
    packed = march_rays(rays_o, rays_d, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                        max_samples_per_ray, jitter, contract)
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


def _sqrt(x: torch.Tensor) -> torch.Tensor:
    """Correctly rounded float32 sqrt, as the kernel's ``sqrtf``: torch's vectorised float32 sqrt
    can be one ulp off; float64 sqrt rounded to float32 is exact (53 >= 2 * 24 + 2 bits)."""
    return torch.sqrt(x.double()).float()


def _contracted_step(o: torch.Tensor, d: torch.Tensor, t: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """kernels/raymarch.py ``contracted_step``, same float32 operation order."""
    p = o + d * t[:, None]
    r2 = p[:, 0] * p[:, 0] + p[:, 1] * p[:, 1] + p[:, 2] * p[:, 2]
    outside = r2 > 1.0
    r2o = torch.where(outside, r2, torch.ones_like(r2))
    r = _sqrt(r2o)
    dr = (d[:, 0] * p[:, 0] + d[:, 1] * p[:, 1] + d[:, 2] * p[:, 2]) / r
    a = dr / r2o
    s = (2.0 - 1.0 / r) / r
    b2 = torch.clamp_min(1.0 - dr * dr, 0.0)
    return torch.where(outside, step / _sqrt(a * a + b2 * (s * s)), step.expand_as(r2))


def _contract_point(p: torch.Tensor) -> torch.Tensor:
    """kernels/raymarch.py ``contract_point``, same float32 operation order."""
    r2 = p[:, 0] * p[:, 0] + p[:, 1] * p[:, 1] + p[:, 2] * p[:, 2]
    r = _sqrt(torch.where(r2 <= 1.0, torch.ones_like(r2), r2))
    return torch.where((r2 <= 1.0)[:, None], p, p * ((2.0 - 1.0 / r) / r)[:, None])


def _march_rays_contracted(rays_o, rays_d, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                           max_samples_per_ray, jitter) -> PackedSamples:
    """The contracted march, one step of every ray at a time (the steps are sequential per ray)."""
    device = rays_o.device
    f32 = dict(dtype=torch.float32, device=device)
    res, occ_bitfield, box_min, box_max, grid_scale, near_t, far_t, step = _kernel_scalars(
        aabb, occ_bitfield, occ_resolution, near, far, step_size, device)
    num_rays = rays_o.shape[0]
    t0 = near_t.expand(num_rays).clone()
    t1 = far_t.expand(num_rays).clone()
    active = (torch.isfinite(rays_o).all(1) & torch.isfinite(rays_d).all(1) & (rays_d != 0.0).any(1)
              & torch.isfinite(t0) & torch.isfinite(t1) & (t1 > t0))
    u = jitter if jitter is not None else torch.zeros(num_rays, **f32)
    ts = t0 + u * _contracted_step(rays_o, rays_d, t0, step)
    n = torch.zeros(num_rays, dtype=torch.int64, device=device)
    out_ray, out_ts, out_te, out_k = [], [], [], []
    k = 0
    while k < MAX_STEPS_PER_RAY:
        active &= (n < int(max_samples_per_ray)) & (ts < t1)
        if not bool(active.any()):
            break
        te = torch.minimum(ts + _contracted_step(rays_o, rays_d, ts, step), t1)
        mid = 0.5 * (ts + te)
        g = (_contract_point(rays_o + rays_d * mid[:, None]) - box_min) * grid_scale
        keep = active & _occupied(g, res, occ_bitfield)
        idx = keep.nonzero().squeeze(1)
        out_ray.append(idx)
        out_ts.append(ts[idx])
        out_te.append(te[idx])
        out_k.append(torch.full_like(idx, k))
        n += keep.long()
        ts = torch.where(active, te, ts)
        k += 1
    if out_ray:
        ray, t_s, t_e, kk = (torch.cat(v) for v in (out_ray, out_ts, out_te, out_k))
        order = torch.argsort(ray * MAX_STEPS_PER_RAY + kk)  # packed by ray, then along the ray
        ray, t_s, t_e = ray[order], t_s[order], t_e[order]
    else:
        ray, t_s, t_e = torch.zeros(0, dtype=torch.int64, device=device), torch.zeros(0, **f32), torch.zeros(0, **f32)
    counts = n.int()
    offsets = (torch.cumsum(counts, 0, dtype=torch.int32) - counts).int()
    return PackedSamples(ray.int(), t_s, t_e, offsets, counts)
