"""The ops: torch autograd wrappers around the Warp kernels (``kernels/``), one module per op family.

The functional API, importable from here: the grid encodings (:func:`hashgrid_encode` with
:class:`HashGridSpec`, :func:`cpgrid_encode` with :class:`CPGridSpec`), ray marching through the
occupancy grid into packed samples (:func:`march_rays`, :func:`march_rays_within_budget`,
:func:`march_rays_window`) and volume compositing along them (:func:`composite_rays`). Each has a
pure-torch twin of the same name and signature in :mod:`warpnerf.ops.reference`.

Importing this package loads torch, not Warp: Warp and the kernels load (and compile, once per
machine) with the first launch.
"""

from warpnerf.ops.composite import TRANSMITTANCE_EPS, active_sample_counts, composite_rays
from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines
from warpnerf.ops.hashgrid import hashgrid_encode
from warpnerf.ops.hashgrid_spec import HashGridSpec
from warpnerf.ops.raymarch import (MarchState, PackedSamples, march_rays, march_rays_window,
                                   march_rays_within_budget)

__all__ = [
    "CPGridSpec",
    "HashGridSpec",
    "MarchState",
    "PackedSamples",
    "TRANSMITTANCE_EPS",
    "active_sample_counts",
    "composite_rays",
    "cpgrid_encode",
    "hashgrid_encode",
    "init_cp_lines",
    "march_rays",
    "march_rays_window",
    "march_rays_within_budget",
]
