"""Pure-torch twin of :func:`warpnerf.ops.cpgrid.cpgrid_encode` (same name, same signature).

Vectorised over points, looping over levels and axes, differentiated by torch autograd. It is
the reference of ``tests/ops/test_cpgrid.py`` and a baseline for timing; it favours clarity over speed.
"""

from __future__ import annotations

import torch

from warpnerf.ops.cpgrid import CPGridSpec


def _interpolate_lines(lines: torch.Tensor, xc: torch.Tensor, spec: CPGridSpec, level: int, axis: int) -> torch.Tensor:
    """The R lines of ``level`` along ``axis`` read at the clamped coordinates xc[:, axis] -> (N, R)."""
    s = spec.resolutions[level]
    pos = xc[:, axis] * (s - 1)
    # the last cell is closed on the right: x = 1 lands at fraction 1 of cell s-2
    base = pos.detach().floor().long().clamp(0, s - 2)
    frac = (pos - base.to(pos.dtype))[:, None]
    rows = spec.offsets[level] + base
    return (1.0 - frac) * lines[rows, axis] + frac * lines[rows + 1, axis]


def cpgrid_encode(x: torch.Tensor, lines: torch.Tensor, spec: CPGridSpec, level_weights: torch.Tensor | None = None,
                  known_output: torch.Tensor | None = None) -> torch.Tensor:
    """Encode points x (N, 3) in [0, 1] (clamped) with lines (n_rows, 3, R) -> (N, L*R).

    Feature (l, r) is ``w_l * v^{l,x}_r(x) * v^{l,y}_r(y) * v^{l,z}_r(z)``, with
    ``w_l = level_weights[l]`` (G²fR mask); a level with weight 0 is skipped and gives zeros.
    ``known_output`` (the Warp op's shortcut for an output computed earlier) is accepted and
    ignored: the twin always computes.
    """
    n = x.shape[0]
    xc = x.clamp(0.0, 1.0)
    feats = []
    for level in range(spec.n_levels):
        w = 1.0 if level_weights is None else level_weights[level]
        if level_weights is not None and float(w) == 0.0:
            feats.append(torch.zeros(n, spec.rank, dtype=lines.dtype, device=lines.device))
            continue
        prod = _interpolate_lines(lines, xc, spec, level, 0)
        prod = prod * _interpolate_lines(lines, xc, spec, level, 1)
        prod = prod * _interpolate_lines(lines, xc, spec, level, 2)
        feats.append(prod * w)
    return torch.cat(feats, dim=1)
