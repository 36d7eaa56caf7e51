"""The G²fR level mask (paper eq. 15) with the 0-based ramp: w_1 = 1, level i ramps over i-1 <= tau < i."""

import dataclasses
import math

import pytest
import torch

from warpnerf.model.g2fr import (G2FR_BETA, MASK_MODES, G2fRSchedule, LevelWeights, g2fr_level_weight, g2fr_tau,
                                 g2fr_weights)


def test_tau_sweeps_levels_over_beta_of_training():
    assert g2fr_tau(0, 100, 8, 0.5) == 0.0
    assert g2fr_tau(25, 100, 8, 0.5) == pytest.approx(4.0)
    assert g2fr_tau(50, 100, 8, 0.5) == 8.0
    assert g2fr_tau(99, 100, 8, 0.5) == 8.0  # clamped at M after beta * T
    assert g2fr_tau(-3, 100, 8, 0.5) == 0.0
    for bad in (dict(total_steps=0, beta=0.5), dict(total_steps=10, beta=0.0), dict(total_steps=10, beta=1.5)):
        with pytest.raises(ValueError):
            g2fr_tau(0, bad["total_steps"], 8, bad["beta"])


@pytest.mark.parametrize("mode", MASK_MODES)
def test_first_level_always_on(mode):
    for tau in (0.0, 0.3, 5.0):
        assert g2fr_level_weight(1, tau, mode) == 1.0


def test_cosine_ramp_is_zero_based():
    # level i ramps over i - 1 <= tau < i: w_i = (1 - cos((tau - i + 1) pi)) / 2
    for level in (2, 3, 7):
        assert g2fr_level_weight(level, level - 2 + 0.999, "cosine") == 0.0  # before its ramp
        assert g2fr_level_weight(level, level - 1.0, "cosine") == 0.0  # ramp start
        assert g2fr_level_weight(level, level - 0.5, "cosine") == pytest.approx(0.5)
        assert g2fr_level_weight(level, level - 0.75, "cosine") == pytest.approx((1 - math.cos(0.25 * math.pi)) / 2)
        assert g2fr_level_weight(level, float(level), "cosine") == 1.0  # ramp end
        assert g2fr_level_weight(level, level + 3.0, "cosine") == 1.0
    # the literal eq. 15 indexing (i <= tau < i + 1) would leave level 2 off at tau = 1.5
    assert g2fr_level_weight(2, 1.5, "cosine") == pytest.approx(0.5)


def test_binary_switches_at_the_end_of_the_ramp():
    for level in (2, 5):
        assert g2fr_level_weight(level, level - 1.0, "binary") == 0.0
        assert g2fr_level_weight(level, level - 0.01, "binary") == 0.0
        assert g2fr_level_weight(level, float(level), "binary") == 1.0
    with pytest.raises(ValueError, match="smooth"):
        g2fr_level_weight(2, 0.5, "smooth")


@pytest.mark.parametrize("mode", MASK_MODES)
def test_all_levels_on_from_beta_T(mode):
    n, total, beta = 8, 200, 0.3
    assert torch.equal(g2fr_weights(60, total, n, beta, mode), torch.ones(n))  # t = beta * T
    assert torch.equal(g2fr_weights(199, total, n, beta, mode), torch.ones(n))
    assert g2fr_weights(59, total, n, beta, mode)[-1] < 1.0  # the finest level is still ramping


@pytest.mark.parametrize("mode", MASK_MODES)
def test_weights_monotone_in_t_and_coarse_to_fine(mode):
    n, total, beta = 6, 120, 0.5
    w = torch.stack([g2fr_weights(t, total, n, beta, mode) for t in range(total + 1)])  # (T + 1, n)
    assert w.dtype == torch.float32 and w.shape == (total + 1, n)
    assert ((w >= 0) & (w <= 1)).all() and (w[:, 0] == 1).all()
    assert (w[1:] >= w[:-1]).all()  # no level ever switches back off
    assert (w[:, :-1] >= w[:, 1:]).all()  # a finer level is never ahead of a coarser one
    assert w[0].tolist() == [1.0] + [0.0] * (n - 1)


def test_schedule_and_active_levels():
    s = G2fRSchedule(4, 100, beta=0.5)
    assert s.beta == 0.5 and G2fRSchedule(4, 100).beta == G2FR_BETA
    # tau = 4 t / 50: level 2 ramps over 12.5 < t < 25, level 3 over 25 .. 37.5, level 4 over 37.5 .. 50
    assert [s.active_levels(t) for t in (0, 12, 13, 25, 26, 37, 38, 100)] == [1, 1, 2, 2, 3, 3, 4, 4]
    binary = G2fRSchedule(4, 100, beta=0.5, mode="binary")  # a level switches on at the end of its ramp
    assert [binary.active_levels(t) for t in (0, 24, 25, 37, 38, 49, 50)] == [1, 1, 2, 2, 3, 3, 4]
    off = G2fRSchedule(4, 100, enabled=False)
    assert torch.equal(off(0), torch.ones(4)) and off.active_levels(0) == 4
    with pytest.raises(ValueError):
        G2fRSchedule(4, 100, mode="smooth")
    with pytest.raises(ValueError):
        G2fRSchedule(4, 0)

# --- host-side level weights (one launcher, no device read per launch) ---


def test_level_weights_is_an_immutable_host_value():
    w = LevelWeights((1, 0.25, 0.0))
    assert w.values == (1.0, 0.25, 0.0) and w.active == (0, 1) and len(w) == 3 and list(w) == [1.0, 0.25, 0.0]
    assert w.to("cuda") is w  # lives on no device: moving it is a no-op, never a copy
    assert torch.equal(w.as_tensor(), torch.tensor([1.0, 0.25, 0.0]))
    with pytest.raises(dataclasses.FrozenInstanceError):
        w.values = (0.0,)
    for bad in ((1.0, 2.0), (float("nan"),), (-0.1,)):
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            LevelWeights(bad)
    assert hash(w) == hash(LevelWeights((1.0, 0.25, 0.0)))


@pytest.mark.parametrize("mode", ["cosine", "binary"])
def test_schedule_host_weights_equal_the_tensor_form(mode):
    sched = G2fRSchedule(8, 200, beta=0.5, mode=mode)
    for step in (0, 13, 40, 77, 100, 199):
        assert torch.equal(sched.level_weights(step).as_tensor(), g2fr_weights(step, 200, 8, 0.5, mode))
        assert torch.equal(sched(step), g2fr_weights(step, 200, 8, 0.5, mode))
    assert G2fRSchedule(4, 10, enabled=False).level_weights(0) == LevelWeights.ones(4)


@pytest.mark.parametrize("model", ["ngp", "mtrf"])
def test_trainer_weights_are_the_ones_the_kernel_receives(monkeypatch, model):
    """The weights the trainer computes at a step reach the encoder's kernel unchanged,
    and only the levels they switch on are launched."""
    from tiny_scene import tiny_scene
    from warpnerf.train.config import build_config
    from warpnerf.ops import launch as launch_mod
    from warpnerf.train.tasks import make_task
    from warpnerf.train.trainer import Trainer

    cfg = build_config("full", overrides=dict(
        model=model, levels=6, log2_table_size=12, base_resolution=4, max_resolution=64, cp_rank=2,
        cp_max_resolution=64, hidden=16, target_samples=2048, batch_rays=256, occ_resolution=16, occ_warmup=4,
        occ_update_every=4, iters=100, g2fr=True, g2fr_beta=0.5, video_frames=0))
    trainer = Trainer(cfg, tiny_scene(size=16), make_task(cfg), "cpu")
    step = 22  # tau = 6 * 22 / 50 = 2.64: levels 1-2 on, level 3 ramping (w = 0.90), 4-6 off
    expected = trainer.level_weights(step)
    assert isinstance(expected, LevelWeights) and expected.active == (0, 1, 2) and 0 < expected[2] < 1
    assert torch.equal(expected.as_tensor(), g2fr_weights(step, 100, 6, 0.5))

    seen = []
    real_launch = launch_mod.launch

    def spy(kernel, dim, inputs, device, outputs=None):
        # layout (GridLauncher): fwd(x, params, levels, *meta, weights, ...), bwd(x, params, grad_out, levels, ...)
        key = getattr(kernel, "key", "")
        if key.endswith("_encode_fwd") or key.endswith("_encode_bwd"):
            bwd = key.endswith("_bwd")
            at = 3 if bwd else 2
            n_meta = len(inputs) - at - (9 if bwd else 6)  # after meta: weights, (2 flags,) start, stop, chunk, outputs
            seen.append((bwd, tuple(inputs[at + 1 + n_meta].numpy().tolist()), inputs[at].numpy().tolist()))
        return real_launch(kernel, dim, inputs, device, outputs)

    monkeypatch.setattr(launch_mod, "launch", spy)
    trainer.train_step(step)
    assert any(not bwd for bwd, _, _ in seen) and any(bwd for bwd, _, _ in seen)  # forward and backward
    want = tuple(torch.tensor(expected.values, dtype=torch.float32).tolist())  # what float32 kernels hold
    for _, weights, levels in seen:
        assert weights == want
        assert set(levels) <= {0, 1, 2}
    assert sorted({m for _, _, lv in seen for m in lv}) == [0, 1, 2]
