"""OccupancyGrid: update rule, cell layout shared with march_rays, and input checks."""

import pytest
import torch

from warpnerf.model.occupancy import OccupancyGrid
from warpnerf.ops.raymarch import march_rays

AABB = (-1.0, -0.5, -2.0, 1.0, 1.5, 0.0)  # not a cube, not centred: catches axis and layout mix-ups
CENTRE = torch.tensor([0.2, 0.4, -1.1])
RADIUS = 0.6


def ball(x: torch.Tensor) -> torch.Tensor:
    return 50.0 * ((x - CENTRE).norm(dim=-1) < RADIUS).float()


def cell_centres(res: int) -> torch.Tensor:
    """(res^3, 3) world centres in the documented layout idx = (ix * res + iy) * res + iz."""
    lo, hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    ijk = torch.stack(torch.meshgrid(*[torch.arange(res)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return lo + (ijk + 0.5) / res * (hi - lo)


def test_warmup_update_finds_the_ball():
    res = 16
    grid = OccupancyGrid(AABB, resolution=res, warmup_steps=10)
    assert grid.occupied_fraction() == 1.0  # untouched grid samples everywhere
    grid.update(0, ball, generator=torch.Generator().manual_seed(0))
    dist = (cell_centres(res) - CENTRE).norm(dim=1)
    half_diagonal = 0.5 * (torch.tensor(AABB[3:]) - torch.tensor(AABB[:3])).norm() / res
    inside = dist < RADIUS - half_diagonal
    outside = dist > RADIUS + half_diagonal
    assert inside.sum() > 50
    assert bool((grid.bitfield[inside] == 1).all()) and bool((grid.bitfield[outside] == 0).all())
    assert torch.equal(grid.density[inside], torch.full((int(inside.sum()),), 50.0))
    assert 0.0 < grid.occupied_fraction() < 0.2


def test_marching_a_fitted_grid_stays_near_the_ball():
    """End to end through the shared cell layout: grid update -> march_rays."""
    res = 16
    grid = OccupancyGrid(AABB, resolution=res)
    grid.update(0, ball, generator=torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(2)
    origins = CENTRE + torch.randn(256, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 4.0])
    dirs = CENTRE + torch.randn(256, 3, generator=g) * 0.4 - origins
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    s = march_rays(origins, dirs, grid.aabb, grid.bitfield, grid.resolution, 0.0, 10.0, 0.01)
    mid = 0.5 * (s.t_starts + s.t_ends)
    points = origins[s.ray_indices.long()] + dirs[s.ray_indices.long()] * mid[:, None]
    cell_diagonal = float((torch.tensor(AABB[3:]) - torch.tensor(AABB[:3])).norm()) / res
    assert s.t_starts.numel() > 1000
    assert float((points - CENTRE).norm(dim=1).max()) < RADIUS + cell_diagonal
    # and it does not miss the ball: half of the samples are truly inside it
    assert float(((points - CENTRE).norm(dim=1) < RADIUS).float().mean()) > 0.5


def test_ema_max_rule_and_threshold():
    res = 8
    grid = OccupancyGrid(AABB, resolution=res, decay=0.9, threshold=0.01, warmup_steps=100)
    old = torch.rand(res**3, generator=torch.Generator().manual_seed(3)) * 2.0
    grid.density.copy_(old)
    grid.update(0, lambda x: torch.full((x.shape[0],), 0.8))  # warm-up: every cell is sampled
    assert torch.equal(grid.density, torch.maximum(old * 0.9, torch.tensor(0.8)))
    threshold = min(0.01, float(grid.density.mean()))
    assert torch.equal(grid.bitfield, (grid.density > threshold).to(torch.uint8))

    # mean below the threshold: the mean decides
    grid.density.zero_()
    grid.update(1, lambda x: 1e-3 * (x[:, 0] > 0).float())
    assert float(grid.density.mean()) < 0.01
    assert torch.equal(grid.bitfield, (grid.density > grid.density.mean()).to(torch.uint8))
    assert 0.3 < grid.occupied_fraction() < 0.7


@pytest.mark.parametrize("uniform_fraction, lo, hi", [(0.25, 0.18, 0.26), (1 / 16, 0.045, 0.075)])
def test_after_warmup_only_picked_cells_change(uniform_fraction, lo, hi):
    res = 16
    grid = OccupancyGrid(AABB, resolution=res, decay=0.5, warmup_steps=1, uniform_fraction=uniform_fraction)
    grid.update(0, ball, generator=torch.Generator().manual_seed(4))
    occupied = grid.bitfield == 1
    grid.density.fill_(1.0)  # every picked cell now visibly decays to 0.5
    grid.update(5, lambda x: torch.zeros(x.shape[0]), generator=torch.Generator().manual_seed(5))
    changed = grid.density != 1.0
    assert bool((grid.density[changed] == 0.5).all())
    # picked: all occupied cells (fewer than a quarter here) plus uniform_fraction * res^3 uniform
    # draws with repeats, i.e. 1 - exp(-f) distinct cells: 22 % for 1/4, 6.1 % for 1/16
    assert 0.0 < float(occupied.float().mean()) < 0.25 and bool(changed[occupied].all())
    fraction_of_rest = float(changed[~occupied].float().mean())
    assert lo < fraction_of_rest < hi


def test_maybe_update_follows_update_every():
    grid = OccupancyGrid(AABB, resolution=4, update_every=16)
    calls = []

    def density(x):
        calls.append(x.shape[0])
        return torch.zeros(x.shape[0])

    assert grid.maybe_update(0, density) and grid.maybe_update(32, density)
    assert not grid.maybe_update(17, density)
    assert calls == [64, 64]


def test_same_generator_same_grid():
    grids = []
    for _ in range(2):
        grid = OccupancyGrid(AABB, resolution=16, warmup_steps=0)
        grid.update(0, ball, generator=torch.Generator().manual_seed(6))
        grids.append(grid)
    assert torch.equal(grids[0].density, grids[1].density) and torch.equal(grids[0].bitfield, grids[1].bitfield)


def test_density_fn_is_chunked_and_runs_without_grad():
    grid = OccupancyGrid(AABB, resolution=80)  # 512000 cells: two chunks of 2**18 points
    sizes = []

    def density(x):
        sizes.append((x.shape[0], torch.is_grad_enabled()))
        return torch.zeros(x.shape[0], 1)  # (N, 1) is accepted

    grid.update(0, density)
    assert sizes == [(2**18, False), (80**3 - 2**18, False)]


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="min < max"):
        OccupancyGrid((0, 0, 0, 1, 1, -1))
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGrid(AABB, resolution=0)
    with pytest.raises(ValueError, match="uniform_fraction"):
        OccupancyGrid(AABB, uniform_fraction=0.0)
    grid = OccupancyGrid(AABB, resolution=4)
    with pytest.raises(ValueError, match="one density per point"):
        grid.update(0, lambda x: torch.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        grid.update(0, lambda x: torch.full((x.shape[0],), float("nan")))


def test_occupied_box_bounds_the_occupied_cells():
    res = 8
    grid = OccupancyGrid(AABB, resolution=res)
    assert grid.occupied_box() == pytest.approx(AABB)  # a new grid is fully occupied
    grid.bitfield.zero_()
    assert grid.occupied_box() is None
    cells = grid.bitfield.view(res, res, res)
    cells[2, 5, 1] = 1
    cells[4, 3, 6] = 1
    lo, hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    size = (hi - lo) / res
    want = (lo + size * torch.tensor([2, 3, 1])).tolist() + (lo + size * torch.tensor([5, 6, 7])).tolist()
    assert grid.occupied_box() == pytest.approx(want)


def test_the_grid_marches_with_its_own_box_bitfield_and_skips():
    """OccupancyGrid.sample / .march_window are the ops' marches given the grid's own arguments:
    the same samples as spelling them out, with and without the empty-space skips."""
    from warpnerf.ops.raymarch import MarchState, march_rays_window, march_rays_within_budget

    grid = OccupancyGrid(AABB, resolution=16)
    grid.update(0, ball, generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(4)
    o = CENTRE + torch.randn(300, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])
    d = torch.nn.functional.normalize(CENTRE + torch.randn(300, 3, generator=g) * 0.5 - o, dim=-1)
    jitter = torch.rand(300, generator=g)
    got, n = grid.sample(o, d, 0.0, 10.0, 0.01, 64, jitter, max_total_samples=3000)
    for skips in ({}, dict(occupied_box=grid.occupied_box(), occupied_blocks=grid.occupied_blocks())):
        want, m = march_rays_within_budget(o, d, grid.aabb, grid.bitfield, grid.resolution, 0.0, 10.0, 0.01, 64,
                                           jitter, max_total_samples=3000, **skips)
        assert n == m and all(torch.equal(a, b) for a, b in zip(got, want))
    assert 0 < n < 300 and got.t_starts.numel() > 1000
    # the skips change where a ray's state resumes (k), never its samples; with them, the state too
    skips = dict(occupied_box=grid.occupied_box(), occupied_blocks=grid.occupied_blocks())
    s1, s2, s3 = (MarchState.start(300, 0.0, "cpu") for _ in range(3))
    for _ in range(3):
        w1 = grid.march_window(o, d, s1, 8, 0.0, 10.0, 0.01, 64)
        w2 = march_rays_window(o, d, s2, 8, grid.aabb, grid.bitfield, grid.resolution, 0.0, 10.0, 0.01, 64)
        w3 = march_rays_window(o, d, s3, 8, grid.aabb, grid.bitfield, grid.resolution, 0.0, 10.0, 0.01, 64, **skips)
        keep = torch.arange(8) < w1[2][:, None]
        for w in (w2, w3):
            assert torch.equal(w1[2], w[2]) and torch.equal(w1[0][keep], w[0][keep]) and torch.equal(w1[1][keep], w[1][keep])
        assert torch.equal(s1.taken, s2.taken) and all(torch.equal(a, b) for a, b in zip(s1, s3))
