"""Regularisers on packed ray samples (pure torch: a few cumulative sums per step, not a hot loop).

:func:`distortion_loss` is mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15) in its
linear-time form: it pulls each ray's compositing weight into as short a stretch of the ray as
the pixels allow, which removes the thin haze a grid field otherwise leaves along rays (fern: the
rays reached transmittance 1e-4 only at their last sample, so neither rendering nor training
could stop early). Its weights are those of :func:`warpnerf.ops.composite.composite_rays`
(the same transmittance cut-off), recomputed with autograd.
"""

from __future__ import annotations

import torch

from warpnerf.ops.composite import TRANSMITTANCE_EPS
from warpnerf.ops.raymarch import PackedSamples

__all__ = ["packed_weights", "distortion_loss"]


def _exclusive_ray_cumsum(x: torch.Tensor, packed: PackedSamples) -> torch.Tensor:
    """Per sample, the sum of ``x`` over the samples before it on its ray (a ray's samples are
    contiguous in ``packed``), in float64 so that a long batch's running sum loses nothing."""
    x64 = x.double()
    run = torch.cumsum(x64, 0)
    first = packed.ray_offsets.long().index_select(0, packed.ray_indices.long())
    return (run - x64) - (run.index_select(0, first) - x64.index_select(0, first))


def packed_weights(sigmas: torch.Tensor, packed: PackedSamples,
                   transmittance_eps: float = TRANSMITTANCE_EPS) -> torch.Tensor:
    """(S,) compositing weights ``T_i (1 - exp(-sigma_i delta_i))`` of packed samples, 0 once
    ``T_i`` < ``transmittance_eps`` (as :func:`~warpnerf.ops.composite.composite_rays`);
    differentiable w.r.t. ``sigmas``.

    Example:
        >>> from warpnerf.ops.raymarch import PackedSamples
        >>> i32 = lambda *v: torch.tensor(v, dtype=torch.int32)
        >>> p = PackedSamples(i32(0, 0), torch.tensor([0.0, 1.0]), torch.tensor([1.0, 2.0]), i32(0), i32(2))
        >>> [round(w, 4) for w in packed_weights(torch.tensor([float("inf"), 1.0]), p).tolist()]
        [1.0, 0.0]
    """
    # an optical depth of 1e4 already leaves exp(-s) = 0; the clamp keeps the running sums finite
    # (exp activations may give inf) and exact enough in float64
    s = (sigmas.float() * (packed.t_ends - packed.t_starts)).clamp_max(1e4)
    trans = torch.exp(-_exclusive_ray_cumsum(s, packed)).float()
    return torch.where(trans >= transmittance_eps, trans * -torch.expm1(-s), torch.zeros_like(s))


def distortion_loss(weights: torch.Tensor, packed: PackedSamples, num_rays: int) -> torch.Tensor:
    """(num_rays,) mip-NeRF 360's distortion loss of each ray,

        sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (t1_i - t0_i),

    m the samples' midpoints, in the units of ``packed``'s t (the ray space's; mip-NeRF 360
    normalises t to [0, 1]: scale the loss weight to the scene's t range). Samples along a ray
    are in increasing t, so the double sum is 2 sum_i w_i (m_i W_<i - (w m)_<i) with per-ray
    prefix sums W_<i and (w m)_<i: linear time.

    Example (all the weight in one sample of length 1: only its own term, 1/3):
        >>> from warpnerf.ops.raymarch import PackedSamples
        >>> i32 = lambda *v: torch.tensor(v, dtype=torch.int32)
        >>> p = PackedSamples(i32(0, 0), torch.tensor([0.0, 1.0]), torch.tensor([1.0, 2.0]), i32(0), i32(2))
        >>> round(float(distortion_loss(torch.tensor([1.0, 0.0]), p, 1)), 4)
        0.3333
    """
    mid = 0.5 * (packed.t_starts + packed.t_ends)
    before_w = _exclusive_ray_cumsum(weights, packed)
    before_wm = _exclusive_ray_cumsum(weights * mid, packed)
    inter = 2.0 * weights.double() * (mid.double() * before_w - before_wm)
    intra = (weights * weights * (packed.t_ends - packed.t_starts)).double() / 3.0
    per_ray = weights.new_zeros(num_rays, dtype=torch.float64)
    return per_ray.index_add(0, packed.ray_indices.long(), inter + intra).float()
