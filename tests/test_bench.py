"""Benchmark plumbing (warpnerf/bench.py): warm-up, median, --repeats honoured by both arms."""

import pytest

from warpnerf import bench


def test_median_seconds_warms_up_then_takes_the_median(monkeypatch):
    calls = []
    clock = iter([0.0, 1.0, 10.0, 12.0, 20.0, 20.5])  # three timed runs of 1.0, 2.0, 0.5 s
    monkeypatch.setattr(bench.time, "perf_counter", lambda: next(clock))
    assert bench.median_seconds(lambda: calls.append(1), repeats=3, warmup=2) == 1.0
    assert len(calls) == 5  # 2 untimed + 3 timed
    with pytest.raises(ValueError, match="repeats"):
        bench.median_seconds(lambda: None, repeats=0)


def test_encoding_bench_honours_repeats_for_both_arms(monkeypatch):
    seen = []
    real = bench.median_seconds
    monkeypatch.setattr(bench, "median_seconds", lambda fn, reps, warmup=2: seen.append(reps) or real(fn, reps, warmup))
    res = bench.bench_encoding(n=1024, levels=2, log2_table_size=8, repeats=3)
    assert res["repeats"] == res["torch_repeats"] == 3
    assert seen and set(seen) == {3}  # Warp and torch twin timed the same number of times
    assert res["warp_fwdbwd_pts_s"] > 0 and res["ratio_fwdbwd"] > 0


def test_twin_swap_replaces_the_ops_the_renderer_calls():
    """bench step's torch arm must swap the names the renderer really uses (it broke silently once,
    when the renderer moved to march_rays_within_budget)."""
    from warpnerf import encoders, renderer

    names = [(encoders, "hashgrid_encode"), (renderer, "march_rays_within_budget"), (renderer, "composite_rays")]
    before = [getattr(m, n) for m, n in names]
    with bench._twin_ops():
        during = [getattr(m, n) for m, n in names]
    assert all(a is not b for a, b in zip(before, during))
    assert [getattr(m, n) for m, n in names] == before
