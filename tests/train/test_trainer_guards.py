"""Runs that go wrong stop with one clear line, or stay bounded: a non-finite loss, a run that does
not learn, the per-step sample budget, the memory budget."""

import math

import pytest
import torch

from trainer_helpers import make_trainer


def test_non_finite_loss_is_a_clear_error():
    from warpnerf.train.trainer import TrainingError

    t = make_trainer(iters=10)
    with torch.no_grad():
        t.field.color_net[-1].bias.fill_(float("nan"))
    with pytest.raises(TrainingError, match="non-finite loss"):
        for s in range(10):
            t.train_step(s)


def test_learning_guard_stops_a_run_that_does_not_learn():
    """A learning rate so small that nothing moves: the run stays at the background-only loss level
    and the guard stops it after the warm-ups with a line naming the step and what to try."""
    from warpnerf.train.trainer import TrainingError

    t = make_trainer(iters=400, lr=1e-12, lr_warmup=0, log_every=20)
    with pytest.raises(TrainingError, match=r"not learning at step 240: .* try a lower --lr"):
        t.fit(progress=False)


def test_sample_budget_bounds_a_step_when_the_grid_is_full_or_empty():
    """Force the pathological states of a collapsed run: an empty grid (no samples, the ray count
    climbs to its cap), then a full one with that many rays. No step may take more samples than
    sample_budget, rays past the budget stay out of the loss, and the grid re-opens when empty."""
    budget = 8192
    t = make_trainer(iters=50, sample_budget=budget, max_samples_per_ray=256, occ_warmup=0, lr_warmup=0)
    seen = []
    render = t.renderer.render_rays

    def spy(*a, **kw):
        out = render(*a, **kw)
        seen.append((out.n_samples, out.n_rays, a[0].shape[0]))
        return out

    t.renderer.render_rays = spy
    t.n_rays = 1 << 16
    t.occupancy.bitfield.fill_(1)
    stats = t.train_step(1)  # not an update step: the full grid stays
    n_samples, n_kept, n_rays = seen[-1]
    assert n_samples <= budget and 0 < n_kept < n_rays == 1 << 16
    assert math.isfinite(stats["loss"])
    # an update that would empty the grid re-opens it instead
    t.field.density_net[-1].bias.data[0] = -math.inf  # density exactly 0 everywhere ...
    t.occupancy.density.zero_()  # ... and nothing remembered: this update empties the grid
    t.train_step(t.occupancy.update_every)
    assert t.occupancy.occupied_fraction() == 1.0
    assert all(s <= budget for s, _, _ in seen)


def test_peak_memory_over_budget_is_a_clear_error():
    from warpnerf.train.trainer import TrainingError

    t = make_trainer(iters=10)
    t.cfg.memory_budget_mb = 1  # set after the config check, which refuses 1 MB for these tensors up front
    with pytest.raises(TrainingError, match=r"peak memory \d+ MB exceeds memory_budget_mb = 1 at step 0"):
        t.fit(progress=False)

