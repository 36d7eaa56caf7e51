"""Pure-torch twins of the occupancy-grid ops in :mod:`warpnerf.ops.occupancy` (same names, signatures).

Same float32 operations as ``kernels/occupancy.py``: the cell of a point, the max and the bitfield
are exactly the kernels'; the sample points equal them up to float rounding (a compiler may fuse
the kernel's multiply-add).
"""

from __future__ import annotations

from typing import Sequence

import torch

__all__ = ["occupancy_sample_points", "occupancy_scatter_max", "occupancy_ema", "occupancy_bitfield"]


def _vec3(v: Sequence[float], device) -> torch.Tensor:
    """3 floats rounded to float32, as the kernels receive them."""
    return torch.tensor([float(x) for x in v], dtype=torch.float32, device=device)


def occupancy_sample_points(cells: torch.Tensor, jitter: torch.Tensor, lo: Sequence[float],
                            cell_size: Sequence[float], res: int) -> torch.Tensor:
    """See :func:`warpnerf.ops.occupancy.occupancy_sample_points`."""
    res = int(res)
    c = cells.long()
    ijk = torch.stack([c // (res * res), (c // res) % res, c % res], dim=1).float()
    return _vec3(lo, cells.device) + (ijk + jitter) * _vec3(cell_size, cells.device)


def occupancy_scatter_max(points: torch.Tensor, sigmas: torch.Tensor, lo: Sequence[float],
                          grid_scale: Sequence[float], res: int, out: torch.Tensor) -> torch.Tensor:
    """See :func:`warpnerf.ops.occupancy.occupancy_scatter_max`."""
    res = int(res)
    g = (points - _vec3(lo, points.device)) * _vec3(grid_scale, points.device)
    inside = ((g >= 0.0) & (g < float(res))).all(1)  # NaN fails both tests, as in cell_index
    cell = torch.floor(g[inside]).long()
    flat = (cell[:, 0] * res + cell[:, 1]) * res + cell[:, 2]
    out.scatter_reduce_(0, flat, sigmas[inside], reduce="amax", include_self=True)
    return out


def occupancy_ema(fresh: torch.Tensor, decay: float, density: torch.Tensor) -> torch.Tensor:
    """See :func:`warpnerf.ops.occupancy.occupancy_ema`."""
    decayed = density * torch.tensor(float(decay), dtype=torch.float32, device=density.device)
    density.copy_(torch.where(fresh >= 0.0, torch.maximum(decayed, fresh), density))
    return density


def occupancy_bitfield(density: torch.Tensor, threshold: float, bitfield: torch.Tensor) -> torch.Tensor:
    """See :func:`warpnerf.ops.occupancy.occupancy_bitfield`."""
    bitfield.copy_(density > torch.tensor(float(threshold), dtype=torch.float32, device=density.device))
    return bitfield
