"""Benchmark plumbing (warpnerf/studies/bench.py): warm-up, median, --repeats honoured by both arms and by the
roofline; the roofline's gather probe (kernels/roofline.py) against a torch gather-sum."""

import math

import pytest
import torch

from warpnerf import openmp

from warpnerf.studies import bench


def _recording_median(monkeypatch):
    """Patch bench.median_seconds to record (timed function's name, repeats) of every timing."""
    seen = []
    real = bench.median_seconds

    def record(fn, reps, warmup=2):
        seen.append((fn.__qualname__, reps))
        return real(fn, reps, warmup)

    monkeypatch.setattr(bench, "median_seconds", record)
    return seen


def test_median_seconds_warms_up_then_takes_the_median(monkeypatch):
    calls = []
    clock = iter([0.0, 1.0, 10.0, 12.0, 20.0, 20.5])  # three timed runs of 1.0, 2.0, 0.5 s
    monkeypatch.setattr(bench.time, "perf_counter", lambda: next(clock))
    assert bench.median_seconds(lambda: calls.append(1), repeats=3, warmup=2) == 1.0
    assert len(calls) == 5  # 2 untimed + 3 timed
    with pytest.raises(ValueError, match="repeats"):
        bench.median_seconds(lambda: None, repeats=0)


def test_encoding_bench_honours_repeats_for_both_arms(monkeypatch):
    seen = _recording_median(monkeypatch)
    res = bench.bench_encoding(n=1024, levels=2, log2_table_size=8, repeats=3)
    assert res["repeats"] == res["torch_repeats"] == 3
    assert seen and {reps for _, reps in seen} == {3}  # Warp, torch twin and roofline timed alike
    names = {name for name, _ in seen}
    assert "bench_encoding.<locals>.alloc" in names and "gather_rate.<locals>.run" in names
    assert res["warp_fwdbwd_pts_s"] > 0 and res["ratio_fwdbwd"] > 0
    # timings of a loaded machine: only their presence and sign are facts a unit test can check
    assert res["warp_bwd_alloc_s"] > 0 and res["warp_bwd_alloc_fraction"] > 0
    roof = res["roofline"]
    assert roof["gather_table_rows"] == 2 << 8 and roof["gather_points"] == 1024 * 2
    assert roof["machine_gathers_s"] > 0 and roof["encoding_fwd_gathers_s"] > 0
    # same gather count and thread split as the forward (0.86 measured on a contended VM at n=4096, L=4;
    # above 1 where the grid's caches help): a measured ratio, so only its sign is asserted
    assert roof["encoding_fwd_fraction"] > 0 and math.isfinite(roof["encoding_fwd_fraction"])
    assert "roofline: machine" in bench.format_encoding(res)
    # the figures move by ~25 % with torch's OpenMP wait setting: recorded beside them
    assert res["openmp_wait"] == openmp.describe() and f"OpenMP wait {res['openmp_wait']}" in \
        bench.format_encoding(res)


def test_encoding_bench_without_roofline(monkeypatch):
    seen = _recording_median(monkeypatch)
    res = bench.bench_encoding(n=256, levels=2, log2_table_size=8, repeats=1, torch_repeats=1, roofline=False)
    assert res["roofline"] is None and "roofline" not in bench.format_encoding(res)
    assert "gather_rate.<locals>.run" not in {name for name, _ in seen}


@pytest.mark.parametrize("n_threads", [1, 2])
def test_gather_probe_sums_the_rows_a_torch_gather_reads(threads, n_threads):
    """The probe kernel reads the rows it is given: bit-identical to torch adding them in the same order."""
    threads(n_threads)
    gen = torch.Generator().manual_seed(0)
    table = torch.randn(64, 2, generator=gen)
    rows = torch.randint(0, 64, (1001, 8), generator=gen, dtype=torch.int32)
    expected = table[rows[:, 0].long()]
    for k in range(1, 8):
        expected = expected + table[rows[:, k].long()]
    assert torch.equal(bench.gather_sum(table, rows), expected)
    with pytest.raises(ValueError, match="rows"):
        bench.gather_sum(table, rows[:, :4])


def test_mlp_roofline_counts_linear_flops_and_honours_repeats(monkeypatch):
    seen = _recording_median(monkeypatch)
    density = torch.nn.Sequential(torch.nn.Linear(32, 64), torch.nn.ReLU(), torch.nn.Linear(64, 16))
    color = torch.nn.Sequential(torch.nn.Linear(31, 64), torch.nn.ReLU(), torch.nn.Linear(64, 64), torch.nn.ReLU(),
                                torch.nn.Linear(64, 3))
    flops = bench.mlp_flops_per_sample(density, color)
    assert flops == 2 * (32 * 64 + 64 * 16) + 2 * (31 * 64 + 64 * 64 + 64 * 3)
    n = 4096
    # small layers and activations stay below the GEMM peak (0.3-0.5 measured here); a ratio of two
    # timings, so only its sign is asserted (a busy machine can skew either one)
    peak = bench.gemm_flop_rate(3, shape=(n, 64, 64))
    mlp_s = bench.mlp_seconds((density, color), n, 3)
    assert peak > 0 and mlp_s > 0 and 3 * flops * n / mlp_s / peak > 0
    assert [reps for _, reps in seen] == [3, 3]
    assert all(p.grad is None for p in [*density.parameters(), *color.parameters()])  # nothing accumulated


def test_format_step_prints_the_roofline_line():
    res = dict(scene="chair", scene_source="builtin", rays_per_step=1024, samples_per_step=5e4, device="cpu",
               threads=2, warp_iters_s=5.0, warp_samples_s=2.5e5, torch_iters_s=1.0, torch_samples_s=5e4, ratio=5.0,
               roofline=dict(gemm_flops_s=8e10, mlp_flops_s=3e10, mlp_fraction=0.375, mlp_step_fraction=0.4))
    assert "roofline: GEMM 80.0 GFLOP/s, MLPs fwd+bwd reach 30.0 GFLOP/s (38%), 40% of the warp step" in \
        bench.format_step(res)
    assert "roofline" not in bench.format_step({**res, "roofline": None})
    assert "OpenMP wait GOMP_SPINCOUNT=10000" in bench.format_step({**res, "openmp_wait": "GOMP_SPINCOUNT=10000"})


def test_openmp_wait_defaults_and_their_description(monkeypatch):
    for k in openmp.WAIT_SETTINGS:  # set first, so that monkeypatch restores each afterwards
        monkeypatch.setenv(k, "x")
        monkeypatch.delenv(k)
    assert openmp.describe() == "default"
    assert openmp.set_wait_defaults() is True
    assert openmp.describe() == "GOMP_SPINCOUNT=10000 KMP_BLOCKTIME=0"
    monkeypatch.delenv("KMP_BLOCKTIME")
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")  # any wait setting of the user's: nothing changes
    assert openmp.set_wait_defaults() is False
    assert openmp.describe() == "OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=10000"


def test_twin_arm_runs_every_op_of_a_render_on_its_twin(monkeypatch):
    """bench step's torch arm is warpnerf.ops.use_backend("torch"): the ops a renderer calls (it broke
    silently once, when bench swapped names by hand and the renderer moved to march_rays_within_budget)
    reach their twins, and the Warp ops come back afterwards."""
    from warpnerf.model.occupancy import OccupancyGrid
    from warpnerf.ops import current_backend, registry

    calls = []
    for op_module, name in registry.OPS:
        module = registry.TWIN_MODULES[getattr(op_module, name).__twin__[0]]
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _real=real, _name=name, **k: calls.append(_name) or _real(*a, **k))
    grid = OccupancyGrid((-1, -1, -1, 1, 1, 1), resolution=4, warmup_steps=1)
    rays = torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    with bench._twin_ops():
        assert current_backend() == "torch"
        grid.update(0, lambda x: (x.norm(dim=-1) < 0.5).float(), torch.Generator().manual_seed(0))
        packed, _ = grid.sample(*rays, 0.0, 10.0, 0.1, max_total_samples=100)
    assert current_backend() == "warp"
    assert {"occupancy_sample_points", "occupancy_scatter_max", "occupancy_ema", "occupancy_bitfield",
            "march_rays_within_budget"} <= set(calls)
    n = len(calls)
    grid.sample(*rays, 0.0, 10.0, 0.1)
    assert len(calls) == n and packed.t_starts.numel() > 0


def test_render_bench_times_test_views_of_a_run(chair_run):
    """bench render: rounds and every-sample renders of the same views, same image quality,
    the rounds evaluating fewer samples per pixel; bad input is a clear error."""
    from warpnerf.studies.bench import bench_render, format_render

    rounds = bench_render(str(chair_run), views=2, device="cpu")
    every = bench_render(str(chair_run), views=2, device="cpu", every_sample=True)
    assert rounds["views"] == every["views"] and len(rounds["views"]) == 2
    assert rounds["median_s"] > 0 and rounds["min_s"] <= rounds["median_s"] <= rounds["max_s"]
    assert abs(rounds["psnr"] - every["psnr"]) < 1e-3
    assert 0 < rounds["samples_per_pixel"] <= every["samples_per_pixel"]
    assert "s per view" in format_render(rounds)
    with pytest.raises(ValueError, match="views must be >= 1"):
        bench_render(str(chair_run), views=0)
