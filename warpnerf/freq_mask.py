"""The G²fR level mask (paper eq. 15): which grid levels may speak at iteration t.

tau = M * min(t / (beta * T), 1) sweeps from 0 to the number of levels M over the first
``beta`` fraction of training. Level 1 is always on. Level i (1-based, i >= 2) fades in with
a cosine ramp, following BARF's coarse-to-fine schedule; the binary variant switches it on
at the end of its ramp.

Index convention (a deliberate deviation from the text of eq. 15): printed literally, eq. 15
ramps level i over i <= tau < i + 1, but tau never exceeds M, so the finest level M would keep
weight 0 for the whole run. We use BARF's 0-based form, where level i ramps over
i - 1 <= tau < i: w_i = (1 - cos((tau - i + 1) pi)) / 2. Every level is then fully on once
t >= beta T, which is the behaviour the paper describes.

The weights multiply each level's features inside the encoding kernel; a level whose weight
is 0 is skipped entirely (no table reads, no gradient).
"""

from __future__ import annotations

import math

import torch

from .config import G2FR_BETA

# the level ramps this module implements; the config's choices and checks read this registry
MASK_MODES = ("cosine", "binary")


def g2fr_tau(step: int, total_steps: int, n_levels: int, beta: float) -> float:
    """Optimisation progress tau in [0, n_levels] (paper eq. 15)."""
    if total_steps <= 0:
        raise ValueError(f"total_steps must be positive, got {total_steps}")
    if not 0.0 < beta <= 1.0:
        raise ValueError(f"g2fr beta must be in (0, 1], got {beta}")
    return n_levels * min(max(step, 0) / (beta * total_steps), 1.0)


def g2fr_level_weight(level: int, tau: float, mode: str = "cosine") -> float:
    """Weight w_i(tau) of the 1-based level ``level``."""
    if mode not in MASK_MODES:
        raise ValueError(f"unknown g2fr mask mode '{mode}': expected one of {MASK_MODES}")
    if level == 1:
        return 1.0
    ramp = tau - (level - 1)  # progress through this level's ramp (see the module docstring)
    if ramp < 0.0:
        return 0.0
    if ramp >= 1.0:
        return 1.0
    if mode == "binary":
        return 0.0
    return 0.5 * (1.0 - math.cos(ramp * math.pi))


def g2fr_weights(step: int, total_steps: int, n_levels: int, beta: float, mode: str = "cosine") -> torch.Tensor:
    """Per-level weights (n_levels,) float32 at iteration ``step`` of ``total_steps``."""
    tau = g2fr_tau(step, total_steps, n_levels, beta)
    return torch.tensor([g2fr_level_weight(i + 1, tau, mode) for i in range(n_levels)], dtype=torch.float32)


class G2fRSchedule:
    """Callable schedule: ``schedule(step) -> (n_levels,) weights``; all ones when disabled."""

    def __init__(self, n_levels: int, total_steps: int, beta: float = G2FR_BETA, mode: str = "cosine", enabled: bool = True):
        # validate once, up front, so a bad config fails before training starts
        g2fr_tau(0, total_steps, n_levels, beta)
        g2fr_level_weight(2, 0.0, mode)
        self.n_levels, self.total_steps, self.beta, self.mode, self.enabled = n_levels, total_steps, beta, mode, enabled

    def __call__(self, step: int) -> torch.Tensor:
        if not self.enabled:
            return torch.ones(self.n_levels, dtype=torch.float32)
        return g2fr_weights(step, self.total_steps, self.n_levels, self.beta, self.mode)

    def active_levels(self, step: int) -> int:
        return int((self(step) > 0).sum())
