"""Monitoring: TensorBoard scalars, the held-out PSNR curve and the encoding's Lipschitz bound (eq. 17)."""

import json

import pytest
import torch

from tiny_scene import tiny_scene
from warpnerf.model.encoders import make_grid_encoder
from warpnerf.train.config import ConfigError, build_config
from warpnerf.train.monitor import TAGS, Monitor, lipschitz_bound
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

TINY = dict(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128, hidden=32, target_samples=8192,
            batch_rays=256, occ_resolution=32, occ_warmup=16, occ_update_every=8, lr=2e-2, video_frames=0,
            march_steps=256)


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
    trainer.fit(progress=False)
    monitor.close()
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert set(TAGS) <= tags, set(TAGS) - tags
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
