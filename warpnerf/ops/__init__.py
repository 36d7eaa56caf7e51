"""The ops: torch autograd wrappers around the Warp kernels (``kernels/``), one module per op family.

The functional API, importable from here: the grid encodings (:func:`hashgrid_encode` with
:class:`HashGridSpec`, :func:`cpgrid_encode` with :class:`CPGridSpec`), ray marching through the
occupancy grid into packed samples (:func:`march_rays`, :func:`march_rays_within_budget`,
:func:`march_rays_window`), volume compositing along them (:func:`composite_rays`) and the
occupancy grid's update steps (:func:`occupancy_sample_points`, :func:`occupancy_scatter_max`,
:func:`occupancy_ema`, :func:`occupancy_bitfield`). Each has a pure-torch twin of the same name and
signature in :mod:`warpnerf.ops.reference`; ``with use_backend("torch"):`` runs every op on its twin
(:mod:`warpnerf.ops.registry`, which lists the ops in ``OPS``).

Importing this package loads torch, not Warp: Warp and the kernels load (and compile, once per
machine) with the first launch.
"""

from warpnerf.ops.composite import TRANSMITTANCE_EPS, active_sample_counts, composite_rays
from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines
from warpnerf.ops.hashgrid import hashgrid_encode
from warpnerf.ops.hashgrid_spec import HashGridSpec
from warpnerf.ops.occupancy import occupancy_bitfield, occupancy_ema, occupancy_sample_points, occupancy_scatter_max
from warpnerf.ops.raymarch import (MarchState, PackedSamples, march_rays, march_rays_window,
                                   march_rays_within_budget)
from warpnerf.ops.registry import current_backend, use_backend

__all__ = [
    "CPGridSpec",
    "HashGridSpec",
    "MarchState",
    "PackedSamples",
    "TRANSMITTANCE_EPS",
    "active_sample_counts",
    "composite_rays",
    "cpgrid_encode",
    "current_backend",
    "hashgrid_encode",
    "init_cp_lines",
    "march_rays",
    "march_rays_window",
    "march_rays_within_budget",
    "occupancy_bitfield",
    "occupancy_ema",
    "occupancy_sample_points",
    "occupancy_scatter_max",
    "use_backend",
]
