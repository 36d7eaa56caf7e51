"""Peak memory is per run, not per process: runs that share a process (table, sweep) must not
inherit an earlier run's high-water mark (a mic run was stopped at step 0 by memory_budget_mb)."""

import os

import numpy as np
import pytest

from warpnerf.train.trainer import peak_rss_mb, start_memory_window


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux /proc/self/clear_refs")
def test_memory_window_forgets_an_earlier_runs_peak():
    start_memory_window()
    base = peak_rss_mb()
    big = np.ones(400 * 2**20 // 8)  # 400 MB, touched
    assert peak_rss_mb() > base + 350
    del big
    start_memory_window()
    assert peak_rss_mb() < base + 100


# --- the size settings' memory, known before anything is allocated (issue #64) -----------------------------


def test_training_bytes_of_a_small_config_in_closed_form():
    """2 levels of 2 features, a 16-row table, resolutions 2 and 4: the coarse level is dense (2^3 = 8 rows),
    the fine one hashed (min(4^3, 16) = 16 rows); hidden 8, 3 geometry features."""
    from warpnerf.train.config import TrainConfig
    from warpnerf.train.memory import training_bytes

    cfg = TrainConfig(levels=2, features=2, log2_table_size=4, base_resolution=2, max_resolution=4, hidden=8,
                      geo_features=3, occ_resolution=10, batch_rays=100, sample_budget=1000)
    mlp = (4 + 1) * 8 + 9 * (1 + 3) + (3 + 16 + 1) * 8 + 9 * 8 + 9 * 3  # density, colour MLP (weights + biases)
    assert mlp == 335
    assert training_bytes(cfg) == {
        "grid": (8 + 16) * 2 * 4 * 4,  # rows x features x float32 x (value, gradient, two Adam moments)
        "mlp": 335 * 4 * 4,
        "occupancy": 10**3 * 9,
        "rays": 100 * 64,
        "samples": 1000 * (12 + 12 + 4 * 4),
    }


@pytest.mark.parametrize("model", ["ngp", "mtrf"])
def test_grid_and_mlp_terms_count_the_real_parameters(model):
    """The estimate's trained tensors are the field's: the same rows and parameter counts as the modules."""
    from warpnerf.model.encoders import make_grid_encoder
    from warpnerf.model.field import GridField
    from warpnerf.train.config import TrainConfig
    from warpnerf.train.memory import training_bytes

    cfg = TrainConfig(model=model, levels=6, features=4, log2_table_size=12, base_resolution=4, max_resolution=96,
                      cp_rank=4, cp_max_resolution=64, hidden=24, geo_features=7)
    field = GridField((-1, -1, -1, 1, 1, 1), make_grid_encoder(cfg), cfg.hidden, cfg.geo_features)
    grid = sum(p.numel() for p in field.encoder.parameters())
    mlp = sum(p.numel() for n, p in field.named_parameters() if not n.startswith("encoder."))
    est = training_bytes(cfg)
    assert est["grid"] == grid * 16 and est["mlp"] == mlp * 16


def test_the_presets_fit_their_budget_many_times_over():
    from warpnerf.train.config import build_config
    from warpnerf.train.memory import MB, training_bytes

    for task in ("full", "fewshot", "pose"):
        for model in ("ngp", "mtrf"):
            cfg = build_config(task, None, {"model": model})
            assert sum(training_bytes(cfg).values()) < cfg.memory_budget_mb * MB / 8, (task, model)
