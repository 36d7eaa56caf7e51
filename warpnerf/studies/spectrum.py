"""Frequency analysis of grid encodings: the numbers behind G²fR's sections 3.3-4.2.

Three questions, each answered by a function family here and a notebook in ``notebooks/``:

1. What band does one linear-interpolation pulse occupy? Closed-form Fourier transforms of the
   triangular pulse Λ and of Λ² (paper eq. 8, "Bandwidth of Single Pulse", Fig. 3a), an FFT of
   the sampled pulse that reproduces them, and the energy bandwidth of scaled pulses Λ(x/a).
2. How does the band of a grid level depend on its resolution s? A level is a sum of pulses
   Λ((s-1)x - t) (eq. 9); its transform is eq. 14's first term, and its bandwidth grows linearly
   with the number of cells s - 1 (Fig. 3b).
3. What does the G²fR mask (eq. 15) do during training? A 1-D fit with the project's Warp grid
   encoding + a small MLP, recording the spectrum of the fitted function (a spectrogram), the
   Lipschitz bound L_Ψ of eq. 17 and the loss, with and without the mask; the same fit with
   positional encoding shows PE's discrete spectrum against the grid's continuous one (Fig. 1).

Units and conventions (used throughout):

* ``omega`` is angular frequency in **rad per unit length** of x, with the transform
  F(ω) = ∫ f(x) e^{-iωx} dx (the paper's convention; its closed forms hold as printed).
* ``freqs`` / ``nu`` is ordinary frequency in **cycles per unit length** of x, ν = ω / 2π.
  The encodings see x in [0, 1], so ν counts oscillations across the whole input domain.
* An *energy spectrum* is |F|²; *energy bandwidth* is defined in :func:`energy_bandwidth`.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from warpnerf.model.encoders import HashGridEncoder, PositionalEncoder
from warpnerf.model.g2fr import G2FR_BETA, make_schedule
from warpnerf.ops.hashgrid_spec import HashGridSpec

__all__ = [
    "triangle_ft",
    "triangle_sq_ft",
    "pulse_ft",
    "numeric_ft",
    "energy_bandwidth",
    "pulse_bandwidth",
    "grid_function_from_pulses",
    "grid_function_ft",
    "grid_energy_spectrum",
    "grid_bandwidth",
    "periodic_spectrum",
    "line_spectrum",
    "high_frequency_energy_fraction",
    "comb_energy_fraction",
    "lipschitz_from_features",
    "default_signal",
    "FitConfig",
    "FitResult",
    "fit_grid_1d",
    "fit_pe_1d",
]

# Below this |ω| the closed forms lose digits to cancellation (1 - cos ω, ω - sin ω), so we
# switch to their Taylor series; at 1e-2 the series' first dropped terms are < 1e-12.
_SMALL_OMEGA = 1e-2


# ----------------------------------------------------------------------------------------------
# 1. Single pulses
# ----------------------------------------------------------------------------------------------


def triangle_ft(omega: np.ndarray) -> np.ndarray:
    """F[Λ](ω) = (2 - 2 cos ω) / ω² for Λ(x) = max(0, 1 - |x|) (paper eq. 8).

    Real and even because Λ is real and even; equals sinc²(ω / 2π) with numpy's normalised sinc.
    Checked against the direct integral 2∫₀¹(1-x)cos(ωx)dx: the paper's expression is exact.

    Args:
        omega: any shape, rad per unit length.
    Returns:
        same shape, units of length (the transform of a dimensionless pulse). F(0) = 1 = ∫Λ.
    """
    w = np.asarray(omega, dtype=np.float64)
    small = np.abs(w) < _SMALL_OMEGA
    ws = np.where(small, 1.0, w)  # keep the unused branch finite
    exact = (2.0 - 2.0 * np.cos(ws)) / ws**2
    series = 1.0 - w**2 / 12.0 + w**4 / 360.0
    return np.where(small, series, exact)


def triangle_sq_ft(omega: np.ndarray) -> np.ndarray:
    """F[Λ²](ω) = (4ω - 4 sin ω) / ω³ (paper, "Bandwidth of Single Pulse").

    Derived by parts from 2∫₀¹(1-x)² cos(ωx) dx; the paper's expression is exact, and
    F(0) = 2/3 = ∫Λ². Args and units as :func:`triangle_ft`.
    """
    w = np.asarray(omega, dtype=np.float64)
    small = np.abs(w) < _SMALL_OMEGA
    ws = np.where(small, 1.0, w)
    exact = (4.0 * ws - 4.0 * np.sin(ws)) / ws**3
    series = 2.0 / 3.0 - w**2 / 30.0 + w**4 / 1260.0
    return np.where(small, series, exact)


def pulse_ft(omega: np.ndarray, scale: float = 1.0, power: int = 1) -> np.ndarray:
    """F[Λ^k(x / a)](ω) = a · F[Λ^k](a ω) for k = ``power`` in {1, 2} and a = ``scale`` > 0.

    A grid level with s points is built from Λ((s-1)x - t), i.e. a = 1 / (s - 1): wider pulses
    (a > 1) have proportionally narrower spectra (Fig. 3b uses a = 4).
    """
    if scale <= 0:
        raise ValueError(f"pulse scale must be positive, got {scale}")
    base = {1: triangle_ft, 2: triangle_sq_ft}.get(power)
    if base is None:
        raise ValueError(f"closed forms exist for power 1 and 2 only, got {power}")
    return scale * base(scale * np.asarray(omega, dtype=np.float64))


def numeric_ft(samples: np.ndarray, x0: float, dx: float, n_fft: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Continuous Fourier transform of a function sampled at x_n = x0 + n·dx, by FFT.

    F(ω_k) ≈ Σ_n f(x_n) e^{-iω_k x_n} dx = dx · e^{-iω_k x0} · FFT(f)_k: the ``dx`` factor turns the
    DFT sum into the integral, and the phase factor moves the origin from the first sample to
    x = 0 (without it an even pulse would show an oscillating phase). The rectangle-rule error
    is O(dx²) for a piecewise-linear f whose kinks sit on samples.

    Args:
        samples: (N,) real or complex samples; the function must be ~0 outside the window.
        x0: position of the first sample, length units.
        dx: sample spacing, length units.
        n_fft: zero-pad to this length (finer frequency spacing); default N.
    Returns:
        omega (n_fft,) rad per unit length, ascending; F (n_fft,) complex, length units.
    """
    f = np.asarray(samples)
    n = int(n_fft or f.shape[-1])
    spec = np.fft.fft(f, n=n)
    omega = 2.0 * np.pi * np.fft.fftfreq(n, d=dx)
    spec = dx * np.exp(-1j * omega * x0) * spec
    order = np.argsort(omega)
    return omega[order], spec[order]


def energy_bandwidth(spectrum: np.ndarray, freqs: np.ndarray, fraction: float = 0.99) -> float:
    """Frequency below which ``fraction`` of the spectral energy lies.

    Definition: with E(f) = |S(f)|² on an ascending grid of non-negative frequencies
    (one-sided; for the real signals here the negative half mirrors it), the bandwidth B solves
    ∫₀^B E df = fraction · ∫ E df over the grid, with trapezoid integrals and linear
    interpolation inside the bin that crosses the target. B is in the units of ``freqs``. The
    grid must reach far enough that the energy beyond it is negligible (the callers below leave
    < 1e-6 of it out).

    Args:
        spectrum: (K,) complex or real spectrum (amplitude, not energy).
        freqs: (K,) ascending, >= 0.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"energy fraction must be in (0, 1), got {fraction}")
    freqs = np.asarray(freqs, dtype=np.float64)
    energy = np.abs(np.asarray(spectrum)) ** 2
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (energy[1:] + energy[:-1]) * np.diff(freqs))])
    if cum[-1] <= 0:
        return 0.0
    cum /= cum[-1]
    k = int(np.searchsorted(cum, fraction))
    # linear interpolation between the two grid points that straddle the target fraction
    t = (fraction - cum[k - 1]) / max(cum[k] - cum[k - 1], 1e-300)
    return float(freqs[k - 1] + t * (freqs[k] - freqs[k - 1]))


def pulse_bandwidth(scale: float = 1.0, power: int = 1, fraction: float = 0.99, n: int = 200_001) -> float:
    """Energy bandwidth of Λ^k(x / a), cycles per unit length (numeric, closed-form spectrum).

    The grid runs to ν = 400 / a cycles, where the omitted |F|² tail (~ν⁻⁴) is < 1e-8 of the total.
    Measured: Λ 0.649, Λ² 1.167, Λ(x/4) 0.162 cycles per unit length at 99 %.
    """
    nu = np.linspace(0.0, 400.0 / scale, n)
    return energy_bandwidth(pulse_ft(2.0 * np.pi * nu, scale, power), nu, fraction)


# ----------------------------------------------------------------------------------------------
# 2. A grid level as a sum of pulses
# ----------------------------------------------------------------------------------------------


def grid_function_from_pulses(values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """ψ(x) = Σ_t h_t Λ((s-1)x - t) (paper eq. 9) on the whole real line.

    Inside [0, 1] this is the linear interpolation the grid encoding computes; outside it fades to
    0 within one cell, which is what makes its transform (eq. 14) continuous.

    Args:
        values: (s,) grid values h_t, s >= 2.
        x: (N,) positions, length units.
    Returns:
        (N,) float64.
    """
    h = np.asarray(values, dtype=np.float64)
    s = h.shape[-1]
    u = (s - 1) * np.asarray(x, dtype=np.float64)[:, None] - np.arange(s)[None, :]
    return np.maximum(0.0, 1.0 - np.abs(u)) @ h


def grid_function_ft(values: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Closed-form transform of :func:`grid_function_from_pulses` (paper eq. 14, k = 1 term).

    F(ω) = (1/(s-1)) · F[Λ](ω/(s-1)) · Σ_t h_t e^{-iωt/(s-1)}: each pulse is the unit pulse scaled
    by a = 1/(s-1) and shifted to t/(s-1). The printed eq. 14 writes the same factor as
    (s-1)(2 - 2cos(ω/(s-1)))/ω².

    Args:
        values: (..., s) grid values (leading axes, e.g. random draws, are kept).
        omega: (K,) rad per unit length.
    Returns:
        (..., K) complex, length units.
    """
    h = np.asarray(values, dtype=np.float64)
    s = h.shape[-1]
    w = np.asarray(omega, dtype=np.float64)
    phases = np.exp(-1j * np.outer(np.arange(s), w) / (s - 1))  # (s, K)
    return pulse_ft(w, 1.0 / (s - 1)) * (h @ phases)


def grid_energy_spectrum(
    resolution: int, nu: np.ndarray, n_draws: int = 64, seed: int = 0
) -> np.ndarray:
    """Mean energy spectrum |F(ν)|² of a grid level with random values, over ``n_draws`` draws.

    Values are i.i.d. standard normal (seeded): zero mean, so no constant-level rectangle adds a
    spectral line at 0, and the phase sum is white on average, leaving the pulse's envelope
    |F[Λ](ω/(s-1))|² to set the shape.

    Args:
        resolution: s, grid points per axis (cells: s - 1).
        nu: (K,) cycles per unit length.
    Returns:
        (K,) energy, length² units.
    """
    rng = np.random.default_rng(seed)
    h = rng.standard_normal((n_draws, resolution))
    return np.mean(np.abs(grid_function_ft(h, 2.0 * np.pi * np.asarray(nu))) ** 2, axis=0)


def grid_bandwidth(resolution: int, fraction: float = 0.99, n_draws: int = 64, seed: int = 0) -> float:
    """Energy bandwidth (cycles per unit length) of a random grid level with ``resolution`` points.

    Frequency grid: 0 … 8(s-1) cycles with 64 points per s-1 cycles, enough to resolve
    the envelope and to leave < 1e-6 of the energy out. Measured at 99 %: ≈ 0.65·(s-1), i.e.
    the single-pulse bandwidth times the number of cells; linear in s - 1 (not exactly in s:
    B(256)/B(8) = 36.4 = 255/7, while 256/8 = 32).
    """
    cells = resolution - 1
    nu = np.linspace(0.0, 8.0 * cells, 8 * 64 + 1)
    return energy_bandwidth(np.sqrt(grid_energy_spectrum(resolution, nu, n_draws, seed)), nu, fraction)


# ----------------------------------------------------------------------------------------------
# Spectra of sampled functions
# ----------------------------------------------------------------------------------------------


def periodic_spectrum(values: np.ndarray, remove_mean: bool = True, window: str = "hann") -> tuple[np.ndarray, np.ndarray]:
    """One-sided amplitude spectrum of samples at x_n = n/N, n < N (the domain [0, 1)).

    Amplitudes are scaled so that a sin(2πkx) shows a at bin k (|rfft(v·w)|·2/Σw; bin 0 is not
    doubled). The mean is removed by default: an offset says nothing about frequency content and
    would dominate energy fractions.

    ``window="hann"`` (default) tapers both ends. A fitted function rarely meets itself at x = 1,
    and the DFT reads that mismatch as a jump whose 1/ν tail spreads energy over every bin; early
    in a masked fit this tail, not the function, would dominate the high frequencies. The price
    is that a pure tone occupies bins k-1..k+1 (at 0.5, 1, 0.5 of its amplitude).
    ``window="none"`` is exact for periodic signals.

    Args:
        values: (..., N) real samples.
    Returns:
        freqs (N//2 + 1,) cycles per unit length; amplitude (..., N//2 + 1).
    """
    v = np.asarray(values, dtype=np.float64)
    if remove_mean:
        v = v - v.mean(axis=-1, keepdims=True)
    n = v.shape[-1]
    if window == "hann":
        w = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / n)  # periodic Hann: exact 3-bin tones
    elif window == "none":
        w = np.ones(n)
    else:
        raise ValueError(f"unknown window '{window}': expected 'hann' or 'none'")
    amp = np.abs(np.fft.rfft(v * w, axis=-1)) * (2.0 / w.sum())
    amp[..., 0] *= 0.5
    return np.fft.rfftfreq(n, d=1.0 / n), amp


def line_spectrum(
    fn: Callable[[np.ndarray], np.ndarray], half_width: float = 8.0, samples_per_unit: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """|F(ν)| of ``fn`` sampled on the window [-W, W), W = ``half_width``, by :func:`numeric_ft`.

    Frequency spacing is 1/(2W) cycles per unit length. A function with compact support inside
    the window gets its continuous transform sampled; a function periodic with a period dividing
    2W gets exact lines (height ~ W times its amplitude) and zeros in between. That contrast is
    Fig. 1: PE-MLP functions are periodic sums of sinusoids, grid-MLP ones are sums of pulses.

    Returns:
        nu (K,) cycles per unit length, >= 0; amplitude (K,) length units.
    """
    n = int(round(2 * half_width * samples_per_unit))
    dx = 1.0 / samples_per_unit
    x = -half_width + dx * np.arange(n)
    omega, spec = numeric_ft(np.asarray(fn(x), dtype=np.float64), x[0], dx)
    keep = omega >= 0
    return omega[keep] / (2.0 * np.pi), np.abs(spec[keep])


def high_frequency_energy_fraction(spectrum: np.ndarray, freqs: np.ndarray, cutoff: float) -> np.ndarray:
    """Share of spectral energy Σ|S|² strictly above ``cutoff`` (units of ``freqs``).

    Args:
        spectrum: (..., K) amplitudes (e.g. a spectrogram, iterations × frequencies).
        freqs: (K,) frequencies.
    Returns:
        (...) in [0, 1]; 0 where the spectrum is all zero.
    """
    e = np.abs(np.asarray(spectrum)) ** 2
    hi = e[..., np.asarray(freqs) > cutoff].sum(axis=-1)
    tot = e.sum(axis=-1)
    return np.where(tot > 0, hi / np.where(tot > 0, tot, 1.0), 0.0)


def comb_energy_fraction(spectrum: np.ndarray, freqs: np.ndarray, spacing: float) -> float:
    """Share of energy on the comb ν ∈ spacing·ℤ (bins within 1e-9 of a multiple).

    For a window whose frequency step divides ``spacing``, a function with only those frequencies
    scores 1 and a continuous spectrum scores about step / spacing.
    """
    f = np.asarray(freqs, dtype=np.float64) / spacing
    on = np.abs(f - np.round(f)) < 1e-9
    e = np.abs(np.asarray(spectrum)) ** 2
    return float(e[on].sum() / e.sum())


def lipschitz_from_features(features: np.ndarray, dx: float, level_weights: np.ndarray | None = None,
                            n_features: int = 1) -> tuple[float, np.ndarray]:
    """Estimate of L_Ψ (paper eq. 17) from an encoding sampled on a uniform 1-D grid.

    The sup over all pairs (x, y) is replaced by the sup over neighbouring samples, which is exact
    for piecewise-linear ψ_m once every cell holds two samples (finest cell >= 2 dx).

    Args:
        features: (N, G*F) encoding Ψ at x_n = x_0 + n·dx, *without* level weights; G groups
            (grid levels, or PE frequency bands) of ``n_features`` columns each.
        dx: sample spacing, length units.
        level_weights: (G,) w_m; None means ones.
    Returns:
        L_Ψ = max_n sqrt(Σ_m w_m² ||Δψ_m||²) / dx (feature units per unit length), and the
        unweighted per-group bounds L_m = max_n ||Δψ_m|| / dx, shape (G,).
    """
    d = np.diff(np.asarray(features, dtype=np.float64), axis=0)
    per = (d.reshape(d.shape[0], -1, n_features) ** 2).sum(-1)  # (N-1, G) squared norms
    w2 = np.ones(per.shape[1]) if level_weights is None else np.asarray(level_weights, dtype=np.float64) ** 2
    total = float(np.sqrt((per * w2).sum(1).max()) / dx)
    return total, np.sqrt(per.max(0)) / dx


# ----------------------------------------------------------------------------------------------
# 3. 1-D fitting experiment
# ----------------------------------------------------------------------------------------------


def default_signal(x: np.ndarray) -> np.ndarray:
    """Target for the 1-D fits: one low, one mid and one high frequency, periodic on [0, 1).

    sin(2π·2x) + 0.5 sin(2π·6x + 1) + 0.35 sin(2π·28x + 2): the 28-cycle term needs a level with
    >= ~57 cells, i.e. one of the three finest levels of the default grid.
    """
    x = np.asarray(x, dtype=np.float64)
    return np.sin(2 * np.pi * 2 * x) + 0.5 * np.sin(2 * np.pi * 6 * x + 1.0) + 0.35 * np.sin(2 * np.pi * 28 * x + 2.0)


@dataclass
class FitConfig:
    """Small-by-default 1-D fit: ~0.6 s on two shared CPU cores, after ~2 s of Warp start-up."""

    steps: int = 400  # Adam iterations, full batch
    record_every: int = 10  # record spectrum / L_Ψ / loss every this many steps (and at 0 and the end)
    n_train: int = 256  # training points, uniform random in [0, 1] (seeded)
    n_eval: int = 1024  # dense evaluation grid x_n = n / n_eval for spectra and L_Ψ
    noise_std: float = 0.0  # Gaussian noise on the training targets
    lr: float = 1e-2  # Adam learning rate for table and MLP
    hidden: int = 32  # MLP width
    n_hidden_layers: int = 2  # ReLU layers before the linear output
    seed: int = 0  # seeds data, table and MLP init
    # grid encoding (dim = 1, all levels dense): resolutions 4, 7, 13, 23, 43, 78, 141, 256
    n_levels: int = 8
    n_features: int = 2
    base_resolution: int = 4
    max_resolution: int = 256
    init_scale: float = 1e-4  # table init U(-a, a), Instant-NGP's choice
    # G²fR mask (paper eq. 15)
    g2fr: bool = True  # apply the mask; False trains all levels from step 0
    beta: float = G2FR_BETA  # fraction of training over which levels are switched on
    mask_mode: str = "cosine"  # "cosine" (BARF ramp) or "binary"
    schedule: str = "fixed"  # "fixed" (eq. 15 over beta of the steps) or "adaptive" (a level opens on a loss plateau)
    plateau_window: int = 10  # adaptive: steps per loss window (model.g2fr.AdaptiveG2fRSchedule)
    plateau_tol: float = 0.5  # adaptive: the next level opens when a window's gain falls to this share of the largest since the last opened
    # positional encoding baseline
    pe_n_freqs: int = 7  # frequencies 2^k·π rad, k < n: 0.5 … 32 cycles per unit length

    def grid_spec(self) -> HashGridSpec:
        return HashGridSpec.create(1, self.n_levels, self.n_features, 12, self.base_resolution, self.max_resolution)


@dataclass
class FitResult:
    """Record of one 1-D fit; R = number of records, K = n_eval // 2 + 1 frequencies, G groups."""

    steps: np.ndarray  # (R,) iteration of each record
    train_loss: np.ndarray  # (R,) MSE on the training points
    test_loss: np.ndarray  # (R,) MSE against the clean target on the dense grid
    freqs: np.ndarray  # (K,) cycles per unit length
    spectrogram: np.ndarray  # (R, K) amplitude spectrum of the fitted function (Hann window)
    target_spectrum: np.ndarray  # (K,) amplitude spectrum of the clean target (Hann window)
    lipschitz: np.ndarray  # (R,) L_Ψ of eq. 17 with the level weights of that step
    lipschitz_per_level: np.ndarray  # (R, G) unweighted per-group bounds L_m
    level_weights: np.ndarray  # (R, G) w_m used at each record (ones for PE / no mask)
    x_eval: np.ndarray  # (n_eval,) dense grid in [0, 1)
    prediction: np.ndarray  # (n_eval,) final fitted function
    target: np.ndarray  # (n_eval,) clean target
    x_train: np.ndarray  # (n_train,)
    y_train: np.ndarray  # (n_train,) (noisy) training targets
    predict: Callable[[np.ndarray], np.ndarray] = field(repr=False, default=None)
    """Final model on the whole real line (see :func:`fit_grid_1d` / :func:`fit_pe_1d`)."""


def _mlp(in_dim: int, cfg: FitConfig) -> torch.nn.Sequential:
    layers, d = [], in_dim
    for _ in range(cfg.n_hidden_layers):
        layers += [torch.nn.Linear(d, cfg.hidden), torch.nn.ReLU()]
        d = cfg.hidden
    layers.append(torch.nn.Linear(d, 1))
    return torch.nn.Sequential(*layers)


def _fit(cfg: FitConfig, encode, params: list, mlp, weights_at, n_groups: int, group_width: int,
         signal) -> dict:
    """Shared Adam loop on one torch thread (see :func:`_one_torch_thread`)."""
    with _one_torch_thread():
        return _fit_loop(cfg, encode, params, mlp, weights_at, n_groups, group_width, signal)


@contextlib.contextmanager
def _one_torch_thread():
    """Run torch ops single-threaded, restoring the caller's setting afterwards.

    The MLP's matrices are tiny (256 x 32); with two OpenMP threads on a shared two-core machine
    each op waits on a descheduled partner, which measured 35 s per fit instead of 0.5 s. It also
    makes the fit's float results independent of the caller's thread setting.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _fit_loop(cfg: FitConfig, encode, params: list, mlp, weights_at, n_groups: int, group_width: int,
              signal) -> dict:
    """Adam, full batch; ``encode(x, w)`` gives unweighted features when w is None."""
    rng = np.random.default_rng(cfg.seed)
    x_train = np.sort(rng.uniform(0.0, 1.0, cfg.n_train))
    y_clean = signal(x_train)
    y_train = y_clean + cfg.noise_std * rng.standard_normal(cfg.n_train)
    x_eval = np.arange(cfg.n_eval) / cfg.n_eval
    target = signal(x_eval)
    xt = torch.tensor(x_train, dtype=torch.float32)[:, None]
    yt = torch.tensor(y_train, dtype=torch.float32)[:, None]
    xe = torch.tensor(x_eval, dtype=torch.float32)[:, None]
    te = torch.tensor(target, dtype=torch.float32)[:, None]
    opt = torch.optim.Adam(params + list(mlp.parameters()), lr=cfg.lr, eps=1e-15)
    rec = {k: [] for k in ("steps", "train_loss", "test_loss", "pred", "lip", "lip_m", "w")}

    def record(step: int, w: torch.Tensor | None):
        with torch.no_grad():
            feats = encode(xe, None)  # unweighted ψ_m, for L_m
            wv = torch.ones(n_groups) if w is None else w
            pred = mlp(feats * wv.repeat_interleave(group_width)[None, :])
            train = mlp(encode(xt, w))
        lip, lip_m = lipschitz_from_features(feats.numpy(), 1.0 / cfg.n_eval, wv.numpy(), group_width)
        rec["steps"].append(step)
        rec["train_loss"].append(float(((train - yt) ** 2).mean()))
        rec["test_loss"].append(float(((pred - te) ** 2).mean()))
        rec["pred"].append(pred[:, 0].numpy().astype(np.float64))
        rec["lip"].append(lip)
        rec["lip_m"].append(lip_m)
        rec["w"].append(wv.numpy().copy())

    record(0, weights_at(0))
    for step in range(1, cfg.steps + 1):
        w = weights_at(step)
        loss = ((mlp(encode(xt, w)) - yt) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if hasattr(weights_at, "observe"):  # an adaptive schedule opens levels from the loss
            weights_at.observe(step, float(loss.detach()))
        if step % cfg.record_every == 0 or step == cfg.steps:
            record(step, w)

    freqs, spectrogram = periodic_spectrum(np.stack(rec["pred"]))
    _, target_spec = periodic_spectrum(target)
    return dict(
        steps=np.array(rec["steps"]), train_loss=np.array(rec["train_loss"]), test_loss=np.array(rec["test_loss"]),
        freqs=freqs, spectrogram=spectrogram, target_spectrum=target_spec, lipschitz=np.array(rec["lip"]),
        lipschitz_per_level=np.stack(rec["lip_m"]), level_weights=np.stack(rec["w"]), x_eval=x_eval,
        prediction=rec["pred"][-1], target=target, x_train=x_train, y_train=y_train,
    )


def fit_grid_1d(cfg: FitConfig | None = None, signal: Callable[[np.ndarray], np.ndarray] = default_signal) -> FitResult:
    """Fit ``signal`` on [0, 1] with the Warp grid encoding (dim 1) + ReLU MLP, with or without G²fR.

    Deterministic for a given config (seeded numpy data, seeded torch init, bit-reproducible Warp
    op). ``cfg.g2fr`` switches the mask of eq. 15 (schedule over ``cfg.beta`` of the steps).

    ``FitResult.predict`` evaluates the final model on the real line with each level extended by
    eq. 9 (it fades to 0 within one cell outside [0, 1]) and the constant MLP(0) removed, so the
    function has compact support and a continuous transform (Fig. 1, right).

    Example:
        >>> r = fit_grid_1d(FitConfig(steps=50))
        >>> r.spectrogram.shape   # (records, frequencies)
        (6, 513)
    """
    cfg = cfg or FitConfig()
    spec = cfg.grid_spec()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        grid = HashGridEncoder(spec, init_scale=cfg.init_scale)  # the project's Warp encoding
        mlp = _mlp(spec.out_dim, cfg)
    schedule = make_schedule(cfg.schedule, spec.n_levels, cfg.steps, cfg.beta, cfg.mask_mode, enabled=cfg.g2fr,
                             window=cfg.plateau_window, tol=cfg.plateau_tol)

    out = _fit(cfg, grid, [grid.table], mlp, schedule, spec.n_levels, spec.n_features, signal)
    cells = torch.tensor([s - 1 for s in spec.resolutions], dtype=torch.float32)

    def predict(x: np.ndarray) -> np.ndarray:
        xt = torch.tensor(np.asarray(x), dtype=torch.float32)[:, None]
        with torch.no_grad(), _one_torch_thread():
            feats = grid(xt.clamp(0, 1)).view(-1, spec.n_levels, spec.n_features)
            # eq. 9 outside [0, 1]: the edge value times the edge pulse Λ((s-1)·distance)
            dist = (xt - xt.clamp(0, 1)).abs()  # (N, 1)
            fade = (1.0 - cells[None, :] * dist).clamp(min=0.0)  # (N, L)
            z = (feats * fade[..., None]).reshape(xt.shape[0], -1)
            return (mlp(z) - mlp(torch.zeros(1, spec.out_dim)))[:, 0].numpy().astype(np.float64)

    return FitResult(**out, predict=predict)


def fit_pe_1d(cfg: FitConfig | None = None, signal: Callable[[np.ndarray], np.ndarray] = default_signal) -> FitResult:
    """The same fit with positional encoding (``cfg.pe_n_freqs`` bands, no raw x) + the same MLP.

    Uses the project's :class:`~warpnerf.model.encoders.PositionalEncoder`. No mask (``cfg.g2fr`` is
    ignored); L_Ψ groups are the frequency bands, whose bounds are the fixed 2^k·π (the speed of
    the point (sin, cos) on the unit circle). ``FitResult.predict`` is the model on the real line
    minus its mean over one period (2 units, set by the lowest band, 0.5 cycles per unit length),
    so its transform is a comb of lines at multiples of 0.5 cycles per unit length (Fig. 1, left).
    """
    cfg = cfg or FitConfig()
    # no raw x: it is not periodic and would smear the lines that make PE's spectrum discrete;
    # columns come in (sin, cos) pairs per band, the L_Ψ groups
    pe = PositionalEncoder(1, cfg.pe_n_freqs, include_input=False)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        mlp = _mlp(pe.out_dim, cfg)

    def encode(x, w):
        return pe(x)

    out = _fit(cfg, encode, [], mlp, lambda step: None, cfg.pe_n_freqs, 2, signal)
    period = 2.0
    x_period = torch.arange(2048, dtype=torch.float32)[:, None] * (period / 2048)
    with torch.no_grad(), _one_torch_thread():
        mean = float(mlp(pe(x_period)).mean())

    def predict(x: np.ndarray) -> np.ndarray:
        xt = torch.tensor(np.asarray(x), dtype=torch.float32)[:, None]
        with torch.no_grad(), _one_torch_thread():
            return (mlp(pe(xt))[:, 0] - mean).numpy().astype(np.float64)

    return FitResult(**out, predict=predict)
