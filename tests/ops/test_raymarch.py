"""march_rays: Warp kernel vs. its pure-torch twin, plus checks that do not trust either."""

import math

import pytest
import torch

from warpnerf.ops.raymarch import MarchState, march_rays, march_rays_window
from warpnerf.ops.reference.raymarch import march_rays as march_rays_ref
from warpnerf.ops.reference.raymarch import march_rays_window as march_rays_window_ref

AABB = (-1.5, -1.0, -0.5, 1.5, 1.25, 1.0)  # not a cube: catches axis mix-ups
RES = 8


def random_rays(seed: int, num_rays: int = 512):
    """Unit rays from inside and outside the box, some with axis-aligned directions (d_a = 0)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    origins = lo - 1.0 + torch.rand(num_rays, 3, generator=g) * (hi - lo + 2.0)
    dirs = torch.randn(num_rays, 3, generator=g)
    dirs[: num_rays // 8, 1:] = 0.0
    dirs[num_rays // 8 : num_rays // 4, 0] = 0.0
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    bitfield = (torch.rand(RES**3, generator=g) < 0.4).to(torch.uint8)
    jitter = torch.rand(num_rays, generator=g)
    return origins, dirs, bitfield, jitter


def midpoint_cells(samples, origins, dirs):
    """Float64 grid coordinates of every sample midpoint (independent of the kernel's float32 math)."""
    ray = samples.ray_indices.long()
    mid = 0.5 * (samples.t_starts.double() + samples.t_ends.double())
    p = origins.double()[ray] + dirs.double()[ray] * mid[:, None]
    lo, hi = torch.tensor(AABB[:3], dtype=torch.float64), torch.tensor(AABB[3:], dtype=torch.float64)
    return (p - lo) / (hi - lo) * RES


@pytest.mark.parametrize("use_grid", [True, False])
@pytest.mark.parametrize("use_jitter", [False, True])
def test_matches_twin_exactly(use_grid, use_jitter):
    origins, dirs, bitfield, jitter = random_rays(0)
    args = (origins, dirs, AABB, bitfield if use_grid else None, RES, 0.3, 3.5, 0.02)
    kwargs = dict(jitter=jitter if use_jitter else None)
    out = march_rays(*args, **kwargs)
    ref = march_rays_ref(*args, **kwargs)
    assert out.t_starts.numel() > 1000
    for name, a, b in zip(out._fields, out, ref):
        assert a.dtype == b.dtype and torch.equal(a, b), name


def test_max_samples_per_ray_keeps_the_first():
    origins, dirs, bitfield, _ = random_rays(1)
    full = march_rays(origins, dirs, AABB, bitfield, RES, 0.0, 10.0, 0.01)
    capped = march_rays(origins, dirs, AABB, bitfield, RES, 0.0, 10.0, 0.01, max_samples_per_ray=7)
    ref = march_rays_ref(origins, dirs, AABB, bitfield, RES, 0.0, 10.0, 0.01, max_samples_per_ray=7)
    assert int(full.ray_counts.max()) > 7
    assert torch.equal(capped.ray_counts, torch.clamp(full.ray_counts, max=7))
    first = torch.cat([torch.arange(o, o + c) for o, c in zip(full.ray_offsets.tolist(), capped.ray_counts.tolist())])
    assert torch.equal(capped.t_starts, full.t_starts[first.long()])
    for a, b in zip(capped, ref):
        assert torch.equal(a, b)


def test_samples_only_in_occupied_cells_inside_the_box():
    origins, dirs, bitfield, jitter = random_rays(2)
    near, far, step = 0.3, 3.5, 0.02
    s = march_rays(origins, dirs, AABB, bitfield, RES, near, far, step, jitter=jitter)
    g = midpoint_cells(s, origins, dirs)
    # a midpoint within 1e-5 cells of a face may round to either side in float32 (error ~1e-6 cells)
    frac = g - g.floor()
    on_face = ((frac < 1e-5) | (frac > 1 - 1e-5)).any(1)
    inside = ((g >= 0) & (g < RES)).all(1)
    cell = g.floor().long().clamp(0, RES - 1)
    occupied = bitfield[(cell[:, 0] * RES + cell[:, 1]) * RES + cell[:, 2]] == 1
    assert bool((inside & occupied | on_face).all())
    assert on_face.float().mean() < 1e-3
    assert bool((s.t_starts >= near).all() and (s.t_ends <= far).all() and (s.t_ends > s.t_starts).all())
    # t_end = t_start + step rounded in float32: one ulp of t (2.4e-7 at t < 4) over the step
    assert bool((s.t_ends - s.t_starts <= step + 2.4e-7).all())
    # packing: grouped by ray, in order, consistent with offsets and counts
    assert torch.equal(s.ray_indices, torch.repeat_interleave(torch.arange(len(origins)), s.ray_counts.long()).int())
    assert torch.equal(s.ray_offsets, (torch.cumsum(s.ray_counts, 0) - s.ray_counts).int())
    same_ray = s.ray_indices[1:] == s.ray_indices[:-1]
    assert bool((s.t_starts[1:][same_ray] > s.t_starts[:-1][same_ray]).all())


def test_rays_missing_the_box_get_no_samples():
    origins = torch.tensor([[0.0, 3.0, 0.0], [0.0, 3.0, 0.0], [-5.0, 0.0, 0.0], [-5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    dirs = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    # away from the box; beside it (parallel); behind the origin; box beyond `far`; inside but near > exit
    s = march_rays(origins, dirs, AABB, None, RES, near=0.0, far=3.0, step_size=0.01)
    assert s.ray_counts[:3].tolist() == [0, 0, 0]
    assert int(s.ray_counts[3]) == 0  # the box starts at t = 3.5 > far
    s = march_rays(origins[4:], dirs[4:], AABB, None, RES, near=1.5, far=9.0, step_size=0.01)
    assert s.ray_counts.tolist() == [0] and s.t_starts.numel() == 0
    # a zero direction inside the box would otherwise march until far = inf
    s = march_rays(origins[4:], torch.zeros(1, 3), AABB, None, RES, near=0.0, far=math.inf, step_size=0.01)
    assert s.ray_counts.tolist() == [0]


def test_without_grid_samples_cover_the_box_chord():
    origin, direction = torch.tensor([[-4.0, 0.1, 0.2]]), torch.tensor([[1.0, 0.0, 0.0]])
    s = march_rays(origin, direction, AABB, None, RES, near=0.0, far=math.inf, step_size=0.25)
    # the box spans x in [-1.5, 1.5]: t in [2.5, 5.5], 12 steps, the last one ends exactly at the exit
    assert s.ray_counts.tolist() == [12]
    assert s.t_starts[0].item() == 2.5 and s.t_ends[-1].item() == 5.5
    assert torch.equal(s.t_starts[1:], s.t_ends[:-1])
    jittered = march_rays(origin, direction, AABB, None, RES, 0.0, math.inf, 0.25, jitter=torch.tensor([0.5]))
    assert jittered.ray_counts.tolist() == [12]
    assert jittered.t_starts[0].item() == 2.625 and jittered.t_ends[-1].item() == 5.5
    assert jittered.t_ends[-1] - jittered.t_starts[-1] == 0.125


def test_rays_requiring_grad_are_left_alone():
    origins, dirs, bitfield, _ = random_rays(3, num_rays=16)
    origins.requires_grad_(True)
    s = march_rays(origins, dirs, AABB, bitfield, RES, 0.0, 5.0, 0.05)
    assert origins.grad is None and not s.t_starts.requires_grad


def test_two_threads_bit_identical(threads):
    origins, dirs, bitfield, jitter = random_rays(4, num_rays=1000)
    results = []
    for n_threads in (1, 2):
        threads(n_threads)
        results.append(march_rays(origins, dirs, AABB, bitfield, RES, 0.0, 6.0, 0.01, jitter=jitter))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_no_rays():
    s = march_rays(torch.zeros(0, 3), torch.zeros(0, 3), AABB, None, RES, 0.0, 1.0, 0.1)
    assert all(x.shape == (0,) for x in s)


def test_bad_inputs_raise():
    origins, dirs, bitfield, jitter = random_rays(5, num_rays=4)
    ok = dict(rays_o=origins, rays_d=dirs, aabb=AABB, occ_bitfield=bitfield, occ_resolution=RES, near=0.0, far=5.0,
              step_size=0.1)
    bad = [
        (TypeError, "rays_o must be float32", dict(rays_o=origins.double())),
        (TypeError, "rays_d must be a torch tensor", dict(rays_d=dirs.tolist())),
        (ValueError, r"rays_d must have shape \(R, 3\)", dict(rays_d=dirs[:, :2])),
        (ValueError, "differ in shape", dict(rays_d=dirs[:3])),
        (TypeError, "occ_bitfield must be a uint8", dict(occ_bitfield=bitfield.bool())),
        (ValueError, "occ_bitfield must have shape", dict(occ_resolution=RES + 1)),
        (ValueError, "aabb must have 6", dict(aabb=AABB[:5])),
        (ValueError, "min < max", dict(aabb=(0, 0, 0, 1, -1, 1))),
        (ValueError, "step_size > 0", dict(step_size=0.0)),
        (ValueError, "near <= far", dict(near=2.0, far=1.0)),
        (ValueError, "max_samples_per_ray", dict(max_samples_per_ray=0)),
        (ValueError, "jitter must have shape", dict(jitter=jitter[:2])),
        (TypeError, "jitter must be a float32", dict(jitter=jitter.double())),
    ]
    for error, message, change in bad:
        with pytest.raises(error, match=message):
            march_rays(**{**ok, **change})


def test_sample_budget_keeps_a_prefix_of_whole_rays():
    """march_rays_within_budget: the longest prefix of rays that fits keeps exactly the samples
    march_rays gives it; later rays get none; without a cap it is march_rays."""
    from warpnerf.ops.raymarch import march_rays_within_budget
    from warpnerf.ops.reference import raymarch as twin_mod

    g = torch.Generator().manual_seed(0)
    o = torch.rand(64, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -3.0])
    d = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    args = (o, d, (-1, -1, -1, 1, 1, 1), None, 1, 0.0, 10.0, 0.05)
    full = march_rays(*args)
    same, n_all = march_rays_within_budget(*args)
    assert n_all == 64 and all(torch.equal(a, b) for a, b in zip(full, same))
    budget = int(full.ray_counts.sum()) // 3
    cut, n = march_rays_within_budget(*args, max_total_samples=budget)
    csum = torch.cumsum(full.ray_counts, 0)
    assert n == int((csum <= budget).sum()) and 0 < n < 64
    assert cut.t_starts.shape[0] == int(csum[n - 1]) <= budget
    assert torch.equal(cut.ray_counts[:n], full.ray_counts[:n]) and int(cut.ray_counts[n:].sum()) == 0
    assert torch.equal(cut.t_starts, full.t_starts[: cut.t_starts.shape[0]])
    for cap in (None, budget):  # the torch twin (bench step's torch arm) gives the same packing
        twin, n_twin = twin_mod.march_rays_within_budget(*args, max_total_samples=cap)
        warp, n_warp = march_rays_within_budget(*args, max_total_samples=cap)
        assert n_twin == n_warp and all(torch.equal(a, b) for a, b in zip(twin, warp))


def test_non_finite_rays_return_quickly_with_no_samples():
    """Issue 11: a NaN pose with an infinite far bound made every ray step ~16.7M times."""
    import time

    from warpnerf.kernels.raymarch import MAX_STEPS_PER_RAY as kernel_cap
    from warpnerf.ops.raymarch import MAX_STEPS_PER_RAY
    from warpnerf.ops.reference import raymarch as twin_mod

    assert kernel_cap == MAX_STEPS_PER_RAY
    nan, inf = float("nan"), float("inf")
    o = torch.tensor([[nan, 0.0, -3.0], [0.0, 0.0, -3.0], [0.0, inf, -3.0], [0.0, 0.0, -3.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [nan, nan, nan], [0.0, 0.0, 1.0], [inf, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d[1, 2] = 1.0  # NaN only on two axes
    march_rays(o, d, AABB, None, RES, near=0.0, far=math.inf, step_size=0.01)  # compile outside the timing
    t0 = time.perf_counter()
    s = march_rays(o, d, AABB, None, RES, near=0.0, far=math.inf, step_size=0.01)
    seconds = time.perf_counter() - t0
    assert s.ray_counts[:4].tolist() == [0, 0, 0, 0]
    assert s.ray_counts[4] > 0  # the finite ray beside them is marched as usual
    assert seconds < 5.0  # 5 rays; before the guard the NaN ray alone stepped 2^24 times
    ref = twin_mod.march_rays(o, d, AABB, None, RES, near=0.0, far=math.inf, step_size=0.01)
    assert torch.equal(ref.ray_counts, s.ray_counts) and torch.equal(ref.t_starts, s.t_starts)


def test_step_too_small_for_the_step_cap_is_a_clear_error():
    o, d = torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="steps along the box diagonal"):
        march_rays(o, d, AABB, None, RES, near=0.0, far=10.0, step_size=1e-6)


# ---- the contracted (unbounded-scene) march ---------------------------------------------------

CONTRACTED_BOX = (-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)


def contracted_rays(seed: int, num_rays: int = 256):
    """Rays from inside and outside the unit ball (cameras of a 360° capture sit near it)."""
    g = torch.Generator().manual_seed(seed)
    origins = (torch.rand(num_rays, 3, generator=g) * 2 - 1) * 2.5
    dirs = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=g), dim=-1)
    dirs[:8, 1:] = 0.0  # axis-aligned directions
    dirs[:8, 0] = 1.0
    bitfield = (torch.rand(RES**3, generator=g) < 0.5).to(torch.uint8)
    return origins, dirs, bitfield, torch.rand(num_rays, generator=g)


@pytest.mark.parametrize("use_grid", [True, False])
@pytest.mark.parametrize("use_jitter", [False, True])
@pytest.mark.parametrize("cap", [1024, 5])
def test_contracted_matches_twin_exactly(use_grid, use_jitter, cap):
    origins, dirs, bitfield, jitter = contracted_rays(1)
    args = (origins, dirs, CONTRACTED_BOX, bitfield if use_grid else None, RES, 0.05, 1000.0, 0.02, cap)
    kwargs = dict(jitter=jitter if use_jitter else None, contract=True)
    out = march_rays(*args, **kwargs)
    ref = march_rays_ref(*args, **kwargs)
    assert out.t_starts.numel() > 1000
    for name, a, b in zip(out._fields, out, ref):
        assert a.dtype == b.dtype and torch.equal(a, b), name


def test_contracted_march_covers_the_ray_in_growing_steps():
    """Without a grid the samples tile [near + u dt, far] end to end; each is ~ one step long in the
    contracted space (checked against float64 contract()), also on rays passing the ball sideways."""
    from warpnerf.geometry.contraction import contract

    origins, dirs, _, jitter = contracted_rays(2, 64)
    step = 0.02
    s = march_rays(origins, dirs, CONTRACTED_BOX, None, RES, 0.05, 1000.0, step, jitter=jitter, contract=True)
    all_gaps = []
    for r in range(64):
        lo, n = int(s.ray_offsets[r]), int(s.ray_counts[r])
        ts, te = s.t_starts[lo:lo + n].double(), s.t_ends[lo:lo + n].double()
        assert torch.equal(ts[1:], te[:-1]) and float(te[-1]) == 1000.0
        x = origins[r].double() + dirs[r].double() * ts[:, None]
        inside = x.norm(dim=-1) <= 1.0
        torch.testing.assert_close((te - ts)[:-1][inside[:-1]], torch.full_like(ts, step)[:-1][inside[:-1]])
        c = contract(x)
        gaps = (c[1:] - c[:-1]).norm(dim=-1)
        # first order: exactly one step; shorter chords only where the contraction bends (towards far)
        assert float(gaps.max()) < 1.05 * step
        all_gaps.append(gaps)
    assert float(torch.cat(all_gaps).median()) > 0.9 * step
    # a line's contracted image is a few units long (measured up to 4.2 here): the wrapper's guard says 8
    assert int(s.ray_counts.max()) < 8 / step


def test_contracted_march_refuses_an_infinite_far():
    o, d, _, _ = contracted_rays(3, 4)
    with pytest.raises(ValueError, match="finite far"):
        march_rays(o, d, CONTRACTED_BOX, None, RES, 0.05, math.inf, 0.02, contract=True)


def test_contracted_grid_cells_are_looked_up_in_contracted_space():
    """A single occupied cell far out in contracted space (a 'distant background' shell cell) is
    found by a ray from the centre towards it, at the world distance the inverse contraction gives."""
    from warpnerf.geometry.contraction import uncontract

    res = 8
    bitfield = torch.zeros(res**3, dtype=torch.uint8)
    ix, iy, iz = 7, 4, 4  # contracted x in [1.5, 2), y and z in [0, 0.5)
    bitfield[(ix * res + iy) * res + iz] = 1
    o = torch.zeros(1, 3)
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.05, 0.05]]), dim=-1)
    s = march_rays(o, d, CONTRACTED_BOX, bitfield, res, 0.0, 1000.0, 0.01, contract=True)
    assert s.t_starts.numel() > 0
    mid = 0.5 * (s.t_starts + s.t_ends)
    c = (o + d * mid[:, None])
    from warpnerf.geometry.contraction import contract

    cc = contract(c)
    assert bool(((cc[:, 0] >= 1.5) & (cc[:, 0] < 2.0)).all())
    # world distances: from |contract| = 1.5 (r = 2) onwards
    assert float(mid.min()) > 0.9 * float(uncontract(torch.tensor([[1.5, 0.0, 0.0]])).norm())


def march_in_windows(march, origins, dirs, window, args, kwargs):
    """Every window of every ray until all are finished: per ray, the concatenated (t_start,
    t_end) lists, and the list of per-window (t_starts, t_ends, counts, state) results."""
    state = MarchState.start(origins.shape[0], args[3], origins.device)
    per_ray = [[] for _ in range(origins.shape[0])]
    rounds = []
    while not bool(state.finished.all()):
        ts, te, counts = march(origins, dirs, state, window, *args, **kwargs)
        rounds.append((ts, te, counts, MarchState(*(v.clone() for v in state))))
        for r in torch.nonzero(counts).squeeze(1).tolist():
            n = int(counts[r])
            per_ray[r] += list(zip(ts[r, :n].tolist(), te[r, :n].tolist()))
        assert len(rounds) < 1000
    return per_ray, rounds


def check_windows(origins, dirs, window, args, kwargs, min_samples):
    """Marching window after window gives exactly march_rays' samples (no jitter), and the
    kernel and its twin agree on every window's samples, counts and resume state."""
    full = march_rays(origins, dirs, *args, contract=kwargs.get("contract", False))
    per_ray, rounds = march_in_windows(march_rays_window, origins, dirs, window, args, kwargs)
    assert full.t_starts.numel() > min_samples
    for r in range(origins.shape[0]):
        lo, n = int(full.ray_offsets[r]), int(full.ray_counts[r])
        assert per_ray[r] == list(zip(full.t_starts[lo:lo + n].tolist(), full.t_ends[lo:lo + n].tolist())), r
    _, rounds_ref = march_in_windows(march_rays_window_ref, origins, dirs, window, args, kwargs)
    assert len(rounds_ref) == len(rounds)
    for (ts, te, counts, state), (ts_r, te_r, counts_r, state_r) in zip(rounds, rounds_ref):
        assert torch.equal(counts, counts_r)
        valid = torch.arange(window)[None, :] < counts[:, None].long()
        assert torch.equal(ts[valid], ts_r[valid]) and torch.equal(te[valid], te_r[valid])
        assert torch.equal(state.k, state_r.k) and torch.equal(state.taken, state_r.taken)


@pytest.mark.parametrize("contract", [False, True])
@pytest.mark.parametrize("window,cap", [(1, 1024), (3, 1024), (4, 7)])
def test_window_march_yields_the_full_march_and_matches_its_twin(contract, window, cap):
    if contract:
        origins, dirs, bitfield, _ = contracted_rays(2, 96)
        args = (CONTRACTED_BOX, bitfield, RES, 0.05, 1000.0, 0.02, cap)
    else:
        origins, dirs, bitfield, _ = random_rays(2, 96)
        args = (AABB, bitfield, RES, 0.3, 3.5, 0.02, cap)
    check_windows(origins, dirs, window, args, dict(contract=contract), min_samples=100)


@pytest.mark.parametrize("window", [1, 4])
def test_window_march_near_the_occupied_box_yields_the_same_samples(window):
    """With ``occupied_box`` (the box around the occupied cells) the window march starts each ray
    just before that box and stops just after it: still exactly march_rays' samples, and the
    kernel agrees with its twin."""
    origins, dirs, _, _ = random_rays(6, 1000)
    res = 16
    bitfield = torch.zeros(res, res, res, dtype=torch.uint8)
    g = torch.Generator().manual_seed(6)
    bitfield[5:11, 3:9, 7:13] = (torch.rand(6, 6, 6, generator=g) < 0.5).to(torch.uint8)
    lo, hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    cell = (hi - lo) / res
    box = tuple((lo + cell * torch.tensor([5, 3, 7])).tolist() + (lo + cell * torch.tensor([11, 9, 13])).tolist())
    args = (AABB, bitfield.flatten(), res, 0.3, 3.5, 0.01, 1024)
    check_windows(origins, dirs, window, args, dict(occupied_box=box), min_samples=300)


@pytest.mark.parametrize("use_jitter", [False, True])
def test_march_near_the_occupied_box_yields_the_same_samples(use_jitter):
    """march_rays with ``occupied_box`` (what training passes) skips the candidates far from the
    occupied cells and emits exactly the samples of the full march, also for rays that graze
    the box's faces and for a box computed by the occupancy grid itself."""
    from warpnerf.model.occupancy import OccupancyGrid

    origins, dirs, _, jitter = random_rays(7, 1000)
    res = 16
    grid = OccupancyGrid(AABB, resolution=res)
    bits = torch.zeros(res, res, res, dtype=torch.uint8)
    g = torch.Generator().manual_seed(7)
    bits[5:11, 3:9, 7:13] = (torch.rand(6, 6, 6, generator=g) < 0.5).to(torch.uint8)
    bits[5, 3, 7] = bits[10, 8, 12] = 1  # the box's corner cells, so it is exactly [5, 11) x [3, 9) x [7, 13)
    grid.bitfield.copy_(bits.flatten())
    box = grid.occupied_box()
    lo, hi = torch.tensor(AABB[:3]), torch.tensor(AABB[3:])
    assert torch.allclose(torch.tensor(box[:3]), lo + (hi - lo) * torch.tensor([5, 3, 7]) / res)
    # rays along the box's faces and edges: origins on a face plane, directions within it
    face = torch.tensor(box[:3]).expand(200, 3).clone()
    face[:, 1:] += torch.rand(200, 2, generator=g) * (torch.tensor(box[4:]) - torch.tensor(box[1:3]))
    face_dirs = torch.nn.functional.normalize(torch.cat([torch.zeros(200, 1), torch.randn(200, 2, generator=g)], 1), dim=1)
    o, d = torch.cat([origins, face - 3 * face_dirs]), torch.cat([dirs, face_dirs])
    jit = torch.cat([jitter, torch.rand(200, generator=g)]) if use_jitter else None
    args = (o, d, AABB, grid.bitfield, res, 0.3, 8.0, 0.01)
    full = march_rays(*args, jitter=jit)
    tight = march_rays(*args, jitter=jit, occupied_box=box)
    ref = march_rays_ref(*args, jitter=jit, occupied_box=box)
    assert full.t_starts.numel() > 2000
    for name, a, b, c in zip(full._fields, full, tight, ref):
        assert torch.equal(a, b) and torch.equal(a, c), name


def clustered_grid(res: int, seed: int) -> torch.Tensor:
    """(res^3,) bitfield with occupied cells in a few clusters and large empty regions between
    them, so many blocks of cells are empty and many are partly occupied."""
    g = torch.Generator().manual_seed(seed)
    bits = torch.zeros(res, res, res, dtype=torch.uint8)
    for _ in range(8):
        c = torch.randint(0, res - res // 4, (3,), generator=g).tolist()
        n = torch.randint(1, res // 4 + 1, (3,), generator=g).tolist()
        bits[c[0]:c[0] + n[0], c[1]:c[1] + n[1], c[2]:c[2] + n[2]] = 1
    bits.view(-1)[torch.randint(0, res**3, (res,), generator=g)] = 1  # isolated cells
    return bits.flatten()


@pytest.mark.parametrize("res,block", [(32, 8), (20, 8), (16, 4), (16, 16)])
@pytest.mark.parametrize("use_jitter", [False, True])
def test_march_across_empty_blocks_yields_the_same_samples(res, block, use_jitter):
    """With ``occupied_blocks`` the march jumps across blocks of cells that hold no occupied cell
    instead of testing every candidate there: exactly the samples of the full march, for any
    block size (also one that does not divide the resolution), with or without jitter and for
    rays along the box's axes (d_a = 0)."""
    from warpnerf.model.occupancy import OccupancyGrid

    origins, dirs, _, jitter = random_rays(8, 1500)
    grid = OccupancyGrid(AABB, resolution=res)
    grid.bitfield.copy_(clustered_grid(res, res + block))
    blocks = grid.occupied_blocks(block)
    assert 0.05 < float(blocks[1].float().mean()) < 0.9 or block == res  # some blocks empty, some not
    jit = jitter if use_jitter else None
    args = (origins, dirs, AABB, grid.bitfield, res, 0.3, 8.0, 0.004)
    full = march_rays(*args, jitter=jit)
    skipped = march_rays(*args, jitter=jit, occupied_blocks=blocks)
    both = march_rays(*args, jitter=jit, occupied_blocks=blocks, occupied_box=grid.occupied_box())
    assert full.t_starts.numel() > 2000
    for name, a, b, c in zip(full._fields, full, skipped, both):
        assert torch.equal(a, b) and torch.equal(a, c), name


@pytest.mark.parametrize("window", [1, 5])
def test_window_march_across_empty_blocks_yields_the_same_samples(window):
    """The rendering march with ``occupied_blocks`` and ``occupied_box``: window after window the
    samples of the full march, and the same counts and resume state as the twin."""
    from warpnerf.model.occupancy import OccupancyGrid

    origins, dirs, _, _ = random_rays(9, 600)
    grid = OccupancyGrid(AABB, resolution=24)
    grid.bitfield.copy_(clustered_grid(24, 1))
    assert 0.1 < float(grid.occupied_blocks(8)[1].float().mean()) < 0.9
    args = (AABB, grid.bitfield, 24, 0.3, 3.5, 0.006, 1024)
    check_windows(origins, dirs, window, args, dict(occupied_blocks=grid.occupied_blocks(8),
                                                    occupied_box=grid.occupied_box()), min_samples=300)


def test_occupied_blocks_mark_every_block_with_an_occupied_cell():
    """Block (bx, by, bz) is 1 exactly when some cell (x, y, z) with x // b = bx, ... is occupied
    (brute force over the cells); blocks past the grid's edge (res not a multiple of b) count
    only the cells inside; the blocks follow every change of the bitfield like the box."""
    from warpnerf.model.occupancy import OccupancyGrid

    res, b = 20, 8
    grid = OccupancyGrid((0, 0, 0, 1, 1, 1), resolution=res)
    assert bool(grid.occupied_blocks(b)[1].all())  # a new grid is fully occupied
    bits = clustered_grid(res, 3)
    grid.bitfield.copy_(bits)
    block, got = grid.occupied_blocks(b)
    nb = 3
    want = torch.zeros(nb, nb, nb, dtype=torch.uint8)
    for x, y, z in torch.nonzero(bits.view(res, res, res)).tolist():
        want[x // b, y // b, z // b] = 1
    assert block == b and got.shape == (nb**3,) and torch.equal(got, want.flatten())
    grid.bitfield.zero_()
    assert int(grid.occupied_blocks(b)[1].sum()) == 0
    with pytest.raises(ValueError, match="occupied_blocks"):
        march_rays(torch.zeros(1, 3), torch.ones(1, 3) / 3**0.5, (0, 0, 0, 1, 1, 1), grid.bitfield, res, 0.0, 2.0,
                   0.1, occupied_blocks=(4, got))


def test_occupied_box_follows_every_change_of_the_bitfield():
    """The grid computes its occupied box once per bitfield state: a grid update, an in-place
    torch change and a new tensor each give a fresh box."""
    from warpnerf.model.occupancy import OccupancyGrid

    grid = OccupancyGrid((0, 0, 0, 1, 1, 1), resolution=8)
    assert grid.occupied_box() == (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    grid.bitfield.zero_()
    assert grid.occupied_box() is None
    grid.bitfield[(2 * 8 + 3) * 8 + 4] = 1
    assert grid.occupied_box() == (0.25, 0.375, 0.5, 0.375, 0.5, 0.625)
    ball = lambda x: 100.0 * ((x - 0.5).norm(dim=-1) < 0.2).float()
    grid.update(step=0, density_fn=ball, generator=torch.Generator().manual_seed(0))
    lo, hi = grid.occupied_box()[:3], grid.occupied_box()[3:]
    assert all(0.2 <= a < 0.5 < b <= 0.8 for a, b in zip(lo, hi))
    grid.bitfield = torch.ones_like(grid.bitfield)
    assert grid.occupied_box() == (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)


def test_window_march_resumes_only_rays_not_finished():
    """A finished ray (k = -1) gets no samples and keeps its state; a subset of rays marched
    with ``MarchState.select`` continues where it stopped."""
    origins, dirs, bitfield, _ = random_rays(3, 64)
    args = (AABB, bitfield, RES, 0.3, 3.5, 0.02)
    state = MarchState.start(64, 0.3, origins.device)
    march_rays_window(origins, dirs, state, 2, *args)
    state.k[:32] = -1
    before = MarchState(*(v.clone() for v in state))
    _, _, counts = march_rays_window(origins, dirs, state, 2, *args)
    assert int(counts[:32].sum()) == 0 and torch.equal(state.k[:32], before.k[:32])
    assert torch.equal(state.taken[:32], before.taken[:32])
    pick = torch.arange(32, 64)
    sub = before.select(pick)
    ts_sub, _, counts_sub = march_rays_window(origins[pick], dirs[pick], sub, 2, *args)
    assert torch.equal(counts_sub, counts[32:]) and torch.equal(sub.k, state.k[32:])


def test_window_march_two_threads_bit_identical(threads):
    origins, dirs, bitfield, _ = random_rays(5, num_rays=1000)
    results = []
    for n_threads in (1, 2):
        threads(n_threads)
        state = MarchState.start(1000, 0.0, origins.device)
        out = [march_rays_window(origins, dirs, state, 5, AABB, bitfield, RES, 0.0, 6.0, 0.01) for _ in range(3)]
        valid = [torch.arange(5)[None, :] < n[:, None].long() for _, _, n in out]  # the rest is garbage
        results.append([t for (ts, te, n), v in zip(out, valid) for t in (ts[v], te[v], n)] + list(state))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_window_march_bad_inputs_raise():
    origins, dirs, bitfield, _ = random_rays(4, 8)
    state = MarchState.start(8, 0.3, origins.device)
    with pytest.raises(ValueError, match="window must be >= 1"):
        march_rays_window(origins, dirs, state, 0, AABB, bitfield, RES, 0.3, 3.5, 0.02)
    with pytest.raises(ValueError, match="state.k"):
        march_rays_window(origins, dirs, MarchState.start(7, 0.3, "cpu"), 2, AABB, bitfield, RES, 0.3, 3.5, 0.02)
