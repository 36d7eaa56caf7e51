"""What a configuration's size settings cost in memory, known before anything is allocated.

A size flag off by a few orders of magnitude (``--log2-table-size 40``, ``--hidden 1000000``,
``--occ-resolution 5000``, ``--batch-rays 2000000000``, ``export --resolution 2000``, ``render --scale
1000``) would otherwise load the data, write the run folder and then die in an allocation (a
traceback, or the OOM killer taking the machine down with it). The estimates here are lower bounds
of what the code allocates (every term is a tensor that exists at the peak), so a configuration
that fits its ``memory_budget_mb`` is never refused, and one that cannot fit is refused in one line
naming the setting, before any file is read or written. What the scene adds (its images) is not
counted: it is checked while training runs (``Trainer``'s peak-memory check).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:  # the CLI imports config.py (and so this module) for --help: no torch here
    from warpnerf.train.config import TrainConfig

MB = 1 << 20
ADAM_COPIES = 4  # a trained float32 tensor: the values, their gradient and Adam's two moments
SH_FEATURES = 16  # the colour MLP's view-direction encoding (degree-4 spherical harmonics)
RAY_BYTES = 64  # a training ray of the first step: pixel (view, u, v) int64s, colour, origin, direction, march state
PIXEL_BYTES = 64  # a rendered pixel: ray origin and direction, (u, v), colour, depth, opacity, march state
OCC_CELL_BYTES = 9  # an occupancy cell: float32 density EMA, uint8 bitfield, the update's float32 fresh maxima


def grid_rows(cfg: "TrainConfig") -> int:
    """Rows of the encoding's trained table: the hash grid's ``sum_m min(s_m^3, 2^k)`` (its coarse
    levels are dense), Mtrf's ``sum_m s_m`` lines (of 3 axes x ``cp_rank`` each); the resolutions
    ``s_m`` grow geometrically from ``base_resolution`` as in ``HashGridSpec``/``CPGridSpec``."""
    top = cfg.max_resolution if cfg.model == "ngp" else cfg.cp_max_resolution
    n, base = cfg.levels, cfg.base_resolution
    growth = 1.0 if n == 1 else math.exp(math.log(max(top, base) / base) / (n - 1))
    res = [max(2, int(math.floor(base * growth**m + 1e-6))) for m in range(n)]
    if cfg.model == "ngp":
        return sum(min(s**3, 2**cfg.log2_table_size) for s in res)
    return sum(res)


def training_bytes(cfg: "TrainConfig") -> dict[str, int]:
    """Bytes a training run of ``cfg`` allocates whatever the scene, by part (a lower bound of the peak):

    ========== ==========================================================================================
    grid       ``grid_rows`` x (``features``, or 3 x ``cp_rank`` for Mtrf) x 4 B x 4 (value, gradient, two
               Adam moments); e.g. the default hash grid: 16 levels x 2^19 rows x 2 x 16 B = 256 MB
    mlp        the density MLP ``(L F + 1) h + (h + 1)(1 + g)`` and the colour MLP ``(g + 16 + 1) h +
               (h + 1) h + (h + 1) 3`` parameters (``h = hidden``, ``g = geo_features``), x 4 B x 4
    occupancy  ``occ_resolution^3`` cells x 9 B
    rays       ``batch_rays`` x 64 B (the first step draws that many rays)
    samples    ``sample_budget`` x (12 B of marching + 12 B position + 4 B x the encoding's width) per sample
    ========== ==========================================================================================
    """
    width = cfg.levels * (cfg.features if cfg.model == "ngp" else cfg.cp_rank)  # encoding output per sample
    per_row = cfg.features if cfg.model == "ngp" else 3 * cfg.cp_rank
    h, g = cfg.hidden, cfg.geo_features
    mlp_params = (width + 1) * h + (h + 1) * (1 + g) + (g + SH_FEATURES + 1) * h + (h + 1) * h + (h + 1) * 3
    return {
        "grid": grid_rows(cfg) * per_row * 4 * ADAM_COPIES,
        "mlp": mlp_params * 4 * ADAM_COPIES,
        "occupancy": cfg.occ_resolution**3 * OCC_CELL_BYTES,
        "rays": cfg.batch_rays * RAY_BYTES,
        "samples": cfg.sample_budget * (12 + 12 + 4 * width),
    }


# the settings that size each part, for the message
_PART_KEYS = {"grid": {"ngp": "log2_table_size, levels, features", "mtrf": "cp_rank, cp_max_resolution, levels"},
              "mlp": "hidden", "occupancy": "occ_resolution", "rays": "batch_rays", "samples": "sample_budget"}


def over_budget(need: int, budget_mb: int, what: str, lower: str) -> Optional[str]:
    """The one-line refusal when ``need`` bytes exceed ``budget_mb`` (``what`` needs them; lower ``lower``),
    else None. Callers raise it as their layer's error (ConfigError, PathError, ExportError)."""
    if need <= budget_mb * MB:
        return None
    return (f"{what} needs at least {need / MB:,.0f} MB, over memory_budget_mb = {budget_mb}; lower {lower} "
            "(or raise memory_budget_mb on a machine with the memory)")


def training_memory_problem(cfg: "TrainConfig") -> Optional[str]:
    """:func:`over_budget` for :func:`training_bytes` against ``cfg.memory_budget_mb``, naming the largest part."""
    parts = training_bytes(cfg)
    largest = max(parts, key=parts.get)
    keys = _PART_KEYS[largest]
    keys = keys[cfg.model] if isinstance(keys, dict) else keys
    return over_budget(sum(parts.values()), cfg.memory_budget_mb,
                       f"this configuration (its {largest}: {parts[largest] / MB:,.0f} MB)", keys)


def render_bytes(height: int, width: int, frames: int = 1, depth: bool = False) -> int:
    """A rendered ``height`` x ``width`` image's working memory (64 B a pixel), plus ``frames`` uint8
    frames kept for a video (3 B a pixel, twice as wide with the depth map beside the RGB)."""
    return height * width * PIXEL_BYTES + frames * height * width * (2 if depth else 1) * 3


def mesh_bytes(resolution: int) -> int:
    """Marching cubes at ``resolution`` samples per axis: the float32 density grid and its padded copy."""
    return resolution**3 * 4 + (resolution + 2) ** 3 * 4
