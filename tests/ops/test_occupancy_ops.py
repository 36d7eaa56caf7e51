"""The occupancy-grid ops (warpnerf/ops/occupancy.py) against their torch twins
(warpnerf/ops/reference/occupancy.py), and OccupancyGrid.update through them against the code path it
replaced (the kernels launched by the grid itself)."""

import pytest
import torch

from warpnerf.model.occupancy import OccupancyGrid
from warpnerf.ops import occupancy as ops
from warpnerf.ops.reference import occupancy as twins

AABB = (-1.0, -0.5, -2.0, 1.0, 1.5, 0.0)  # not a cube, not centred


def _grid_floats(res, aabb=AABB):
    lo, hi = list(aabb[:3]), list(aabb[3:])
    return lo, [(h - l) / res for l, h in zip(lo, hi)], [res / (h - l) for l, h in zip(lo, hi)]


@pytest.mark.parametrize("res", [1, 7, 16])
def test_sample_points_match_the_twin(res):
    g = torch.Generator().manual_seed(res)
    cells = torch.randint(0, res**3, (5000,), generator=g, dtype=torch.int32)
    jitter = torch.rand(5000, 3, generator=g)
    lo, cell_size, _ = _grid_floats(res)
    got = ops.occupancy_sample_points(cells, jitter, lo, cell_size, res)
    want = twins.occupancy_sample_points(cells, jitter, lo, cell_size, res)
    assert got.shape == (5000, 3) and got.dtype == torch.float32
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("res", [1, 5, 16])
def test_scatter_max_matches_the_twin_exactly_with_repeated_cells(res):
    g = torch.Generator().manual_seed(10 + res)
    lo, _, scale = _grid_floats(res)
    n = 4000
    # points spread a little beyond the box (some fall outside), then many into a few cells
    box_lo, box_hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    points = box_lo + (torch.rand(n, 3, generator=g) * 1.2 - 0.1) * (box_hi - box_lo)
    points[: n // 2] = points[torch.randint(0, 8, (n // 2,), generator=g)] + 1e-7 * torch.randn(n // 2, 3, generator=g)
    points[5] = float("nan")
    points[6] = torch.tensor(AABB[3:])  # the max corner is outside ([0, res) is half-open)
    points[7] = torch.tensor(AABB[:3])  # the min corner is inside
    sigmas = torch.rand(n, generator=g) * 10.0
    sigmas[::97] = float("inf")
    fill = torch.full((res**3,), -1.0)
    fill[::3] = 2.5  # cells holding a value already: the max includes it
    got = ops.occupancy_scatter_max(points, sigmas, lo, scale, res, fill.clone())
    want = twins.occupancy_scatter_max(points, sigmas, lo, scale, res, fill.clone())
    assert torch.equal(got, want)
    assert bool((got > fill).any())  # something was scattered, with repeats (n >> res^3 for res 5)


def test_ema_and_bitfield_match_the_twins_exactly():
    g = torch.Generator().manual_seed(3)
    n = 4096
    density = torch.rand(n, generator=g) * 3.0
    density[::11] = 0.0
    fresh = torch.where(torch.rand(n, generator=g) < 0.5, torch.rand(n, generator=g) * 3.0, torch.full((n,), -1.0))
    fresh[::13] = 0.0  # sampled, empty
    fresh[::17] = float("inf")
    got = ops.occupancy_ema(fresh, 0.95, density.clone())
    want = twins.occupancy_ema(fresh, 0.95, density.clone())
    assert torch.equal(got, want) and not torch.equal(got, density)
    for threshold in (0.01, float(got[got.isfinite()].mean()), 1.0 / 3.0):
        bits_got = ops.occupancy_bitfield(got, threshold, torch.full((n,), 7, dtype=torch.uint8))
        bits_want = twins.occupancy_bitfield(got, threshold, torch.full((n,), 7, dtype=torch.uint8))
        assert bits_got.dtype == torch.uint8 and torch.equal(bits_got, bits_want)
        assert set(bits_got.unique().tolist()) <= {0, 1}


def test_ops_check_their_inputs():
    with pytest.raises(TypeError, match="cells"):
        ops.occupancy_sample_points(torch.zeros(3, dtype=torch.int64), torch.rand(3, 3), [0.0] * 3, [1.0] * 3, 2)
    with pytest.raises(ValueError, match="contiguous"):
        ops.occupancy_ema(torch.zeros(4), 0.9, torch.zeros(8)[::2])
    with pytest.raises(TypeError, match="bitfield"):
        ops.occupancy_bitfield(torch.zeros(4), 0.1, torch.zeros(4))


def _old_update(grid: OccupancyGrid, step, density_fn, generator):
    """OccupancyGrid.update as it was before the ops existed (the grid launching the kernels), verbatim
    but for the names."""
    from warpnerf.device import init_warp
    from warpnerf.kernels.occupancy import occupancy_bitfield, occupancy_ema, occupancy_sample_points, occupancy_scatter_max
    from warpnerf.ops.launch import as_warp, launch

    wp = init_warp()
    lo, hi = grid.aabb[:3], grid.aabb[3:]
    res = grid.resolution
    cells = grid._pick_cells(step, generator)
    jitter = grid._random(torch.rand, (cells.shape[0], 3), generator)
    points = torch.empty(cells.shape[0], 3, dtype=torch.float32, device=grid.device)
    cell_size = wp.vec3(*[(h - l) / res for l, h in zip(lo, hi)])
    launch(occupancy_sample_points, cells.shape[0],
           [as_warp(cells), as_warp(jitter, wp.vec3), wp.vec3(*lo), cell_size, res, as_warp(points, wp.vec3)], grid.device)
    sigmas = grid._evaluate(density_fn, points)
    fresh = torch.full((grid.num_cells,), -1.0, dtype=torch.float32, device=grid.device)
    grid_scale = wp.vec3(*[res / (h - l) for l, h in zip(lo, hi)])
    launch(occupancy_scatter_max, cells.shape[0],
           [as_warp(points, wp.vec3), as_warp(sigmas), wp.vec3(*lo), grid_scale, res, as_warp(fresh)], grid.device)
    launch(occupancy_ema, grid.num_cells, [as_warp(fresh), grid.decay, as_warp(grid.density)], grid.device)
    threshold = min(grid.threshold, float(grid.density.mean()))
    launch(occupancy_bitfield, grid.num_cells, [as_warp(grid.density), threshold, as_warp(grid.bitfield)], grid.device)
    grid._updates += 1


def _field(x):
    """A smooth density with structure at every scale, so cell faces and the max matter."""
    return 40.0 * torch.relu(torch.sin(5.0 * x[:, 0]) * torch.cos(3.0 * x[:, 1] + x[:, 2]) - 0.3) + 1e-3 * x[:, 2] ** 2


def test_update_through_the_ops_is_bit_identical_to_the_old_code_path():
    """Warm-up and partial updates (random picks, with repeats), several in a row: the same density
    and bitfield, bit for bit, as the kernels launched the old way, from the same generator state."""
    new, old = (OccupancyGrid(AABB, resolution=12, warmup_steps=2, uniform_fraction=0.5) for _ in range(2))
    g_new, g_old = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    for step in range(5):
        new.update(step, _field, g_new)
        _old_update(old, step, _field, g_old)
        assert torch.equal(new.density, old.density), step
        assert torch.equal(new.bitfield, old.bitfield), step
        assert 0.0 < new.occupied_fraction() < 1.0


def test_update_on_the_torch_twins_matches_the_warp_ops():
    """The same update with every op on its twin (use_backend): equal grids (the sample points may
    differ in the last bit, which a density smooth across cells never shows in the bitfield)."""
    from warpnerf.ops import use_backend

    warp_grid, torch_grid = (OccupancyGrid(AABB, resolution=10, warmup_steps=1) for _ in range(2))
    g_w, g_t = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    for step in range(3):
        warp_grid.update(step, _field, g_w)
        with use_backend("torch"):
            torch_grid.update(step, _field, g_t)
        torch.testing.assert_close(torch_grid.density, warp_grid.density, rtol=1e-5, atol=1e-6)
        assert torch.equal(torch_grid.bitfield, warp_grid.bitfield)
