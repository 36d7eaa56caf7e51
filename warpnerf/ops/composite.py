"""``composite_rays``: volume rendering of packed samples (Warp forward + hand-written backward).

One thread per ray, in both directions; every output element belongs to one ray, so on CPU the
rays are split into fixed chunks on the thread pool (:func:`warpnerf.ops.launch.launch_over_rays`)
and the result does not depend on the thread count. The math and the gradient derivation are
in ``kernels/composite.py``.
"""

from __future__ import annotations

from typing import Sequence, Union

import torch

from warpnerf.device import init_warp
from warpnerf.ops.launch import as_warp, launch_over_rays, twin_dispatch

__all__ = ["composite_rays", "active_sample_counts", "TRANSMITTANCE_EPS"]

# default early-termination threshold on a ray's transmittance (the renderer's rounds use it too)
TRANSMITTANCE_EPS = 1e-4


@twin_dispatch
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
    """Alpha-composite packed samples front to back.

    With delta_i = t_end_i - t_start_i:
    alpha_i = 1 - exp(-sigma_i delta_i), T_i = prod_{j<i} (1 - alpha_j), w_i = T_i alpha_i.
    A ray stops once T_i < ``transmittance_eps``: that sample and all later ones get weight 0
    and zero gradient (the cut-off itself is not differentiated). Non-contiguous inputs are copied.

    Args:
        sigmas: (S,) float32 densities >= 0 (already activated), per unit of t. Differentiable.
        rgbs: (S, 3) float32 colours in [0, 1]. Differentiable.
        t_starts, t_ends: (S,) float32 sample intervals. Not differentiable.
        ray_offsets, ray_counts: (R,) int32; ray r owns samples [offset, offset + count)
            (as returned by :func:`warpnerf.ops.raymarch.march_rays`).
        background: 3 floats, or an (R, 3) float32 tensor, composited behind each ray with weight
            1 - opacity. Not differentiable.
        transmittance_eps: early-termination threshold on T (0 disables it).
        return_weights: also return the per-sample weights.

    Returns:
        ``(rgb, opacity, depth)`` or ``(rgb, opacity, depth, weights)``:
        rgb (R, 3), opacity (R,) = sum w_i, depth (R,) = sum w_i (t_start_i + t_end_i) / 2, the
        expected t *not* normalised by opacity (divide by opacity for the depth of the surface),
        weights (S,). All are differentiable w.r.t. ``sigmas``; rgb also w.r.t. ``rgbs``.

    Example:
        >>> sig = torch.tensor([0.0, 1e9]); col = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        >>> t0 = torch.tensor([0.0, 1.0]); t1 = torch.tensor([1.0, 2.0])
        >>> one = torch.tensor([0], dtype=torch.int32), torch.tensor([2], dtype=torch.int32)
        >>> rgb, opacity, depth = composite_rays(sig, col, t0, t1, *one)
        >>> rgb.tolist(), opacity.tolist(), depth.tolist()
        ([[1.0, 0.0, 0.0]], [1.0], [1.5])
    """
    bg_tensor, bg_const = _check_inputs(sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, background)
    eps = float(transmittance_eps)
    if not eps >= 0.0:
        raise ValueError(f"composite_rays: transmittance_eps must be >= 0, got {transmittance_eps}")
    out = _CompositeRays.apply(
        sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor, bg_const, eps, bool(return_weights)
    )
    return out if return_weights else out[:3]


@twin_dispatch
def active_sample_counts(
    sigmas: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    ray_offsets: torch.Tensor,
    ray_counts: torch.Tensor,
    transmittance_eps: float = TRANSMITTANCE_EPS,
) -> torch.Tensor:
    """(R,) int32: per ray, the samples :func:`composite_rays` gives a weight (or a gradient), i.e.
    those before the ray's transmittance fell below ``transmittance_eps``; the rest of the ray
    weighs exactly 0. Compositing only the first ``count`` samples of each ray gives the same
    outputs as compositing all of them. Not differentiable (a count); arguments as in
    :func:`composite_rays`.

    Example:
        >>> sig = torch.tensor([0.0, 1e9, 5.0]); t0 = torch.tensor([0.0, 1.0, 2.0]); t1 = t0 + 1.0
        >>> active_sample_counts(sig, t0, t1, torch.tensor([0], dtype=torch.int32),
        ...                      torch.tensor([3], dtype=torch.int32)).tolist()
        [2]
    """
    # the checks of composite_rays (an expanded zero view stands in for the colours)
    _check_inputs(sigmas, sigmas.new_zeros(1, 3).expand(sigmas.shape[0], 3), t_starts, t_ends, ray_offsets,
                  ray_counts, (0.0, 0.0, 0.0), op="active_sample_counts")
    eps = float(transmittance_eps)
    if not eps >= 0.0:
        raise ValueError(f"active_sample_counts: transmittance_eps must be >= 0, got {transmittance_eps}")
    num_rays = ray_offsets.shape[0]
    counts = torch.zeros(num_rays, dtype=torch.int32, device=sigmas.device)
    if num_rays:
        init_warp()
        from warpnerf.kernels.composite import composite_active_counts  # lazy: Warp loads with the first launch, not with the op's module

        sigmas, t_starts, t_ends = (t.detach().contiguous() for t in (sigmas, t_starts, t_ends))
        inputs = [as_warp(sigmas), as_warp(t_starts), as_warp(t_ends), as_warp(ray_offsets.contiguous()),
                  as_warp(ray_counts.contiguous()), eps, as_warp(counts)]
        launch_over_rays(composite_active_counts, num_rays, inputs, sigmas.device)
    return counts


def _check_inputs(sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, background, op="composite_rays"):
    named = dict(
        sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends, ray_offsets=ray_offsets, ray_counts=ray_counts
    )
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{op}: {name} must be a torch tensor, got {type(t).__name__}")
        want = torch.int32 if name.startswith("ray_") else torch.float32
        if t.dtype != want:
            raise TypeError(f"{op}: {name} must be {want}, got {t.dtype}")
        if t.device != sigmas.device:
            raise ValueError(f"{op}: {name} is on {t.device} but sigmas is on {sigmas.device}")
    if sigmas.dim() != 1 or ray_offsets.dim() != 1:
        raise ValueError(
            f"{op}: sigmas must be (S,) and ray_offsets (R,), "
            f"got {tuple(sigmas.shape)} and {tuple(ray_offsets.shape)}"
        )
    num_samples, num_rays = sigmas.shape[0], ray_offsets.shape[0]
    shapes = dict(rgbs=(num_samples, 3), t_starts=(num_samples,), t_ends=(num_samples,), ray_counts=(num_rays,))
    for name, shape in shapes.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"{op}: {name} must have shape {shape}, got {tuple(named[name].shape)}")
    # out-of-range segments would make the kernels read and write outside the sample arrays
    ends = ray_offsets.long() + ray_counts.long()
    if num_rays and not bool(((ray_offsets >= 0) & (ray_counts >= 0) & (ends <= num_samples)).all()):
        raise ValueError(
            f"{op}: every [ray_offset, ray_offset + ray_count) must lie inside [0, {num_samples}]"
        )

    if isinstance(background, torch.Tensor) and background.dim() == 2:
        if background.dtype != torch.float32:
            raise TypeError(f"{op}: background must be float32, got {background.dtype}")
        if tuple(background.shape) != (num_rays, 3):
            raise ValueError(
                f"{op}: a background tensor must have shape ({num_rays}, 3), got {tuple(background.shape)}"
            )
        if background.device != sigmas.device:
            raise ValueError(f"{op}: background is on {background.device} but sigmas is on {sigmas.device}")
        return background.detach(), None
    bg = background.detach().cpu().tolist() if isinstance(background, torch.Tensor) else list(background)
    if len(bg) != 3:
        raise ValueError(f"{op}: background must be 3 floats or an (R, 3) tensor, got {background!r}")
    return None, tuple(float(c) for c in bg)


def _launch_inputs(wp, sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor, bg_const, eps):
    """The leading kernel arguments shared by the forward and backward kernels."""
    if bg_tensor is None:
        bg_arr = as_warp(sigmas.new_zeros(1, 3), wp.vec3)
        bg_vec = wp.vec3(*bg_const)
    else:
        bg_arr = as_warp(bg_tensor, wp.vec3)
        bg_vec = wp.vec3(0.0)
    return [
        as_warp(sigmas),
        as_warp(rgbs, wp.vec3),
        as_warp(t_starts),
        as_warp(t_ends),
        as_warp(ray_offsets),
        as_warp(ray_counts),
        bg_arr,
        int(bg_tensor is not None),
        bg_vec,
        eps,
    ]


class _CompositeRays(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor, bg_const, eps, return_weights):
        num_rays = ray_offsets.shape[0]
        rgb = sigmas.new_zeros(num_rays, 3)
        opacity = sigmas.new_zeros(num_rays)
        depth = sigmas.new_zeros(num_rays)
        weights = sigmas.new_zeros(sigmas.shape[0])
        if num_rays:
            wp = init_warp()
            from warpnerf.kernels.composite import composite_rays_fwd  # lazy: Warp loads with the first launch, not with the op's module

            inputs = _launch_inputs(
                wp, sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor, bg_const, eps
            )
            outputs = [as_warp(rgb, wp.vec3), as_warp(opacity), as_warp(depth), as_warp(weights)]
            launch_over_rays(composite_rays_fwd, num_rays, inputs + outputs, sigmas.device)
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            ctx.save_for_backward(sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor)
            ctx.bg_const, ctx.eps, ctx.return_weights = bg_const, eps, return_weights
        return rgb, opacity, depth, weights

    @staticmethod
    def backward(ctx, grad_rgb, grad_opacity, grad_depth, grad_weights):
        sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor = ctx.saved_tensors
        grad_sigmas = torch.zeros_like(sigmas)
        grad_rgbs = torch.zeros_like(rgbs)
        num_rays = ray_offsets.shape[0]
        if num_rays:
            wp = init_warp()
            from warpnerf.kernels.composite import composite_rays_bwd  # lazy: Warp loads with the first launch, not with the op's module

            inputs = _launch_inputs(
                wp, sigmas, rgbs, t_starts, t_ends, ray_offsets, ray_counts, bg_tensor, ctx.bg_const, ctx.eps
            )
            cotangents = [
                as_warp(grad_rgb, wp.vec3),
                as_warp(grad_opacity),
                as_warp(grad_depth),
                as_warp(grad_weights),
                int(ctx.return_weights),
            ]
            outputs = [as_warp(grad_sigmas), as_warp(grad_rgbs, wp.vec3)]
            launch_over_rays(composite_rays_bwd, num_rays, inputs + cotangents + outputs, sigmas.device)
        return (
            grad_sigmas if ctx.needs_input_grad[0] else None,
            grad_rgbs if ctx.needs_input_grad[1] else None,
            None, None, None, None, None, None, None, None,
        )
