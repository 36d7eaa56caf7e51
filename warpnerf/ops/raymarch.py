"""``march_rays``: occupancy-grid ray marching into packed samples (Warp kernel, no gradient).

Two passes over the rays with the same kernel: count samples per ray, exclusive cumsum in
torch, fill the packed arrays. Outputs are per ray and disjoint, so on CPU the rays are split
into fixed chunks (see :mod:`warpnerf.device`) that run on the thread pool; on CUDA each pass
is one launch. The result never depends on the thread count.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import torch

from warpnerf.device import init_warp
from warpnerf.ops.launch import aabb_floats, as_warp, launch_over_rays, twin_dispatch

__all__ = ["march_rays", "march_rays_within_budget", "march_rays_window", "MarchState", "PackedSamples",
           "prefix_rows", "rays_within_budget"]


# candidate steps one ray may take at most (= kernels/raymarch.py MAX_STEPS_PER_RAY, kept here so the
# torch twin does not import Warp; a test checks they agree)
MAX_STEPS_PER_RAY = 65536


class PackedSamples(NamedTuple):
    """Samples of all rays in one flat array, grouped by ray in ray order.

    Samples of ray r are ``[ray_offsets[r], ray_offsets[r] + ray_counts[r])``.
    """

    ray_indices: torch.Tensor  # (S,) int32, ray of each sample, non-decreasing
    t_starts: torch.Tensor  # (S,) float32, interval start along the ray (units of t, see march_rays)
    t_ends: torch.Tensor  # (S,) float32, interval end
    ray_offsets: torch.Tensor  # (R,) int32, index of the ray's first sample
    ray_counts: torch.Tensor  # (R,) int32, number of samples of the ray


def prefix_rows(ray_offsets: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``counts[r]`` samples of every ray r of a packed array, in packed order: (ray, row),
    both (sum(counts),) int64, ``row`` indexing the packed array (``counts`` <= the rays' counts)."""
    counts = counts.long()
    ray = torch.repeat_interleave(torch.arange(counts.shape[0], device=counts.device), counts)
    local = torch.arange(ray.shape[0], device=counts.device) - (torch.cumsum(counts, 0) - counts)[ray]
    return ray, ray_offsets.long()[ray] + local


@twin_dispatch
def march_rays(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb: Sequence[float],
    occ_bitfield: Optional[torch.Tensor],
    occ_resolution: int,
    near: float,
    far: float,
    step_size: float,
    max_samples_per_ray: int = 1024,
    jitter: Optional[torch.Tensor] = None,
    contract: bool = False,
    occupied_box: Optional[Sequence[float]] = None,
    occupied_blocks: Optional[tuple] = None,
) -> PackedSamples:
    """March rays through the occupied cells of the scene box with a fixed step.

    A ray is x(t) = o + t d. ``t``, ``near``, ``far`` and ``step_size`` are in units of |d|:
    pass unit directions to make them metric distances. The marched interval [t0, t1] is
    [near, far] intersected with the ray's interval inside the box. Sample k covers
    ``[t0 + (k + u) step, min(t0 + (k + 1 + u) step, t1)]`` with u = ``jitter[r]`` (0 without
    jitter), and is kept when its midpoint lies in an occupied cell of the grid. Only the last
    sample of a ray can be shorter than ``step_size``; with jitter, [t0, t0 + u step) is left
    out, which fresh offsets every iteration average away. Non-contiguous inputs are copied.
    Rays with a NaN/inf origin or direction get no samples, and no ray takes more than
    ``MAX_STEPS_PER_RAY`` candidate steps, so bad input can never hang the march.

    Args:
        rays_o: (R, 3) float32 ray origins.
        rays_d: (R, 3) float32 ray directions (unit length recommended, see above).
        aabb: 6 floats (xmin, ymin, zmin, xmax, ymax, zmax), the box the grid covers.
        occ_bitfield: (res^3,) uint8, 1 = occupied, cell (ix, iy, iz) at (ix * res + iy) * res + iz
            (:class:`warpnerf.model.occupancy.OccupancyGrid` layout); ``None`` = the whole box is occupied.
        occ_resolution: res, cells per axis.
        near, far: clip range of t (``far`` may be ``inf``: the box bounds the march).
        step_size: sample spacing along t, > 0.
        max_samples_per_ray: cap on the samples of one ray (the first ones along the ray are kept).
        jitter: optional (R,) float32 in [0, 1), per-ray shift of the first sample in units of
            ``step_size``; stratified training draws ``torch.rand(R, generator=g)``.
        contract: unbounded scenes (MipNeRF-360 contraction, ``kernels/raymarch.py``
            ``march_rays_contracted``): rays live in the normalised world and are marched over
            [near, far] (``far`` finite) with no box; each step is ``step_size`` long in the
            contracted space (world steps ~ ``step_size * |x|^2`` on rays leaving the scene)
            and the occupancy cell is the one of the *contracted* midpoint, ``aabb`` being the
            grid's box in contracted space (``(-2, -2, -2, 2, 2, 2)``).
        occupied_box: optional 6 floats bounding every occupied cell
            (:meth:`~warpnerf.model.occupancy.OccupancyGrid.occupied_box`): rays then skip the candidates
            far from it. The samples are the same with or without it (ignored when ``contract``).
    Returns:
        :class:`PackedSamples` on the device of ``rays_o``. Not differentiable: the outputs carry
        no gradient w.r.t. the rays; recompute positions as ``o[ray] + t * d[ray]`` in torch.

    Example:
        >>> o = torch.tensor([[0.0, 0.0, -3.0]]); d = torch.tensor([[0.0, 0.0, 1.0]])
        >>> s = march_rays(o, d, (-1, -1, -1, 1, 1, 1), None, 1, near=0.0, far=10.0, step_size=0.5)
        >>> s.t_starts.tolist()
        [2.0, 2.5, 3.0, 3.5]
    """
    return march_rays_within_budget(rays_o, rays_d, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                                    max_samples_per_ray, jitter, contract=contract, occupied_box=occupied_box,
                                    occupied_blocks=occupied_blocks)[0]


@twin_dispatch
def march_rays_within_budget(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb: Sequence[float],
    occ_bitfield: Optional[torch.Tensor],
    occ_resolution: int,
    near: float,
    far: float,
    step_size: float,
    max_samples_per_ray: int = 1024,
    jitter: Optional[torch.Tensor] = None,
    max_total_samples: Optional[int] = None,
    contract: bool = False,
    occupied_box: Optional[Sequence[float]] = None,
    occupied_blocks: Optional[tuple] = None,
) -> tuple[PackedSamples, int]:
    """:func:`march_rays` with a cap on the packed samples of the whole batch (a memory bound).

    When the rays would take more than ``max_total_samples`` samples, only the longest prefix of
    rays that fits keeps its samples; the remaining rays get none (``ray_counts`` 0) and are never
    filled, so the allocation stays within the budget whatever the occupancy grid holds. Returns
    ``(samples, n)``: rays [0, n) were marched (n = R without a cap); callers that must not lose
    rays march the rest in another call.
    """
    _check_rays(rays_o, rays_d, jitter)
    lo, hi, res, near, far, step_size = _check_march(rays_o, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                                                     max_samples_per_ray, contract)
    device = rays_o.device
    num_rays = rays_o.shape[0]
    if occ_bitfield is None:
        # a single always-occupied cell: the kernel then only tests "inside the box"
        res, occupied_blocks = 1, None
        occ_bitfield = torch.ones(1, dtype=torch.uint8, device=device)
    counts = torch.zeros(num_rays, dtype=torch.int32, device=device)
    empty_f = torch.zeros(0, dtype=torch.float32, device=device)
    if num_rays == 0:
        return PackedSamples(counts.clone(), empty_f, empty_f.clone(), counts.clone(), counts), 0

    wp = init_warp()
    from warpnerf.kernels import raymarch as kernels  # lazy: Warp loads with the first launch, not with the op's module

    kernel = kernels.march_rays_contracted if contract else kernels.march_rays
    jitter_t = jitter if jitter is not None else empty_f.new_zeros(1)
    offsets = torch.zeros(num_rays, dtype=torch.int32, device=device)
    # the uniform march visits only candidates near the occupied cells' box, across empty blocks (same samples)
    grid = _march_grid(kernels, lo, hi, res, occ_bitfield, None if contract else occupied_box,
                       None if contract else occupied_blocks, device)
    head = [
        as_warp(rays_o, wp.vec3),
        as_warp(rays_d, wp.vec3),
        as_warp(jitter_t),
        int(jitter is not None),
        grid,
        near,
        far,
        step_size,
        int(max_samples_per_ray),
    ]
    ws_counts = as_warp(counts)
    ws_offsets = as_warp(offsets)
    dummy_i = as_warp(torch.zeros(1, dtype=torch.int32, device=device))
    dummy_f = as_warp(torch.zeros(1, dtype=torch.float32, device=device))
    launch_over_rays(kernel, num_rays, head + [0, ws_offsets, ws_counts, dummy_i, dummy_f, dummy_f], device)

    if max_total_samples is not None:
        if int(max_total_samples) < 1:
            raise ValueError(f"march_rays: max_total_samples must be >= 1, got {max_total_samples}")
        # drop whole rays from the end so the fill pass never allocates more than the budget
        keep = rays_within_budget(counts, int(max_total_samples))
        counts[keep:] = 0
    else:
        keep = num_rays
    total = int(counts.sum(dtype=torch.int64))
    if total >= 2**31:
        raise ValueError(f"march_rays: {total} samples exceed int32 indexing; march fewer rays at once")
    torch.cumsum(counts, 0, out=offsets)
    offsets -= counts
    ray_indices = torch.empty(total, dtype=torch.int32, device=device)
    t_starts = torch.empty(total, dtype=torch.float32, device=device)
    t_ends = torch.empty(total, dtype=torch.float32, device=device)
    if total > 0:
        outs = [as_warp(ray_indices), as_warp(t_starts), as_warp(t_ends)]
        launch_over_rays(kernel, num_rays, head + [1, ws_offsets, ws_counts, *outs], device)
    return PackedSamples(ray_indices, t_starts, t_ends, offsets, counts), keep


def _march_grid(kernels, lo: list, hi: list, res: int, occ_bitfield: torch.Tensor, occupied_box, occupied_blocks,
                device):
    """The kernels' ``MarchGrid``: the grid's box, scale, bitfield and resolution, the box around its
    occupied cells (:func:`_padded_box`) and the empty-block bits (:func:`_block_args`)."""
    wp = init_warp()
    grid = kernels.MarchGrid()
    grid.aabb_min, grid.aabb_max = wp.vec3(*lo), wp.vec3(*hi)
    grid.grid_scale = wp.vec3(*[res / (h - l) for l, h in zip(lo, hi)])
    grid.bitfield, grid.res = as_warp(occ_bitfield, wp.uint8), int(res)
    box_lo, box_hi = _padded_box(occupied_box, lo, hi)
    grid.box_min, grid.box_max = wp.vec3(*box_lo), wp.vec3(*box_hi)
    grid.blocks, grid.block = _block_args(occupied_blocks, res, device)
    return grid


def _block_args(occupied_blocks, res: int, device) -> list:
    """(blocks, block) of the empty-block skip: ``occupied_blocks`` (b, blocks) as
    :meth:`~warpnerf.model.occupancy.OccupancyGrid.occupied_blocks` returns it, or one occupied
    block covering the grid (nothing is skipped)."""
    wp = init_warp()
    if occupied_blocks is None:
        return [as_warp(torch.ones(1, dtype=torch.uint8, device=device), wp.uint8), max(int(res), 1)]
    block, bits = occupied_blocks
    nb = -(-int(res) // int(block))
    if not isinstance(bits, torch.Tensor) or bits.dtype != torch.uint8 or tuple(bits.shape) != (nb**3,):
        raise ValueError(f"march_rays: occupied_blocks must be (block, ({nb}^3,) uint8 tensor) for resolution {res} "
                         f"and block {block}")
    return [as_warp(bits.to(device), wp.uint8), int(block)]


def _padded_box(occupied_box, lo: list, hi: list) -> tuple[list, list]:
    """(min, max) corners of ``occupied_box`` grown by 1e-4 of the scene box per side (a margin
    far above float rounding, so a ray grazing a face is never cut short), or the scene box."""
    if occupied_box is None:
        return lo, hi
    box_lo, box_hi = aabb_floats(occupied_box)
    pad = [1e-4 * (h - l) for l, h in zip(lo, hi)]
    return [b - p for b, p in zip(box_lo, pad)], [b + p for b, p in zip(box_hi, pad)]


class MarchState(NamedTuple):
    """Where each ray of a :func:`march_rays_window` march resumes (all (R,), updated in place)."""

    k: torch.Tensor  # int32, next candidate step along the ray; -1 once the ray is finished
    t: torch.Tensor  # float32, next sample's start (contracted march; the uniform one derives it from k)
    taken: torch.Tensor  # int32, samples emitted so far

    @staticmethod
    def start(num_rays: int, near: float, device) -> "MarchState":
        """Every ray at its first candidate step."""
        return MarchState(torch.zeros(num_rays, dtype=torch.int32, device=device),
                          torch.full((num_rays,), float(near), dtype=torch.float32, device=device),
                          torch.zeros(num_rays, dtype=torch.int32, device=device))

    def select(self, index: torch.Tensor) -> "MarchState":
        """The state of rays ``index`` (a copy), for marching a subset of the rays on."""
        return MarchState(*(v.index_select(0, index) for v in self))

    @property
    def finished(self) -> torch.Tensor:
        """(R,) bool: rays with no samples left."""
        return self.k < 0


@twin_dispatch
def march_rays_window(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    state: MarchState,
    window: int,
    aabb: Sequence[float],
    occ_bitfield: Optional[torch.Tensor],
    occ_resolution: int,
    near: float,
    far: float,
    step_size: float,
    max_samples_per_ray: int = 1024,
    contract: bool = False,
    occupied_box: Optional[Sequence[float]] = None,
    occupied_blocks: Optional[tuple] = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The next at most ``window`` samples of every ray, from where ``state`` says it stopped.

    Marching a ray window after window (``state`` from :meth:`MarchState.start`, updated in
    place) yields exactly the samples of :func:`march_rays` without jitter, in order; a renderer
    that stops a ray once it is opaque never marches the rest of it. Returns ``(t_starts,
    t_ends, counts)``: (R, window) float32 intervals of which the first ``counts[r]`` of row r
    are samples (the rest is garbage), and (R,) int32 counts. Arguments as in :func:`march_rays`;
    ``occupied_box`` (6 floats, e.g. :meth:`~warpnerf.model.occupancy.OccupancyGrid.occupied_box`), a box
    holding every occupied cell: the uniform march then skips the candidates before and after
    it (same samples, fewer steps). Ignored by the contracted march.
    """
    _check_rays(rays_o, rays_d, None)
    lo, hi, res, near, far, step_size = _check_march(rays_o, aabb, occ_bitfield, occ_resolution, near, far, step_size,
                                                     max_samples_per_ray, contract)
    window = int(window)
    if window < 1:
        raise ValueError(f"march_rays_window: window must be >= 1, got {window}")
    num_rays, device = rays_o.shape[0], rays_o.device
    for name, v, dtype in (("k", state.k, torch.int32), ("t", state.t, torch.float32),
                           ("taken", state.taken, torch.int32)):
        if v.dtype != dtype or tuple(v.shape) != (num_rays,) or v.device != device or not v.is_contiguous():
            raise ValueError(f"march_rays_window: state.{name} must be a contiguous ({num_rays},) {dtype} tensor "
                             f"on {device}, got {tuple(v.shape)} {v.dtype} on {v.device}")
    counts = torch.zeros(num_rays, dtype=torch.int32, device=device)
    t_starts = torch.empty(num_rays, window, dtype=torch.float32, device=device)
    t_ends = torch.empty(num_rays, window, dtype=torch.float32, device=device)
    if num_rays == 0:
        return t_starts, t_ends, counts
    if occ_bitfield is None:
        res, occupied_blocks = 1, None
        occ_bitfield = torch.ones(1, dtype=torch.uint8, device=device)
    wp = init_warp()
    from warpnerf.kernels import raymarch as kernels  # lazy: Warp loads with the first launch, not with the op's module

    grid = _march_grid(kernels, lo, hi, res, occ_bitfield, None if contract else occupied_box,
                       None if contract else occupied_blocks, device)
    inputs = [as_warp(rays_o.contiguous(), wp.vec3), as_warp(rays_d.contiguous(), wp.vec3), int(contract), grid,
              near, far, step_size, int(max_samples_per_ray), window, as_warp(state.k), as_warp(state.t), as_warp(state.taken), as_warp(counts),
              as_warp(t_starts.view(-1)), as_warp(t_ends.view(-1))]
    launch_over_rays(kernels.march_rays_window, num_rays, inputs, device)
    return t_starts, t_ends, counts


def rays_within_budget(ray_counts: torch.Tensor, max_total_samples: int) -> int:
    """Length of the longest prefix of rays whose (R,) ``ray_counts`` sum to at most
    ``max_total_samples``."""
    csum = torch.cumsum(ray_counts, 0, dtype=torch.int64)
    return int(torch.searchsorted(csum, torch.tensor([max_total_samples], device=csum.device), right=True)[0])


def _check_march(rays_o, aabb, occ_bitfield, occ_resolution, near, far, step_size, max_samples_per_ray, contract):
    """Validate the march's scalars and grid; returns (lo, hi, res, near, far, step_size)."""
    lo, hi = aabb_floats(aabb)
    res = _check_grid(occ_bitfield, occ_resolution, rays_o.device)
    near, far, step_size = float(near), float(far), float(step_size)
    if not (step_size > 0.0 and near == near and far == far and near <= far):
        raise ValueError(
            f"march_rays: need step_size > 0 and near <= far, got step_size={step_size}, near={near}, far={far}"
        )
    if contract and far == float("inf"):
        raise ValueError("march_rays: a contracted march needs a finite far bound")
    # contracted: steps of one step_size along the line's contracted image, a few units long
    # (up to 4.2 measured on random rays, tests/ops/test_raymarch.py); 8 leaves room
    diagonal = 8.0 if contract else sum((h - l) ** 2 for l, h in zip(lo, hi)) ** 0.5
    if diagonal / step_size > MAX_STEPS_PER_RAY:
        raise ValueError(f"march_rays: step_size {step_size} needs more than {MAX_STEPS_PER_RAY} steps along the box "
                         f"diagonal {diagonal:.4g}; use a step of at least {diagonal / MAX_STEPS_PER_RAY:.3g}")
    if int(max_samples_per_ray) < 1:
        raise ValueError(f"march_rays: max_samples_per_ray must be >= 1, got {max_samples_per_ray}")
    return lo, hi, res, near, far, step_size


def _check_rays(rays_o, rays_d, jitter) -> None:
    for name, t in (("rays_o", rays_o), ("rays_d", rays_d)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"march_rays: {name} must be a torch tensor, got {type(t).__name__}")
        if t.dtype != torch.float32:
            raise TypeError(f"march_rays: {name} must be float32, got {t.dtype}")
        if t.dim() != 2 or t.shape[1] != 3:
            raise ValueError(f"march_rays: {name} must have shape (R, 3), got {tuple(t.shape)}")
    if rays_o.shape != rays_d.shape:
        raise ValueError(f"march_rays: rays_o {tuple(rays_o.shape)} and rays_d {tuple(rays_d.shape)} differ in shape")
    if rays_o.device != rays_d.device:
        raise ValueError(f"march_rays: rays_o is on {rays_o.device} but rays_d is on {rays_d.device}")
    if jitter is not None:
        if not isinstance(jitter, torch.Tensor) or jitter.dtype != torch.float32:
            raise TypeError("march_rays: jitter must be a float32 tensor of shape (R,)")
        if tuple(jitter.shape) != (rays_o.shape[0],) or jitter.device != rays_o.device:
            raise ValueError(
                f"march_rays: jitter must have shape ({rays_o.shape[0]},) on {rays_o.device}, "
                f"got {tuple(jitter.shape)} on {jitter.device}"
            )


def _check_grid(occ_bitfield, occ_resolution, device) -> int:
    res = int(occ_resolution)
    if res < 1:
        raise ValueError(f"march_rays: occ_resolution must be >= 1, got {occ_resolution}")
    if occ_bitfield is None:
        return res
    if not isinstance(occ_bitfield, torch.Tensor) or occ_bitfield.dtype != torch.uint8:
        raise TypeError("march_rays: occ_bitfield must be a uint8 tensor (1 = occupied) or None")
    if tuple(occ_bitfield.shape) != (res**3,):
        raise ValueError(
            f"march_rays: occ_bitfield must have shape ({res**3},) for resolution {res}, got {tuple(occ_bitfield.shape)}"
        )
    if occ_bitfield.device != device:
        raise ValueError(f"march_rays: occ_bitfield is on {occ_bitfield.device} but the rays are on {device}")
    return res
