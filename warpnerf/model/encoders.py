"""Input encodings as torch modules: the multi-resolution hash grid (Warp op), NeRF's
positional encoding, and spherical harmonics for view directions.

G²fR masks the levels of the two grid encoders, the hash grid (``HashGridEncoder``, Instant-NGP)
and the multi-resolution CP decomposition (``CPGridEncoder``, the paper's Mtrf): their
``forward(x, level_weights)`` takes the per-level weights of :class:`warpnerf.model.g2fr.G2fRSchedule`,
best as the host value :class:`warpnerf.model.g2fr.LevelWeights` (the trainer's form: no device
read per launch); floats, an (L,) tensor or ``None`` (all ones) also work.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines
from warpnerf.ops.hashgrid import HashGridSpec, hashgrid_encode


class HashGridEncoder(nn.Module):
    """Instant-NGP multi-resolution hash grid with a learnable flat table (``self.table``).

    Input (N, D) points in [0, 1]^D (clamped), output (N, L*F).
    """

    def __init__(self, spec: HashGridSpec, init_scale: float = 1e-4, generator: torch.Generator | None = None):
        super().__init__()
        self.spec = spec
        # Instant-NGP initialises features uniformly in [-1e-4, 1e-4]
        init = (torch.rand(spec.n_rows, spec.n_features, generator=generator) * 2 - 1) * init_scale
        self.table = nn.Parameter(init)

    @property
    def out_dim(self) -> int:
        return self.spec.out_dim

    def grid_parameters(self):
        return [self.table]

    def forward(self, x: torch.Tensor, level_weights=None, known_output=None) -> torch.Tensor:
        return hashgrid_encode(x.contiguous(), self.table, self.spec, level_weights, known_output)

    def extra_repr(self) -> str:
        s = self.spec
        return f"dim={s.dim}, levels={s.n_levels}, features={s.n_features}, T=2^{s.log2_table_size}, res={s.resolutions[0]}..{s.resolutions[-1]}"


class CPGridEncoder(nn.Module):
    """Multi-resolution CP decomposition: the paper's "Mtrf", as we read it.

    Input (N, 3) points in [0, 1]^3 (clamped), output (N, L*R); learnable ``self.lines``.

    What G²fR says: Mtrf is "a multi-resolution version of CP-TensoRF [3]" (Sec. 5), ~11 MB,
    trained 50k steps (Tab. 2), and G²fR's coarse-to-fine mask acts on its levels as on NGP's.
    Nothing else is specified; the choices below are ours, each with the reason.

    * **Levels.** L levels (``cfg.levels``, 16), each a CP factorisation of a 3-D grid of s_l
      points per axis, s_l growing geometrically from ``base_resolution`` (16) to
      ``cp_max_resolution`` (512) like Instant-NGP's levels — "multi-resolution" in the sense
      G²fR needs: a level is the unit the mask switches on, and a level's line length bounds
      the frequencies it can hold (the paper's spectrum argument for grids).
    * **Rank per level.** R components per level (``cp_rank``), the same on every level.
      TensoRF's single-resolution CP uses 96 density + 288 appearance components at up to 500
      points; spreading the rank over 16 levels, each level needs far fewer.
    * **Line lengths.** One line of s_l values per axis, component and level, read with linear
      interpolation (align corners). Lines are fixed-length: TensoRF's CP grows its lines during
      training (128 -> 500 points per axis); here the coarse-to-fine progression comes from the
      levels instead (and, with G²fR, from the mask), so no re-sampling of Adam state is needed.
    * **Density and appearance share components.** TensoRF keeps separate density and
      appearance factors (density summed to one scalar, appearance projected by a basis matrix
      into a small MLP). We feed one set of features to the same field as NGP (density MLP ->
      15 geometry features -> color MLP), so Mtrf and NGP differ only in the encoding that
      G²fR masks, and the comparison of Tab. 1 is about the encoding.
    * **Concatenated, not summed.** The R components of every level stay separate features and
      the L levels are concatenated (L*R = 128 MLP inputs), as the hash grid's levels are. A
      sum over components is what the MLP's first linear layer computes anyway (TensoRF's
      density sum and appearance basis matrix are both linear maps of the components), so
      concatenation contains TensoRF's readout and lets the MLP weigh components per level.
    * **What G²fR masks.** The per-level weight w_l multiplies the R features of level l
      (columns [l*R, (l+1)*R)); levels with w_l = 0 are skipped entirely. Components within a
      level are never masked separately.
    * **Training.** TensoRF's recipe where it carries over: lines start N(0, 0.2^2)
      (:func:`~warpnerf.ops.cpgrid.init_cp_lines`) and have their own Adam rate ``cp_lr``
      (0.02, TensoRF's; the MLPs keep ``lr``). TensoRF's L1 density and TV losses are not used
      (short runs, see docs); its negative density shift is available as ``cp_density_shift``
      but off by default: it slowed training in our measurements (tiny scene 26.6 -> 18.6 dB
      at -4) and the occupancy grid empties within the warm-up without it.

    Size: 3 * R * sum(s_l) parameters; the default (R = 8, 16..512) is 57,984 (0.23 MB), far
    below the paper's ~11 MB; ``cp_rank`` 16/32 doubles/quadruples it (docs/studies/2026-12-07-mtrf.md).
    """

    def __init__(self, spec: CPGridSpec, generator: torch.Generator | None = None):
        super().__init__()
        self.spec = spec
        self.lines = nn.Parameter(init_cp_lines(spec, generator=generator))

    @property
    def out_dim(self) -> int:
        return self.spec.out_dim

    def grid_parameters(self):
        return [self.lines]

    def forward(self, x: torch.Tensor, level_weights=None, known_output=None) -> torch.Tensor:
        return cpgrid_encode(x.contiguous(), self.lines, self.spec, level_weights, known_output)

    def extra_repr(self) -> str:
        s = self.spec
        return f"levels={s.n_levels}, rank={s.rank}, res={s.resolutions[0]}..{s.resolutions[-1]}"


class PositionalEncoder(nn.Module):
    """NeRF positional encoding: [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs.

    Input (N, D), output (N, D * (2 * n_freqs + include_input)).
    """

    def __init__(self, in_dim: int, n_freqs: int, include_input: bool = True):
        super().__init__()
        self.in_dim, self.n_freqs, self.include_input = in_dim, n_freqs, include_input
        self.register_buffer("freqs", (2.0 ** torch.arange(n_freqs)) * math.pi, persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.n_freqs + int(self.include_input))

    def forward(self, x: torch.Tensor, band_weights: torch.Tensor | None = None) -> torch.Tensor:
        """``band_weights`` (n_freqs,) optionally masks frequency bands (BARF / FreeNeRF style)."""
        arg = x[..., None, :] * self.freqs[:, None].to(x.dtype)  # (N, K, D)
        enc = torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)  # (N, K, 2D)
        if band_weights is not None:
            enc = enc * band_weights.to(enc)[:, None]
        enc = enc.flatten(-2)
        return torch.cat([x, enc], dim=-1) if self.include_input else enc


class SphericalHarmonicsEncoder(nn.Module):
    """Real spherical harmonics of unit directions up to degree 3 (16 outputs), as in Instant-NGP."""

    out_dim = 16

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        x, y, z = d.unbind(-1)
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        return torch.stack(
            [
                torch.full_like(x, 0.28209479177387814),
                -0.48860251190291987 * y,
                0.48860251190291987 * z,
                -0.48860251190291987 * x,
                1.0925484305920792 * xy,
                -1.0925484305920792 * yz,
                0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * xz,
                0.54627421529603959 * (xx - yy),
                0.59004358992664352 * y * (-3.0 * xx + yy),
                2.8906114426405538 * xy * z,
                0.45704579946446572 * y * (1.0 - 5.0 * zz),
                0.3731763325901154 * z * (5.0 * zz - 3.0),
                0.45704579946446572 * x * (1.0 - 5.0 * zz),
                1.4453057213202769 * z * (xx - yy),
                0.59004358992664352 * x * (-xx + 3.0 * yy),
            ],
            dim=-1,
        )


def make_grid_encoder(cfg, generator: torch.Generator | None = None) -> nn.Module:
    """The grid encoder a :class:`warpnerf.train.config.TrainConfig` asks for (``cfg.model``)."""
    if cfg.model == "ngp":
        spec = HashGridSpec.create(3, cfg.levels, cfg.features, cfg.log2_table_size, cfg.base_resolution,
                                   cfg.max_resolution)
        return HashGridEncoder(spec, generator=generator)
    if cfg.model == "mtrf":
        spec = CPGridSpec.create(cfg.levels, cfg.cp_rank, cfg.base_resolution, cfg.cp_max_resolution)
        return CPGridEncoder(spec, generator=generator)
    raise ValueError(f"unknown model '{cfg.model}'")  # config.validate names the choices
