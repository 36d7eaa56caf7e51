"""Monitoring: TensorBoard scalars, the held-out PSNR curve and the encoding's Lipschitz bound (eq. 17)."""

import io
import json

import numpy as np
import pytest
import torch

from tiny_scene import tiny_scene
from warpnerf.model.encoders import make_grid_encoder
from warpnerf.train.config import ConfigError, build_config
from warpnerf.train.monitor import IMAGE_TAGS, LEVEL_BLOCK, TAGS, Monitor, final_tags, lipschitz_bound
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

TINY = dict(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128, hidden=32, target_samples=8192,
            batch_rays=256, occ_resolution=32, occ_warmup=16, occ_update_every=8, lr=2e-2, video_frames=0,
            march_steps=256)


def _png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def test_lipschitz_bound_follows_eq17():
    cfg = build_config("full", overrides=dict(levels=6, log2_table_size=12, base_resolution=4, max_resolution=64))
    enc = make_grid_encoder(cfg, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        for p in enc.parameters():
            p.uniform_(-1, 1)  # trained-like magnitudes (init is 1e-4)
    ones = torch.ones(6)
    full = lipschitz_bound(enc, ones)
    # masking fine levels (G2fR early in training) lowers the bound: fewer high-frequency terms in eq. 17
    coarse = lipschitz_bound(enc, torch.tensor([1.0, 1, 0, 0, 0, 0]))
    assert 0 < coarse < full
    # eq. 17: the squared difference is the w_m^2-weighted sum over levels, so for a single pair
    # the bound with weights w equals sqrt(sum_m w_m^2 * (bound of level m alone)^2) when n_pairs = 1
    w = torch.tensor([1.0, 0.5, 0.25, 1.0, 0.0, 0.7])
    per_level = [lipschitz_bound(enc, torch.eye(6)[m], n_pairs=1) for m in range(6)]
    expect = sum(float(w[m]) ** 2 * per_level[m] ** 2 for m in range(6)) ** 0.5
    assert lipschitz_bound(enc, w, n_pairs=1) == pytest.approx(expect, rel=1e-4)
    # a linear stand-in Psi(x) = A x has L = largest singular value of A; random pairs approach it from below
    lin = torch.nn.Linear(3, 4, bias=False)
    stand_in = lambda x, w=None: lin(x)  # noqa: E731
    stand_in.parameters = lin.parameters
    sv = float(torch.linalg.matrix_norm(lin.weight.detach(), ord=2))
    assert 0.95 * sv < lipschitz_bound(stand_in, None) <= sv * (1 + 1e-4)


def test_bad_log_value_is_a_config_error():
    with pytest.raises(ConfigError, match="log must be"):
        build_config("full", overrides=dict(log="wandb"))


def test_tensorboard_event_file_holds_every_tag(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = build_config("pose", overrides={**TINY, "iters": 12, "log": "tensorboard", "log_every": 4,
                                          "heldout_every": 6, "heldout_views": 2, "g2fr": True, "out": str(tmp_path)})
    trainer = Trainer(cfg, tiny_scene(size=24, n_test=3), make_task(cfg), "cpu")
    monitor = Monitor(trainer)
    trainer.callbacks.append(monitor)
    rates, weights = {}, {}  # what the optimizers used and the G2fR weights, step by step, for comparison

    def record(trainer, step, stats):
        rates[step] = {**{f"lr/{g['name']}": g["lr"] for g in trainer.optimizer.param_groups},
                       "lr/pose": trainer.task.optimizer.param_groups[0]["lr"]}
        weights[step] = list(trainer.level_weights(step))

    trainer.callbacks.append(record)
    trainer.fit(progress=False)
    monitor.close()
    acc = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0})
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert set(TAGS) <= tags, set(TAGS) - tags
    assert set(IMAGE_TAGS) <= set(acc.Tags()["images"])
    # learning rates: the ones Adam used at each logged step (warm-up and decay included), per group
    for tag in ("lr/grid", "lr/mlp", "lr/pose"):
        events = acc.Scalars(tag)
        assert [e.step for e in events] == [0, 4, 8, 11]
        assert [e.value for e in events] == pytest.approx([rates[e.step][tag] for e in events], rel=1e-6)
    assert acc.Scalars("lr/grid")[0].value < acc.Scalars("lr/grid")[1].value  # the warm-up is visible
    # G2fR level weights: one block per level, brightness 255 w_m, as the schedule gave them
    shots = acc.Images("g2fr/level_weights")
    assert [e.step for e in shots] == [0, 4, 8, 11]
    for e in shots:
        img = _png(e.encoded_image_string)
        assert img.shape == (LEVEL_BLOCK, LEVEL_BLOCK * 8, 3)
        expect = np.round(np.array(weights[e.step]) * 255)
        assert img[0, ::LEVEL_BLOCK, 0].tolist() == expect.tolist()
    assert _png(shots[0].encoded_image_string).mean() < _png(shots[-1].encoded_image_string).mean() == 255
    # held-out images at the held-out checks: the 2 views side by side (24 px: below 64 px the check renders at
    # full resolution, not half)
    for tag in ("heldout/prediction", "heldout/ground_truth"):
        events = acc.Images(tag)
        assert [e.step for e in events] == [5, 11]
        assert (events[0].height, events[0].width) == (24, 48)
    gt = _png(acc.Images("heldout/ground_truth")[0].encoded_image_string)
    assert gt.std() > 0  # the scene's images, not a blank
    steps = [e.step for e in acc.Scalars("train/loss")]
    assert steps == [0, 4, 8, 11]  # every log_every steps and the last
    assert [e.step for e in acc.Scalars("heldout/psnr")] == [5, 11]
    # the held-out curve in history is the one written to TensorBoard
    hist = trainer.history["heldout"]
    assert [s for s, _ in hist] == [5, 11]
    assert [v for _, v in hist] == pytest.approx([e.value for e in acc.Scalars("heldout/psnr")], rel=1e-6)
    assert all(5.0 < v < 60.0 for _, v in hist)
    # G2fR: levels switch on over training, and the Lipschitz bound follows them up
    lv = [e.value for e in acc.Scalars("g2fr/active_levels")]
    assert lv[0] < lv[-1] == 8
    rot = [e.value for e in acc.Scalars("pose/rot_err_deg")]
    assert rot[0] == pytest.approx(trainer.task.history["rot_err_deg"][1], rel=1e-5)
    assert all(e.value > 0 for e in acc.Scalars("perf/step_seconds"))


def test_run_folder_has_heldout_curve(tmp_path):
    """run_training: history.json holds the held-out curve and training.png is drawn with it."""
    import os

    from warpnerf.runs.run import run_training

    os.environ["WARPNERF_CACHE"] = str(tmp_path / "cache")
    cfg = build_config("full", overrides={**TINY, "scene": "chair", "builtin_resolution": 24, "iters": 8,
                                          "heldout_every": 4, "eval_max_views": 1, "out": str(tmp_path / "run"),
                                          "log_every": 4})
    metrics = run_training(cfg, progress=False)
    hist = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [s for s, _ in hist["heldout"]] == [3, 7]
    assert [s for s, _ in hist["lipschitz"]] == [0, 4, 7]
    assert (tmp_path / "run" / "training.png").stat().st_size > 1000
    assert 0 <= metrics["heldout_seconds"] < metrics["train_seconds"]


def test_final_metrics_are_logged_at_the_last_step(tmp_path, monkeypatch):
    """run_training with --log tensorboard: test/psnr and test/ssim (test/lpips when its weights are on disk) at the
    last step, equal to metrics.json's."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from warpnerf.runs.run import run_training

    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    cfg = build_config("full", overrides={**TINY, "scene": "chair", "builtin_resolution": 24, "iters": 6,
                                          "heldout_every": 0, "eval_max_views": 1, "out": str(tmp_path / "run"),
                                          "log_every": 3, "log": "tensorboard", "checkpoint_every": 0})
    metrics = run_training(cfg, progress=False)
    acc = EventAccumulator(str(tmp_path / "run" / "tb"))
    acc.Reload()
    for tag in final_tags("test"):
        key = tag.split("/")[1]
        if metrics[key] is None:  # LPIPS without its weights: not logged
            assert tag not in acc.Tags()["scalars"]
            continue
        (event,) = acc.Scalars(tag)
        assert event.step == 5 and event.value == pytest.approx(metrics[key], rel=1e-6)
