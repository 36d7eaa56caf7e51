"""Drive one run: load the scene, build task and trainer, train, evaluate, write the run folder.

Run folder layout::

    config.toml       resolved configuration (re-usable with --config)
    metrics.json      psnr, ssim, timings, task metrics, config_hash; written last: marks the run finished
    history.json      training curves
    checkpoint.pt     full training state (periodic, atomic; for --resume and ``warpnerf eval``)
    renders/          test views (prediction | ground truth) and depth
    turntable.mp4     orbit video (spiral for forward-facing scenes); turntable.gif without imageio-ffmpeg
    training.png      loss / PSNR curves; pose runs add cameras.png and pose_error.png
    .warpnerf-run     marker: warpnerf made this folder; ``--overwrite`` removes only marked folders
    .warpnerf-lock    pid of the process training into the folder (removed when it ends)
"""

from __future__ import annotations

import os
import signal
import time
from typing import Optional

import torch

from warpnerf import device as devmod
from warpnerf.data.background import SettledBackground
from warpnerf.data.errors import DatasetError
from warpnerf.runs import record, video
from warpnerf.runs.folder import (CHECKPOINT, MARKER, RESULT_NEUTRAL_KEYS, RunLock, check_scene, clear_run_folder,
                                  config_hash, folder_state, is_marked, load_scene_for, load_state_checked,
                                  read_checkpoint, read_metrics, read_run_config, resolve_data_root, write_config,
                                  write_marker)
from warpnerf.train import plots
from warpnerf.train.checkpoint import WriteError, _fault, save_checkpoint
from warpnerf.train.config import ConfigError, TrainConfig, forward_facing_preset
from warpnerf.train.evaluate import eval_view_count, evaluate, write_json
from warpnerf.train.metrics import configure_lpips
from warpnerf.train.monitor import Monitor, heldout_split
from warpnerf.train.pause import wait_while_paused
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer, TrainingError, peak_rss_mb, start_memory_window


def _configure_lpips(cfg: TrainConfig) -> None:
    """Pick the LPIPS weights evaluation uses (``--lpips-weights``; unusable path: one-line error)."""
    try:
        configure_lpips(cfg.lpips_weights)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _check_writable(out_dir: str) -> None:
    probe = os.path.abspath(out_dir)
    while not os.path.exists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        raise ConfigError(f"run folder {out_dir}: {probe} exists and is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ConfigError(f"run folder {out_dir}: {probe} is not writable")


class TrainingInterrupted(Exception):
    """SIGINT/SIGTERM: a checkpoint was saved at a step boundary ``step`` (the CLI exits 130)."""

    def __init__(self, message: str, step: Optional[int] = None):
        super().__init__(message)
        self.step = step


def _config_diff(a: TrainConfig, b: TrainConfig) -> list[str]:
    da, db = a.to_dict(), b.to_dict()
    return [k for k in da if k not in RESULT_NEUTRAL_KEYS and da[k] != db[k]]


def prepare_run(cfg: TrainConfig, overwrite: bool = False, resume: bool = False, force: bool = False) -> str:
    """Decide what happens to the run folder *before* anything loads or is written.

    Returns "fresh", "resume" or "finished" (a resumed run that has nothing left to do). Raises
    ConfigError when the folder holds another run, an unfinished run without ``resume``, a
    finished run without ``overwrite``, a changed config on resume without ``force``, a folder
    another live process is training into, or ``overwrite`` of a folder warpnerf did not create."""
    out_dir = cfg.run_dir()
    who = RunLock.live_owner(out_dir) if os.path.isdir(out_dir) else None
    if who is not None:
        raise ConfigError(f"run folder {out_dir} is in use by {who} (lock {os.path.join(out_dir, '.warpnerf-lock')}); "
                          "wait for it or choose another --out")
    state = folder_state(out_dir)
    if state == "foreign":
        raise ConfigError(f"run folder {out_dir} exists and is not a warpnerf run folder; choose another --out")
    if resume:
        if state in ("absent", "empty"):
            raise ConfigError(f"nothing to resume: {out_dir} holds no run")
        saved = read_run_config(out_dir)
        changed = _config_diff(saved, cfg)
        if changed and not force:
            raise ConfigError(f"{out_dir}/config.toml: config changed on resume ({', '.join(changed)}); "
                              "pass --force to continue with the new values")
        if state == "finished" and not changed:
            return "finished"
        _check_writable(out_dir)
        return "resume"
    if state == "finished" and not overwrite:
        raise ConfigError(f"run folder {out_dir} holds a finished run; pass --overwrite to replace it or choose another --out")
    if state == "unfinished" and not overwrite:
        raise ConfigError(f"run folder {out_dir} holds an unfinished run; continue it with --resume {out_dir} "
                          "or replace it with --overwrite")
    if state in ("finished", "unfinished") and not is_marked(out_dir):
        raise ConfigError(f"run folder {out_dir} was not created by warpnerf (no {MARKER}); --overwrite removes only "
                          "folders warpnerf made: remove it yourself or choose another --out")
    _check_writable(out_dir)
    return "fresh"


class _Terminated(SystemExit):
    """SIGTERM outside the training loop: unwind (releasing the run folder's lock) and exit 143."""


def _on_sigterm(signum, frame):
    raise _Terminated(128 + signum)


# What SIGINT/SIGTERM raise out of run_training: TrainingInterrupted in the training loop (a checkpoint
# was saved at a step boundary), KeyboardInterrupt (SIGINT) or _Terminated (SIGTERM) anywhere else
# (the folder keeps its last checkpoint). A sweep stops on any of them instead of counting a failure.
INTERRUPTS: tuple = (TrainingInterrupted, KeyboardInterrupt, _Terminated)


def run_training(cfg: TrainConfig, progress: bool = True, overwrite: bool = False, resume: bool = False,
                 force: bool = False) -> dict:
    """Train and evaluate one configuration; returns the metrics written to metrics.json.

    Everything the user can get wrong (config values, device, run folder, data) is checked before
    the first file is written. With ``cfg.checkpoint_every`` a checkpoint is
    saved atomically every that many steps; SIGINT/SIGTERM save one at the next step boundary and
    raise TrainingInterrupted. ``resume`` continues an unfinished run folder bit-identically from its last checkpoint.
    A file that cannot be written (a full disk) is a one-line TrainingError naming it; the last checkpoint
    is kept, and the message says how to continue from it."""
    try:
        if cfg.threads is not None:
            devmod.limit_cpu_threads(cfg.threads)
        device = devmod.resolve_device(cfg.device)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    _configure_lpips(cfg)
    if not resume:  # a resumed run keeps what its config.toml says
        try:
            resolve_data_root(cfg)  # config.toml names the data, not "whatever $WARPNERF_DATA says"
        except DatasetError as e:
            raise ConfigError(str(e)) from None
    prepare_run(cfg, overwrite, resume, force)  # fails before the folder is touched
    lock = RunLock(cfg.run_dir()).acquire()  # atomic: of two runs into one folder, one gets here
    installed = False
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)  # unwind through the finally below
        installed = True
    except ValueError:  # not the main thread
        previous = None
    try:
        if lock.note:
            print(f"note: {lock.note}")
        mode = prepare_run(cfg, overwrite, resume, force)  # again, now that no other run can change the folder
        return _run_locked(cfg, mode, device, progress, overwrite)
    except WriteError as e:  # a full disk: the last checkpoint is intact, the run continues from it
        ckpt = os.path.join(cfg.run_dir(), CHECKPOINT)
        how = (f"free space, then continue from the last checkpoint with: warpnerf train --resume {cfg.run_dir()}"
               if os.path.exists(ckpt) and os.path.exists(os.path.join(cfg.run_dir(), "config.toml"))
               else "free space and run again")
        raise TrainingError(f"{e}; {how}") from e
    finally:
        if installed:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
        lock.release()


def after_training_line(cfg: TrainConfig, n_eval: int) -> str:
    """The banner's second line: what runs after the training bar ends, and the flags that shorten it."""
    views = f"{n_eval} {cfg.eval_split} view{'s' if n_eval != 1 else ''} (--eval-max-views N renders fewer)"
    refine = (f", their poses refined first ({cfg.pose_refine_steps} steps)"
              if (cfg.task == "pose" or cfg.refine_test_poses) and cfg.pose_refine_steps > 0 else "")
    video = (f"a {cfg.video_frames}-frame turntable video (--video-frames 0 skips it)" if cfg.video_frames > 0
             else "no video (--video-frames 0)")
    return f"after training: evaluation on {views}{refine}; {video}"


def progress_legend(cfg: TrainConfig) -> str:
    """The training bar's abbreviations, spelled out once before it starts."""
    legend = ("progress bar: lv = active G2fR levels, occ = occupied fraction of the occupancy grid, "
              "spr = samples per ray, rays = rays per step")
    if cfg.task == "pose":
        legend += ", rot / trans = training-pose rotation error (deg) / translation error (x100)"
    return legend


def _run_locked(cfg: TrainConfig, mode: str, device: str, progress: bool, overwrite: bool) -> dict:
    start_memory_window()  # this run's peak memory, not that of earlier runs in this process
    out_dir = cfg.run_dir()
    if mode == "finished":
        print(f"{out_dir} is already finished; nothing to do")
        return dict(read_metrics(out_dir), already_finished=True)
    t_start = time.perf_counter()
    code, cpu_meter = record.git_state(), record.CpuMeter().start()  # the code that trains, and the CPU left to others
    ckpt_path = os.path.join(out_dir, CHECKPOINT)
    state = None
    if mode == "resume" and os.path.exists(ckpt_path):  # a bad checkpoint fails before the scene loads
        state = read_checkpoint(out_dir, map_location="cpu")
    scene = load_scene_for(cfg, progress)
    # what the background detection decided from the pixels, for the checkpoint and metrics.json: a viewer's
    # cameras-only load has no pixel to decide it from (warpnerf.data.background.SettledBackground)
    settled = SettledBackground.of(scene, cfg.background).to_dict()
    if mode == "resume":
        check_scene(out_dir, scene, (state or {}).get("scene_source"))
    task = make_task(cfg)
    trainer = Trainer(cfg, scene, task, device)  # checks the view selection against the scene
    if state is not None:
        load_state_checked(trainer, state, out_dir)
    if overwrite and mode == "fresh" and folder_state(out_dir) in ("finished", "unfinished"):
        clear_run_folder(out_dir)  # marked folders only (prepare_run checked); keeps the lock
    os.makedirs(out_dir, exist_ok=True)
    if mode == "fresh":
        write_marker(out_dir)
    for name in os.listdir(out_dir):  # temp files of writes a crash cut short
        if name.startswith(".tmp-"):
            os.unlink(os.path.join(out_dir, name))
    if mode == "resume" and os.path.exists(os.path.join(out_dir, "metrics.json")):
        os.unlink(os.path.join(out_dir, "metrics.json"))  # --force on a finished run: it is unfinished again
    write_config(os.path.join(out_dir, "config.toml"), cfg)
    preset = f"configs/{cfg.task}.toml"
    ff_preset = forward_facing_preset(cfg.task, cfg.scene, cfg.data_root, ndc=cfg.ndc,
                                      unbounded=cfg.unbounded)  # as build_config decided
    if ff_preset:
        preset += f" + {os.path.basename(ff_preset)}"
    print(f"scene '{scene.name}' from {scene.source} ({scene.root}); task {cfg.task} (preset {preset}); "
          f"G2fR {'on' if cfg.g2fr else 'off'}; device {device}; threads {devmod.num_threads()}; run folder {out_dir}"
          + (f"; resumed at step {trainer.step}" if mode == "resume" else ""))
    framing = getattr(getattr(scene, "normalization", None), "framing", "")
    if framing:  # a capture's world was mapped from its rig: say how (warpnerf.data.normalize)
        print(f"framing: {framing}")
    if scene.background_note:  # images without alpha: what stands behind the field (warpnerf.data.background)
        print(f"background: {scene.background_note}")
    print(after_training_line(cfg, eval_view_count(trainer)))
    if progress:
        print(progress_legend(cfg))
    caveat = task.caveat(scene)
    if caveat:
        print(caveat)

    stop = []

    def on_signal(signum, frame):  # a Warp launch cannot be interrupted: stop at the next step boundary
        stop.append(signum)

    def save() -> None:
        save_checkpoint(ckpt_path, {**trainer.state_dict(), "config_hash": config_hash(cfg),
                                    "scene_source": scene.source,  # view/render/eval compare it
                                    "scene_background": settled})  # a viewer's cameras-only load applies it

    def checkpoint_due(n_done: int) -> bool:
        # for --resume, and for 'warpnerf view' to follow the run
        every = cfg.checkpoint_every
        return n_done < cfg.iters and every > 0 and n_done % every == 0

    def on_step_end(n_done: int) -> None:
        _fault(f"step:{n_done}")
        saved = bool(stop) or checkpoint_due(n_done)
        if saved:
            save()
        if not stop and n_done < cfg.iters:  # RUN/PAUSE (warpnerf view's Pause): wait here, checkpoint saved;
            # fit counts this call's time in the next step's: take the wait back out of train_seconds
            trainer.train_seconds -= wait_while_paused(out_dir, n_done, on_pause=None if saved else save,
                                                       should_stop=lambda: bool(stop))
        if stop:
            raise TrainingInterrupted(f"interrupted at step {n_done}; checkpoint saved to {ckpt_path}; "
                                      f"continue with: warpnerf train --resume {out_dir}", step=n_done)

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for s in handlers:
            signal.signal(s, on_signal)
    except ValueError:  # not the main thread: no signal handling
        handlers = {}
    monitor = Monitor(trainer, progress=progress)
    trainer.callbacks.append(monitor)
    try:
        trainer.fit(progress, on_step_end)
        for name, p in trainer.field.named_parameters():
            if not torch.isfinite(p).all():
                raise TrainingError(f"parameter {name} became non-finite during training; try a lower --lr")
        save()
    except BaseException:
        monitor.close()
        raise
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    try:  # the monitor stays open for the final metrics (TensorBoard's test/psnr, ... at the last step)
        _fault("after_train")
        t_eval = time.perf_counter()
        results = evaluate(trainer, out_dir, progress)
        eval_seconds = time.perf_counter() - t_eval
        monitor.log_final(results, cfg.iters - 1, cfg.eval_split)
    finally:
        monitor.close()
    metrics = {
        "psnr": results["psnr"],
        "ssim": results["ssim"],
        "lpips": results["lpips"],
        "iters": cfg.iters,
        "train_seconds": trainer.train_seconds,
        "heldout_seconds": monitor.heldout_seconds,  # part of train_seconds: held-out PSNR renders
        "heldout_history": [list(p) for p in trainer.history["heldout"]],  # [step, held-out PSNR dB] pairs
        "heldout_epochs": [round(e, 3) for e in trainer.history.get("heldout_epochs", [])],  # epochs at each pair
        "heldout_split": heldout_split(trainer),
        "eval_split": cfg.eval_split,
        "epochs": round(trainer.epochs, 3),  # passes over the training pixels
        "g2fr_schedule": cfg.g2fr_schedule,
        "g2fr_open_steps": list(getattr(trainer.schedule, "open_steps", [])),  # adaptive, heldout: when each level opened
        "g2fr_close_steps": list(getattr(trainer.schedule, "close_steps", [])),  # heldout: when the last ones closed
        "g2fr_heldout_checks": [list(c) for c in getattr(trainer.schedule, "checks", [])],  # heldout: [step, val PSNR]
        "view_set": cfg.view_set if cfg.task == "fewshot" and not cfg.views.strip() else None,
        "eval_seconds": eval_seconds,
        "n_train_views": len(trainer.views),
        "train_view_ids": trainer.views.ids,
        "scene": scene.name,
        "scene_source": scene.source,
        "scene_background": settled,
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
    write_json(os.path.join(out_dir, "history.json"), trainer.history)
    plots.plot_training_curves(os.path.join(out_dir, "training.png"),
                               {"step": trainer.history["step"], "training batch loss (MSE)": trainer.history["loss"],
                                "training batch PSNR (dB)": trainer.history["psnr"],
                                **({"held-out PSNR (dB)": trainer.history["heldout"]} if trainer.history["heldout"] else {}),
                                "encoding Lipschitz bound L_Psi (eq. 17)": trainer.history["lipschitz"]},
                               title=f"{scene.name} / {cfg.task}: training curves (test metrics in metrics.json)")
    task.artifacts(trainer, out_dir)
    if cfg.video_frames > 0:
        video.render_run_video(trainer, out_dir, cfg.video_frames, progress)  # turntable.mp4 (.gif without ffmpeg)
    metrics["peak_rss_mb"] = peak_rss_mb()  # after training, evaluation and video
    metrics["total_seconds"] = time.perf_counter() - t_start
    metrics["config_hash"] = config_hash(cfg)
    metrics["code"] = code  # {"commit", "dirty"} of the checkout that trained (None outside git)
    metrics["cpu"] = cpu_meter.stop()  # this process's share of the run: were other processes busy (record.CpuMeter)
    # written once, last and atomically: its presence marks the folder finished
    write_json(os.path.join(out_dir, "metrics.json"), metrics)
    return metrics


def evaluate_run(run_dir: str, progress: bool = True, device: Optional[str] = None) -> dict:
    """Re-evaluate a finished run folder from its config and checkpoint; ``device`` overrides the
    run's (a CUDA-trained run can be scored on a CPU)."""
    cfg = read_run_config(run_dir)
    metrics = read_metrics(run_dir)
    if metrics is None:
        raise ConfigError(f"{run_dir} is not a finished run (no complete metrics.json); resume it with "
                          f"warpnerf train --resume {run_dir}")
    if metrics["config_hash"] != config_hash(cfg):
        raise ConfigError(f"{run_dir}/metrics.json belongs to another configuration than {run_dir}/config.toml")
    if device is not None:
        cfg.device = device
    try:
        dev = devmod.resolve_device(cfg.device)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    _configure_lpips(cfg)
    state = read_checkpoint(run_dir, map_location="cpu")
    if state.get("config_hash") != metrics["config_hash"]:
        raise ConfigError(f"{run_dir}/checkpoint.pt belongs to another configuration than {run_dir}/metrics.json")
    scene = load_scene_for(cfg, progress)
    check_scene(run_dir, scene, metrics.get("scene_source") or state.get("scene_source"))
    task = make_task(cfg)
    trainer = Trainer(cfg, scene, task, dev)
    load_state_checked(trainer, state, run_dir)
    os.makedirs(os.path.join(run_dir, "eval"), exist_ok=True)
    results = evaluate(trainer, os.path.join(run_dir, "eval"), progress)
    results.update(task.metrics(trainer))
    write_json(os.path.join(run_dir, "eval", "metrics.json"), results)
    return results
