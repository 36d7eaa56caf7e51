"""The few-shot protocol's pieces: seeded random view sets, val-split held-out curves and evaluation,
epochs (passes over the training pixels) and the adaptive and held-out G²fR schedules."""

import dataclasses

import pytest
import torch

from tiny_scene import tiny_scene
from trainer_helpers import TINY, make_trainer
from warpnerf.model.g2fr import (AdaptiveG2fRSchedule, G2fRSchedule, HeldoutG2fRSchedule, g2fr_level_weight,
                                 make_schedule)
from warpnerf.train.config import ConfigError, build_config
from warpnerf.train.evaluate import eval_views
from warpnerf.train.monitor import HeldoutViews, Monitor, heldout_split
from warpnerf.train.tasks import FewShotTask, make_task
from warpnerf.train.trainer import Trainer


def test_random_view_set_is_seeded_and_distinct_from_fps():
    views = tiny_scene().train
    pick = lambda **kw: FewShotTask(build_config("fewshot", overrides=dict(n_views=6, **kw))).selected_ids(views)
    a0, a0_again, a1 = pick(view_set="random", seed=0), pick(view_set="random", seed=0), pick(view_set="random", seed=1)
    assert a0 == a0_again and len(set(a0)) == 6 and all(0 <= i < len(views) for i in a0)
    assert a0 != a1  # another seed, another set
    assert a0 == torch.randperm(len(views), generator=torch.Generator().manual_seed(0))[:6].tolist()
    assert pick(seed=0) == pick(seed=1)  # fps does not depend on the seed
    assert pick(view_set="random", seed=0, g2fr=False) == a0  # both arms of a seed train the same views
    with pytest.raises(ConfigError, match="view_set"):
        build_config("fewshot", overrides=dict(view_set="clustered"))


def scene_with_val():
    """The tiny scene with a val split that differs from its test split (its images are black)."""
    s = tiny_scene()
    val = dataclasses.replace(s.test, images=torch.zeros_like(s.test.images))
    return dataclasses.replace(s, val=val)


def trainer_on(scene, **kw):
    cfg = build_config("fewshot", overrides={**TINY, "n_views": 6, **kw})
    return Trainer(cfg, scene, make_task(cfg), "cpu")


def test_heldout_curve_reads_val_and_falls_back_to_test():
    t = trainer_on(scene_with_val(), heldout_views=2)
    assert heldout_split(t) == "val"
    assert float(Monitor(t)._heldout.images.abs().max()) == 0.0  # the black val images, not the test ones
    assert heldout_split(trainer_on(scene_with_val(), heldout_split="test")) == "test"
    assert heldout_split(trainer_on(tiny_scene())) == "test"  # no val split: test, and the metrics say so


def test_eval_split_val_measures_val_views():
    t = trainer_on(scene_with_val(), eval_split="val", eval_view_stride=2)
    views = eval_views(t)
    assert len(views) == 2 and float(views.images.abs().max()) == 0.0
    with pytest.raises(ConfigError, match="no such split"):
        eval_views(trainer_on(tiny_scene(), eval_split="val"))


def test_epochs_count_rays_over_training_pixels():
    t = make_trainer("fewshot", n_views=4, iters=6, log_every=1)
    t.fit(progress=False)
    pixels = 4 * 32 * 32
    assert t.rays_seen > 0 and t.epochs == pytest.approx(t.rays_seen / pixels)
    assert t.history["epochs"] == sorted(t.history["epochs"]) and t.history["epochs"][-1] == pytest.approx(t.epochs)


def test_adaptive_opens_a_level_per_plateaued_window():
    s = AdaptiveG2fRSchedule(n_levels=5, window=4, tol=0.1)
    assert s.level_weights(0).values == (1.0, 0.0, 0.0, 0.0, 0.0)
    losses = [1.0] * 4 + [0.5] * 4 + [0.48] * 4 + [0.3] * 4 + [0.29] * 4
    for step, loss in enumerate(losses):
        s.observe(step, loss)
    # window gains: 0.5 -> 50 % (the largest), 0.48 -> 4 % <= 0.1 x 50 %: opens at 12 (and the largest resets);
    # 0.3 -> 37.5 %, 0.29 -> 3.3 % <= 0.1 x 37.5 %: opens at 20
    assert s.open_steps == [12, 20]
    for step in (12, 14, 16, 20, 22, 40):
        tau = 1 + sum(min(max(step - o, 0) / 4, 1.0) for o in s.open_steps)
        assert s.level_weights(step).values == tuple(g2fr_level_weight(i + 1, tau) for i in range(5))
    assert s.level_weights(16).values == (1.0, 1.0, 0.0, 0.0, 0.0)  # level 2 fully in one window after 12


def test_adaptive_stops_at_the_last_level_and_disabled_is_all_ones():
    s = AdaptiveG2fRSchedule(n_levels=3, window=2, tol=0.0)
    for step in range(40):
        s.observe(step, 1.0)
    assert s.open_steps == [4, 6] and s.level_weights(100).values == (1.0, 1.0, 1.0)
    off = AdaptiveG2fRSchedule(n_levels=3, window=2, enabled=False)
    off.observe(0, 1.0)
    assert off.level_weights(0).values == (1.0, 1.0, 1.0) and off.open_steps == []


def test_make_schedule_and_bad_values():
    assert type(make_schedule("fixed", 4, 100)) is G2fRSchedule
    assert type(make_schedule("adaptive", 4, 100)) is AdaptiveG2fRSchedule
    with pytest.raises(ValueError, match="schedule"):
        make_schedule("plateau", 4, 100)
    with pytest.raises(ConfigError, match="g2fr_plateau_tol"):
        build_config("fewshot", overrides=dict(g2fr_plateau_tol=1.5))
    with pytest.raises(ConfigError, match="g2fr_plateau_tol"):
        build_config("fewshot", overrides=dict(g2fr_plateau_tol=float("nan")))
    with pytest.raises(ConfigError, match="g2fr_plateau_window"):
        build_config("fewshot", overrides=dict(g2fr_plateau_window=1))


def test_trainer_feeds_the_loss_to_the_adaptive_schedule():
    t = make_trainer("fewshot", n_views=6, iters=40, g2fr=True, g2fr_schedule="adaptive", g2fr_plateau_window=5,
                     g2fr_plateau_tol=1.0)  # tol 1: no gain exceeds the largest, so every window after the first opens
    t.fit(progress=False)
    assert t.schedule.open_steps == [10, 15, 20, 25, 30, 35, 40][: len(t.schedule.open_steps)]
    assert len(t.schedule.open_steps) == 7  # windows ending at steps 9, 14, ..., 39 each opened one level


def feed(schedule, psnrs):
    """Report ``psnrs`` as the next checks (after steps window - 1, 2 window - 1, ...), as Trainer.fit would."""
    step = schedule.checks[-1][0] if schedule.checks else -1
    for psnr in psnrs:
        step += 1
        while not schedule.wants_heldout(step):
            assert step < 10_000, "the schedule stopped asking for checks"
            step += 1
        schedule.observe_heldout(step, psnr)


def heldout_tau(s, step):
    """tau of :class:`HeldoutG2fRSchedule` by its definition, from the recorded open and close steps."""
    ramp = lambda t0: min(max(step - t0, 0) / s.window, 1.0)  # noqa: E731
    return 1 + sum(map(ramp, s.open_steps)) - sum(map(ramp, s.close_steps))


def test_heldout_waits_while_val_rises_and_opens_on_a_plateau():
    s = HeldoutG2fRSchedule(n_levels=6, window=5, drop=0.5, min_gain=0.1, average=1)
    assert [t for t in range(20) if s.wants_heldout(t)] == [4, 9, 14, 19]
    # checks after steps 4, 9, ...: rising by more than 0.1 dB keeps the mask; 20.05 and 20.1 beat the best
    # by no more than 0.1 dB (plateaus: open at 15 and 20); 20.7 is a dip within the 0.5 dB guard (opens at 30)
    feed(s, [18.0, 20.0, 20.05, 20.1, 21.0, 20.7])
    assert s.open_steps == [15, 20, 30] and s.close_steps == [] and not s.frozen
    assert [c[0] for c in s.checks] == [4, 9, 14, 19, 24, 29]
    assert s.level_weights(14).values == (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert s.level_weights(25).values == (1.0, 1.0, 1.0, 0.0, 0.0, 0.0)
    for step in range(0, 40):
        tau = heldout_tau(s, step)
        assert s.level_weights(step).values == tuple(g2fr_level_weight(i + 1, tau) for i in range(6))


def test_heldout_guard_closes_the_levels_opened_since_the_best_and_freezes():
    s = HeldoutG2fRSchedule(n_levels=8, window=5, drop=0.5, min_gain=0.1, average=1)
    # best 22.0 after step 9 with no level open; plateaus open levels at 15, 20, 25; the check after 24
    # (21.6) is within 0.5 dB; after 29, 21.4 is 0.6 dB below the best: the three levels close at step 30
    feed(s, [20.0, 22.0, 21.9, 21.95, 21.6, 21.4])
    assert s.open_steps == [15, 20, 25] and s.close_steps == [30, 30, 30] and s.frozen
    before = [s.level_weights(t).values for t in range(60)]
    assert s.active_levels(29) == 4 and s.active_levels(45) == 1  # back to the levels of the best check
    assert not any(s.wants_heldout(t) for t in range(30, 200))  # frozen: nothing is asked ...
    s.observe_heldout(34, 10.0)
    s.observe_heldout(39, 30.0)  # ... and nothing reported moves it
    assert [s.level_weights(t).values for t in range(60)] == before and len(s.checks) == 6
    for step in range(60):  # every past step's mask follows from the recorded steps
        assert s.level_weights(step).values == tuple(g2fr_level_weight(i + 1, heldout_tau(s, step)) for i in range(8))


def test_heldout_keeps_the_level_that_set_the_best():
    s = HeldoutG2fRSchedule(n_levels=8, window=5, drop=0.5, min_gain=0.1, average=1)
    # opens at 10 (plateau after 9); the check after 14 (23.0) is the best with that level open, so the
    # drop after 24 closes only the level opened at 20 (the plateau after 19), not the one opened at 10
    feed(s, [22.0, 22.0, 23.0, 22.9, 22.4])
    assert s.open_steps == [10, 20] and s.close_steps == [25] and s.frozen
    assert s.active_levels(40) == 2


def test_heldout_dip_with_no_new_level_waits():
    s = HeldoutG2fRSchedule(n_levels=4, window=5, drop=0.5, min_gain=0.1, average=1)
    feed(s, [22.0, 20.0])  # 2 dB below the best, but no level opened since: nothing to close, and no plateau
    assert s.open_steps == [] and s.close_steps == [] and not s.frozen
    feed(s, [22.05])  # back within 0.1 dB of the best: a plateau, after step 14
    assert s.open_steps == [15] and not s.frozen


def test_heldout_judges_the_mean_of_the_last_checks():
    # one check 0.5 dB low: the mean of the last three is 0.17 dB below the best, within drop 0.25; judged alone
    # (average 1) the same check closes the three levels opened since the best
    psnrs = [20.0, 20.0, 20.0, 19.5, 20.0]
    mean3 = HeldoutG2fRSchedule(n_levels=8, window=5, drop=0.25, min_gain=0.1)
    feed(mean3, psnrs)
    assert mean3.open_steps == [10, 15, 20, 25] and not mean3.frozen
    alone = HeldoutG2fRSchedule(n_levels=8, window=5, drop=0.25, min_gain=0.1, average=1)
    feed(alone, psnrs[:4])
    assert alone.open_steps == [10, 15] and alone.close_steps == [20, 20] and alone.frozen


def test_heldout_never_opens_past_the_last_level_and_disabled_is_all_ones():
    s = HeldoutG2fRSchedule(n_levels=4, window=3, drop=0.5, min_gain=0.1, average=1)
    feed(s, [20.0] * 12)
    assert s.open_steps == [6, 9, 12] and s.level_weights(100).values == (1.0,) * 4
    assert s.wants_heldout(35) and not s.frozen  # all open: the guard still watches
    off = HeldoutG2fRSchedule(n_levels=3, window=3, enabled=False)
    assert not any(off.wants_heldout(t) for t in range(20)) and off.level_weights(0).values == (1.0,) * 3
    with pytest.raises(ValueError, match="drop"):
        HeldoutG2fRSchedule(n_levels=3, drop=-1.0)


def test_heldout_state_round_trip_makes_the_same_decisions():
    psnrs = [19.0, 21.0, 21.05, 21.5, 21.45, 21.3, 21.0, 20.9]  # the last mean of three, 0.35 dB below the best, freezes
    ref = HeldoutG2fRSchedule(n_levels=8, window=4)
    feed(ref, psnrs)
    assert ref.frozen and ref.close_steps  # the sequence reaches the guard, so all state is exercised
    first = HeldoutG2fRSchedule(n_levels=8, window=4)
    feed(first, psnrs[:6])
    assert first.open_steps and len(first.checks) == 6  # stopped mid-way, with levels open and checks to average
    resumed = HeldoutG2fRSchedule(n_levels=8, window=4)
    resumed.load_state_dict(first.state_dict())
    step = 6 * 4 - 1  # the last check fed
    for psnr in psnrs[6:]:
        step += 4
        resumed.observe_heldout(step, psnr)
    assert resumed.state_dict() == ref.state_dict()
    assert [resumed.level_weights(t) for t in range(60)] == [ref.level_weights(t) for t in range(60)]


def test_make_schedule_heldout_and_bad_values():
    s = make_schedule("heldout", 4, 100, heldout_window=7, drop=0.3, min_gain=0.2, average=2)
    assert type(s) is HeldoutG2fRSchedule and (s.window, s.drop, s.min_gain, s.average) == (7, 0.3, 0.2, 2)
    for key, bad in (("g2fr_heldout_drop", -0.1), ("g2fr_heldout_min_gain", float("nan")), ("g2fr_heldout_window", 0),
                     ("g2fr_heldout_views", 0), ("g2fr_heldout_average", 0)):
        with pytest.raises(ConfigError, match=key):
            build_config("fewshot", overrides={key: bad})


def test_trainer_feeds_val_psnr_to_the_heldout_schedule():
    # the curve reads test (as the paper-regime sweeps set it); the schedule must still read val
    # (drop 100 dB: the guard never freezes the schedule, so it asks after every window to the end)
    t = trainer_on(scene_with_val(), iters=30, g2fr=True, g2fr_schedule="heldout", g2fr_heldout_window=5,
                   g2fr_heldout_views=2, g2fr_heldout_drop=100.0, heldout_split="test")
    assert t.schedule_views.split == "val" and float(t.schedule_views.images.abs().max()) == 0.0  # the black val views
    t.fit(progress=False)
    assert [c[0] for c in t.schedule.checks] == [4, 9, 14, 19, 24, 29]
    # the last check came after the last step: the same field renders the same PSNR, and it is val's, not test's
    val, test = HeldoutViews(t, "val", 2).check(t, 29)[0], HeldoutViews(t, "test", 2).check(t, 29)[0]
    assert t.schedule.checks[-1][1] == val != test
    assert t.schedule.open_steps  # rendering a field against black views does not keep rising by 0.1 dB a check


def test_heldout_schedule_needs_a_val_split():
    with pytest.raises(ConfigError, match="heldout reads the val split, and scene 'spheres' has none; choose"):
        trainer_on(tiny_scene(), g2fr=True, g2fr_schedule="heldout")
    trainer_on(tiny_scene(), g2fr=False, g2fr_schedule="heldout")  # off: no schedule reads val


def test_config_names_a_shipped_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no configs/ folder here: the name resolves to the shipped file
    cfg = build_config("fewshot", "fewshot_paper")
    assert (cfg.downscale, cfg.log2_table_size, cfg.random_background) == (4, 19, False)
    assert build_config("fewshot", "fewshot_paper.toml") == cfg
    (tmp_path / "fewshot_paper.toml").write_text("iters = 7\n")  # a file of that name wins
    assert build_config("fewshot", "fewshot_paper.toml").iters == 7
    with pytest.raises(ConfigError, match="not found"):
        build_config("fewshot", "no_such_preset")


def test_config_file_task_picks_the_preset_when_no_task_is_given(tmp_path):
    # `warpnerf train --config fewshot_paper` once trained task full with G²fR off: the file's
    # `task = "fewshot"` was overwritten by --task's default
    cfg = build_config(None, "fewshot_paper")
    assert cfg.task == "fewshot"
    assert cfg == build_config("fewshot", "fewshot_paper")  # the few-shot preset lies beneath the file
    assert build_config("pose", "fewshot_paper").task == "pose"  # an explicit --task still wins
    assert build_config(None).task == "full"
    bad = tmp_path / "bad.toml"
    bad.write_text('task = "fewshoot"\n')
    with pytest.raises(ConfigError, match="task"):
        build_config(None, str(bad))


def test_cli_train_config_file_sets_the_task(tmp_path, monkeypatch):
    import warpnerf.runs.run as run_mod
    from warpnerf.cli.app import main

    seen = {}

    def fake_run(cfg, **kwargs):
        seen["cfg"] = cfg
        return {"psnr": 0.0, "ssim": 0.0, "iters": cfg.iters, "train_seconds": 0.0, "render_seconds_per_view": 0.0}

    monkeypatch.setattr(run_mod, "run_training", fake_run)
    main(["train", "--config", "fewshot_paper", "--scene", "chair", "--out", str(tmp_path / "r"), "--quiet"])
    assert seen["cfg"].task == "fewshot" and seen["cfg"].g2fr
