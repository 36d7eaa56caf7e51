"""A thin training loop: sample pixels, render, MSE, Adam; its state for checkpoints.

Tasks supply views and poses through hooks; evaluation, pose refinement and the file helpers live
in :mod:`warpnerf.train.evaluate`, the turntable in :mod:`warpnerf.runs.video`.
"""

from __future__ import annotations

import ctypes
import gc
import sys
import time
from typing import TYPE_CHECKING, Callable, NamedTuple, Optional

import numpy as np
import torch
from tqdm.auto import tqdm

from warpnerf.data.scene import Scene
from warpnerf.model.encoders import make_grid_encoder
from warpnerf.model.field import GridField
from warpnerf.model.g2fr import make_schedule
from warpnerf.model.occupancy import OccupancyGrid
from warpnerf.model.renderer import Renderer, default_step, pixel_rays
from warpnerf.train import metrics as M
from warpnerf.train.checkpoint import CheckpointError, rng_state, set_rng_state
from warpnerf.train.config import ConfigError, TrainConfig
from warpnerf.train.error_map import ErrorMap
from warpnerf.train.monitor import HeldoutViews

try:
    import resource
except ImportError:  # pragma: no cover - Windows
    resource = None

if TYPE_CHECKING:  # tasks call back into the trainer; the trainer only names their type
    from warpnerf.train.tasks import Task

# training compaction (Renderer._active_prefixes): on while the last compacted step kept less than
# this share of its marched samples; tried again every COMPACT_PROBE_EVERY steps (the occupancy
# grid's update period, so a 16-step window always holds one probe and one update)
COMPACT_BELOW = 0.7
COMPACT_PROBE_EVERY = 16
# --background learned: the colour's Adam rate over the field's. At the field's own rate the tiny spheres'
# background (0.3, 0.6, 0.2), started at grey, was still 0.07 off after 300 steps while the field painted the
# rest as haze (occupancy 59 %); at 5x it was within 0.02 by step 60 and the grid pruned to 5 %
# (tests/data/test_background.py).
BG_LR_SCALE = 5.0


class PixelBatch(NamedTuple):
    """One step's training pixels (:meth:`Trainer.sample_pixels`), sorted by (view, row, column)."""

    view: torch.Tensor  # (n,) int64 view ids
    row: torch.Tensor  # (n,) int64 pixel rows
    col: torch.Tensor  # (n,) int64 pixel columns
    rgb: torch.Tensor  # (n, 3) target colours
    weight: Optional[torch.Tensor]  # (n,) loss weights; None for uniform sampling

    @property
    def u(self) -> torch.Tensor:
        """(n,) pixel-centre columns: the centre of pixel (i, j) is (i + 0.5, j + 0.5)."""
        return self.col.float() + 0.5

    @property
    def v(self) -> torch.Tensor:
        """(n,) pixel-centre rows."""
        return self.row.float() + 0.5


class TrainingError(RuntimeError):
    """Training cannot go on (e.g. a non-finite loss); one line, names the step."""


def _adam(params, lr: float):
    # instant-ngp's Adam settings; the fused CPU kernel avoids one pass per parameter tensor
    kwargs = dict(lr=lr, betas=(0.9, 0.99), eps=1e-15)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, foreach=True, **kwargs)


# Adam moments of table rows that no sample touches decay by beta1 = 0.9 per step (second moments by
# 0.99) and reach float32's denormal range (< 1.2e-38) some hundreds of steps later. Arithmetic on
# denormals is ~10x slower on x86 CPUs: at step 2500 of lego full, 23 % of the table's first moments
# were denormal and Adam took 19 ms of a 96 ms step instead of 4. Every MOMENT_FLUSH_EVERY steps the
# moments below these bounds are set to 0 (none decays from above a bound into the denormal range in
# between). The parameter updates this changes: a first moment below 1e-30 moved its parameter by
# < 1e-15 * lr (eps = 1e-15 bounds the denominator); a second moment below 1e-36 changed the
# denominator sqrt(v) + eps by < 0.1 %.
MOMENT_FLUSH_EVERY = 100
MOMENT_FLUSH_BELOW = {"exp_avg": 1e-30, "exp_avg_sq": 1e-36}


def flush_tiny_moments(optimizer: torch.optim.Optimizer) -> None:
    """Set Adam moments below :data:`MOMENT_FLUSH_BELOW` to 0 in place (see there for why)."""
    for state in optimizer.state.values():
        for key, below in MOMENT_FLUSH_BELOW.items():
            m = state.get(key)
            if m is not None:
                m.masked_fill_(m.abs() < below, 0.0)


def ray_mse(rgb: torch.Tensor, target: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean squared error of (R, 3) ray colours; with per-ray ``weight`` (R,) (error sampling's importance
    weights) the weighted mean over rays of each ray's channel mean: an unbiased estimate of the
    mean over all pixels."""
    if weight is None:
        return torch.nn.functional.mse_loss(rgb, target)
    return (weight * (rgb - target).square().mean(dim=-1)).mean()


class Trainer:
    def __init__(self, cfg: TrainConfig, scene: Scene, task: Task, device: str):
        self.cfg, self.scene, self.task = cfg, scene, task
        self.device = torch.device("cpu" if device == "cpu" else device)
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)  # unused by training, but checkpoints carry its state: keep it reproducible
        self.gen = torch.Generator(device=self.device).manual_seed(cfg.seed)
        views = task.train_views(scene)
        self.views = views
        self.images = views.images.to(self.device)
        # random backgrounds need each pixel's alpha; scenes without one keep their fixed background (a learned
        # one is fixed within a step: warpnerf.data.background)
        learned = cfg.background == "learned"
        self.alpha = (views.alpha.to(self.device) if cfg.random_background and views.alpha is not None and not learned
                      else None)
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=self.device)
        # --background learned: the colour behind every ray, sigmoid(logit), trained with the field
        self.background_logit = (torch.nn.Parameter(torch.logit(self.background.clamp(0.01, 0.99)))
                                 if learned else None)
        self.train_c2w = views.c2w.to(self.device)
        encoder = make_grid_encoder(cfg, generator=torch.Generator().manual_seed(cfg.seed))
        mtrf = cfg.model == "mtrf"
        self.field = GridField(scene.aabb, encoder, cfg.hidden, cfg.geo_features,
                               density_shift=cfg.cp_density_shift if mtrf else 0.0).to(self.device)
        self.occupancy = OccupancyGrid(scene.aabb, cfg.occ_resolution, self.device, threshold=cfg.occ_threshold,
                                       warmup_steps=cfg.occ_warmup, update_every=cfg.occ_update_every,
                                       uniform_fraction=cfg.occ_uniform_fraction)
        # the scene's ray space (ray map, box, marching bounds: DESIGN §6) is all the renderer needs
        self.renderer = Renderer(self.field, self.occupancy, scene.ray_space,
                                 cfg.render_step or default_step(scene.aabb, cfg.march_steps),
                                 scene.background, cfg.max_samples_per_ray, sample_budget=cfg.sample_budget)
        groups = self.field.param_groups(cfg.lr, cfg.weight_decay_mlp, cfg.cp_lr if mtrf else None)
        if self.background_logit is not None:
            lr = BG_LR_SCALE * cfg.lr
            groups = [*groups, {"params": [self.background_logit], "lr": lr, "base_lr": lr}]
        self.optimizer = _adam(groups, cfg.lr)
        self._sync_background()
        self.schedule = make_schedule(cfg.g2fr_schedule, cfg.levels, cfg.iters, cfg.g2fr_beta, cfg.g2fr_mask,
                                      enabled=cfg.g2fr, window=cfg.g2fr_plateau_window, tol=cfg.g2fr_plateau_tol,
                                      heldout_window=cfg.g2fr_heldout_window, drop=cfg.g2fr_heldout_drop,
                                      min_gain=cfg.g2fr_heldout_min_gain, average=cfg.g2fr_heldout_average)
        # the held-out schedule's own views: always val (never test, whatever heldout_split the curve reads)
        self.schedule_views = None
        if cfg.g2fr and cfg.g2fr_schedule == "heldout":
            if scene.val is None:
                raise ConfigError(f"--g2fr-schedule heldout reads the val split, and scene '{scene.name}' has none; "
                                  f"choose --g2fr-schedule fixed or adaptive")
            self.schedule_views = HeldoutViews(self, "val", cfg.g2fr_heldout_views)
        self.n_rays = cfg.batch_rays
        # a share of the rays drawn where the error is (instant-ngp's error map), importance-weighted
        self.error_map = (ErrorMap(*self.images.shape[:3], share=cfg.error_sampling, device=self.device)
                          if cfg.error_sampling > 0 else None)
        # linear lr warm-up from 1 % (nerfacc): at lr 1e-2 and 2^16 samples a step, thin scenes (mic)
        # diverge without it; capped at a tenth of the run so that short runs keep most of their steps
        self.lr_warmup = min(cfg.lr_warmup, cfg.iters // 10)
        self.history: dict[str, list] = {"step": [], "loss": [], "psnr": [], "samples_per_ray": [], "epochs": []}
        self.rays_seen = 0  # training rays drawn so far: epochs = rays_seen / training pixels
        self.train_seconds = 0.0
        self.step = 0  # the next step to run (a resumed run starts past 0)
        self.loss_ratio: Optional[float] = None  # EMA of loss / background-only loss (check_learning)
        # the share of marched samples the last compacted step kept (Renderer._active_prefixes)
        self.kept_fraction = 1.0
        self.callbacks: list = []  # called as cb(trainer, step, stats) after every step (warpnerf.train.monitor)
        task.setup(self)

    def _sync_background(self) -> None:
        """A learned background's current colour into ``self.background`` and the renderer (rendering and
        evaluation use it as a constant)."""
        if self.background_logit is not None:
            with torch.no_grad():
                self.background = torch.sigmoid(self.background_logit).detach().clone()
            self.renderer.background = tuple(float(c) for c in self.background.tolist())

    # --- training ---------------------------------------------------------------------------

    def level_weights(self, step: int):
        """G²fR weights of ``step`` as a host :class:`~warpnerf.model.g2fr.LevelWeights`: the grid
        launchers read it without touching the device (no CUDA sync per launch)."""
        return self.schedule.level_weights(step)

    def sample_pixels(self, n: int) -> PixelBatch:
        """Random (view, pixel) batch of ``n`` rays; the loss weights are ``None`` for uniform
        sampling, with ``error_sampling`` the importance weights of :class:`~warpnerf.train.error_map.ErrorMap`."""
        nv, h, w = self.images.shape[:3]
        weight = None
        if self.error_map is not None:
            idx, px, py, weight = self.error_map.sample(n, self.gen)
        else:
            idx = torch.randint(0, nv, (n,), generator=self.gen, device=self.device)
            px = torch.randint(0, w, (n,), generator=self.gen, device=self.device)
            py = torch.randint(0, h, (n,), generator=self.gen, device=self.device)
        # sort by view so consecutive rays (and their samples) come from one camera: better locality
        order = torch.argsort(idx * (h * w) + py * w + px)
        idx, px, py = idx[order], px[order], py[order]
        weight = None if weight is None else weight[order]
        return PixelBatch(idx, py, px, self.images[idx, py, px], weight)

    def train_step(self, step: int) -> dict:
        cfg = self.cfg
        weights = self.level_weights(step)
        # the grid thresholds optical thickness sigma * step (instant-ngp / nerfacc), not raw sigma
        if self.occupancy.maybe_update(step, lambda x: self.field.density(x, weights) * self.renderer.step_at(x), self.gen):
            if not bool(self.occupancy.bitfield.any()):
                # an update that empties the grid leaves no sample and so no gradient to recover
                # from: re-open every cell and let the next updates prune again
                self.occupancy.bitfield.fill_(1)
        batch = self.sample_pixels(self.n_rays)
        target = batch.rgb
        c2w = self.task.camera_poses(self, batch.view)
        o, d = pixel_rays(c2w, batch.u, batch.v, self.views.focal, self.views.cx, self.views.cy)
        jitter = torch.rand(o.shape[0], generator=self.gen, device=self.device)
        background = None
        if self.alpha is not None:
            # the target was composited on the scene's background: swap it for a random one per ray,
            # so a transparent field cannot pass for the (white) background (instant-ngp, nerfacc)
            background = torch.rand(o.shape[0], 3, generator=self.gen, device=self.device)
            low = cfg.background_low_late if step >= cfg.background_late_from * cfg.iters else cfg.background_low
            background = low + (1.0 - low) * background
            target = target + (1.0 - self.alpha[batch.view, batch.row, batch.col])[:, None] * (background - self.background)
        # compaction pays when many samples lie behind opaque surfaces (lego late in training: 0.91x
        # the step time) and costs when few do (fern, 1 % behind: 1.15x): compact while the last
        # compacted step kept less than COMPACT_BELOW of its samples, and probe every 16 steps
        compact = step % COMPACT_PROBE_EVERY == 0 or self.kept_fraction < COMPACT_BELOW
        distortion_weight = cfg.distortion_weight * self.distortion_ramp(step)
        out = self.renderer.render_rays(o.contiguous(), d.contiguous(), weights, jitter, background, compact=compact,
                                        distortion=distortion_weight > 0)
        if compact:
            self.kept_fraction = out.n_active / max(out.n_samples, 1)
        rgb = out.rgb
        if self.background_logit is not None:
            # the composite used the colour as a constant (the field's gradients are right); this adds the
            # colour's own gradient, (1 - opacity) per ray, without changing the value
            colour = torch.sigmoid(self.background_logit)
            rgb = rgb + (1.0 - out.opacity.detach())[:, None] * (colour - colour.detach())
        # rays past the sample budget got no samples: leave them out of the loss
        kept = out.n_rays
        weight = None if batch.weight is None else batch.weight[:kept]
        mse = ray_mse(rgb[:kept], target[:kept], weight)
        if self.error_map is not None:
            self.error_map.update(batch.view[:kept], batch.col[:kept], batch.row[:kept],
                                  (rgb[:kept].detach() - target[:kept]).square().mean(dim=-1))
        loss = mse
        if out.distortion is not None and kept:
            loss = mse + distortion_weight * out.distortion[:kept].mean()
        with torch.no_grad():
            # the loss of rendering nothing (background only) on the same pixels: see check_learning
            bg = self.background.expand_as(target) if background is None else background
            empty_loss = ray_mse(bg[:kept], target[:kept], weight)
        if not torch.isfinite(loss):
            raise TrainingError(f"non-finite loss ({loss.item()}) at step {step}; try a lower --lr")
        factor = cfg.lr_final_ratio ** (step / max(cfg.iters - 1, 1))
        if step < self.lr_warmup:
            factor *= 0.01 + 0.99 * step / self.lr_warmup
        for g in self.optimizer.param_groups:
            g["lr"] = g.get("base_lr", cfg.lr) * factor
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self._sync_background()
        if (step + 1) % MOMENT_FLUSH_EVERY == 0:
            flush_tiny_moments(self.optimizer)
        self.task.optimizer_step(self, step)
        # adapt the ray count so a step costs about target_samples samples (instant-ngp)
        spr = out.n_samples / max(kept, 1)
        want = cfg.target_samples / max(spr, 1.0)
        self.n_rays = int(min(max(0.5 * self.n_rays + 0.5 * want, 256), 1 << 16))
        # "loss" is the photometric MSE (PSNR, the learning check); a regulariser is not in it
        self.rays_seen += int(kept)
        return {"loss": mse.item(), "empty_loss": empty_loss.item(), "samples_per_ray": spr}

    @property
    def epochs(self) -> float:
        """Passes over the training pixels so far (rays drawn / pixels of the training views): the unit in
        which runs of different batch sizes and image sizes train equally long."""
        return self.rays_seen / max(self.images.shape[0] * self.images.shape[1] * self.images.shape[2], 1)

    def distortion_ramp(self, step: int) -> float:
        """Share of ``distortion_weight`` applied at ``step``: 0 during the occupancy warm-up, then a
        linear ramp to 1 over as many steps. The loss is lowest for an empty field; on the early,
        foggy field it emptied the built-in forward-facing 'yard' by step 50 and training never
        recovered (18 dB at step 900 where the run without it was past 30 dB)."""
        w = self.cfg.occ_warmup
        return min(max((step - w) / max(w, 1), 0.0), 1.0)

    def check_learning(self, step: int, loss_ratio: float) -> None:
        """Stop a run that is not learning, with one line naming the step and what to try.

        ``loss_ratio`` is the recent training loss over the loss of rendering background only on
        the same pixels. A field that stays near 1 after the lr and occupancy warm-ups has
        collapsed to empty space (or diverged): more steps will not help."""
        cfg = self.cfg
        start = max(self.lr_warmup, cfg.occ_warmup) + 200
        if cfg.learn_guard and step >= start and loss_ratio > 0.5:
            raise TrainingError(
                f"not learning at step {step}: the training loss is {loss_ratio:.2f}x that of rendering the "
                f"background only; try a lower --lr (now {cfg.lr:g}) or a longer --lr-warmup")
        peak = peak_rss_mb()
        if peak > cfg.memory_budget_mb:
            raise TrainingError(f"peak memory {peak:.0f} MB exceeds memory_budget_mb = {cfg.memory_budget_mb} at step "
                                f"{step}; lower sample_budget or --downscale the images")

    def fit(self, progress: bool = True, on_step_end: Optional[Callable[[int], None]] = None) -> None:
        """Run steps ``self.step`` .. ``cfg.iters - 1``; ``on_step_end(n_done)`` after each one
        (checkpoints, interrupts). A resumed trainer continues where its state left off."""
        cfg = self.cfg
        bar = tqdm(range(self.step, cfg.iters), desc=f"train {self.scene.name}/{cfg.task}", disable=not progress,
                   dynamic_ncols=True, mininterval=0.5, initial=self.step, total=cfg.iters)
        t0 = time.perf_counter()
        for step in bar:
            stats = self.train_step(step)
            self.schedule.observe(step, stats["loss"])
            if self.schedule.wants_heldout(step):
                self.schedule.observe_heldout(step, self.schedule_views.check(self, step)[0])
            r = stats["loss"] / max(stats["empty_loss"], 1e-12)
            self.loss_ratio = r if self.loss_ratio is None else 0.9 * self.loss_ratio + 0.1 * r
            if step % cfg.log_every == 0:
                self.check_learning(step, self.loss_ratio)
            extra = self.task.after_step(self, step)
            if step % cfg.log_every == 0 or step == cfg.iters - 1:
                psnr = M.psnr_from_mse(stats["loss"])
                self.history["step"].append(step)
                self.history["loss"].append(stats["loss"])
                self.history["psnr"].append(psnr)
                self.history["samples_per_ray"].append(stats["samples_per_ray"])
                self.history["epochs"].append(self.epochs)
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{psnr:.2f}", rays=self.n_rays,
                                spr=f"{stats['samples_per_ray']:.0f}", occ=f"{self.occupancy.occupied_fraction():.3f}",
                                lv=self.schedule.active_levels(step), **extra)
            for callback in self.callbacks:
                callback(self, step, stats)
            self.step = step + 1
            if on_step_end is not None:
                self.train_seconds += time.perf_counter() - t0
                t0 = time.perf_counter()
                on_step_end(self.step)
        self.train_seconds += time.perf_counter() - t0


    # --- checkpoints ------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Everything needed to continue training bit-identically (and to evaluate): step, field,
        Adam state, occupancy grid, RNG streams, adaptive ray count, loss-ratio EMA, history, the
        task's state."""
        return {"step": self.step, "field": self.field.state_dict(), "optimizer": self.optimizer.state_dict(),
                "occ_density": self.occupancy.density, "occ_bitfield": self.occupancy.bitfield,
                "rng": rng_state(self.gen), "n_rays": self.n_rays, "loss_ratio": self.loss_ratio,
                "kept_fraction": self.kept_fraction, "history": self.history, "train_seconds": self.train_seconds,
                "task": self.task.state_dict(), "schedule": self.schedule.state_dict(), "rays_seen": self.rays_seen,
                **({"error_map": self.error_map.state_dict()} if self.error_map is not None else {}),
                **({"background_logit": self.background_logit.detach().clone()}
                   if self.background_logit is not None else {})}

    def load_state_dict(self, state: dict) -> None:
        saved = state["field"]
        if "aabb_min" in saved and not (torch.equal(saved["aabb_min"].cpu(), self.field.aabb_min.cpu())
                                        and torch.equal(saved["aabb_size"].cpu(), self.field.aabb_size.cpu())):
            # the occupancy grid and the marcher use the scene's box: a field from another box would
            # be read through the wrong cells (LLFF's NDC box grew with the loader of 48fe570)
            def box(lo, size):
                return "(" + ", ".join(f"{v:.4g}" for v in (*lo.tolist(), *(lo + size).tolist())) + ")"

            raise CheckpointError(
                f"the checkpoint's scene box {box(saved['aabb_min'].cpu(), saved['aabb_size'].cpu())} is not this "
                f"scene's {box(self.field.aabb_min.cpu(), self.field.aabb_size.cpu())}: it was trained on another "
                f"scene or by an older loader (LLFF's NDC box changed); train it again")
        self.field.load_state_dict(saved)
        self.occupancy.density.copy_(state["occ_density"])
        self.occupancy.bitfield.copy_(state["occ_bitfield"])
        self.optimizer.load_state_dict(state["optimizer"])
        set_rng_state(state["rng"], self.gen)
        self.step, self.n_rays = int(state["step"]), int(state["n_rays"])
        self.loss_ratio = state.get("loss_ratio")
        self.kept_fraction = float(state.get("kept_fraction", 1.0))
        self.history = {k: list(v) for k, v in state["history"].items()}
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.task.load_state_dict(state["task"])
        self.schedule.load_state_dict(state.get("schedule", {}))
        self.rays_seen = int(state.get("rays_seen", 0))
        if self.error_map is not None and "error_map" in state:
            self.error_map.load_state_dict(state["error_map"])
        if self.background_logit is not None and "background_logit" in state:
            with torch.no_grad():
                self.background_logit.copy_(state["background_logit"])
            self._sync_background()


def start_memory_window() -> None:
    """Begin a new peak-memory window for the run about to start.

    Runs that share a process (``warpnerf table``/``sweep`` run them one after another) would
    otherwise inherit the previous runs' high-water mark: a mic run after two lego runs was
    stopped by ``memory_budget_mb`` at step 0 with a "peak" of 4401 MB that it never used. The
    previous run's garbage is collected and returned to the system (glibc ``malloc_trim``), then
    Linux's peak-RSS counter is reset (``/proc/self/clear_refs``, value 5); elsewhere this is a no-op
    and the peak stays the process's."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:  # not Linux, or not permitted
        pass


def peak_rss_mb() -> float:
    """Peak resident memory of this process since the run began (``start_memory_window``), MB
    (0 where the platform does not say)."""
    if resource is None:  # pragma: no cover - Windows
        return 0.0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0
