"""Geometry of a multi-resolution hash grid (Instant-NGP), shared by the Warp op and its twin.

Notation follows the G²fR paper: level m has ``s_m`` grid *points* per axis, an input
coordinate x in [0, 1] lands at ``(s_m - 1) * x`` in grid units, and the level's feature is
the D-linear interpolation of the 2^D surrounding grid points (paper eq. 9).

A level whose s_m^D points fit in the table size T is stored densely (index
x + s*y + s*s*z); a finer level is hashed into T slots with Instant-NGP's spatial hash
(x * 1) XOR (y * 2654435761) XOR (z * 805459861) mod T, computed in uint32.
All levels live in one flat (total_rows, F) table; ``offsets[m]`` is the first row of level m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

HASH_PRIMES = (1, 2654435761, 805459861)

# Input dimensions and feature counts the op supports. Warp generates one kernel pair per
# (D, F, dtype); keeping F to Instant-NGP's set (tiny-cuda-nn allows the same) makes the set of
# kernels finite, so tests/test_cuda_compile.py can compile every one of them for the GPU.
SUPPORTED_DIMS = (1, 2, 3)
SUPPORTED_FEATURES = (1, 2, 4, 8)


@dataclass(frozen=True)
class HashGridSpec:
    """Static description of a grid; build it with :meth:`create`."""

    dim: int  # input dimension D (1, 2 or 3)
    n_levels: int  # L
    n_features: int  # F per level
    log2_table_size: int  # T = 2**log2_table_size rows per hashed level
    resolutions: tuple[int, ...]  # s_m, grid points per axis, per level
    offsets: tuple[int, ...]  # first table row of each level, plus the total at the end
    hashed: tuple[bool, ...]  # level stored by hash (True) or densely (False)

    @staticmethod
    def create(
        dim: int = 3,
        n_levels: int = 16,
        n_features: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
    ) -> "HashGridSpec":
        """Levels grow geometrically from ``base_resolution`` to ``max_resolution`` points per axis."""
        if dim not in SUPPORTED_DIMS:
            raise ValueError(f"hash grid input dimension must be 1, 2 or 3, got {dim}")
        if n_levels < 1:
            raise ValueError(f"need n_levels >= 1, got {n_levels}")
        if n_features not in SUPPORTED_FEATURES:
            raise ValueError(f"hash grid features per level must be one of {SUPPORTED_FEATURES}, got {n_features}")
        if not 2 <= base_resolution <= max_resolution:
            raise ValueError(f"need 2 <= base_resolution <= max_resolution, got {base_resolution}, {max_resolution}")
        if not 4 <= log2_table_size <= 30:
            raise ValueError(f"log2_table_size must be in [4, 30], got {log2_table_size}")
        growth = 1.0 if n_levels == 1 else math.exp(math.log(max_resolution / base_resolution) / (n_levels - 1))
        table_size = 2**log2_table_size
        resolutions, offsets, hashed = [], [0], []
        for m in range(n_levels):
            # the small epsilon keeps exact powers (e.g. 16 * 2**k) from flooring one below
            s = max(2, int(math.floor(base_resolution * growth**m + 1e-6)))
            dense_size = s**dim
            resolutions.append(s)
            hashed.append(dense_size > table_size)
            offsets.append(offsets[-1] + min(dense_size, table_size))
        return HashGridSpec(dim, n_levels, n_features, log2_table_size, tuple(resolutions), tuple(offsets), tuple(hashed))

    @property
    def table_size(self) -> int:
        return 2**self.log2_table_size

    @property
    def n_rows(self) -> int:
        """Rows of the flat feature table."""
        return self.offsets[-1]

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features
