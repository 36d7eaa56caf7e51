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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:  # annotations only: torch itself loads when a tensor is asked for (see g2fr_weights)
    import torch

# G²fR beta: levels are switched on over the first beta * T steps (paper eq. 15). The paper gives
# no value; 0.5 is what the few-shot and pose presets were tuned with. This is the one default:
# TrainConfig, G2fRSchedule and the spectrum experiments all read it from here.
G2FR_BETA = 0.5

# the level ramps this module implements; the config's choices and checks read this registry
MASK_MODES = ("cosine", "binary")

# what moves tau: the step count (eq. 15, G2fRSchedule), the training loss (AdaptiveG2fRSchedule) or the
# PSNR of held-out val views (HeldoutG2fRSchedule)
SCHEDULES = ("fixed", "adaptive", "heldout")


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
    import torch  # lazy: the config imports this module for G2FR_BETA, and 'import warpnerf.cli' stays torch-free

    tau = g2fr_tau(step, total_steps, n_levels, beta)
    return torch.tensor([g2fr_level_weight(i + 1, tau, mode) for i in range(n_levels)], dtype=torch.float32)


@dataclass(frozen=True)
class LevelWeights:
    """The G²fR weights w_m of L grid levels as host floats, in [0, 1].

    What the trainer hands the encoders: an immutable host value, so the grid launchers decide
    which levels to launch without reading a device tensor (no CUDA sync per launch). ``to()``
    returns the value itself (it lives on no device), so code written for the tensor form works.

    Example:
        >>> w = LevelWeights((1.0, 0.5, 0.0))
        >>> w.active, len(w), w.as_tensor().tolist()
        ((0, 1), 3, [1.0, 0.5, 0.0])
    """

    values: tuple[float, ...]

    def __post_init__(self):
        vals = tuple(float(v) for v in self.values)
        if not all(0.0 <= v <= 1.0 for v in vals):  # also rejects NaN
            raise ValueError(f"level weights must lie in [0, 1], got {vals}")
        object.__setattr__(self, "values", vals)

    @classmethod
    def ones(cls, n_levels: int) -> "LevelWeights":
        return cls((1.0,) * n_levels)

    @property
    def active(self) -> tuple[int, ...]:
        """0-based ids of the levels with w_m > 0 (the only ones a kernel reads)."""
        return tuple(m for m, w in enumerate(self.values) if w > 0.0)

    def __len__(self) -> int:
        return len(self.values)

    def __iter__(self):
        return iter(self.values)

    def __getitem__(self, m):
        return self.values[m]

    def to(self, *args, **kwargs) -> "LevelWeights":
        return self

    def as_tensor(self, device=None, dtype: torch.dtype | None = None) -> torch.Tensor:
        """(L,) tensor of the weights, float32 unless ``dtype`` says otherwise (a host-to-device copy
        when ``device`` is a GPU)."""
        import torch  # lazy: see g2fr_weights

        return torch.tensor(self.values, dtype=torch.float32 if dtype is None else dtype, device=device)


class G2fRSchedule:
    """Callable schedule: ``schedule(step) -> (n_levels,) weights``; all ones when disabled.
    :meth:`level_weights` gives the same weights as a host :class:`LevelWeights`."""

    def __init__(self, n_levels: int, total_steps: int, beta: float = G2FR_BETA, mode: str = "cosine", enabled: bool = True):
        # validate once, up front, so a bad config fails before training starts
        g2fr_tau(0, total_steps, n_levels, beta)
        g2fr_level_weight(2, 0.0, mode)
        self.n_levels, self.total_steps, self.beta, self.mode, self.enabled = n_levels, total_steps, beta, mode, enabled

    def __call__(self, step: int) -> torch.Tensor:
        return self.level_weights(step).as_tensor()

    def level_weights(self, step: int) -> LevelWeights:
        """The weights of ``step`` as a host value (what the trainer passes to the field)."""
        if not self.enabled:
            return LevelWeights.ones(self.n_levels)
        tau = g2fr_tau(step, self.total_steps, self.n_levels, self.beta)
        return LevelWeights(tuple(g2fr_level_weight(i + 1, tau, self.mode) for i in range(self.n_levels)))

    def active_levels(self, step: int) -> int:
        return len(self.level_weights(step).active)

    def observe(self, step: int, loss: float) -> None:
        """Eq. 15 depends on the step alone: the loss is not used."""

    def wants_heldout(self, step: int) -> bool:
        """Whether the trainer should measure the held-out PSNR after ``step`` (:meth:`observe_heldout`)."""
        return False

    def observe_heldout(self, step: int, psnr: float) -> None:
        """The mean val PSNR (dB) after ``step``; only schedules that ask for it (:meth:`wants_heldout`) use it."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class AdaptiveG2fRSchedule(G2fRSchedule):
    """G²fR whose tau follows the fit, not a budget: a level opens when the levels already open have
    stopped paying off (not in the paper).

    Eq. 15 ties tau to ``t / (beta T)``, so the same mask regularises differently at 1000 and at 20k
    steps (docs/studies/2026-12-07-fewshot-regime.md). Here the trainer reports each step's training
    loss (:meth:`observe`). At the end of every ``window`` steps the window's mean loss is compared with
    the previous window's: its relative improvement is the window's *gain*. When a gain falls to ``tol``
    times the largest gain since the last level opened, the open levels count as fitted and the next
    level ramps in over the following ``window`` steps (cosine or binary, as in eq. 15). The test is a
    ratio, so it needs no loss scale. Level 1 is on from the start; tau starts at 1 (eq. 15's first unit
    of tau ramps no level). No total step count enters: runs of any length share the mask step by step.

    Example (a loss that stops improving opens a level each window):
        >>> s = AdaptiveG2fRSchedule(n_levels=4, window=2, tol=0.25)
        >>> for t in range(8):
        ...     s.observe(t, 1.0)
        >>> s.open_steps, s.active_levels(8)
        ([4, 6, 8], 3)
    """

    def __init__(self, n_levels: int, window: int = 10, tol: float = 0.5, mode: str = "cosine", enabled: bool = True):
        if window < 2:
            raise ValueError(f"adaptive g2fr window must be >= 2 steps, got {window}")
        if not 0.0 <= tol <= 1.0:
            raise ValueError(f"adaptive g2fr tol must be in [0, 1], got {tol}")
        g2fr_level_weight(2, 0.0, mode)
        self.n_levels, self.mode, self.enabled = n_levels, mode, enabled
        self.window, self.tol = int(window), float(tol)
        self.total_steps, self.beta = None, None  # no budget: that is the point
        self.open_steps: list[int] = []  # the step at which each level from 2 on began to ramp in
        self._sum, self._count, self._last, self._peak = 0.0, 0, None, 0.0

    def tau(self, step: int) -> float:
        """1 + each level opened by ``step``, ramping over ``window`` steps from its open step (the mask
        of any step the run has reached, not only the latest)."""
        return 1.0 + sum(min(max(step - s, 0) / self.window, 1.0) for s in self.open_steps)

    def level_weights(self, step: int) -> LevelWeights:
        if not self.enabled:
            return LevelWeights.ones(self.n_levels)
        tau = self.tau(step)
        return LevelWeights(tuple(g2fr_level_weight(i + 1, tau, self.mode) for i in range(self.n_levels)))

    def observe(self, step: int, loss: float) -> None:
        """Add one step's training loss; at the end of a window, open the next level if the loss has stopped
        improving at the pace it had since the last level opened."""
        if not self.enabled or len(self.open_steps) >= self.n_levels - 1:
            return
        self._sum += float(loss)
        self._count += 1
        if self._count < self.window:
            return
        mean = self._sum / self._count
        self._sum, self._count = 0.0, 0
        if self._last is not None:
            gain = (self._last - mean) / max(self._last, 1e-30)  # this window's relative improvement
            self._peak = max(self._peak, gain)
            if gain <= self.tol * self._peak:
                self.open_steps.append(step + 1)
                self._peak = 0.0
        self._last = mean

    def state_dict(self) -> dict:
        return {"open_steps": list(self.open_steps), "sum": self._sum, "count": self._count, "last": self._last,
                "peak": self._peak}

    def load_state_dict(self, state: dict) -> None:
        self.open_steps = [int(s) for s in state.get("open_steps", [])]
        self._sum, self._count = float(state.get("sum", 0.0)), int(state.get("count", 0))
        self._last, self._peak = state.get("last"), float(state.get("peak", 0.0))


class HeldoutG2fRSchedule(G2fRSchedule):
    """G²fR whose levels open while a held-out PSNR has stopped rising, and close again when it falls (not in
    the paper).

    The adaptive schedule reads the training loss, which keeps falling while the fine levels overfit: on mic
    in the paper's regime both masked arms' held-out PSNR peaks and then declines as the last levels open
    (docs/studies/2026-12-07-fewshot-paper-regime.md). This schedule reads what declines. After every
    ``window`` steps (steps window - 1, 2 window - 1, ...: :meth:`wants_heldout`) the trainer renders a few
    views of the scene's **val** split and reports their mean PSNR (:meth:`observe_heldout`). The schedule
    judges the mean of the last ``average`` checks (the *value*; early in training one check can dip by
    several dB and recover by the next), and ``best`` is the highest value so far. At each check, in this order:

    1. **Guard.** If the value is more than ``drop`` dB below ``best``: when levels have opened since the check
       that set ``best``, those levels close (their weight ramps back to 0 over ``window`` steps from the next
       step) and the schedule freezes: the mask goes back to the levels that gave the best held-out PSNR and
       no level opens again. When none has, nothing changes (a dip that no level caused: wait for it).
    2. **Plateau.** Otherwise, unless the value beats ``best`` by more than ``min_gain`` dB (still rising), the
       next level opens: it ramps in over ``window`` steps from the next step (cosine or binary, as in eq. 15).

    Level 1 is on from the start (tau starts at 1). No step budget enters, and the val split it reads is
    the one settings are chosen on, never test. The mask of any step is a function of ``open_steps`` and
    ``close_steps`` alone (:meth:`tau`); closed levels are always the last ones opened, so ``close_steps[j]``
    belongs to ``open_steps[len(open_steps) - len(close_steps) + j]``.

    Example (one check per value, ``average=1``: a PSNR that stops rising opens a level; a fall of more than
    ``drop`` below the best closes the level opened since the best, 50, and freezes the mask; the level
    opened at 30 was open when the best was measured and stays):
        >>> s = HeldoutG2fRSchedule(n_levels=6, window=10, drop=0.5, min_gain=0.1, average=1)
        >>> [t for t in range(40) if s.wants_heldout(t)]
        [9, 19, 29, 39]
        >>> for step, psnr in [(9, 20.0), (19, 22.0), (29, 22.05), (39, 22.3), (49, 21.9), (59, 21.6)]:
        ...     s.observe_heldout(step, psnr)
        >>> s.open_steps, s.close_steps, s.frozen, s.wants_heldout(69)
        ([30, 50], [60], True, False)
        >>> s.active_levels(59), s.active_levels(80)
        (3, 2)
    """

    def __init__(self, n_levels: int, window: int = 10, drop: float = 0.25, min_gain: float = 0.1, average: int = 3,
                 mode: str = "cosine", enabled: bool = True):
        if window < 1:
            raise ValueError(f"heldout g2fr window must be >= 1 step, got {window}")
        if average < 1:
            raise ValueError(f"heldout g2fr average must be >= 1 check, got {average}")
        if not (drop >= 0.0 and math.isfinite(drop)):
            raise ValueError(f"heldout g2fr drop must be a finite number of dB >= 0, got {drop}")
        if not (min_gain >= 0.0 and math.isfinite(min_gain)):
            raise ValueError(f"heldout g2fr min_gain must be a finite number of dB >= 0, got {min_gain}")
        g2fr_level_weight(2, 0.0, mode)
        self.n_levels, self.mode, self.enabled = n_levels, mode, enabled
        self.window, self.drop, self.min_gain, self.average = int(window), float(drop), float(min_gain), int(average)
        self.total_steps, self.beta = None, None  # no budget
        self.open_steps: list[int] = []  # the step at which each level from 2 on began to ramp in
        self.close_steps: list[int] = []  # the step at which each closed level began to ramp out (the last ones opened)
        self.checks: list[tuple[int, float]] = []  # (step, val PSNR dB) of every check
        self.best: Optional[float] = None  # the best value (mean of the last `average` checks) so far ...
        self.best_open = 0  # ... and how many levels had opened when it was measured
        self.frozen = False

    def tau(self, step: int) -> float:
        """1 + each level opened by ``step`` (ramping in over ``window`` steps from its open step) - each closed
        level (ramping out over ``window`` steps from its close step): the mask of any step the run has reached."""
        ramp = lambda s: min(max(step - s, 0) / self.window, 1.0)  # noqa: E731
        return 1.0 + sum(ramp(s) for s in self.open_steps) - sum(ramp(s) for s in self.close_steps)

    def level_weights(self, step: int) -> LevelWeights:
        if not self.enabled:
            return LevelWeights.ones(self.n_levels)
        tau = self.tau(step)
        return LevelWeights(tuple(g2fr_level_weight(i + 1, tau, self.mode) for i in range(self.n_levels)))

    def wants_heldout(self, step: int) -> bool:
        """After every ``window``-th step, until the schedule has frozen."""
        return self.enabled and not self.frozen and (step + 1) % self.window == 0

    def observe_heldout(self, step: int, psnr: float) -> None:
        """One check's mean val PSNR (dB) after ``step``: close and freeze on a drop, else open on a plateau."""
        if not self.enabled or self.frozen:
            return
        self.checks.append((int(step), float(psnr)))
        recent = [p for _, p in self.checks[-self.average:]]
        value = sum(recent) / len(recent)
        if self.best is not None and value < self.best - self.drop:
            if len(self.open_steps) > self.best_open:
                self.close_steps = [step + 1] * (len(self.open_steps) - self.best_open)
                self.frozen = True
            return
        rising = self.best is None or value > self.best + self.min_gain
        if self.best is None or value > self.best:
            self.best, self.best_open = value, len(self.open_steps)
        if not rising and len(self.open_steps) < self.n_levels - 1:
            self.open_steps.append(step + 1)

    def state_dict(self) -> dict:
        return {"open_steps": list(self.open_steps), "close_steps": list(self.close_steps),
                "checks": [list(c) for c in self.checks], "best": self.best, "best_open": self.best_open,
                "frozen": self.frozen}

    def load_state_dict(self, state: dict) -> None:
        self.open_steps = [int(s) for s in state.get("open_steps", [])]
        self.close_steps = [int(s) for s in state.get("close_steps", [])]
        self.checks = [(int(s), float(p)) for s, p in state.get("checks", [])]
        self.best = None if state.get("best") is None else float(state["best"])
        self.best_open, self.frozen = int(state.get("best_open", 0)), bool(state.get("frozen", False))


def make_schedule(kind: str, n_levels: int, total_steps: int, beta: float = G2FR_BETA, mode: str = "cosine",
                  enabled: bool = True, window: int = 10, tol: float = 0.5, heldout_window: int = 10,
                  drop: float = 0.25, min_gain: float = 0.1, average: int = 3) -> G2fRSchedule:
    """The schedule named ``kind`` (one of :data:`SCHEDULES`)."""
    if kind == "fixed":
        return G2fRSchedule(n_levels, total_steps, beta, mode, enabled)
    if kind == "adaptive":
        return AdaptiveG2fRSchedule(n_levels, window, tol, mode, enabled)
    if kind == "heldout":
        return HeldoutG2fRSchedule(n_levels, heldout_window, drop, min_gain, average, mode, enabled)
    raise ValueError(f"unknown g2fr schedule '{kind}': expected one of {SCHEDULES}")
