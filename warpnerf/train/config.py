"""Training configuration: one typed dataclass, presets in ``configs/*.toml``, CLI overrides.

Precedence: dataclass defaults < task preset (``configs/<task>.toml``) < ``--config FILE`` <
command-line flags. Unknown keys are an error that names the key and the file.

The dataclass is the single source of truth: each field's annotation gives its type (files are
checked against it, :func:`field_type`), its trailing comment is its help text
(:func:`field_help`), :data:`CHOICES` names the registries its values come from, and
:mod:`warpnerf.cli.flags` turns all of that into the ``warpnerf train`` flags.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
import inspect
import io
import math
import os
import sys
import textwrap
import tokenize
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, fields
from importlib import resources
from typing import Any, Optional, Union

from warpnerf.model.g2fr import G2FR_BETA, MASK_MODES, SCHEDULES
from warpnerf.train.memory import training_memory_problem

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


# grid encodings a field can use: Instant-NGP's hash grid and the paper's multi-resolution CP ("Mtrf")
MODELS = ("ngp", "mtrf")

# where monitor.py sends its scalars
LOG_MODES = ("none", "tensorboard")

# few-shot view sets (tasks.FewShotTask) and the splits a run can be measured on
VIEW_SETS = ("fps", "random")
SPLITS = ("test", "val")

# where the pose task's training cameras start (tasks.PoseTask): the paper's perturbed ground truth, or
# BARF's LLFF protocol, every camera at the scene's average pose
POSE_INITS = ("noise", "identity")


class Registry(Sequence):
    """The names of a registry that lives in a module too heavy to import for ``--help``.

    ``Registry("warpnerf.train.tasks", "TASKS")`` behaves like ``tuple(warpnerf.train.tasks.TASKS)`` but imports
    the module (torch) only when first read, so the CLI's choices and :func:`validate` use the very
    registry the code dispatches on without slowing ``warpnerf --help``.
    """

    def __init__(self, module: str, attr: str):
        self.module, self.attr = module, attr

    @functools.cached_property
    def names(self) -> tuple:
        return tuple(getattr(importlib.import_module(self.module), self.attr))

    def __getitem__(self, i):
        return self.names[i]

    def __len__(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        return f"Registry({self.module}.{self.attr})"


def exp_decay(start: float, end: float, frac: float) -> float:
    """Exponential schedule from ``start`` (frac 0) to ``end`` (frac 1): the learning rates'."""
    return start * (end / start) ** frac


class ConfigError(ValueError):
    """A bad configuration file or value (one line, names the key)."""


@dataclass
class TrainConfig:
    # --- what to train ---
    scene: str = "chair"  # built-in scene name (see 'warpnerf scenes'), or a dataset scene under data_root
    data_root: Optional[str] = None  # dataset folder (unset: $WARPNERF_DATA)
    task: str = "full"  # what to train: full (all views), fewshot (n_views views), pose (noisy poses refined)
    model: str = "ngp"  # grid encoding: ngp (Instant-NGP hash grid) | mtrf (multi-resolution CP, paper's Mtrf)
    downscale: int = 1  # integer image downscale applied at load time
    builtin_resolution: Optional[int] = None  # image size of built-in scenes (unset: the generator's default)
    unbounded: Optional[bool] = None  # COLMAP / transforms.json captures: contract the scene beyond the cameras (360° scenes with a distant background); unset: chosen from the rig (360° rigs are), --no-unbounded keeps a box
    ndc: Optional[bool] = None  # COLMAP / transforms.json captures: train in LLFF's NDC and with the forward-facing preset; unset: chosen from the rig (forward-facing rigs do; LLFF scenes always), --no-ndc keeps a box
    # --- optimisation ---
    iters: int = 2000  # training steps
    batch_rays: int = 4096  # rays per step at the start; adapted to keep target_samples
    target_samples: int = 131072  # samples per step the ray count adapts to (instant-ngp style)
    lr: float = 1e-2  # Adam learning rate of the hash table and the MLPs
    lr_final_ratio: float = 0.1  # exponential decay of lr to lr * ratio at the last step
    lr_warmup: int = 100  # steps of linear lr warm-up from 1 % of lr (nerfacc), at most iters // 10; keeps thin scenes stable
    distortion_weight: float = 0.0  # mip-NeRF 360's distortion loss on the ray space's t (0 = off); concentrates each ray's weight, removing haze
    background: Optional[str] = None  # auto (unset) | white | black | learned | random: images without alpha whose border is one uniform colour (a product shot on white, a render saved as RGB) train against it as a fixed background (auto); white/black fix it (images with alpha are composited on it); learned learns it; random keeps opaque photos (warpnerf.data.background)
    random_background: bool = True  # train against random per-ray backgrounds (instant-ngp) where the images' alpha is known; photos without a detected background (LLFF, captures) count as opaque
    background_low: float = 0.0  # random backgrounds draw each channel from U[background_low, 1]; > 0 keeps them light (closer to a white scene background)
    background_late_from: float = 1.0  # from this fraction of the steps on, random backgrounds draw from U[background_low_late, 1] instead (1 = never)
    background_low_late: float = 1.0  # the low bound after background_late_from (1 = white, the NeRF-synthetic background)
    weight_decay_mlp: float = 1e-6  # L2 on MLP weights (instant-ngp)
    error_sampling: float = 0.0  # share of training rays drawn where each image's recent error is highest (instant-ngp's error map), importance-weighted; 0 = uniform
    # --- G²fR (paper eq. 15) ---
    g2fr: bool = False  # mask grid levels coarse to fine
    g2fr_beta: float = G2FR_BETA  # fraction of training over which levels are switched on
    g2fr_mask: str = "cosine"  # level ramp: cosine (BARF) | binary (on at the end of its ramp)
    g2fr_schedule: str = "fixed"  # fixed (eq. 15: tau from step / (beta * iters)) | adaptive (a level opens when the training loss stops improving; no budget needed) | heldout (a level opens when the val PSNR stops rising, and the levels opened since its best close when it falls; needs a val split)
    g2fr_plateau_window: int = 10  # adaptive: steps per loss window; a new level ramps in over one window (10 and g2fr_plateau_tol 0.5: the best of 7 pairs on lego's val split, docs/studies/2026-12-07-fewshot-paper-regime.md)
    g2fr_plateau_tol: float = 0.5  # adaptive: the next level opens when a window's relative loss improvement falls to this fraction of the largest since the last level opened
    g2fr_heldout_window: int = 10  # heldout: steps between val PSNR checks; a level ramps in (or out) over one window (10: the adaptive schedule's window)
    g2fr_heldout_views: int = 4  # heldout: val views in each check (evenly spaced; half resolution from 64 px up, like the held-out curve)
    g2fr_heldout_average: int = 3  # heldout: the schedule judges the mean val PSNR of the last this many checks (one check can dip by dB early in training and recover by the next)
    g2fr_heldout_min_gain: float = 0.1  # heldout: a mean that beats the best so far by no more than this (dB) is a plateau: the next level opens
    g2fr_heldout_drop: float = 0.25  # heldout: a mean this many dB below the best closes the levels opened since the best, and no level opens again (0.25: several times the late-run check-to-check noise of mic's val PSNR, seed 0, docs/studies/2026-12-07-fewshot-paper-regime.md)
    # --- hash grid and MLPs ---
    levels: int = 16  # grid levels L
    features: int = 2  # features F per grid level
    log2_table_size: int = 19  # k: hash table rows per level T = 2^k
    base_resolution: int = 16  # points per axis of the coarsest level
    max_resolution: int = 2048  # points per axis of the finest level (over the scene box)
    cp_rank: int = 8  # mtrf: CP components R per level (output L*R features)
    cp_max_resolution: int = 512  # mtrf: line length of the finest level
    cp_lr: float = 2e-2  # mtrf: Adam lr of the CP lines (TensoRF: 0.02); the MLPs keep lr
    cp_density_shift: float = 0.0  # mtrf: added to the density MLP output before exp (TensoRF: -10); < 0 starts nearly empty
    hidden: int = 64  # MLP width
    geo_features: int = 15  # density-MLP features passed to the color MLP
    # --- rendering ---
    occ_resolution: int = 128  # occupancy grid cells per axis
    occ_warmup: int = 256  # steps during which every cell is refreshed
    occ_update_every: int = 16  # steps between occupancy updates
    occ_threshold: float = 0.01  # occupancy: a cell is empty when density x marching step < min(this, the grid's mean) (instant-ngp, nerfacc: 0.01)
    # instant-ngp samples 1/4 of the cells uniformly per update at 2^18 samples per step; at our 2^16
    # that update was ~20 % of a step. Every occupied cell is still re-sampled each update, so pruning
    # keeps its pace; only the discovery of new cells slows. lego full: 30.56 dB in 508 s with 1/16,
    # 30.54 dB in 695 s with 1/4 (docs/studies/2026-12-07-speed.md)
    occ_uniform_fraction: float = 0.0625  # cells sampled uniformly per occupancy update after warm-up, as a fraction of all
    march_steps: int = 1024  # ray-marching steps across the box diagonal (instant-ngp: 1024)
    render_step: float = 0.0  # explicit ray-marching step in scene units; 0 = diagonal / march_steps
    max_samples_per_ray: int = 1024  # cap on samples kept per ray when marching
    sample_budget: int = 262144  # hard cap on packed samples per training step and per render chunk (memory)
    memory_budget_mb: int = 4096  # stop with a clear error when the process's peak memory exceeds this
    learn_guard: bool = True  # stop when the loss stays at the background-only level after warm-up
    # --- tasks ---
    n_views: int = 10  # fewshot: number of training views
    views: str = ""  # fewshot: explicit view list name ("freenerf8") or comma-separated ids (overrides view_set)
    view_set: str = "fps"  # fewshot: fps (farthest-point sampling of camera centres from view 0) | random (n_views drawn with seed)
    pose_init: str = "noise"  # pose: noise (the ground truth perturbed by pose_noise: the paper) | identity (every training camera starts at the average pose: BARF's LLFF protocol; forward-facing scenes)
    pose_noise: Optional[float] = None  # pose: se(3) noise sigma (unset: 0.15 synthetic, 0.01 real)
    pose_noise_rot: Optional[float] = None  # pose: rotation sigma, overrides pose_noise
    pose_noise_trans: Optional[float] = None  # pose: translation sigma, overrides pose_noise
    pose_lr: float = 1e-3  # pose: Adam lr of the se(3) corrections
    pose_lr_final: float = 1e-5  # pose: lr at the last step (exponential)
    pose_lr_by_noise: bool = True  # pose: scale both rates by min(max(noise sigmas) / 0.15, 1), 0.15 being the sigma they are tuned at (Adam moves ~lr per step)
    pose_refine_steps: int = 100  # pose: photometric refinement steps per test view at evaluation
    refine_test_poses: bool = False  # full/fewshot: refine the test views' poses photometrically before evaluation, as task pose always does (pose_refine_steps steps, pose_lr to pose_lr_final): for a capture's held-out photos compared with a pose run on them
    pose_reregister_at: float = 0.0  # pose: at this fraction of the run, search again for views left in a wrong basin (warpnerf.train.reregister; not in the paper); 0 = off
    pose_reregister_passes: int = 2  # pose: search up to this many times, at pose_reregister_at, 2x, ... of the run (views that only stand out once the field is sharp); passes past the run's end are dropped
    pose_reregister_ratio: float = 5.0  # pose: the views searched for are those whose photometric loss exceeds this x the median view's (docs/studies/2026-12-07-mic-reregistration.md)
    # --- evaluation and output ---
    eval_view_stride: int = 8  # evaluate every k-th test view (25 of 200 for Blender scenes)
    eval_max_views: int = 0  # cap on evaluated views (0 = no cap)
    eval_split: str = "test"  # split the final metrics are measured on: test | val (choose settings on val, report test once)
    video_frames: int = 40  # turntable frames (0 = no video)
    out: str = ""  # run folder ('': runs/<scene>_<task>[_g2fr])
    seed: int = 0  # random seed (views, pose noise, ray sampling, initialisation)
    device: str = "auto"  # auto (cuda if Warp sees one, else cpu) | cpu | cuda | cuda:N
    threads: Optional[int] = None  # CPU threads for Warp launches and torch ops (unset: $WARPNERF_THREADS or min(2, cores))
    log_every: int = 50  # steps between progress-bar metric refreshes
    allow_rgb: bool = False  # accept Blender-layout images without alpha (one warning line)
    llff_test: str = "every8"  # LLFF scenes' test views: every8 (every 8th image, NeRF's) | last10 (the last 10 % by name, BARF's)
    # --- monitoring and metrics (warpnerf/train/monitor.py, warpnerf/train/metrics.py) ---
    log: str = "none"  # none | tensorboard: scalars to <run>/tb every log_every steps (pip install 'warpnerf[log]')
    heldout_every: int = 250  # steps between held-out PSNR renders (history "heldout"); 0 = off
    heldout_views: int = 3  # views (evenly spaced, half resolution) in the held-out PSNR
    heldout_split: str = "val"  # split of the held-out PSNR: val (test where a scene has no val split) | test
    checkpoint_every: int = 500  # steps between checkpoint.pt saves (for --resume; 'warpnerf view' follows them); 0 = only at the end
    lpips_weights: str = ""  # LPIPS(alex) weights: full state-dict file or folder (see metrics.py); "" = auto

    def run_dir(self) -> str:
        if self.out:
            return self.out
        return os.path.join("runs", f"{self.scene}_{self.task}{'_g2fr' if self.g2fr else ''}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# where each choice-valued field's names come from: the registries the code dispatches on
CHOICES: dict[str, Sequence] = {
    "task": Registry("warpnerf.train.tasks", "TASKS"),
    "model": MODELS,
    "g2fr_mask": MASK_MODES,
    "g2fr_schedule": SCHEDULES,
    "view_set": VIEW_SETS,
    "eval_split": SPLITS,
    "heldout_split": SPLITS,
    "log": LOG_MODES,
    "pose_init": POSE_INITS,
    "llff_test": Registry("warpnerf.data.llff", "LLFF_TESTS"),
    "background": Registry("warpnerf.data.background", "BACKGROUNDS"),
}


def _field_types() -> dict[str, Any]:
    return {f.name: f for f in fields(TrainConfig)}


@functools.lru_cache(maxsize=None)
def _type_hints() -> dict[str, Any]:
    return typing.get_type_hints(TrainConfig)


def field_type(name: str) -> tuple[type, bool]:
    """``(type, optional)`` of a TrainConfig field from its annotation.

    >>> field_type("iters")
    (<class 'int'>, False)
    >>> field_type("pose_noise")
    (<class 'float'>, True)
    """
    hint = _type_hints()[name]
    if typing.get_origin(hint) in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) != 1 or len(typing.get_args(hint)) != 2:
            raise TypeError(f"TrainConfig.{name}: only Optional[X] unions are supported, got {hint}")
        return args[0], True
    return hint, False


@functools.lru_cache(maxsize=None)
def field_help() -> dict[str, str]:
    """Help text of every TrainConfig field: ``metadata["help"]`` if set, else its trailing comment.

    >>> field_help()["iters"]
    'training steps'
    """
    comments: dict[int, str] = {}
    names: dict[str, int] = {}
    try:
        src = textwrap.dedent(inspect.getsource(TrainConfig))
    except (OSError, TypeError):  # no source shipped: metadata only
        src = ""
    if src:
        for tok in tokenize.generate_tokens(io.StringIO(src).readline):
            if tok.type == tokenize.COMMENT:
                comments[tok.start[0]] = tok.string.lstrip("#").strip()
        for node in ast.parse(src).body[0].body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names[node.target.id] = node.end_lineno
    return {f.name: f.metadata.get("help") or comments.get(names.get(f.name, -1), "") for f in fields(TrainConfig)}


def _coerce(name: str, value: Any, source: str) -> Any:
    """Check a value from a file against the field's annotated type (ints are accepted as floats)."""
    if value is None:
        return None
    typ, _ = field_type(name)
    is_bool = isinstance(value, bool)
    if typ is float and isinstance(value, int) and not is_bool:
        value = float(value)
    if not isinstance(value, typ) or is_bool and typ is not bool:
        raise ConfigError(f"{source}: key '{name}' must be {typ.__name__}, got {value!r}")
    return value


def check_choice(name: str, value: Any) -> None:
    """Raise ConfigError unless ``value`` is one of :data:`CHOICES`'s names for field ``name``."""
    if name in CHOICES and value not in CHOICES[name] and not (value is None and field_type(name)[1]):
        raise ConfigError(f"unknown {name} '{value}': {name} must be one of {', '.join(CHOICES[name])}")


def load_toml(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: malformed TOML: {e}") from None
    data = renamed_keys(data)
    known = _field_types()
    for key in data:
        if key not in known:
            raise ConfigError(f"{path}: unknown config key '{key}'")
    return {k: _coerce(k, v, path) for k, v in data.items()}


# Keys renamed since run folders were first written, so an older config.toml still loads:
# eval_every counted test views while every other *_every counts steps; save_every (for --resume)
# and checkpoint_every (for the viewer) both set how often checkpoint.pt is written.
RENAMED = {"eval_every": "eval_view_stride", "save_every": "checkpoint_every"}


def renamed_keys(data: dict) -> dict:
    """``data`` with the old key names of :data:`RENAMED` under their new names. An old file's
    save_every and checkpoint_every merge into the shorter positive period (0 when neither saves)."""
    if not any(k in data for k in RENAMED):
        return data
    out = {k: v for k, v in data.items() if k not in RENAMED}
    if "eval_every" in data:
        out.setdefault("eval_view_stride", data["eval_every"])
    if "save_every" in data:
        periods = (data["save_every"], data.get("checkpoint_every", 0))
        bad = [v for v in periods if not isinstance(v, int) or isinstance(v, bool)]
        # a bad value is passed on for _coerce to refuse by name
        out["checkpoint_every"] = bad[0] if bad else min((v for v in periods if v > 0), default=0)
    return out


def preset_path(task: str) -> str:
    """Path of the preset shipped for ``task`` (``configs/<task>.toml``)."""
    return str(resources.files("warpnerf.configs").joinpath(f"{task}.toml"))


def shipped_toml(name: str, folder: str = "") -> Optional[str]:
    """Path of ``configs/[folder/]<name>.toml`` shipped with the package (``name`` may end in .toml or
    carry a folder, whose base name counts), or None when there is no such file."""
    stem = os.path.basename(name)
    stem = stem[:-5] if stem.endswith(".toml") else stem
    path = str(resources.files("warpnerf.configs").joinpath(*([folder] if folder else []), f"{stem}.toml"))
    return path if os.path.exists(path) else None


def resolve_config_file(path: str) -> str:
    """``path`` itself when it exists, else the shipped ``configs/<name>.toml`` a bare name names
    (``--config fewshot_paper`` works from any folder and after a plain ``pip install``)."""
    if os.path.exists(path) or os.path.sep in path.rstrip(os.path.sep):
        return path
    return shipped_toml(path) or path


FORWARD_FACING_SUFFIX = "_forward_facing"


def forward_facing_preset(task: str, scene: str, data_root: Optional[str], ndc: Optional[bool] = None,
                          unbounded: Optional[bool] = None) -> Optional[str]:
    """Path of ``configs/<task>_forward_facing.toml`` when one is shipped for ``task`` and ``scene``
    resolves to a scene that trains in NDC (LLFF layout: fern, the built-in ``yard``; a COLMAP or
    transforms.json capture of a forward-facing rig, unless ``ndc`` is False or ``unbounded`` True;
    :func:`warpnerf.data.resolve.is_forward_facing`), else None."""
    path = preset_path(task + FORWARD_FACING_SUFFIX)
    if not os.path.exists(path):
        return None
    from warpnerf.data.resolve import is_forward_facing  # lazy: warpnerf.data loads torch; the CLI imports this module

    return path if is_forward_facing(scene, data_root, ndc=ndc, unbounded=unbounded) else None


def build_config(task: Optional[str], config_file: Optional[str] = None, overrides: Optional[dict] = None) -> TrainConfig:
    """Defaults < task preset < forward-facing preset < ``config_file`` < ``overrides`` (only keys
    whose value is not None).

    ``task`` None (``--task`` not given): the config file's ``task`` key picks the preset, else
    ``full`` (``--config fewshot_paper`` trains few-shot with the few-shot preset beneath it).
    The forward-facing preset applies where :func:`forward_facing_preset` finds one."""
    file_values = load_toml(resolve_config_file(config_file)) if config_file else {}
    if task is None:
        task = file_values.get("task", TrainConfig.task)
        check_choice("task", task)
    values: dict[str, Any] = {}
    preset = preset_path(task)
    if os.path.exists(preset):
        values.update(load_toml(preset))
    overrides = renamed_keys(overrides or {})
    for k in overrides:
        if k not in _field_types():
            raise ConfigError(f"unknown config key '{k}'")
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    chosen = {**values, **file_values, **given}
    ff_preset = forward_facing_preset(task, chosen.get("scene", TrainConfig.scene), chosen.get("data_root"),
                                      ndc=chosen.get("ndc"), unbounded=chosen.get("unbounded"))
    if ff_preset:
        values.update(load_toml(ff_preset))
    values.update(file_values)
    values["task"] = task
    values.update(given)
    cfg = TrainConfig(**values)
    validate(cfg)
    return cfg


_FLOAT_FIELDS = tuple(f.name for f in fields(TrainConfig) if field_type(f.name)[0] is float)


def validate(cfg: TrainConfig) -> None:
    if cfg.builtin_resolution is not None and cfg.builtin_resolution < 8:
        raise ConfigError(f"builtin_resolution must be >= 8 pixels (unset: the generator's default), "
                          f"got {cfg.builtin_resolution}")
    if cfg.iters < 1:
        raise ConfigError(f"iters must be >= 1, got {cfg.iters}")
    if cfg.batch_rays < 1 or cfg.target_samples < 1:
        raise ConfigError("batch_rays and target_samples must be >= 1")
    for name in CHOICES:
        check_choice(name, getattr(cfg, name))
    if not 0.0 < cfg.g2fr_beta <= 1.0:
        raise ConfigError(f"g2fr_beta must be in (0, 1], got {cfg.g2fr_beta}")
    if cfg.downscale < 1:
        raise ConfigError(f"downscale must be >= 1, got {cfg.downscale}")
    if cfg.background == "random" and not cfg.random_background:
        raise ConfigError("background random needs random_background on (--random-background), or choose another "
                          "--background")
    if cfg.ndc and cfg.unbounded:
        raise ConfigError("ndc and unbounded are both on: a scene has one ray space (NDC or contracted); drop one")
    if cfg.lr_warmup < 0:
        raise ConfigError(f"lr_warmup must be >= 0, got {cfg.lr_warmup}")
    if cfg.sample_budget < cfg.max_samples_per_ray:
        raise ConfigError(f"sample_budget ({cfg.sample_budget}) must be >= max_samples_per_ray ({cfg.max_samples_per_ray})")
    if cfg.eval_view_stride < 1:
        raise ConfigError(f"eval_view_stride must be >= 1, got {cfg.eval_view_stride}")
    # one line naming the key for every value out of range, before any data loads or folder is written
    at_least = {"threads": 1, "n_views": 1, "log_every": 1, "levels": 1, "features": 1, "hidden": 1,
                "occ_resolution": 1, "occ_update_every": 1, "march_steps": 1, "max_samples_per_ray": 1,
                "base_resolution": 1, "max_resolution": 1, "cp_rank": 1, "cp_max_resolution": 1,
                "log2_table_size": 1, "checkpoint_every": 0, "eval_max_views": 0, "video_frames": 0,
                "pose_refine_steps": 0, "occ_warmup": 0, "geo_features": 0, "g2fr_plateau_window": 2,
                "g2fr_heldout_window": 1, "g2fr_heldout_views": 1, "g2fr_heldout_average": 1}
    for key, lo in at_least.items():
        value = getattr(cfg, key)
        if value is not None and value < lo:
            raise ConfigError(f"{key} must be >= {lo}, got {value}")
    positive = ("lr", "cp_lr", "pose_lr", "pose_lr_final", "lr_final_ratio")
    for key in positive:
        value = getattr(cfg, key)
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"{key} must be a positive finite number, got {value}")
    if not (0.0 <= cfg.g2fr_plateau_tol <= 1.0):  # also rejects NaN
        raise ConfigError(f"g2fr_plateau_tol must be in [0, 1] (a share of the largest recent improvement), "
                          f"got {cfg.g2fr_plateau_tol}")
    if not 0.0 <= cfg.pose_reregister_at < 1.0:
        raise ConfigError(f"pose_reregister_at must be in [0, 1) (a fraction of the run; 0 = off), got {cfg.pose_reregister_at}")
    if cfg.pose_reregister_passes < 1:
        raise ConfigError(f"pose_reregister_passes must be >= 1, got {cfg.pose_reregister_passes}")
    if not (cfg.pose_reregister_ratio > 1.0 and math.isfinite(cfg.pose_reregister_ratio)):
        raise ConfigError(f"pose_reregister_ratio must be a finite number > 1, got {cfg.pose_reregister_ratio}")
    for key in ("background_low", "background_late_from", "background_low_late"):
        if not 0.0 <= getattr(cfg, key) <= 1.0:
            raise ConfigError(f"{key} must be in [0, 1], got {getattr(cfg, key)}")
    if not 0.0 < cfg.occ_uniform_fraction <= 1.0:
        raise ConfigError(f"occ_uniform_fraction must be in (0, 1], got {cfg.occ_uniform_fraction}")
    if not math.isfinite(cfg.cp_density_shift):
        raise ConfigError(f"cp_density_shift must be a finite number, got {cfg.cp_density_shift}")
    for key in ("pose_noise", "pose_noise_rot", "pose_noise_trans", "render_step", "occ_threshold",
                "distortion_weight", "g2fr_heldout_min_gain", "g2fr_heldout_drop"):
        value = getattr(cfg, key)
        if value is not None and not (value >= 0 and math.isfinite(value)):
            raise ConfigError(f"{key} must be a finite number >= 0, got {value}")
    dev = cfg.device
    if not (dev in ("auto", "cpu", "cuda") or (dev.startswith("cuda:") and dev[5:].isdigit())):
        raise ConfigError(f"unknown device '{dev}': expected auto, cpu, cuda or cuda:N")
    # the checks above name a key's range; NaN slips through any check written as "refuse if
    # value < lo" (every comparison with NaN is false): refuse it, and +-inf, in every float field
    for name in _FLOAT_FIELDS:
        value = getattr(cfg, name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{name} must be a finite number, got {value}")
    # size settings whose tensors cannot fit memory_budget_mb: refused before anything is allocated or written
    if cfg.memory_budget_mb < 1:
        raise ConfigError(f"memory_budget_mb must be >= 1, got {cfg.memory_budget_mb}")
    problem = training_memory_problem(cfg)
    if problem:
        raise ConfigError(problem)
