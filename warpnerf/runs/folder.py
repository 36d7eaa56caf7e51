"""The run folder's files, read back: the one module that opens a run folder a run wrote.

Layout (written by :func:`warpnerf.runs.run.run_training`)::

    config.toml       resolved configuration (:func:`write_config`, :func:`read_run_config`)
    metrics.json      written last: its presence (with ``config_hash``) marks the run finished
    checkpoint.pt     full training state, read only through :func:`read_checkpoint`
    .warpnerf-run     marker: warpnerf created this folder (``--overwrite`` removes only marked folders)
    .warpnerf-lock    pid and host of the process training into the folder (:class:`RunLock`)

Every checkpoint read goes through :func:`warpnerf.train.checkpoint.load_checkpoint`
(``torch.load(..., weights_only=True)`` plus its format and truncation checks), so a foreign file
in a run folder is refused instead of unpickled: ``warpnerf eval``, ``--resume``, ``render``,
``export``, ``view`` and ``bench render`` all read through here.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
from typing import Optional

import tomli_w

from warpnerf import device as devmod
from warpnerf.data.background import SettledBackground, is_opaque
from warpnerf.data.resolve import data_root_from, load_scene
from warpnerf.train.checkpoint import CheckpointError, atomic_write_text, load_checkpoint
from warpnerf.train.config import ConfigError, TrainConfig, build_config, load_toml
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

CONFIG = "config.toml"
METRICS = "metrics.json"
CHECKPOINT = "checkpoint.pt"
MARKER = ".warpnerf-run"
LOCK = ".warpnerf-lock"
_BOOKKEEPING = (MARKER, LOCK)  # files of ours that do not make a folder a run

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
    names = [n for n in os.listdir(out_dir) if not n.startswith(".tmp-") and n not in _BOOKKEEPING]
    if not names:
        return "empty"
    if CONFIG not in names:
        return "foreign"
    return "finished" if read_metrics(out_dir) is not None else "unfinished"


def is_marked(out_dir: str) -> bool:
    """Whether warpnerf created ``out_dir`` (it holds the :data:`MARKER` file). Folders written
    before the marker existed are still read and resumed, but ``--overwrite`` does not remove them."""
    return os.path.isfile(os.path.join(out_dir, MARKER))


def write_marker(out_dir: str) -> None:
    path = os.path.join(out_dir, MARKER)
    if not os.path.exists(path):
        atomic_write_text(path, "warpnerf run folder: --overwrite may remove this folder\n")


def clear_run_folder(out_dir: str) -> None:
    """Empty a marked run folder for ``--overwrite``, keeping the marker and the lock of the
    process that is about to train into it. Refuses (ConfigError) a folder without the marker."""
    import shutil  # lazy: only --overwrite needs it

    if not os.path.isdir(out_dir):
        return
    if not is_marked(out_dir):
        raise ConfigError(f"run folder {out_dir} was not created by warpnerf (no {MARKER}); --overwrite removes only "
                          "folders warpnerf made: remove it yourself or choose another --out")
    for name in os.listdir(out_dir):
        if name in _BOOKKEEPING:
            continue
        path = os.path.join(out_dir, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        else:
            os.unlink(path)


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    except OSError:
        return False
    return True


class RunLock:
    """``out_dir/.warpnerf-lock``: one training process per run folder.

    :meth:`acquire` creates the folder if needed and the lock file with ``O_CREAT | O_EXCL``
    (atomic: of two processes exactly one wins), holding ``pid host``. A lock whose process is no
    longer alive on this host is stale and taken over (``self.note`` says so); a live one, or one
    from another host, raises ConfigError. :meth:`release` removes the lock, and the folder too when
    this lock created it and nothing else was written."""

    def __init__(self, out_dir: str):
        self.out_dir = out_dir
        self.path = os.path.join(out_dir, LOCK)
        self.held = False
        self.created_dir = False
        self.note: Optional[str] = None

    @staticmethod
    def owner(out_dir: str) -> Optional[tuple[int, str]]:
        """(pid, host) in ``out_dir``'s lock, or None when there is none; (-1, "") when unreadable."""
        try:
            with open(os.path.join(out_dir, LOCK)) as fh:
                parts = fh.read().split()
        except FileNotFoundError:
            return None
        except OSError:
            return (-1, "")
        try:
            return int(parts[0]), (parts[1] if len(parts) > 1 else "")
        except (ValueError, IndexError):
            return (-1, "")

    @staticmethod
    def live_owner(out_dir: str) -> Optional[str]:
        """A description of the live process that holds ``out_dir``'s lock, or None (no lock, or stale)."""
        owner = RunLock.owner(out_dir)
        if owner is None:
            return None
        pid, host = owner
        if host and host != socket.gethostname():
            return f"process {pid} on host {host}"
        if pid != os.getpid() and _pid_alive(pid):
            return f"process {pid}"
        return None

    def _busy(self, who: str) -> ConfigError:
        return ConfigError(f"run folder {self.out_dir} is in use by {who} (lock {self.path}); wait for it, or "
                           "delete the lock if that process is gone")

    def acquire(self) -> "RunLock":
        """Create the folder if needed and the lock file in it; ConfigError (one line) when another live
        process holds it or the folder cannot be written (a read-only or virtual file system: os.access
        says yes to root everywhere, so the first write is the test)."""
        if not os.path.isdir(self.out_dir):
            try:
                os.makedirs(self.out_dir)
                self.created_dir = True
            except FileExistsError:
                pass
            except OSError as e:
                raise ConfigError(f"run folder {self.out_dir} cannot be created: {e.strerror or e}; "
                                  "choose another --out") from None
        text = f"{os.getpid()} {socket.gethostname()}\n"
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                who = self.live_owner(self.out_dir)
                if who is not None:
                    self.release()
                    raise self._busy(who) from None
                pid = (self.owner(self.out_dir) or (-1, ""))[0]
                self.note = f"took over the stale lock of process {pid} (no longer running) in {self.out_dir}"
                try:  # a racing process may take it over too: only one of us gets the O_EXCL create after this
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
                continue
            except OSError as e:
                self.release()
                raise ConfigError(f"run folder {self.out_dir} is not writable: {e.strerror or e}; "
                                  "choose another --out") from None
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            self.held = True
            return self
        self.release()
        raise self._busy("another process")

    def release(self) -> None:
        if self.held:
            try:
                if self.owner(self.out_dir) == (os.getpid(), socket.gethostname()):
                    os.unlink(self.path)
            except OSError:
                pass
            self.held = False
        if self.created_dir:
            try:
                os.rmdir(self.out_dir)  # only when empty: nothing was written
            except OSError:
                pass
            self.created_dir = False

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def read_checkpoint(run_dir: str, map_location=None) -> dict:
    """``run_dir/checkpoint.pt`` through :func:`~warpnerf.train.checkpoint.load_checkpoint`
    (CheckpointError for a missing, truncated or foreign file; never unpickles code)."""
    return load_checkpoint(os.path.join(run_dir, CHECKPOINT), map_location=map_location)


ALL_SPLITS = ("train", "val", "test")


def load_scene_for(cfg: TrainConfig, progress: bool = True, splits: tuple[str, ...] = ALL_SPLITS,
                   settled: Optional[SettledBackground] = None):
    """The scene ``cfg`` trains on (name, data root, downscale, ...), loaded or generated; ``splits``: the
    splits to read (a viewer skips val). With ``settled`` (the background a run stored: :func:`stored_background`)
    a cameras-only load: no pixel is read, the images are stand-ins (``load_scene(..., pixels=False)``)."""
    return load_scene(cfg.scene, data_root=cfg.data_root, downscale=cfg.downscale,
                      builtin_resolution=cfg.builtin_resolution, progress=progress, allow_rgb=cfg.allow_rgb,
                      unbounded=cfg.unbounded, ndc=cfg.ndc, llff_test=cfg.llff_test, background=cfg.background,
                      splits=splits, pixels=settled is None, settled=settled)


def stored_background(cfg: TrainConfig, state: dict) -> Optional[SettledBackground]:
    """The background a run trained with, as its checkpoint ``state`` records it (``scene_background``, written
    since runs store it), or None: a run from before, or a record that does not fit ``cfg``'s --background."""
    settled = SettledBackground.from_dict(state.get("scene_background"))
    return settled if settled is not None and settled.mode == (cfg.background or "auto") else None


def resolve_data_root(cfg: TrainConfig) -> None:
    """Record in ``cfg.data_root`` the data root ``$WARPNERF_DATA`` supplies when none was given,
    so the run folder's config.toml reopens the same scene in a shell without that variable."""
    if not cfg.data_root:
        root = data_root_from(None)
        if root:
            cfg.data_root = root


def check_scene(run_dir: str, scene, recorded: Optional[str]) -> None:
    """ConfigError when ``scene`` (as the run's config resolves it now) comes from another source than
    the one the run trained on (``recorded``: metrics.json's or the checkpoint's ``scene_source``),
    e.g. a built-in scene of the same name because the data root is not set in this shell."""
    if recorded and recorded != scene.source:
        hint = ("pass --data-root (or set $WARPNERF_DATA) to the data it trained on" if scene.source == "builtin"
                else "the data root now holds a scene of that name; unset it to use the built-in scene")
        raise ConfigError(f"{run_dir} was trained on the {recorded} scene '{scene.name}', but '{scene.name}' now "
                          f"resolves to the {scene.source} scene at {scene.root}; {hint}")


def load_state_checked(trainer: Trainer, state: dict, run_dir: str, optimizer: bool = True) -> None:
    """``trainer.load_state_dict(state)``; a checkpoint whose tensors do not fit this scene (another
    view count or size) is a one-line CheckpointError instead of torch's size-mismatch traceback.
    ``optimizer=False`` leaves the optimizer's moments (2/3 of a checkpoint) unread: for a viewer, which
    never takes a step."""
    if not optimizer:
        state = {**state, "optimizer": trainer.optimizer.state_dict()}
    try:
        trainer.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{run_dir}/{CHECKPOINT} does not fit the scene '{trainer.scene.name}' as it resolves "
                              f"now ({trainer.scene.source}, {trainer.scene.root}): {first[:200]}") from None


def load_run(run_dir: str, device: str = "auto", progress: bool = False, splits: tuple[str, ...] = ALL_SPLITS,
             optimizer: bool = True, pixels: bool = True) -> Trainer:
    """A :class:`~warpnerf.train.trainer.Trainer` holding a finished run's field, occupancy grid and poses
    (``splits`` and ``optimizer``: see :func:`load_scene_for` and :func:`load_state_checked`).

    ``pixels=False``: a cameras-only scene (for a viewer, which never trains): its images are stand-ins on the
    device and nothing is decoded, with the background the checkpoint records (:func:`stored_background`). A run
    from before checkpoints recorded it is loaded in full instead (its pixels decoded: the background is
    detected from them as in training, over the splits training read: val too when an opaque Blender-layout
    scene is detected on), and ``trainer.scene.pixels`` is True.

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
    settled = None if pixels else stored_background(cfg, state)
    scene = load_scene_for(cfg, progress, splits, settled)
    if (not pixels and settled is None and (cfg.background or "auto") == "auto" and "val" not in splits
            and scene.kind in ("blender", "unbounded") and is_opaque(scene)):
        # training detected the background on the val split's views too (a Blender-layout scene reads val only
        # when asked); without them the detection could settle another colour. Images with transparency were
        # never looked at: no second load for them.
        scene = load_scene_for(cfg, progress, tuple(s for s in ALL_SPLITS if s in splits or s == "val"))
        scene.val = None
    check_scene(run_dir, scene, (read_metrics(run_dir) or {}).get("scene_source") or state.get("scene_source"))
    if not scene.pixels:  # stand-ins on the device: the trainer's .to(device) then copies nothing
        scene.drop_pixels(devmod.torch_device(dev))
    trainer = Trainer(cfg, scene, make_task(cfg), dev)
    load_state_checked(trainer, state, run_dir, optimizer)
    return trainer
