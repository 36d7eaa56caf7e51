"""Drive one run: load the scene, build task and trainer, train, evaluate, write the run folder.

Run folder layout::

    config.toml       resolved configuration (re-usable with --config)
    metrics.json      psnr, ssim, timings, task metrics (see README)
    history.json      training curves
    checkpoint.pt     field, occupancy grid and pose corrections (for ``warpnerf eval``)
    renders/          test views (prediction | ground truth) and depth
    turntable.mp4     orbit video (spiral for forward-facing scenes); turntable.gif without imageio-ffmpeg
    training.png      loss / PSNR curves; pose runs add cameras.png and pose_error.png
"""

from __future__ import annotations

import json
import os
import time
from typing import Optional

import torch

from . import device as devmod
from .config import TrainConfig, build_config, load_toml
from .tasks import make_task
from .trainer import Trainer, write_json


def load_scene_for(cfg: TrainConfig, progress: bool = True):
    from .data.resolve import load_scene

    return load_scene(cfg.scene, data_root=cfg.data_root, downscale=cfg.downscale,
                      builtin_resolution=cfg.builtin_resolution, progress=progress)


def config_text(cfg: TrainConfig) -> str:
    """The resolved configuration as TOML (what ``config.toml`` of a run folder holds)."""
    lines = []
    for key, value in cfg.to_dict().items():
        if value is None:
            continue  # TOML has no null: an absent key means the default
        if isinstance(value, bool):
            lines.append(f"{key} = {'true' if value else 'false'}")
        elif isinstance(value, (int, float)):
            lines.append(f"{key} = {value!r}")
        else:
            lines.append(f'{key} = "{value}"')
    return "\n".join(lines) + "\n"


def write_config(path: str, cfg: TrainConfig) -> None:
    with open(path, "w") as fh:
        fh.write(config_text(cfg))


def finished_metrics(cfg: TrainConfig) -> Optional[dict]:
    """metrics.json of ``cfg.run_dir()`` if that folder holds a finished run of exactly ``cfg``."""
    out_dir = cfg.run_dir()
    cfg_path, metrics_path = os.path.join(out_dir, "config.toml"), os.path.join(out_dir, "metrics.json")
    if not (os.path.exists(cfg_path) and os.path.exists(metrics_path)):
        return None
    with open(cfg_path) as fh:
        if fh.read() != config_text(cfg):
            return None
    with open(metrics_path) as fh:
        metrics = json.load(fh)
    # metrics.json is written twice; total_seconds marks the second (complete) write
    return metrics if "total_seconds" in metrics else None


def _configure_lpips(cfg: TrainConfig) -> None:
    """Pick the LPIPS weights evaluation uses (``--lpips-weights``; unusable path: one-line error)."""
    from . import metrics
    from .config import ConfigError

    try:
        metrics.configure_lpips(cfg.lpips_weights)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def run_training(cfg: TrainConfig, progress: bool = True) -> dict:
    """Train and evaluate one configuration; returns the metrics written to metrics.json."""
    if cfg.threads is not None:
        devmod.set_num_threads(cfg.threads)
    device = devmod.resolve_device(cfg.device)
    _configure_lpips(cfg)
    t_start = time.perf_counter()
    scene = load_scene_for(cfg, progress)
    task = make_task(cfg)
    out_dir = cfg.run_dir()
    os.makedirs(out_dir, exist_ok=True)
    write_config(os.path.join(out_dir, "config.toml"), cfg)
    print(f"scene '{scene.name}' from {scene.source} ({scene.root}); task {cfg.task}; "
          f"G2fR {'on' if cfg.g2fr else 'off'}; device {device}; threads {devmod.num_threads()}; run folder {out_dir}")
    trainer = Trainer(cfg, scene, task, device)
    from .monitor import Monitor

    monitor = Monitor(trainer)
    trainer.callbacks.append(monitor)
    trainer.fit(progress)
    monitor.close()
    torch.save(trainer.state_dict(), os.path.join(out_dir, "checkpoint.pt"))
    t_eval = time.perf_counter()
    results = trainer.evaluate(out_dir, progress)
    eval_seconds = time.perf_counter() - t_eval
    metrics = {
        "psnr": results["psnr"],
        "ssim": results["ssim"],
        "lpips": results["lpips"],
        "iters": cfg.iters,
        "train_seconds": trainer.train_seconds,
        "heldout_seconds": monitor.heldout_seconds,  # part of train_seconds: held-out PSNR renders
        "eval_seconds": eval_seconds,
        "n_train_views": len(trainer.views),
        "train_view_ids": trainer.views.ids,
        "scene": scene.name,
        "scene_source": scene.source,
        "task": cfg.task,
        "model": cfg.model,
        "g2fr": cfg.g2fr,
        "g2fr_beta": cfg.g2fr_beta,
        "g2fr_mask": cfg.g2fr_mask,
        "device": device,
        "threads": devmod.num_threads(),
        "seed": cfg.seed,
        **{k: v for k, v in results.items() if k not in ("psnr", "ssim", "lpips")},
        **task.metrics(trainer),
    }
    write_json(os.path.join(out_dir, "metrics.json"), metrics)
    write_json(os.path.join(out_dir, "history.json"), trainer.history)
    from . import plots, video

    plots.plot_training_curves(os.path.join(out_dir, "training.png"),
                               {"step": trainer.history["step"], "training batch loss (MSE)": trainer.history["loss"],
                                "training batch PSNR (dB)": trainer.history["psnr"],
                                **({"held-out PSNR (dB)": trainer.history["heldout"]} if trainer.history["heldout"] else {}),
                                "encoding Lipschitz bound L_Psi (eq. 17)": trainer.history["lipschitz"]},
                               title=f"{scene.name} / {cfg.task}: training curves (test metrics in metrics.json)")
    task.artifacts(trainer, out_dir)
    if cfg.video_frames > 0:
        video.render_run_video(trainer, out_dir, cfg.video_frames, progress)  # turntable.mp4 (.gif without ffmpeg)
    from .trainer import peak_rss_mb

    metrics["peak_rss_mb"] = peak_rss_mb()  # after training, evaluation and video
    metrics["total_seconds"] = time.perf_counter() - t_start
    write_json(os.path.join(out_dir, "metrics.json"), metrics)
    return metrics


def evaluate_run(run_dir: str, progress: bool = True) -> dict:
    """Re-evaluate a finished run folder from its config and checkpoint."""
    cfg_path = os.path.join(run_dir, "config.toml")
    ckpt = os.path.join(run_dir, "checkpoint.pt")
    for p in (cfg_path, ckpt):
        if not os.path.exists(p):
            from .config import ConfigError

            raise ConfigError(f"not a finished run folder: {p} is missing")
    values = load_toml(cfg_path)
    cfg = build_config(values.pop("task"), overrides=values)
    cfg.out = run_dir
    device = devmod.resolve_device(cfg.device)
    _configure_lpips(cfg)
    scene = load_scene_for(cfg, progress)
    task = make_task(cfg)
    trainer = Trainer(cfg, scene, task, device)
    trainer.load_state_dict(torch.load(ckpt, map_location=trainer.device))
    results = trainer.evaluate(os.path.join(run_dir, "eval"), progress)
    results.update(task.metrics(trainer))
    write_json(os.path.join(run_dir, "eval", "metrics.json"), results)
    return results
