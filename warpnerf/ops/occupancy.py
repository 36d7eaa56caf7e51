"""The occupancy grid's update kernels (``kernels/occupancy.py``) as thin torch ops (no gradient).

One function per kernel, same name, torch tensors in and out; the grid that strings them together
is :class:`warpnerf.model.occupancy.OccupancyGrid`. Each has a pure-torch twin of the same name in
:mod:`warpnerf.ops.reference.occupancy`.

Cell layout (shared with the marcher): grid coordinates g = (p - lo) * grid_scale, cell
floor(g) when 0 <= g < res on every axis, flat index (ix * res + iy) * res + iz. Boxes and
scales are given as 3 Python floats and reach the kernels rounded to float32.

Every op is one launch, never split across CPU threads (``occupancy_scatter_max``: several
samples may max into one cell; the max does not depend on the order).
"""

from __future__ import annotations

from typing import Sequence

import torch

from warpnerf.device import init_warp
from warpnerf.ops.launch import as_warp, launch, twin_dispatch

__all__ = ["occupancy_sample_points", "occupancy_scatter_max", "occupancy_ema", "occupancy_bitfield"]


@twin_dispatch
def occupancy_sample_points(cells: torch.Tensor, jitter: torch.Tensor, lo: Sequence[float],
                            cell_size: Sequence[float], res: int) -> torch.Tensor:
    """(M, 3) float32 world points ``lo + (ijk(cell) + jitter) * cell_size``: one point per picked cell.

    Args:
        cells: (M,) int32 flat cell indices in [0, res^3) (repeats allowed).
        jitter: (M, 3) float32 offsets in [0, 1)^3 inside each cell.
        lo: 3 floats, the grid's min corner; cell_size: 3 floats, (hi - lo) / res per axis.
        res: cells per axis.
    """
    _check(cells, torch.int32, 1, "cells")
    _check(jitter, torch.float32, 2, "jitter")
    wp = init_warp()
    from warpnerf.kernels import occupancy as kernels  # lazy: Warp loads with the first launch, not with the op's module

    points = torch.empty(cells.shape[0], 3, dtype=torch.float32, device=cells.device)
    launch(kernels.occupancy_sample_points, cells.shape[0],
           [as_warp(cells), as_warp(jitter, wp.vec3), wp.vec3(*lo), wp.vec3(*cell_size), int(res),
            as_warp(points, wp.vec3)], cells.device)
    return points


@twin_dispatch
def occupancy_scatter_max(points: torch.Tensor, sigmas: torch.Tensor, lo: Sequence[float],
                          grid_scale: Sequence[float], res: int, out: torch.Tensor) -> torch.Tensor:
    """``out[cell(p_i)] = max(out[cell(p_i)], sigmas[i])`` in place, for the points inside the grid.

    Args:
        points: (M, 3) float32 world points; sigmas: (M,) float32 their densities.
        lo: 3 floats, the grid's min corner; grid_scale: 3 floats, res / (hi - lo) per axis.
        res: cells per axis.
        out: (res^3,) float32, contiguous, updated in place (the grid pre-fills -1 = not sampled).
    Returns ``out``.
    """
    _check(points, torch.float32, 2, "points")
    _check(sigmas, torch.float32, 1, "sigmas")
    _check(out, torch.float32, 1, "out", inplace=True)
    wp = init_warp()
    from warpnerf.kernels import occupancy as kernels  # lazy: Warp loads with the first launch, not with the op's module

    launch(kernels.occupancy_scatter_max, points.shape[0],
           [as_warp(points, wp.vec3), as_warp(sigmas), wp.vec3(*lo), wp.vec3(*grid_scale), int(res), as_warp(out)],
           points.device)
    return out


@twin_dispatch
def occupancy_ema(fresh: torch.Tensor, decay: float, density: torch.Tensor) -> torch.Tensor:
    """``density = max(density * decay, fresh)`` in place where ``fresh >= 0`` (the sampled cells).

    ``fresh``, ``density``: (res^3,) float32, ``density`` contiguous. Returns ``density``."""
    _check(fresh, torch.float32, 1, "fresh")
    _check(density, torch.float32, 1, "density", inplace=True)
    init_warp()
    from warpnerf.kernels import occupancy as kernels  # lazy: Warp loads with the first launch, not with the op's module

    launch(kernels.occupancy_ema, density.shape[0], [as_warp(fresh), float(decay), as_warp(density)], density.device)
    return density


@twin_dispatch
def occupancy_bitfield(density: torch.Tensor, threshold: float, bitfield: torch.Tensor) -> torch.Tensor:
    """``bitfield = density > threshold`` (1 = occupied) in place.

    ``density``: (res^3,) float32; ``bitfield``: (res^3,) uint8, contiguous. Returns ``bitfield``."""
    _check(density, torch.float32, 1, "density")
    _check(bitfield, torch.uint8, 1, "bitfield", inplace=True)
    wp = init_warp()
    from warpnerf.kernels import occupancy as kernels  # lazy: Warp loads with the first launch, not with the op's module

    launch(kernels.occupancy_bitfield, density.shape[0], [as_warp(density), float(threshold),
                                                          as_warp(bitfield, wp.uint8)], density.device)
    return bitfield


def _check(t, dtype, dim: int, name: str, inplace: bool = False) -> None:
    if not isinstance(t, torch.Tensor) or t.dtype != dtype or t.dim() != dim or (dim == 2 and t.shape[1] != 3):
        shape = "(N,)" if dim == 1 else "(N, 3)"
        got = f"{tuple(t.shape)} {t.dtype}" if isinstance(t, torch.Tensor) else type(t).__name__
        raise TypeError(f"occupancy ops: {name} must be a {shape} {dtype} tensor, got {got}")
    if inplace and not t.is_contiguous():
        raise ValueError(f"occupancy ops: {name} is written in place and must be contiguous")
