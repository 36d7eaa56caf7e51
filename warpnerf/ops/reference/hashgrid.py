"""Pure-torch twin of :func:`warpnerf.ops.hashgrid.hashgrid_encode` (same name, same signature).

Vectorised, differentiated by torch autograd. It is the baseline of ``warpnerf bench encoding``
and the reference of ``tests/ops/test_hashgrid.py``; it favours clarity over speed.
"""

from __future__ import annotations

import itertools

import torch

from warpnerf.ops.hashgrid_spec import HASH_PRIMES, HashGridSpec


def _level_rows(corner: torch.Tensor, spec: HashGridSpec, m: int) -> torch.Tensor:
    """Table rows of integer grid corners (N, D) int64 at level m."""
    s = spec.resolutions[m]
    if spec.hashed[m]:
        h = torch.zeros_like(corner[:, 0])
        for d in range(spec.dim):
            h = h ^ ((corner[:, d] * HASH_PRIMES[d]) & 0xFFFFFFFF)
        local = h & (spec.table_size - 1)
    else:
        local = torch.zeros_like(corner[:, 0])
        stride = 1
        for d in range(spec.dim):
            local = local + corner[:, d] * stride
            stride *= s
    return local + spec.offsets[m]


def hashgrid_encode(x: torch.Tensor, table: torch.Tensor, spec: HashGridSpec, level_weights: torch.Tensor | None = None,
                    known_output: torch.Tensor | None = None) -> torch.Tensor:
    """Encode points x (N, D) in [0, 1] (clamped) with table (rows, F) -> (N, L*F).

    Level m's features are multiplied by ``level_weights[m]`` (G²fR mask, eq. 15).
    ``known_output`` (the Warp op's shortcut for an output computed earlier) is accepted and
    ignored: the twin always computes.
    """
    n = x.shape[0]
    feats = []
    xc = x.clamp(0.0, 1.0)
    for m in range(spec.n_levels):
        w = 1.0 if level_weights is None else level_weights[m]
        if level_weights is not None and float(w) == 0.0:
            # a masked level contributes exact zeros; skipping it keeps the benchmark baseline fair
            feats.append(torch.zeros(n, spec.n_features, dtype=table.dtype, device=table.device))
            continue
        s = spec.resolutions[m]
        pos = xc * (s - 1)
        # the last cell is closed on the right: x = 1 lands at fraction 1 of cell s-2
        base = pos.detach().floor().long().clamp(0, s - 2)
        frac = pos - base.to(pos.dtype)
        acc = torch.zeros(n, spec.n_features, dtype=table.dtype, device=table.device)
        for bits in itertools.product((0, 1), repeat=spec.dim):
            corner = base + torch.tensor(bits, device=x.device)
            wgt = torch.ones(n, dtype=x.dtype, device=x.device)
            for d, b in enumerate(bits):
                wgt = wgt * (frac[:, d] if b else 1.0 - frac[:, d])
            acc = acc + wgt[:, None] * table[_level_rows(corner, spec, m)]
        feats.append(acc * w)
    return torch.cat(feats, dim=1)
