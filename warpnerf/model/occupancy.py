"""The occupancy grid: it keeps the density of the scene box and marches rays through it.

A res^3 grid of cells over the scene box keeps an exponential moving max of the density seen
in each cell (instant-ngp / nerfacc rule) and a bitfield of the cells worth sampling. Like
nerfacc's ``OccGridEstimator``, the grid is also what the renderer asks for samples
(:meth:`OccupancyGrid.sample`, :meth:`OccupancyGrid.march_window`): it hands the marcher
(:mod:`warpnerf.ops.raymarch`) its own box, bitfield, occupied box and occupied blocks. The
update's steps are the ops of :mod:`warpnerf.ops.occupancy`; they share the cell layout with the
marcher: cell of world point p = floor((p - aabb_min) / (aabb_max - aabb_min) * res), flat index
(ix * res + iy) * res + iz.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence

import torch

from warpnerf.ops.launch import aabb_floats
from warpnerf.ops.occupancy import occupancy_bitfield, occupancy_ema, occupancy_sample_points, occupancy_scatter_max
from warpnerf.ops.raymarch import MarchState, PackedSamples, march_rays_window, march_rays_within_budget

__all__ = ["OccupancyGrid"]

# density_fn is called on at most this many points at once (bounds the MLP's activation memory)
_EVAL_CHUNK = 2**18


class OccupancyGrid:
    """Density EMA and occupancy bitfield over the scene box.

    Update rule (nerfacc's variant of instant-ngp's): each update picks cells, evaluates
    ``density_fn`` at one uniformly jittered point per picked cell, and sets
    ``density = max(density * decay, sigma)`` on the picked cells only (a cell picked twice
    takes the larger sigma). During warm-up (step < ``warmup_steps``) every cell is picked;
    afterwards ``uniform_fraction`` * res^3 uniformly random cells (with repeats; instant-ngp
    and nerfacc: 1/4, the trainer's default 1/16) plus up to res^3 / 4 random currently
    occupied cells. A cell is occupied when density > min(threshold, mean density). The trainer's
    ``density_fn`` returns optical thickness (density * the marching step there), as nerfacc's
    ``occ_eval_fn`` does, so ``threshold`` is a thickness (instant-ngp and nerfacc: 0.01).
    Before the first update every cell is occupied, so an untrained model is sampled everywhere.

    Attributes:
        aabb: 6 floats (xmin, ymin, zmin, xmax, ymax, zmax).
        resolution: res, cells per axis.
        density: (res^3,) float32 EMA of the density (same units as ``density_fn``).
        bitfield: (res^3,) uint8, 1 = occupied (what :meth:`sample` and :meth:`march_window` skip by).

    Example:
        >>> grid = OccupancyGrid((-1, -1, -1, 1, 1, 1), resolution=16)
        >>> ball = lambda x: 100.0 * (x.norm(dim=-1) < 0.5).float()
        >>> grid.update(step=0, density_fn=ball, generator=torch.Generator().manual_seed(0))
        >>> 0.0 < grid.occupied_fraction() < 0.1
        True
    """

    def __init__(
        self,
        aabb: Sequence[float],
        resolution: int = 128,
        device="cpu",
        decay: float = 0.95,
        threshold: float = 0.01,
        warmup_steps: int = 256,
        update_every: int = 16,
        uniform_fraction: float = 0.25,
    ):
        lo, hi = aabb_floats(aabb)
        if int(resolution) < 1 or int(update_every) < 1 or not 0.0 <= decay <= 1.0 or not 0.0 < uniform_fraction <= 1.0:
            raise ValueError(
                f"OccupancyGrid: need resolution >= 1, update_every >= 1, decay in [0, 1] and uniform_fraction "
                f"in (0, 1], got {resolution}, {update_every}, {decay}, {uniform_fraction}"
            )
        self.aabb = tuple(lo + hi)
        self.resolution = int(resolution)
        self.device = torch.device(device)
        self.decay = float(decay)
        self.threshold = float(threshold)
        self.warmup_steps = int(warmup_steps)
        self.update_every = int(update_every)
        self.uniform_fraction = float(uniform_fraction)
        num_cells = self.resolution**3
        self.density = torch.zeros(num_cells, dtype=torch.float32, device=self.device)
        self.bitfield = torch.ones(num_cells, dtype=torch.uint8, device=self.device)
        self._updates = 0  # Warp writes the bitfield without bumping torch's version counter
        self._box_key, self._box = None, None
        self._blocks_key, self._blocks = None, None

    @property
    def num_cells(self) -> int:
        return self.resolution**3

    def maybe_update(
        self, step: int, density_fn: Callable[[torch.Tensor], torch.Tensor], generator: Optional[torch.Generator] = None
    ) -> bool:
        """Run :meth:`update` when ``step % update_every == 0``; returns whether it ran."""
        if step % self.update_every != 0:
            return False
        self.update(step, density_fn, generator)
        return True

    def update(
        self, step: int, density_fn: Callable[[torch.Tensor], torch.Tensor], generator: Optional[torch.Generator] = None
    ) -> None:
        """Sample the density in picked cells and refresh ``density`` and ``bitfield``.

        Args:
            step: training step (decides warm-up vs. partial update).
            density_fn: maps (N, 3) float32 world positions to (N,) (or (N, 1)) densities >= 0;
                called under ``torch.no_grad`` on chunks of at most 2**18 points.
            generator: torch generator (any device) for reproducible cell picks and jitter.
        """
        lo, hi = self.aabb[:3], self.aabb[3:]
        res = self.resolution
        cells = self._pick_cells(step, generator)
        jitter = self._random(torch.rand, (cells.shape[0], 3), generator)
        points = occupancy_sample_points(cells, jitter, lo, [(h - l) / res for l, h in zip(lo, hi)], res)
        sigmas = self._evaluate(density_fn, points)

        fresh = torch.full((self.num_cells,), -1.0, dtype=torch.float32, device=self.device)
        occupancy_scatter_max(points, sigmas, lo, [res / (h - l) for l, h in zip(lo, hi)], res, fresh)
        occupancy_ema(fresh, self.decay, self.density)
        threshold = min(self.threshold, float(self.density.mean()))
        occupancy_bitfield(self.density, threshold, self.bitfield)
        self._updates += 1

    def sample(self, rays_o: torch.Tensor, rays_d: torch.Tensor, near: float, far: float, step: float,
               max_samples_per_ray: int = 1024, jitter: Optional[torch.Tensor] = None,
               max_total_samples: Optional[int] = None, contract: bool = False) -> tuple[PackedSamples, int]:
        """March (R, 3) rays through this grid's occupied cells into packed samples (no gradient).

        :func:`~warpnerf.ops.raymarch.march_rays_within_budget` with this grid's box, bitfield and
        resolution, and its :meth:`occupied_box` and :meth:`occupied_blocks` to skip empty space
        (same samples, fewer steps). ``near``, ``far``, ``step``, ``jitter`` and ``contract`` as
        there; ``max_total_samples`` caps the batch's samples: returns ``(samples, n)``, rays
        [0, n) marched (n = R without a cap).

        Example:
            >>> grid = OccupancyGrid((-1, -1, -1, 1, 1, 1), resolution=2)
            >>> o, d = torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])
            >>> grid.sample(o, d, near=0.0, far=10.0, step=0.5)[0].t_starts.tolist()
            [2.0, 2.5, 3.0, 3.5]
        """
        return march_rays_within_budget(rays_o, rays_d, self.aabb, self.bitfield, self.resolution, near, far, step,
                                        max_samples_per_ray, jitter, max_total_samples=max_total_samples,
                                        contract=contract, occupied_box=self.occupied_box(),
                                        occupied_blocks=self.occupied_blocks())

    def march_window(self, rays_o: torch.Tensor, rays_d: torch.Tensor, state: MarchState, window: int, near: float,
                     far: float, step: float, max_samples_per_ray: int = 1024,
                     contract: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The next at most ``window`` samples of every ray from ``state`` (updated in place):
        :func:`~warpnerf.ops.raymarch.march_rays_window` through this grid, skipping empty space as
        :meth:`sample` does. Returns ``(t_starts, t_ends, counts)``."""
        return march_rays_window(rays_o, rays_d, state, window, self.aabb, self.bitfield, self.resolution, near, far,
                                 step, max_samples_per_ray, contract=contract, occupied_box=self.occupied_box(),
                                 occupied_blocks=self.occupied_blocks())

    def occupied_fraction(self) -> float:
        """Fraction of cells currently marked occupied, in [0, 1]."""
        return float(self.bitfield.float().mean())

    def occupied_box(self) -> Optional[tuple]:
        """The box (6 floats, the grid's coordinates) bounding every occupied cell; None when no
        cell is occupied. Computed once per bitfield state (an update, or any in-place torch
        change of ``bitfield``, or a new tensor, starts a new one): the trainer asks every step."""
        key = (self._updates, self.bitfield.data_ptr(), self.bitfield._version)
        if key != self._box_key:
            self._box_key, self._box = key, self._compute_occupied_box()
        return self._box

    def occupied_blocks(self, block: int = 8) -> tuple:
        """``(block, bits)``: bits (nb^3,) uint8 with nb = ceil(res / block), 1 where some cell of
        the block of block^3 cells is occupied (flat index (bx * nb + by) * nb + bz). The marcher
        jumps across empty blocks instead of stepping through them (same samples). Cached per
        bitfield state, like :meth:`occupied_box`."""
        key = (self._updates, self.bitfield.data_ptr(), self.bitfield._version, int(block))
        if key != self._blocks_key:
            res, nb = self.resolution, -(-self.resolution // int(block))
            grid = torch.zeros((nb * block,) * 3, dtype=torch.uint8, device=self.bitfield.device)
            grid[:res, :res, :res] = self.bitfield.view(res, res, res)
            bits = grid.view(nb, block, nb, block, nb, block).amax(dim=(1, 3, 5)).reshape(-1).contiguous()
            self._blocks_key, self._blocks = key, (int(block), bits)
        return self._blocks

    def _compute_occupied_box(self) -> Optional[tuple]:
        res = self.resolution
        grid = self.bitfield.view(res, res, res)
        bounds = []
        for axis in range(3):
            other = tuple(a for a in range(3) if a != axis)
            hit = torch.nonzero(grid.amax(dim=other)).flatten()
            if hit.numel() == 0:
                return None
            bounds.append((int(hit[0]), int(hit[-1]) + 1))
        lo, hi = self.aabb[:3], self.aabb[3:]
        box_lo = [lo[a] + (hi[a] - lo[a]) * bounds[a][0] / res for a in range(3)]
        box_hi = [lo[a] + (hi[a] - lo[a]) * bounds[a][1] / res for a in range(3)]
        return tuple(box_lo + box_hi)

    def _pick_cells(self, step: int, generator: Optional[torch.Generator]) -> torch.Tensor:
        """(M,) int32 cell indices to sample in this update (repeats allowed)."""
        n = self.num_cells
        if step < self.warmup_steps:
            return torch.arange(n, dtype=torch.int32, device=self.device)
        quarter = max(1, n // 4)
        uniform = self._random(torch.randint, (max(1, int(n * self.uniform_fraction)),), generator, high=n)
        occupied = torch.nonzero(self.bitfield).flatten()
        if occupied.numel() > quarter:
            occupied = occupied[self._random(torch.randint, (quarter,), generator, high=occupied.numel())]
        return torch.cat([uniform, occupied]).int()

    def _random(self, sampler, shape, generator, **kwargs) -> torch.Tensor:
        """Draw on the generator's device (torch requires it), then move to the grid's device."""
        device = generator.device if generator is not None else self.device
        return sampler(size=shape, generator=generator, device=device, **kwargs).to(self.device)

    def _evaluate(self, density_fn, points: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            parts = [density_fn(chunk) for chunk in points.split(_EVAL_CHUNK)]
        sigmas = torch.cat([p.reshape(-1) for p in parts]).to(torch.float32)
        if sigmas.shape[0] != points.shape[0]:
            raise ValueError(
                f"OccupancyGrid: density_fn must return one density per point, "
                f"got {sigmas.shape[0]} for {points.shape[0]}"
            )
        # +inf is a legitimate "very dense" (exp activations overflow); NaN would poison the mean
        if bool(torch.isnan(sigmas).any()):
            raise ValueError("OccupancyGrid: density_fn returned NaN")
        return sigmas
