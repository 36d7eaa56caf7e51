"""``warpnerf sweep SPEC.toml``: the paper's tables as a restartable grid of runs.

A spec names scenes, models, tasks, arms (G²fR with the fixed eq. 15 schedule, with the adaptive or
the held-out schedule, or off), seeds, few-shot view sets and config overrides; it expands into one run per
combination, each its own run folder ``<out>/<scene>_<task>_<model>_<arm>_s<seed>`` (few-shot runs of a
view set other than ``fps`` end in ``_<view set>``), built by ``train.config.build_config`` and trained
by ``runs.run.run_training``. The arms of a (scene, view set, seed) are paired: same views, same seed
(initialisation, ray sampling, pose noise); only the arm's G²fR keys differ. The results are collected
into ``<out>/table.md`` (Tab. 1/Tab. 3 shaped, the paper's numbers beside ours, see ``tables.py``),
pose-error plots, and ``<out>/sweep.json`` (status, error and attempts of every run).

Backends:

* ``local`` (default): one run after another in this process, or ``workers`` processes (spawned,
  one fresh process per run so a crash or leak cannot spill into the next run);
* ``ray``: every run a Ray task with ``num_cpus``/``num_gpus`` from the spec; the workers' output
  is streamed to the driver by Ray, results come back to the driver. ``pip install 'warpnerf[cluster]'``.

Restartable: a run whose folder already holds a finished run of the identical configuration
(``runs.folder.finished_metrics``) is skipped; a finished run of another configuration is never
replaced without ``overwrite`` (the sweep refuses before it starts, naming the changed keys); a
failing run is reported with a one-line error and retried up to ``retries`` times; the others carry on.
SIGINT (Ctrl-C) or SIGTERM stops the sweep instead: the running trainings save their checkpoints, they are
not retried and nothing else starts (``SweepInterrupted``, exit 130); the same command again resumes them.
Local workers get the stop as SIGTERM from the driver, Ray tasks as ``ray.cancel(force=False)`` (SIGINT in
the task, on any node); the driver waits for their checkpoints, and a second signal kills them.
``out`` (and ``data_root``) are made absolute on the driver, so every worker writes where the driver
looks, whatever its working directory; scene names cannot lead a run folder or log outside ``out``.

Spec format (TOML; paths relative to the current directory, like command-line flags)::

    out = "runs/sweep"              # parent of the run folders
    scenes = ["lego", "mic"]
    models = ["ngp", "mtrf"]        # default ["ngp"]
    tasks = ["pose"]                # default ["pose", "fewshot"]
    arms = ["g2fr", "nog2fr"]       # default; also "adaptive" (G²fR, levels open on loss plateaus), "heldout" (on val)
    seeds = [0]                     # default [0]
    view_sets = ["fps", "random"]   # few-shot views, default ["fps"] (farthest-point; random: drawn with the seed)
    data_root = "/data"             # optional (default: $WARPNERF_DATA)
    config = "base.toml"            # optional TOML file under the overrides (both arms)
    retries = 1                     # optional
    [resources]                     # per run; ray: task resources, local: CPU threads of a run
    num_cpus = 2
    num_gpus = 0
    [overrides]                     # TrainConfig keys for every run ...
    video_frames = 0
    [overrides.pose]                # ... and per task or per model (task/model tables win)
    iters = 20000
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing as mp
import os
import platform
import signal
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import torch
from tqdm.auto import tqdm

from warpnerf import device as devmod
from warpnerf.studies.tables import write_tables
from warpnerf.train.config import MODELS, VIEW_SETS, ConfigError, TrainConfig, build_config, shipped_toml, tomllib

TASKS = ("full", "fewshot", "pose")
# arm name -> the TrainConfig keys that make it; "nog2fr" is the baseline the masked arms are compared with
ARMS: dict[str, dict] = {
    "g2fr": {"g2fr": True, "g2fr_schedule": "fixed"},  # paper eq. 15
    "nog2fr": {"g2fr": False, "g2fr_schedule": "fixed"},
    "adaptive": {"g2fr": True, "g2fr_schedule": "adaptive"},  # levels open when the training loss plateaus
    "heldout": {"g2fr": True, "g2fr_schedule": "heldout"},  # levels open on val-PSNR plateaus, close on a val drop
}
BASELINE_ARM = "nog2fr"
DEFAULT_VIEW_SET = "fps"
# keys a spec's [overrides] may not set: they are what the sweep itself varies or places
_SWEPT = ("scene", "task", "model", "g2fr", "g2fr_schedule", "view_set", "seed", "out", "data_root", "threads")
MACHINE_FILE = "sweep_machine.txt"  # in the run folder: the machine() line of the worker that ran it
_SPEC_KEYS = {"out", "scenes", "models", "tasks", "arms", "seeds", "view_sets", "data_root", "config", "retries",
              "resources", "overrides", "device"}


@dataclass
class SweepSpec:
    """What to run. ``overrides`` holds TrainConfig keys for every run; ``task_overrides`` and
    ``model_overrides`` map a task or model name to keys for those runs only."""

    scenes: list[str]
    models: list[str] = field(default_factory=lambda: ["ngp"])
    tasks: list[str] = field(default_factory=lambda: ["pose", "fewshot"])
    arms: list[str] = field(default_factory=lambda: ["g2fr", "nog2fr"])
    seeds: list[int] = field(default_factory=lambda: [0])
    view_sets: list[str] = field(default_factory=lambda: [DEFAULT_VIEW_SET])  # few-shot runs only
    out: str = "runs/sweep"
    data_root: Optional[str] = None
    config: Optional[str] = None
    device: str = "auto"
    retries: int = 1
    num_cpus: Optional[float] = None  # None: local runs use the default thread count, Ray tasks 1 CPU
    num_gpus: float = 0
    overrides: dict = field(default_factory=dict)
    task_overrides: dict = field(default_factory=dict)
    model_overrides: dict = field(default_factory=dict)

    def __post_init__(self):
        for name, values, allowed in (("tasks", self.tasks, TASKS), ("models", self.models, MODELS),
                                      ("arms", self.arms, tuple(ARMS)), ("view_sets", self.view_sets, VIEW_SETS)):
            if not values:
                raise ConfigError(f"sweep spec: '{name}' is empty")
            for v in values:
                if v not in allowed:
                    raise ConfigError(f"sweep spec: unknown {name[:-1]} '{v}': expected one of {', '.join(allowed)}")
        if not self.scenes or not self.seeds:
            raise ConfigError("sweep spec: 'scenes' and 'seeds' must not be empty")
        if self.retries < 0:
            raise ConfigError(f"sweep spec: retries must be >= 0, got {self.retries}")
        for table in (self.overrides, *self.task_overrides.values(), *self.model_overrides.values()):
            for key in table:
                if key in _SWEPT:
                    raise ConfigError(f"sweep spec: '{key}' is set by the sweep itself, not in [overrides]")


def load_spec(path: str) -> SweepSpec:
    """Read a sweep spec; unknown keys and bad values are one-line ``ConfigError``s.

    ``path`` may also name a spec shipped in ``configs/sweeps/`` (e.g. ``nerf_synthetic_pose``)."""
    if not os.path.exists(path):
        shipped = shipped_spec(path)
        if shipped:
            path = shipped
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"sweep spec not found: {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: malformed TOML: {e}") from None
    for key in data:
        if key not in _SPEC_KEYS:
            raise ConfigError(f"{path}: unknown sweep key '{key}' (expected {', '.join(sorted(_SPEC_KEYS))})")
    if "scenes" not in data:
        raise ConfigError(f"{path}: 'scenes' is required")

    def as_list(key, typ):
        v = data.get(key)
        if v is None:
            return None
        v = v if isinstance(v, list) else [v]
        if not all(isinstance(x, typ) and not isinstance(x, bool) for x in v):
            raise ConfigError(f"{path}: '{key}' must be a list of {typ.__name__}")
        return v

    kwargs: dict[str, Any] = {}
    for key, typ in (("scenes", str), ("models", str), ("tasks", str), ("arms", str), ("seeds", int),
                     ("view_sets", str)):
        v = as_list(key, typ)
        if v is not None:
            kwargs[key] = v
    for key in ("out", "data_root", "config", "device"):
        if key in data:
            kwargs[key] = str(data[key])
    if "retries" in data:
        r = data["retries"]
        if not isinstance(r, int) or isinstance(r, bool) or r < 0:
            raise ConfigError(f"{path}: 'retries' must be a whole number >= 0, got {r!r}")
        kwargs["retries"] = r
    res = data.get("resources", {})
    if not isinstance(res, dict):
        raise ConfigError(f"{path}: 'resources' must be a table ([resources]), got {res!r}")
    for key in res:
        if key not in ("num_cpus", "num_gpus"):
            raise ConfigError(f"{path}: unknown [resources] key '{key}' (expected num_cpus, num_gpus)")
        v = res[key]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0 \
                or (key == "num_cpus" and v == 0):
            raise ConfigError(f"{path}: [resources] {key} must be a number {'> 0' if key == 'num_cpus' else '>= 0'}, "
                              f"got {v!r}")
    if "num_cpus" in res:
        kwargs["num_cpus"] = res["num_cpus"]
    if "num_gpus" in res:
        kwargs["num_gpus"] = res["num_gpus"]
    flat, per_task, per_model = {}, {}, {}
    if not isinstance(data.get("overrides", {}), dict):
        raise ConfigError(f"{path}: 'overrides' must be a table ([overrides]), got {data['overrides']!r}")
    for key, value in data.get("overrides", {}).items():
        if isinstance(value, dict):
            if key in TASKS:
                per_task[key] = value
            elif key in MODELS:
                per_model[key] = value
            else:
                raise ConfigError(f"{path}: [overrides.{key}]: '{key}' is neither a task nor a model")
        else:
            flat[key] = value
    try:
        return SweepSpec(**kwargs, overrides=flat, task_overrides=per_task, model_overrides=per_model)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def shipped_spec(name: str) -> Optional[str]:
    """Path of ``configs/sweeps/<name>.toml`` shipped with the package, or None."""
    return shipped_toml(name, "sweeps")


@dataclass
class Run:
    """One run of the sweep: its identity, its folder and its resolved configuration."""

    scene: str
    task: str
    model: str
    arm: str  # a key of ARMS
    seed: int
    cfg: TrainConfig
    view_set: Optional[str] = None  # few-shot runs: a name of VIEW_SETS; None for the other tasks

    @property
    def name(self) -> str:
        return os.path.basename(self.cfg.run_dir())


def run_name(scene: str, task: str, model: str, arm: str, seed: int, view_set: Optional[str] = None) -> str:
    """``<scene>_<task>_<model>_<arm>_s<seed>``, plus ``_<view set>`` for a view set other than fps."""
    suffix = f"_{view_set}" if view_set and view_set != DEFAULT_VIEW_SET else ""
    return f"{scene}_{task}_{model}_{arm}_s{seed}{suffix}"


def _check_inside(out: str, path: str, what: str) -> None:
    out_abs, path_abs = os.path.abspath(out), os.path.abspath(path)
    if os.path.dirname(path_abs) != out_abs:
        raise ConfigError(f"sweep spec: {what} would write {path} outside out {out}; scene names must be plain names "
                          "(no / or ..)")


def expand(spec: SweepSpec) -> list[Run]:
    """All runs of ``spec`` (task-major, then model, scene, view set, seed, arm: the paired arms of a
    (scene, view set, seed) adjacent). View sets apply to the few-shot task only.

    Raises ConfigError when a scene name would put a run folder anywhere but directly in ``spec.out``,
    and when a few-shot view set other than fps would be ignored (an explicit ``views`` list)."""
    for scene in spec.scenes:
        if not isinstance(scene, str) or not scene or scene in (".", "..") or "/" in scene or "\\" in scene \
                or (os.altsep and os.altsep in scene):
            raise ConfigError(f"sweep spec: scene {scene!r} is not a plain name: its run folder and log would land "
                              f"outside out {spec.out}")
    runs = []
    for task in spec.tasks:
        view_sets = spec.view_sets if task == "fewshot" else [None]
        for model in spec.models:
            for scene in spec.scenes:
                for view_set in view_sets:
                    for seed in spec.seeds:
                        for arm in spec.arms:
                            runs.append(_make_run(spec, task, model, scene, view_set, seed, arm))
    return runs


def _make_run(spec: SweepSpec, task: str, model: str, scene: str, view_set: Optional[str], seed: int,
              arm: str) -> Run:
    """One run: the spec's overrides (task and model tables win), then what the sweep varies."""
    values = {**spec.overrides, **spec.model_overrides.get(model, {}), **spec.task_overrides.get(task, {})}
    values.update(ARMS[arm], scene=scene, model=model, seed=seed, data_root=spec.data_root, device=spec.device,
                  out=os.path.join(spec.out, run_name(scene, task, model, arm, seed, view_set)))
    if view_set is not None:
        values["view_set"] = view_set
    cfg = build_config(task, spec.config, overrides=values)
    _check_inside(spec.out, cfg.run_dir(), f"scene {scene!r}")
    if view_set not in (None, DEFAULT_VIEW_SET) and cfg.views.strip():
        raise ConfigError(f"sweep spec: view set '{view_set}' has no effect: few-shot runs train on the explicit "
                          f"views '{cfg.views}'")
    return Run(scene, task, model, arm, seed, cfg, view_set)


# ----------------------------------------------------------------------------- one run (in a worker)

def _one_line(e: BaseException) -> str:
    msg = str(e).strip().splitlines()
    return f"{type(e).__name__}: {msg[0] if msg else ''}".rstrip(": ")


def machine() -> str:
    """This machine in a few words: host, CPU cores, and the GPU torch sees if any."""
    text = f"{platform.node() or 'host'} ({os.cpu_count()} CPU cores"
    try:
        if torch.cuda.is_available():
            text += f", {torch.cuda.get_device_name(0)}"
    except Exception:  # pragma: no cover - torch is a core dependency
        pass
    return text + ")"


def changed_keys(cfg: TrainConfig) -> list[str]:
    """Keys in which the run in ``cfg.run_dir()`` (its config.toml) differs from ``cfg``;
    ``["config.toml (unreadable)"]`` when it cannot be read."""
    from warpnerf.runs.folder import RESULT_NEUTRAL_KEYS, read_run_config  # lazy: see execute_run

    try:
        saved = read_run_config(cfg.run_dir()).to_dict()
    except Exception:  # noqa: BLE001 - a foreign or broken config.toml
        return ["config.toml (unreadable)"]
    now = cfg.to_dict()
    return [k for k in now if k not in RESULT_NEUTRAL_KEYS and saved.get(k) != now[k]] or ["metrics.json"]


def finished_conflict(cfg: TrainConfig) -> Optional[str]:
    """One line when ``cfg.run_dir()`` holds a finished run of another configuration, else None."""
    from warpnerf.runs.folder import folder_state  # lazy: see execute_run

    if folder_state(cfg.run_dir()) != "finished":
        return None
    return (f"{cfg.run_dir()} holds a finished run of another configuration (changed: "
            f"{', '.join(changed_keys(cfg))})")


def _continue_or_replace(cfg: TrainConfig, overwrite: bool = False) -> dict:
    """Train ``cfg`` in its run folder: an unfinished run of the same configuration (a worker that
    crashed or was stopped) continues from its last checkpoint; an unfinished run of another
    configuration is replaced; a finished one only with ``overwrite``."""
    from warpnerf.runs.folder import config_hash, folder_state, read_run_config  # lazy: see execute_run
    from warpnerf.runs.run import run_training  # lazy: see execute_run

    if not overwrite:
        conflict = finished_conflict(cfg)
        if conflict:  # the driver checked too; a run that finished since must not be lost either
            raise ConfigError(f"{conflict}; pass --overwrite to replace it")
    if folder_state(cfg.run_dir()) == "unfinished":
        try:
            same = config_hash(read_run_config(cfg.run_dir())) == config_hash(cfg)
        except Exception:  # noqa: BLE001 - an unreadable config.toml: start again
            same = False
        if same:
            return run_training(cfg, progress=False, resume=True)
    return run_training(cfg, progress=False, overwrite=True)


def execute_run(cfg_values: dict, threads: Optional[int] = None, log_path: Optional[str] = None,
                stream: bool = False, overwrite: bool = False) -> dict:
    """Train one configuration; never raises. Returns ``{"status": "done", "metrics": ...}`` or
    ``{"status": "failed", "error": one line}``, plus ``machine``.

    ``threads``: Warp and torch CPU threads for this run (results do not depend on it, so it is
    not part of the configuration and a restart with another worker count still skips).
    ``log_path``: the run's output goes to this file (and to stdout as well with ``stream``).
    ``overwrite``: a finished run of another configuration in the folder is replaced (else: failed).
    SIGINT/SIGTERM during the run give ``{"status": "interrupted", "error": one line}``: the folder keeps
    its checkpoint (saved at the step boundary when the signal came during training) for a restart.
    """
    # lazy: the command line imports this module to build its parser, and runs/ brings the whole trainer
    # (~0.13 s on top of --help); a worker loads it here, before its output goes to the run's log
    from warpnerf.runs.run import INTERRUPTS

    result: dict = {"machine": machine()}
    log = None
    old_threads = None
    try:
        if threads:
            old_threads = (devmod.num_threads(), torch.get_num_threads())
            devmod.limit_cpu_threads(int(threads))
        cfg = TrainConfig(**cfg_values)
        if log_path:
            os.makedirs(os.path.dirname(log_path) or ".", exist_ok=True)
            log = open(log_path, "a")
        sink = _Tee(log, sys.stdout) if stream and log else (log or sys.stdout)
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            try:
                result.update(status="done", metrics=_continue_or_replace(cfg, overwrite))
                # where it ran, for the table's note when a restarted sweep skips this run
                with open(os.path.join(cfg.run_dir(), MACHINE_FILE), "w") as fh:
                    fh.write(result["machine"] + "\n")
            except INTERRUPTS as e:  # SIGINT/SIGTERM: the sweep stops (not a failure, not retried)
                step = getattr(e, "step", None)
                result.update(status="interrupted", error=f"stopped at step {step}, checkpoint saved" if step
                              is not None else f"stopped ({type(e).__name__}), its last checkpoint kept")
            except BaseException as e:  # noqa: BLE001 - any failure of a run is reported, not raised
                traceback.print_exc()
                result.update(status="failed", error=_one_line(e))
    except KeyboardInterrupt:  # SIGINT (or the sweep's SIGTERM) while the log was being opened
        result.update(status="interrupted", error="stopped before it started")
    except Exception as e:  # noqa: BLE001 - setup failures (bad values, unwritable log)
        result.update(status="failed", error=_one_line(e))
    finally:
        if log:
            log.close()
        if old_threads:
            devmod.set_num_threads(old_threads[0])
            torch.set_num_threads(old_threads[1])
    return result


class _Tee:
    def __init__(self, *streams):
        self.streams = streams

    def write(self, s):
        for st in self.streams:
            st.write(s)
        return len(s)

    def flush(self):
        for st in self.streams:
            st.flush()


def _worker_entry(cfg_values: dict, threads: Optional[int], log_path: str, overwrite: bool = False) -> dict:
    """Entry point of a local worker process (spawned: no forked Warp/torch state)."""
    return execute_run(cfg_values, threads, log_path, overwrite=overwrite)


def _worker_init() -> None:
    """A local worker ignores SIGINT: Ctrl-C reaches the whole process group, and an idle worker would die
    with a traceback. The driver forwards the stop as SIGTERM, which a training run turns into a checkpoint."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# ----------------------------------------------------------------------------- backends

@dataclass
class RunResult:
    run: Run
    status: str = "pending"  # skipped | done | failed | interrupted (SIGINT/SIGTERM stopped it)
    metrics: Optional[dict] = None
    error: str = ""
    attempts: int = 0
    seconds: float = 0.0
    machine: str = ""


class _Progress:
    """Live display of the sweep: a tqdm bar over runs with done / running / failed and ETA."""

    def __init__(self, total: int, skipped: int, enabled: bool):
        self.counts = {"done": skipped, "running": 0, "failed": 0}
        self.bar = tqdm(total=total, initial=skipped, desc="sweep", unit="run", disable=not enabled,
                        dynamic_ncols=True)
        self.enabled = enabled
        self._refresh()

    def _refresh(self):
        self.bar.set_postfix_str(f"done {self.counts['done']}, running {self.counts['running']}, "
                                 f"failed {self.counts['failed']}")

    def started(self, n: int = 1):
        self.counts["running"] += n
        self._refresh()

    def finished(self, res: RunResult, final: bool):
        """``final``: no retry follows (a failure counts as failed, success as done)."""
        self.counts["running"] -= 1
        if res.status == "interrupted":
            self.write(f"STOPPED {res.run.name}: {res.error}")
        elif res.status == "done":
            self.counts["done"] += 1
            self.bar.update(1)
            m = res.metrics or {}
            self.write(f"done    {res.run.name}: PSNR {m.get('psnr', float('nan')):.2f} dB, {res.seconds:.0f} s")
        else:
            if final:
                self.counts["failed"] += 1
                self.bar.update(1)
            retry = "" if final else " (retrying)"
            self.write(f"FAILED  {res.run.name} (attempt {res.attempts}): {res.error}{retry}")
        self._refresh()

    def write(self, line: str):
        if self.enabled:
            self.bar.write(line)
        else:
            print(line, flush=True)

    def close(self):
        self.bar.close()


def _log_path(run: Run) -> str:
    """``<out>/logs/<run>.log``: beside the run folder, which holds only what training writes
    (a file of ours inside it would make run.prepare_run take it for a foreign folder)."""
    run_dir = os.path.normpath(run.cfg.run_dir())
    return os.path.join(os.path.dirname(run_dir), "logs", os.path.basename(run_dir) + ".log")


def _run_local(pending: list[RunResult], spec: SweepSpec, retries: int, workers: int, progress: _Progress,
               overwrite: bool = False) -> None:
    """Sequential in this process (workers <= 1) or a pool of spawned single-use worker processes."""
    threads = spec.num_cpus
    if workers > 1 and threads is None:
        threads = max(1, (os.cpu_count() or 1) // workers)  # share the cores instead of oversubscribing
    threads = int(threads) if threads else None
    if workers <= 1:
        for res in pending:
            while True:
                res.attempts += 1
                progress.started()
                t0 = time.perf_counter()
                out = execute_run(res.run.cfg.to_dict(), threads, _log_path(res.run), overwrite=overwrite)
                _settle(res, out, time.perf_counter() - t0)
                final = res.status in ("done", "interrupted") or res.attempts > retries
                progress.finished(res, final)
                if res.status == "interrupted":
                    return  # the sweep stops: nothing else starts
                if final:
                    break
        return
    ctx = mp.get_context("spawn")
    queue = list(pending)
    running: dict = {}

    def new_pool() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, max_tasks_per_child=1,
                                   initializer=_worker_init)

    pool = new_pool()
    stopping = False

    def stop_workers(sig) -> None:
        # private attribute, but the only way to reach the workers; a worker gone already is fine
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            with contextlib.suppress(Exception):
                proc.kill() if sig == signal.SIGKILL else os.kill(proc.pid, sig)

    try:
        while running or (queue and not stopping):
            while queue and not stopping and len(running) < workers:
                res = queue.pop(0)
                res.attempts += 1
                progress.started()
                fut = pool.submit(_worker_entry, res.run.cfg.to_dict(), threads, _log_path(res.run), overwrite)
                running[fut] = (res, time.perf_counter())
            try:
                done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            except KeyboardInterrupt:  # SIGINT/SIGTERM to the driver: the running trainings checkpoint and stop
                if stopping:  # a second one: do not wait for the checkpoints
                    stop_workers(signal.SIGKILL)
                    for res, _ in running.values():
                        res.status, res.error = "interrupted", "worker killed by a second interrupt"
                    running.clear()
                    break
                stopping = True
                stop_workers(signal.SIGTERM)
                continue
            for fut in done:
                res, t0 = running.pop(fut)
                try:
                    out = fut.result()
                except BrokenProcessPool:
                    if stopping:  # the interrupt ended the worker
                        out = {"status": "interrupted", "error": "worker process ended by the interrupt"}
                    else:  # a worker died (killed, out of memory): that run failed; a fresh pool for the rest
                        out = {"status": "failed", "error": "worker process died (killed or out of memory)"}
                        pool.shutdown(wait=False, cancel_futures=True)
                        for other, (ores, _) in list(running.items()):  # their futures are broken too: resubmit
                            ores.attempts -= 1
                            queue.insert(0, ores)
                            progress.counts["running"] -= 1
                            running.pop(other)
                        pool = new_pool()
                _settle(res, out, time.perf_counter() - t0)
                final = res.status in ("done", "interrupted") or res.attempts > retries
                progress.finished(res, final)
                if res.status == "interrupted" and not stopping:  # a signal reached a worker: stop the others too
                    stopping = True
                    stop_workers(signal.SIGTERM)
                if not final:
                    queue.append(res)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def ray_missing_message() -> str:
    return "the ray backend needs Ray: pip install 'warpnerf[cluster]' (or: pip install ray)"


RAY_STOP_GRACE = 300.0  # s a stopped Ray sweep waits for its running trainings' checkpoints, then kills them


def _run_ray(pending: list[RunResult], spec: SweepSpec, retries: int, address: Optional[str],
             progress: _Progress, overwrite: bool = False) -> None:
    """One Ray task per run with the spec's resources; output streamed by Ray, results gathered here.

    A stop (SIGINT/SIGTERM to the driver, or a run a signal reached) cancels every task with
    ``ray.cancel(force=False)``: a queued task never starts, and Ray raises SIGINT in a running one, which
    its training turns into a checkpoint at the next step boundary, on whatever node it runs. The driver
    waits up to ``RAY_STOP_GRACE`` s for them; a second signal (or the deadline) kills them instead."""
    import ray  # optional extra: warpnerf[cluster]

    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=True)
    # SIGINT/SIGTERM only note the signal here; the loop below acts on it within a second. A KeyboardInterrupt
    # raised inside Ray's blocking calls can be swallowed there (a CI run lost a SIGINT that way), and
    # ray.init's own SIGTERM handler exits at once.
    signals: list[int] = []
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(ValueError):  # not the main thread: Ctrl-C is the caller's
            previous[sig] = signal.signal(sig, lambda signum, frame: signals.append(signum))
    try:
        _ray_loop(ray, pending, spec, retries, progress, overwrite, signals)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _ray_loop(ray, pending: list[RunResult], spec: SweepSpec, retries: int, progress: _Progress, overwrite: bool,
              signals: list[int]) -> None:
    """:func:`_run_ray`'s submit/wait loop; ``signals`` grows by one entry per SIGINT/SIGTERM received."""
    num_cpus = spec.num_cpus if spec.num_cpus is not None else 1
    task = ray.remote(execute_run).options(num_cpus=num_cpus, num_gpus=spec.num_gpus, max_retries=0)
    threads = max(1, int(num_cpus))
    running: dict = {}
    deadline: Optional[float] = None  # set when the stop begins

    def submit(res: RunResult):
        res.attempts += 1
        progress.started()
        ref = task.remote(res.run.cfg.to_dict(), threads, _log_path(res.run), True, overwrite)
        running[ref] = (res, time.perf_counter())

    def cancel(force: bool) -> None:
        for ref in running:
            with contextlib.suppress(Exception):  # a task that just ended
                ray.cancel(ref, force=force)

    def stop() -> None:
        nonlocal deadline
        deadline = time.monotonic() + RAY_STOP_GRACE
        if running:
            progress.write(f"stopping: running trainings save their checkpoints, queued runs do not start (waiting "
                           f"up to {RAY_STOP_GRACE:.0f} s; a second Ctrl-C kills them)")
        cancel(force=False)

    for res in pending:
        submit(res)  # Ray queues what does not fit the cluster's free resources
    acted = 0  # signals already acted on
    while running:
        if len(signals) > acted or (deadline is not None and time.monotonic() > deadline):
            first = deadline is None and len(signals) - acted == 1
            acted = len(signals)
            if first:  # stop gracefully: the running trainings checkpoint
                stop()
                continue
            # a second signal, or the grace period is over: do not wait for the checkpoints
            cancel(force=True)
            for res, _ in running.values():
                res.status, res.error = "interrupted", "Ray task killed before it stopped, its last checkpoint kept"
            return
        try:
            done, _ = ray.wait(list(running), num_returns=1, timeout=1.0)
        except KeyboardInterrupt:  # raised by a caller's handler (not the main thread): counts as a signal
            signals.append(signal.SIGINT)
            continue
        for ref in done:
            res, t0 = running.pop(ref)
            try:
                out = ray.get(ref)
            except Exception as e:  # noqa: BLE001 - worker crash, node lost: the run failed
                cancelled = deadline is not None or isinstance(e, ray.exceptions.TaskCancelledError)
                out = ({"status": "interrupted", "error": "Ray task cancelled (queued, or outside training)"}
                       if cancelled else {"status": "failed", "error": _one_line(e)})
            _settle(res, out, time.perf_counter() - t0)
            final = res.status in ("done", "interrupted") or res.attempts > retries
            progress.finished(res, final)
            if res.status == "interrupted" and deadline is None:  # a signal reached the worker: stop the others
                stop()
            if not final and deadline is None:
                submit(res)


def _settle(res: RunResult, out: dict, seconds: float) -> None:
    res.status = out["status"]
    res.metrics = out.get("metrics")
    res.error = out.get("error", "")
    res.seconds = seconds
    res.machine = out.get("machine", "")


# ----------------------------------------------------------------------------- the sweep

def run_sweep(spec: SweepSpec, backend: str = "local", workers: int = 1, ray_address: Optional[str] = None,
              retries: Optional[int] = None, progress: bool = True, overwrite: bool = False) -> dict:
    """Run (or skip) every run of ``spec`` and write ``table.md``, plots and ``sweep.json`` under ``spec.out``.

    Returns ``{"results": [RunResult], "table": markdown, "failed": [RunResult]}``. SIGINT/SIGTERM stop the
    sweep: the running trainings save a checkpoint, nothing else starts, ``sweep.json`` is written and
    ``SweepInterrupted`` raised (the same call again skips the finished runs and resumes the stopped ones).
    Raises ``ConfigError`` for a bad spec, for a scene name that leads outside ``spec.out`` and, without
    ``overwrite``, for a run folder holding a finished run of another configuration (nothing is
    written then); ``SweepError`` when the Ray backend is not installed.
    ``spec.out`` and ``spec.data_root`` are made absolute here, on the driver: Ray workers run in
    another working directory (and on other nodes), and a relative path would resolve there.
    """
    if backend not in ("local", "ray"):
        raise ConfigError(f"unknown backend '{backend}': expected local or ray")
    if backend == "ray":
        try:
            import ray  # noqa: F401  # optional extra: warpnerf[cluster]
        except ImportError:
            raise SweepError(ray_missing_message()) from None
    retries = spec.retries if retries is None else retries
    if retries < 0:
        raise ConfigError(f"retries must be >= 0, got {retries}")
    from warpnerf.runs.folder import finished_metrics  # lazy: see execute_run

    spec.out = os.path.abspath(spec.out)
    if spec.data_root:
        spec.data_root = os.path.abspath(spec.data_root)
    else:  # as run_training records it in config.toml, so a restart compares equal configurations
        from warpnerf.data.errors import DatasetError  # lazy: see execute_run
        from warpnerf.data.resolve import data_root_from  # lazy: see execute_run

        try:
            spec.data_root = data_root_from(None)
        except DatasetError as e:
            raise ConfigError(str(e)) from None
    runs = expand(spec)
    results = [RunResult(r) for r in runs]
    for res in results:
        done = finished_metrics(res.run.cfg)
        if done is not None:
            res.status, res.metrics = "skipped", done
            with contextlib.suppress(OSError):
                with open(os.path.join(res.run.cfg.run_dir(), MACHINE_FILE)) as fh:
                    res.machine = fh.read().strip()
    pending = [r for r in results if r.status != "skipped"]
    if not overwrite:
        conflicts = [c for c in (finished_conflict(r.run.cfg) for r in pending) if c]
        if conflicts:
            more = f" (and {len(conflicts) - 1} more run folders)" if len(conflicts) > 1 else ""
            raise ConfigError(f"sweep: {conflicts[0]}{more}; pass --overwrite to replace finished runs, "
                              "or choose another out")
    try:
        os.makedirs(spec.out, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"sweep out {spec.out} cannot be created: {e.strerror or e}; choose another out") from None
    bar = _Progress(len(results), len(results) - len(pending), progress)
    bar.write(f"sweep: {len(results)} runs, {len(results) - len(pending)} already finished (skipped), "
              f"{len(pending)} to run on the {backend} backend")
    stopped = False
    try:
        with _sigterm_as_interrupt():
            if pending:
                if backend == "ray":
                    _run_ray(pending, spec, retries, ray_address, bar, overwrite)
                else:
                    _run_local(pending, spec, retries, workers, bar, overwrite)
    except KeyboardInterrupt:  # in the driver between two runs
        stopped = True
    finally:
        bar.close()
        _write_status(spec, results)
    if stopped or any(r.status == "interrupted" for r in results):
        raise SweepInterrupted(_interrupted_summary(results))
    text = write_tables(spec, results)
    failed = [r for r in results if r.status == "failed"]
    return {"results": results, "table": text, "failed": failed}


class SweepError(RuntimeError):
    """A sweep that cannot start (e.g. the Ray backend without Ray installed); one line."""


class SweepInterrupted(Exception):
    """SIGINT/SIGTERM stopped the sweep (the CLI exits 130). ``command``: the command line that continues
    it, for the message (the CLI sets it; else the message says to run the same command again)."""

    def __init__(self, summary: str, command: Optional[str] = None):
        super().__init__(summary)
        self.summary, self.command = summary, command

    def __str__(self) -> str:
        how = f"continue with: {self.command}" if self.command else "run the same command again to continue"
        return f"{self.summary}; {how} (finished runs are skipped, stopped ones resume)"


def _interrupted_summary(results: list[RunResult]) -> str:
    stopped = [r for r in results if r.status == "interrupted"]
    finished = sum(r.status in ("done", "skipped") for r in results)
    what = "; ".join(f"{r.run.name} {r.error}" for r in stopped[:3]) + \
        (f" (and {len(stopped) - 3} more)" if len(stopped) > 3 else "")
    return f"sweep interrupted: {what or 'between runs'}; {finished} of {len(results)} runs finished"


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises KeyboardInterrupt in the driver, as SIGINT does (main thread only): a training run
    replaces it with its own checkpointing handler while it runs and puts this one back after."""
    try:
        previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def _write_status(spec: SweepSpec, results: list[RunResult]) -> None:
    rows = [{"run": r.run.name, "run_dir": r.run.cfg.run_dir(), "scene": r.run.scene, "task": r.run.task,
             "model": r.run.model, "arm": r.run.arm, "seed": r.run.seed, "view_set": r.run.view_set,
             "status": r.status, "error": r.error,
             "attempts": r.attempts, "seconds": round(r.seconds, 2), "machine": r.machine} for r in results]
    tmp = os.path.join(spec.out, "sweep.json.tmp")
    with open(tmp, "w") as fh:
        json.dump({"runs": rows}, fh, indent=1)
    os.replace(tmp, os.path.join(spec.out, "sweep.json"))  # a killed sweep never leaves half a file


# ----------------------------------------------------------------------------- CLI

def add_parser(subparsers) -> None:
    p = subparsers.add_parser("sweep", help="run a grid of trainings from a TOML spec (local or Ray) into tables")
    p.add_argument("spec", help="sweep spec (TOML; see docs/sweep.md)")
    p.add_argument("--backend", default="local", choices=["local", "ray"])
    p.add_argument("--workers", type=int, default=1, help="local: worker processes, one run each (default 1: in process)")
    p.add_argument("--ray-address", default=None, help="ray: cluster address (host:port or auto); default: start a local one")
    p.add_argument("--retries", type=int, default=None, help="retries of a failed run (default: the spec's, else 1)")
    p.add_argument("--out", default=None, help="override the spec's out folder")
    p.add_argument("--data-root", default=None, help="override the spec's data_root")
    p.add_argument("--quiet", action="store_true", help="no progress bar (one line per finished run)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace finished runs of another configuration (default: refuse, naming the changed keys)")
    p.set_defaults(func=run_cli)


def run_cli(args, on_done: Optional[Callable[[dict], None]] = None) -> int:
    """``warpnerf sweep``; ``on_done(result)`` runs after the table is printed (the CLI's ``--record``)."""
    spec = load_spec(args.spec)
    if args.out:
        spec.out = args.out
    if args.data_root:
        spec.data_root = args.data_root
    if args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    try:
        res = run_sweep(spec, backend=args.backend, workers=args.workers, ray_address=args.ray_address,
                        retries=args.retries, progress=not args.quiet, overwrite=getattr(args, "overwrite", False))
    except SweepError as e:
        print(f"warpnerf: error: {e}", file=sys.stderr)
        return 2
    print(res["table"])
    if on_done is not None:
        on_done(res)
    return report_failures(res["failed"])


def report_failures(failed: list[RunResult]) -> int:
    """Print one line per failed run; exit code 1 when any failed, else 0."""
    for r in failed:
        print(f"failed: {r.run.name} after {r.attempts} attempt(s): {r.error} (log: {_log_path(r.run)})",
              file=sys.stderr)
    return 1 if failed else 0
