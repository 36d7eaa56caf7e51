"""The G²fR level weights as a host value, and their path from the trainer to the grid kernel."""

import pytest
import torch

from warpnerf.freq_mask import G2fRSchedule, LevelWeights, g2fr_weights


def test_level_weights_is_an_immutable_host_value():
    w = LevelWeights((1, 0.25, 0.0))
    assert w.values == (1.0, 0.25, 0.0) and w.active == (0, 1) and len(w) == 3 and list(w) == [1.0, 0.25, 0.0]
    assert w.to("cuda") is w  # lives on no device: moving it is a no-op, never a copy
    assert torch.equal(w.as_tensor(), torch.tensor([1.0, 0.25, 0.0]))
    with pytest.raises(Exception):
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
    """Issue 13: the weights the trainer computes at a step reach the encoder's kernel unchanged,
    and only the levels they switch on are launched."""
    from tiny_scene import tiny_scene
    from warpnerf.config import build_config
    from warpnerf.ops import launch as launch_mod
    from warpnerf.tasks import make_task
    from warpnerf.trainer import Trainer

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
            n_meta = len(inputs) - at - (6 if bwd else 4)  # what follows meta: weights (+ 2 flags + 2 grads | start + out)
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
