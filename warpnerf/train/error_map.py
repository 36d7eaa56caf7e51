"""Training pixels drawn where the error is (instant-ngp's error map), with unbiased weights.

Uniform pixel sampling spends most rays of an object-centric scene on background and on parts
that are already fitted. :class:`ErrorMap` keeps, per training image, a coarse grid of cells
(at most ``cells`` per side) holding a running mean of the squared error of the rays that fell
in each cell. A share ``share`` of each batch is drawn with probability proportional to the
cell's root-mean-square error (for a squared loss the gradient of a ray scales with its error,
so this is the proportional-to-gradient choice), the rest uniformly. Every ray carries the
importance weight uniform density / mixture density, so the weighted mean of the per-ray losses
is an unbiased estimate of the mean over all pixels: the objective is the uniform one, only its
gradient noise is lower. Uniform rays keep every cell's estimate fresh; a weight is at most
1 / (1 - share).

Pure torch: a few hundred thousand cells and one multinomial draw per step, far from the hot loops.
"""

from __future__ import annotations

import math

import torch

MAX_CELLS = 1 << 24  # torch.multinomial's limit on categories


def cell_layout(height: int, width: int, cells: int) -> tuple[int, int, int]:
    """Square cells of ``ceil(max(height, width) / cells)`` pixels: (cell size, rows, columns)."""
    cell = max(1, math.ceil(max(height, width) / cells))
    return cell, math.ceil(height / cell), math.ceil(width / cell)


class ErrorMap:
    """Per-image error grid for ``n_views`` images of ``height`` x ``width`` pixels.

    Args:
        share: fraction of each batch drawn in proportion to the cells' RMS error (0 < share < 1).
        cells: cells per side of an image at most; a cell is ``ceil(max(h, w) / cells)`` pixels square.
        decay: weight of the old value when a cell's running mean takes a new batch mean.
    """

    def __init__(self, n_views: int, height: int, width: int, share: float, cells: int = 64,
                 decay: float = 0.5, device: torch.device | str = "cpu"):
        if not 0.0 < share < 1.0:
            raise ValueError(f"error_sampling must be in (0, 1) (a share of the rays), got {share}")
        self.n_views, self.height, self.width = int(n_views), int(height), int(width)
        self.share, self.decay = float(share), float(decay)
        self.cell, self.rows, self.cols = cell_layout(self.height, self.width, cells)
        # torch.multinomial takes at most 2^24 categories: fewer cells per image on huge captures
        while cells > 1 and self.n_views * self.rows * self.cols > MAX_CELLS:
            cells //= 2
            self.cell, self.rows, self.cols = cell_layout(self.height, self.width, cells)
        self.cells_per_view = self.rows * self.cols
        dev = torch.device(device)
        # every cell starts at the same error: the first draws are uniform over cells
        self.sq_err = torch.ones(self.n_views * self.cells_per_view, device=dev)
        # pixels per cell (the last row and column of cells may be cut by the image border)
        ch = torch.clamp(self.height - torch.arange(self.rows, device=dev) * self.cell, max=self.cell)
        cw = torch.clamp(self.width - torch.arange(self.cols, device=dev) * self.cell, max=self.cell)
        self.cell_h, self.cell_w = ch, cw
        self.area = (ch[:, None] * cw[None, :]).reshape(-1).float().repeat(self.n_views)

    def cell_of(self, idx: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
        """Flat cell id of pixels (view idx, column px, row py), all int64."""
        return idx * self.cells_per_view + (py // self.cell) * self.cols + px // self.cell

    def _cell_probabilities(self) -> torch.Tensor:
        p = self.sq_err.clamp_min(0).sqrt()
        total = p.sum()
        # nothing left to fit anywhere: uniform over pixels (a select, not a branch: no device sync on CUDA)
        return torch.where(total > 0, p / total.clamp_min(1e-30), self.area / self.area.sum())

    def sample(self, n: int, gen: torch.Generator):
        """``n`` pixels: view ids, columns, rows (int64) and each pixel's importance weight (float)."""
        dev = self.sq_err.device
        n_err = int(round(self.share * n))
        n_uni = n - n_err
        idx_u = torch.randint(0, self.n_views, (n_uni,), generator=gen, device=dev)
        px_u = torch.randint(0, self.width, (n_uni,), generator=gen, device=dev)
        py_u = torch.randint(0, self.height, (n_uni,), generator=gen, device=dev)
        prob = self._cell_probabilities()
        cells = torch.multinomial(prob, n_err, replacement=True, generator=gen) if n_err else prob.new_zeros(0).long()
        view, rest = cells // self.cells_per_view, cells % self.cells_per_view
        r, c = rest // self.cols, rest % self.cols
        fy, fx = torch.rand(2, n_err, generator=gen, device=dev)
        py_e = r * self.cell + (fy * self.cell_h[r]).long().clamp_max(self.cell_h[r] - 1)
        px_e = c * self.cell + (fx * self.cell_w[c]).long().clamp_max(self.cell_w[c] - 1)
        idx, px, py = torch.cat([idx_u, view]), torch.cat([px_u, px_e]), torch.cat([py_u, py_e])
        # density of the mixture relative to the uniform one, at each drawn pixel
        cell = self.cell_of(idx, px, py)
        pixels = float(self.n_views * self.height * self.width)
        relative = (1.0 - self.share) + self.share * prob[cell] * pixels / self.area[cell]
        return idx, px, py, 1.0 / relative

    @torch.no_grad()
    def update(self, idx: torch.Tensor, px: torch.Tensor, py: torch.Tensor, sq_err: torch.Tensor) -> None:
        """Blend each touched cell's running squared error with the mean ``sq_err`` of its rays."""
        # sums over the touched cells only (a batch touches a few thousand of the map's cells);
        # index_add_ adds each cell's rays in batch order, as a map-sized buffer would
        hit, slot = torch.unique(self.cell_of(idx, px, py), return_inverse=True)
        total = sq_err.new_zeros(hit.shape[0], dtype=torch.float32).index_add_(0, slot, sq_err.float())
        count = torch.zeros_like(total).index_add_(0, slot, torch.ones_like(sq_err, dtype=torch.float32))
        self.sq_err[hit] = self.decay * self.sq_err[hit] + (1.0 - self.decay) * (total / count)

    def state_dict(self) -> dict:
        return {"sq_err": self.sq_err}

    def load_state_dict(self, state: dict) -> None:
        self.sq_err.copy_(state["sq_err"])
