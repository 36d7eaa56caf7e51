"""``hashgrid_encode``: the Warp multi-resolution hash-grid encoding as a torch op.

Forward gathers D-linear interpolated features per level (level-major launches); backward
scatters into the table gradient and, when asked, returns the gradient with respect to the
input points. G²fR level weights (paper eq. 15) are applied inside the kernels: a level with
weight 0 is never launched, so it reads and writes no table memory and its output is 0.

Launches, the CPU thread split and the grad_x sums are :class:`warpnerf.ops.launch.GridLauncher`'s
(shared with the CP grid): forward split by points, backward by *levels* (each group scatters
into a disjoint table slice and its own dx buffer), thread-count independent, so 1- and
2-thread results are bit-identical. On CUDA each pass is a single launch on torch's stream.

Positions outside [0, 1]^D are clamped to the box (their gradient is 0, like ``torch.clamp``);
non-finite positions are an error.
"""

from __future__ import annotations

import torch

from warpnerf.device import init_warp
from warpnerf.ops.hashgrid_spec import SUPPORTED_DIMS, SUPPORTED_FEATURES, HashGridSpec
from warpnerf.ops.launch import (GridEncodeFunction, GridLauncher, check_grid_inputs, check_known_output, level_weight_values,
                                 twin_dispatch)

__all__ = ["hashgrid_encode", "HashGridSpec"]


@twin_dispatch
def hashgrid_encode(
    x: torch.Tensor, table: torch.Tensor, spec: HashGridSpec, level_weights=None,
    known_output: torch.Tensor | None = None,
) -> torch.Tensor:
    """Encode points with a multi-resolution hash grid.

    Args:
        x: (N, D) float32 (or float64) points, expected in [0, 1]^D; outside values are clamped.
            Differentiable (gradient 0 where clamped).
        table: (spec.n_rows, F) features of all levels, same dtype and device as ``x``. Differentiable.
        spec: the grid geometry (:class:`HashGridSpec`).
        level_weights: L G²fR weights w_m in [0, 1]: a host :class:`~warpnerf.model.g2fr.LevelWeights`
            or floats (read without touching the device), an (L,) tensor (read once: a sync on
            CUDA), or ``None`` for all ones. Not differentiable.
        known_output: optional, this call's output already computed without autograd (the
            renderer's first pass): returned as the output, with the usual backward, instead of
            encoding again. Checked for shape, dtype and device only.

    Returns:
        (N, L*F) features; columns [m*F, (m+1)*F) belong to level m and are scaled by w_m.

    Example:
        >>> spec = HashGridSpec.create(dim=3, n_levels=4, log2_table_size=12, base_resolution=4, max_resolution=32)
        >>> table = torch.randn(spec.n_rows, spec.n_features) * 1e-2
        >>> hashgrid_encode(torch.rand(5, 3), table, spec).shape
        torch.Size([5, 8])
    """
    values = _check_inputs(x, table, spec, level_weights)
    check_known_output("hashgrid_encode", known_output, x, spec.out_dim)
    return GridEncodeFunction.apply(x, table, values, _Launcher.get(spec, x.device, x.dtype), known_output)


def _check_inputs(x, table, spec, level_weights) -> tuple[float, ...]:
    check_grid_inputs("hashgrid_encode", x, table, "table", spec, HashGridSpec,
                      lambda s: (s.dim, (s.n_rows, s.n_features)))
    return level_weight_values("hashgrid_encode", level_weights, spec.n_levels)


def kernel_variant_specs():
    """One small spec per kernel variant the op can generate (every D and F it accepts), for
    :func:`warpnerf.ops.registry.kernel_modules`; the dtype is the other variant axis."""
    for dim in SUPPORTED_DIMS:
        for features in SUPPORTED_FEATURES:
            yield f"dim={dim} F={features}", HashGridSpec.create(dim, 1, features, 4, 2, 2)


class _Launcher(GridLauncher):
    """The hash grid's kernels and per-level metadata; launches are :class:`GridLauncher`'s."""

    op = "hashgrid_encode"

    @staticmethod
    def make_kernels(spec: HashGridSpec, wp_dtype):
        from warpnerf.kernels.hashgrid import make_hashgrid_kernels  # lazy: Warp loads with the first launch, not with the op's module

        return make_hashgrid_kernels(spec.dim, spec.n_features, wp_dtype)

    @staticmethod
    def metadata(spec: HashGridSpec):
        wp = init_warp()
        hashed = [int(h) for h in spec.hashed]
        return [spec.resolutions, spec.offsets[:-1], hashed], [wp.uint32(spec.table_size - 1)]
