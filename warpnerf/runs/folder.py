"""The run folder's files, read back: the one module that opens a run folder a run wrote.

Layout (written by :func:`warpnerf.runs.run.run_training`)::

    config.toml       resolved configuration (:func:`write_config`, :func:`read_run_config`)
    metrics.json      written last: its presence (with ``config_hash``) marks the run finished
    checkpoint.pt     full training state, read only through :func:`read_checkpoint`

Every checkpoint read goes through :func:`warpnerf.train.checkpoint.load_checkpoint`
(``torch.load(..., weights_only=True)`` plus its format and truncation checks), so a foreign file
in a run folder is refused instead of unpickled: ``warpnerf eval``, ``--resume``, ``render``,
``export``, ``view`` and ``bench render`` all read through here.
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Optional

import tomli_w

from warpnerf import device as devmod
from warpnerf.data.resolve import load_scene
from warpnerf.train.checkpoint import atomic_write_text, load_checkpoint
from warpnerf.train.config import ConfigError, TrainConfig, build_config, load_toml
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

CONFIG = "config.toml"
METRICS = "metrics.json"
CHECKPOINT = "checkpoint.pt"

RESULT_NEUTRAL_KEYS = ("out", "device", "threads")  # change where/how fast a run goes, not its numbers


def config_text(cfg: TrainConfig) -> str:
    """The resolved configuration as TOML (what ``config.toml`` of a run folder holds).

    Written by a real TOML writer so quotes and backslashes in paths survive the round trip;
    None values are left out (TOML has no null: an absent key means the default)."""
    return tomli_w.dumps({k: v for k, v in cfg.to_dict().items() if v is not None})


def config_hash(cfg: TrainConfig) -> str:
    """sha256 (hex) of the configuration without the keys that do not change results
    (:data:`RESULT_NEUTRAL_KEYS`): metrics.json and checkpoints carry it, and resume, eval and
    ``table --reuse`` compare it."""
    values = {k: v for k, v in cfg.to_dict().items() if v is not None and k not in RESULT_NEUTRAL_KEYS}
    return hashlib.sha256(tomli_w.dumps(values).encode("utf-8")).hexdigest()


def write_config(path: str, cfg: TrainConfig) -> None:
    atomic_write_text(path, config_text(cfg))


def read_run_config(run_dir: str) -> TrainConfig:
    """The TrainConfig stored in ``run_dir/config.toml`` (``out`` set to ``run_dir``)."""
    path = os.path.join(run_dir, CONFIG)
    if not os.path.isfile(path):
        raise ConfigError(f"not a warpnerf run folder: {path} is missing")
    values = load_toml(path)
    task = values.pop("task", None)
    if task is None:
        raise ConfigError(f"{path}: missing key 'task'")
    values["out"] = run_dir
    return build_config(task, overrides=values)


def read_metrics(run_dir: str) -> Optional[dict]:
    """metrics.json of a run folder, or None when absent or unreadable (a run that never finished)."""
    path = os.path.join(run_dir, METRICS)
    try:
        with open(path) as fh:
            metrics = json.load(fh)
    except (OSError, ValueError):
        return None
    return metrics if isinstance(metrics, dict) and "config_hash" in metrics else None


def finished_metrics(cfg: TrainConfig) -> Optional[dict]:
    """metrics.json of ``cfg.run_dir()`` if that folder holds a finished run of exactly ``cfg``
    (same :func:`config_hash`); None otherwise."""
    metrics = read_metrics(cfg.run_dir())
    if metrics is None or metrics.get("config_hash") != config_hash(cfg):
        return None
    return metrics


def folder_state(out_dir: str) -> str:
    """"absent", "empty", "finished" (metrics.json), "unfinished" (config.toml, no metrics) or "foreign"."""
    if not os.path.exists(out_dir):
        return "absent"
    if not os.path.isdir(out_dir):
        return "foreign"
    names = [n for n in os.listdir(out_dir) if not n.startswith(".tmp-")]
    if not names:
        return "empty"
    if CONFIG not in names:
        return "foreign"
    return "finished" if read_metrics(out_dir) is not None else "unfinished"


def read_checkpoint(run_dir: str, map_location=None) -> dict:
    """``run_dir/checkpoint.pt`` through :func:`~warpnerf.train.checkpoint.load_checkpoint`
    (CheckpointError for a missing, truncated or foreign file; never unpickles code)."""
    return load_checkpoint(os.path.join(run_dir, CHECKPOINT), map_location=map_location)


def load_scene_for(cfg: TrainConfig, progress: bool = True):
    """The scene ``cfg`` trains on (name, data root, downscale, ...), loaded or generated."""
    return load_scene(cfg.scene, data_root=cfg.data_root, downscale=cfg.downscale,
                      builtin_resolution=cfg.builtin_resolution, progress=progress, allow_rgb=cfg.allow_rgb,
                      unbounded=cfg.unbounded)


def load_run(run_dir: str, device: str = "auto", progress: bool = False) -> Trainer:
    """A :class:`~warpnerf.train.trainer.Trainer` holding a finished run's field, occupancy grid and poses.

    The checkpoint is read (and checked) before the scene loads, so a bad one fails at once."""
    cfg_path, ckpt = os.path.join(run_dir, CONFIG), os.path.join(run_dir, CHECKPOINT)
    for p in (cfg_path, ckpt):
        if not os.path.exists(p):
            raise ConfigError(f"not a finished run folder: {p} is missing")
    values = load_toml(cfg_path)
    values["device"] = device
    cfg = build_config(values.pop("task"), overrides=values)
    cfg.out = run_dir
    dev = devmod.resolve_device(cfg.device)
    state = read_checkpoint(run_dir, map_location=devmod.torch_device(dev))
    scene = load_scene_for(cfg, progress)
    trainer = Trainer(cfg, scene, make_task(cfg), dev)
    trainer.load_state_dict(state)
    return trainer
