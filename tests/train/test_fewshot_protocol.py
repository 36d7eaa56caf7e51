"""The few-shot protocol's pieces: seeded random view sets, val-split held-out curves and evaluation,
epochs (passes over the training pixels) and the adaptive G²fR schedule."""

import dataclasses

import pytest
import torch

from tiny_scene import tiny_scene
from trainer_helpers import TINY, make_trainer
from warpnerf.model.g2fr import AdaptiveG2fRSchedule, G2fRSchedule, g2fr_level_weight, make_schedule
from warpnerf.train.config import ConfigError, build_config
from warpnerf.train.evaluate import eval_views
from warpnerf.train.monitor import Monitor, heldout_split
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
    assert float(Monitor(t)._heldout[0].abs().max()) == 0.0  # the black val images, not the test ones
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
