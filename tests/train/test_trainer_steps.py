"""The training step: Adam moments, determinism, the G²fR level mask, the occupancy threshold,
sample compaction, and the checkpoint state a resumed run needs."""

import pytest
import torch

from trainer_helpers import make_trainer
from warpnerf.train.config import ConfigError, build_config


def test_flush_tiny_moments_zeroes_only_what_cannot_move_a_parameter():
    from warpnerf.train.trainer import MOMENT_FLUSH_BELOW, flush_tiny_moments

    p = torch.nn.Parameter(torch.zeros(6))
    opt = torch.optim.Adam([p], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    p.grad = torch.ones(6)
    opt.step()
    st = opt.state[p]
    m = torch.tensor([1e-39, -1e-31, 1e-29, -1e-5, 0.0, 2e-30])  # 1e-39: a denormal
    v = torch.tensor([1e-39, 1e-37, 1e-35, 1e-10, 0.0, 1e-20])
    st["exp_avg"].copy_(m)
    st["exp_avg_sq"].copy_(v)
    flush_tiny_moments(opt)
    assert torch.equal(st["exp_avg"], torch.where(m.abs() < MOMENT_FLUSH_BELOW["exp_avg"], 0.0, m))
    assert torch.equal(st["exp_avg_sq"], torch.where(v < MOMENT_FLUSH_BELOW["exp_avg_sq"], 0.0, v))
    assert (st["exp_avg"] != 0).tolist() == [False, False, True, True, False, True]
    assert (st["exp_avg_sq"] != 0).tolist() == [False, False, True, True, False, True]


def test_untouched_rows_keep_no_denormal_moments():
    """A field trained past MOMENT_FLUSH_EVERY steps holds no denormal Adam moment: rows no sample
    reaches (most of a hash table's fine levels on a small scene) would otherwise decay into
    float32's denormal range, where x86 arithmetic is ~10x slower."""
    from warpnerf.train.trainer import MOMENT_FLUSH_EVERY

    t = make_trainer(iters=MOMENT_FLUSH_EVERY)
    for s in range(MOMENT_FLUSH_EVERY - 1):
        t.train_step(s)
    tiny = torch.finfo(torch.float32).tiny
    table = t.optimizer.param_groups[0]["params"][0]
    st = t.optimizer.state[table]
    # what hundreds of steps without a sample leave in a row: denormal moments (100 steps of a tiny
    # scene are too few to get there on their own)
    st["exp_avg"].fill_(1e-39)
    st["exp_avg_sq"].fill_(1e-39)
    t.train_step(MOMENT_FLUSH_EVERY - 1)  # this step ends with a flush
    for key in ("exp_avg", "exp_avg_sq"):
        m = st[key]
        assert not bool(((m != 0) & (m.abs() < tiny)).any()), key
    assert bool((st["exp_avg"] != 0).any())  # the rows this step's samples reached keep their moments


def test_training_is_deterministic_for_a_seed():
    losses = []
    for _ in range(2):
        t = make_trainer(iters=30)
        losses.append([t.train_step(s)["loss"] for s in range(30)])
    assert losses[0] == losses[1]


def backward_node_names(t: torch.Tensor) -> set[str]:
    """Names of every autograd node ``t`` was computed through."""
    names, seen, stack = set(), set(), [t.grad_fn]
    while stack:
        fn = stack.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        names.add(type(fn).__name__)
        stack.extend(f for f, _ in fn.next_functions)
    return names


def test_pose_gradient_path_has_no_cpu_index_backward():
    """``t[idx]``'s backward (index_put_ with accumulate) adds repeated rows from several threads in
    no fixed order on CPU: the gradient of a camera's pose changed in its last bits from run to run,
    so a resumed run could not match an uninterrupted one. Rays and samples are gathered
    with index_select instead."""
    assert "IndexBackward0" in backward_node_names(torch.zeros(2, requires_grad=True)[torch.tensor([0, 0])])
    from warpnerf.model.renderer import pixel_rays

    t = make_trainer("pose", iters=10)
    batch = t.sample_pixels(t.n_rays)
    o, d = pixel_rays(t.task.camera_poses(t, batch.view), batch.u, batch.v, t.views.focal, t.views.cx, t.views.cy)
    out = t.renderer.render_rays(o.contiguous(), d.contiguous(), t.level_weights(0),
                                 torch.rand(o.shape[0], generator=t.gen))
    assert out.n_samples > 0
    names = backward_node_names(out.rgb)
    assert "IndexSelectBackward0" in names and "IndexBackward0" not in names


def test_g2fr_masks_levels_early():
    t = make_trainer(iters=100, g2fr=True, g2fr_beta=0.5)
    assert t.schedule.active_levels(0) == 1
    assert t.schedule.active_levels(60) == 8
    # step 0: the encoder receives the schedule's weights (coarsest level only), so the Adam step
    # moves level 1's table rows and leaves every masked level's rows exactly as initialised
    encoder, seen = t.field.encoder, []
    forward = encoder.forward
    encoder.forward = lambda x, level_weights=None, *known: seen.append(level_weights) or forward(x, level_weights, *known)
    table0 = encoder.table.detach().clone()
    t.train_step(0)
    assert seen and all(list(w) == t.schedule(0).tolist() for w in seen)  # host LevelWeights or a tensor
    assert t.schedule(0).tolist() == [1.0] + [0.0] * 7
    level1 = encoder.spec.offsets[1]
    assert not torch.equal(encoder.table[:level1], table0[:level1])
    assert torch.equal(encoder.table[level1:].detach(), table0[level1:])


def test_occupancy_threshold_is_configurable():
    """--occ-threshold reaches the grid (an optical thickness: the trainer's density_fn multiplies the
    density by the marching step, as nerfacc's occ_eval_fn does); instant-ngp's 0.01 by default."""
    assert make_trainer().occupancy.threshold == 0.01
    assert make_trainer(occ_threshold=0.5).occupancy.threshold == 0.5
    with pytest.raises(ConfigError, match="occ_threshold"):
        build_config("full", overrides={"occ_threshold": -1.0})


def test_training_compaction_follows_the_kept_fraction_and_resumes():
    """The trainer compacts (Renderer._active_prefixes) while the last compacted step kept less than
    COMPACT_BELOW of its samples, probes every COMPACT_PROBE_EVERY steps, and checkpoints the fraction
    (a resumed run makes the same choices)."""
    from warpnerf.train.trainer import COMPACT_BELOW, COMPACT_PROBE_EVERY

    t = make_trainer(iters=80)
    calls = []
    render = t.renderer.render_rays

    def spy(*args, compact=None, **kw):
        before = t.kept_fraction
        out = render(*args, compact=compact, **kw)
        calls.append((compact, before, out.n_active, out.n_samples))
        return out

    t.renderer.render_rays = spy
    for step in range(20):  # untrained: nearly transparent, nothing to drop
        t.train_step(step)
    with torch.no_grad():  # an opaque field: most samples lie behind its first surfaces
        t.field.density_net[2].bias[0] += 4.0
    for step in range(20, 50):
        t.train_step(step)
    for step, (compact, before, n_active, n_samples) in enumerate(calls):
        assert compact == (step % COMPACT_PROBE_EVERY == 0 or before < COMPACT_BELOW), step
        assert n_active <= n_samples and (compact or n_active == n_samples)
    assert {c for c, *_ in calls} == {True, False}  # both choices occur
    assert not any(c for c, *_ in calls[1:16]) and all(c for c, *_ in calls[33:])
    assert min(a / s for c, _, a, s in calls if c) < COMPACT_BELOW
    state = t.state_dict()
    assert state["kept_fraction"] == t.kept_fraction
    other = make_trainer(iters=80)
    other.load_state_dict(state)
    assert other.kept_fraction == t.kept_fraction


def test_a_checkpoint_from_another_scene_box_is_refused_in_one_line():
    """A run trained with another box (another scene, or an LLFF run from before the NDC box held
    every training ray) would be rendered through the wrong occupancy cells: loading says so."""
    from warpnerf.train.checkpoint import CheckpointError

    trainer = make_trainer(iters=1)
    state = trainer.state_dict()
    other = make_trainer(iters=1)
    other.load_state_dict(state)  # same box: loads
    assert torch.equal(other.field.aabb_min, trainer.field.aabb_min)
    state["field"]["aabb_size"] = state["field"]["aabb_size"] * 0.5
    with pytest.raises(CheckpointError, match=r"scene box \(-1, -1, -1, 0, 0, 0\) is not this scene's \(-1, -1, -1, 1, 1, 1\)"):
        other.load_state_dict(state)

