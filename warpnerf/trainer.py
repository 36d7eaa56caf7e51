"""A thin training loop: sample pixels, render, MSE, Adam. Tasks supply views, poses and evaluation."""

from __future__ import annotations

import json
import math
import os
import time
from typing import Optional

import numpy as np
import torch

from . import metrics as M
from .config import TrainConfig, exp_decay
from .data.scene import Scene, Views
from .encoders import make_grid_encoder
from .field import GridField
from .freq_mask import G2fRSchedule
from .occupancy import OccupancyGrid
from .renderer import Renderer, default_step, pixel_rays
from .tasks import Task


class TrainingError(RuntimeError):
    """Training cannot go on (e.g. a non-finite loss); one line, names the step."""


def _adam(params, lr: float):
    # instant-ngp's Adam settings; the fused CPU kernel avoids one pass per parameter tensor
    kwargs = dict(lr=lr, betas=(0.9, 0.99), eps=1e-15)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, foreach=True, **kwargs)


class Trainer:
    def __init__(self, cfg: TrainConfig, scene: Scene, task: Task, device: str):
        self.cfg, self.scene, self.task = cfg, scene, task
        self.device = torch.device("cpu" if device == "cpu" else device)
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator(device=self.device).manual_seed(cfg.seed)
        views = task.train_views(scene)
        self.views = views
        self.images = views.images.to(self.device)
        # random backgrounds need each pixel's alpha; scenes without one keep their fixed background
        self.alpha = views.alpha.to(self.device) if cfg.random_background and views.alpha is not None else None
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=self.device)
        self.train_c2w = views.c2w.to(self.device)
        encoder = make_grid_encoder(cfg, generator=torch.Generator().manual_seed(cfg.seed))
        self.field = GridField(scene.aabb, encoder, cfg.hidden, cfg.geo_features).to(self.device)
        self.occupancy = OccupancyGrid(scene.aabb, cfg.occ_resolution, self.device, warmup_steps=cfg.occ_warmup,
                                       update_every=cfg.occ_update_every)
        ray_transform = None
        if scene.ndc:
            from .data.llff import ndc_rays

            f, w, h = views.focal, views.width, views.height
            ray_transform = lambda o, d: ndc_rays(o, d, f, w, h, near=1.0)  # noqa: E731
        far = math.inf if scene.ndc else scene.far
        self.renderer = Renderer(self.field, self.occupancy, scene.near, far, cfg.render_step or default_step(scene.aabb, cfg.march_steps),
                                 scene.background, cfg.max_samples_per_ray, ray_transform,
                                 sample_budget=cfg.sample_budget)
        self.optimizer = _adam(self.field.param_groups(cfg.lr, cfg.weight_decay_mlp), cfg.lr)
        self.schedule = G2fRSchedule(cfg.levels, cfg.iters, cfg.g2fr_beta, cfg.g2fr_mask, enabled=cfg.g2fr)
        self.n_rays = cfg.batch_rays
        # linear lr warm-up from 1 % (nerfacc): at lr 1e-2 and 2^16 samples a step, thin scenes (mic)
        # diverge without it; capped at a tenth of the run so that short runs keep most of their steps
        self.lr_warmup = min(cfg.lr_warmup, cfg.iters // 10)
        self.history: dict[str, list] = {"step": [], "loss": [], "psnr": [], "samples_per_ray": []}
        self.train_seconds = 0.0
        self.callbacks: list = []  # called as cb(trainer, step, stats) after every step (warpnerf.monitor)
        task.setup(self)

    # --- training ---------------------------------------------------------------------------

    def level_weights(self, step: int):
        """G²fR weights of ``step`` as a host :class:`~warpnerf.freq_mask.LevelWeights`: the grid
        launchers read it without touching the device (no CUDA sync per launch)."""
        return self.schedule.level_weights(step)

    def sample_pixels(self, n: int):
        """Random (view, pixel) batch: view ids (n,), pixel centres u, v (n,), colors (n, 3)."""
        nv, h, w = self.images.shape[:3]
        idx = torch.randint(0, nv, (n,), generator=self.gen, device=self.device)
        px = torch.randint(0, w, (n,), generator=self.gen, device=self.device)
        py = torch.randint(0, h, (n,), generator=self.gen, device=self.device)
        # sort by view so consecutive rays (and their samples) come from one camera: better locality
        order = torch.argsort(idx * (h * w) + py * w + px)
        idx, px, py = idx[order], px[order], py[order]
        return idx, px.float() + 0.5, py.float() + 0.5, self.images[idx, py, px], (idx, py, px)

    def train_step(self, step: int) -> dict:
        cfg = self.cfg
        weights = self.level_weights(step)
        # the grid thresholds optical thickness sigma * step (instant-ngp / nerfacc), not raw sigma
        if self.occupancy.maybe_update(step, lambda x: self.field.density(x, weights) * self.renderer.step, self.gen):
            if not bool(self.occupancy.bitfield.any()):
                # an update that empties the grid leaves no sample and so no gradient to recover
                # from: re-open every cell and let the next updates prune again
                self.occupancy.bitfield.fill_(1)
        idx, u, v, target, pix = self.sample_pixels(self.n_rays)
        c2w = self.task.camera_poses(self, idx)
        o, d = pixel_rays(c2w, u, v, self.views.focal, self.views.cx, self.views.cy)
        jitter = torch.rand(o.shape[0], generator=self.gen, device=self.device)
        background = None
        if self.alpha is not None:
            # the target was composited on the scene's background: swap it for a random one per ray,
            # so a transparent field cannot pass for the (white) background (instant-ngp, nerfacc)
            background = torch.rand(o.shape[0], 3, generator=self.gen, device=self.device)
            target = target + (1.0 - self.alpha[pix])[:, None] * (background - self.background)
        out = self.renderer.render_rays(o.contiguous(), d.contiguous(), weights, jitter, background)
        # rays past the sample budget got no samples: leave them out of the loss
        kept = out.n_rays
        loss = torch.nn.functional.mse_loss(out.rgb[:kept], target[:kept])
        with torch.no_grad():
            # the loss of rendering nothing (background only) on the same pixels: see check_learning
            bg = self.background.expand_as(target) if background is None else background
            empty_loss = torch.nn.functional.mse_loss(bg[:kept], target[:kept])
        if not torch.isfinite(loss):
            raise TrainingError(f"non-finite loss ({loss.item()}) at step {step}; try a lower --lr")
        lr = cfg.lr * cfg.lr_final_ratio ** (step / max(cfg.iters - 1, 1))
        if step < self.lr_warmup:
            lr *= 0.01 + 0.99 * step / self.lr_warmup
        for g in self.optimizer.param_groups:
            g["lr"] = lr
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.task.optimizer_step(self, step)
        # adapt the ray count so a step costs about target_samples samples (instant-ngp)
        spr = out.n_samples / max(kept, 1)
        want = cfg.target_samples / max(spr, 1.0)
        self.n_rays = int(min(max(0.5 * self.n_rays + 0.5 * want, 256), 1 << 16))
        return {"loss": loss.item(), "empty_loss": empty_loss.item(), "samples_per_ray": spr}

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

    def fit(self, progress: bool = True) -> None:
        from tqdm.auto import tqdm

        cfg = self.cfg
        bar = tqdm(range(cfg.iters), desc=f"train {self.scene.name}/{cfg.task}", disable=not progress,
                   dynamic_ncols=True, mininterval=0.5)
        t0 = time.perf_counter()
        ratio = None
        for step in bar:
            stats = self.train_step(step)
            r = stats["loss"] / max(stats["empty_loss"], 1e-12)
            ratio = r if ratio is None else 0.9 * ratio + 0.1 * r
            if step % cfg.log_every == 0:
                self.check_learning(step, ratio)
            extra = self.task.after_step(self, step)
            if step % cfg.log_every == 0 or step == cfg.iters - 1:
                psnr = M.psnr_from_mse(stats["loss"])
                self.history["step"].append(step)
                self.history["loss"].append(stats["loss"])
                self.history["psnr"].append(psnr)
                self.history["samples_per_ray"].append(stats["samples_per_ray"])
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{psnr:.2f}", rays=self.n_rays,
                                spr=f"{stats['samples_per_ray']:.0f}", occ=f"{self.occupancy.occupied_fraction():.3f}",
                                lv=self.schedule.active_levels(step), **extra)
            for callback in self.callbacks:
                callback(self, step, stats)
        self.train_seconds = time.perf_counter() - t0

    # --- evaluation -------------------------------------------------------------------------

    def refine_poses(self, c2w: torch.Tensor, views: Views, rays_per_step: int = 1024) -> torch.Tensor:
        """Photometric refinement of (N, 3, 4) poses against ``views``' images with the field frozen
        (BARF's test-time pose optimisation). Returns refined (N, 3, 4) poses.

        All views are refined together: every step renders ``rays_per_step`` random pixels of each
        view and takes one Adam step on the per-view corrections (rows are independent, so this
        equals refining each view alone, with fewer launches). ``pose_refine_steps`` steps, learning
        rate decaying exponentially from ``pose_lr`` to ``pose_lr_final`` as in training: at a
        constant rate the last steps leave each pose jittering by about one learning rate."""
        from .cameras import PoseCorrection

        n_views, n_steps = c2w.shape[0], self.cfg.pose_refine_steps
        weights = self.level_weights(self.cfg.iters)
        corr = PoseCorrection(n_views).to(self.device)
        opt = torch.optim.Adam(corr.parameters(), lr=self.cfg.pose_lr)
        images = views.images.to(self.device)
        gen = torch.Generator(device=self.device).manual_seed(self.cfg.seed + 7)
        idx = torch.arange(n_views, device=self.device).repeat_interleave(rays_per_step)
        for p in self.field.parameters():
            p.requires_grad_(False)
        try:
            for i in range(n_steps):
                for g in opt.param_groups:
                    g["lr"] = exp_decay(self.cfg.pose_lr, self.cfg.pose_lr_final, i / max(n_steps - 1, 1))
                py = torch.randint(0, views.height, idx.shape, generator=gen, device=self.device)
                px = torch.randint(0, views.width, idx.shape, generator=gen, device=self.device)
                o, d = pixel_rays(corr(c2w[idx], idx), px.float() + 0.5, py.float() + 0.5, views.focal, views.cx,
                                  views.cy)
                out = self.renderer.render_rays(o.contiguous(), d.contiguous(), weights)
                # sum of per-view means: each view's gradient is what refining it alone would see
                loss = torch.nn.functional.mse_loss(out.rgb, images[idx, py, px], reduction="sum") / (3 * rays_per_step)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        finally:
            for p in self.field.parameters():
                p.requires_grad_(True)
        with torch.no_grad():
            return corr(c2w)

    def eval_views(self) -> Views:
        test = self.scene.test
        pick = list(range(0, len(test), self.cfg.eval_every))
        if self.cfg.eval_max_views:
            pick = pick[: self.cfg.eval_max_views]
        return test.subset(pick)

    def evaluate(self, out_dir: Optional[str] = None, progress: bool = True) -> dict:
        from tqdm.auto import tqdm

        views = self.eval_views()
        poses = self.task.eval_poses(self, views)
        weights = self.level_weights(self.cfg.iters)
        psnrs, ssims, lpips, secs, depth_errs = [], [], [], [], []
        if views.depth is not None:
            z_scale = camera_z_scale(views.height, views.width, views.focal, views.cx, views.cy)
        if out_dir:
            os.makedirs(os.path.join(out_dir, "renders"), exist_ok=True)
        for k in tqdm(range(len(views)), desc="evaluate", disable=not progress, dynamic_ncols=True):
            t0 = time.perf_counter()
            img = self.renderer.render_image(poses[k], views.height, views.width, views.focal, views.cx, views.cy,
                                             weights)
            secs.append(time.perf_counter() - t0)
            pred, gt = img["rgb"].clamp(0, 1).cpu(), views.images[k]
            psnrs.append(M.psnr(pred, gt))
            ssims.append(M.ssim(pred, gt))
            lpips.append(M.lpips_or_none(pred, gt))
            if views.depth is not None:
                # ground truth is camera-z depth (0 = background); ours is distance along the unit ray
                fg = views.depth[k] > 0
                pred_z = img["depth"].cpu() * z_scale
                depth_errs.append(float((pred_z[fg] - views.depth[k][fg]).abs().mean()) if fg.any() else 0.0)
            if out_dir:
                save_png(os.path.join(out_dir, "renders", f"test_{views.ids[k]:03d}.png"),
                         torch.cat([pred, gt], dim=1))
                save_png(os.path.join(out_dir, "renders", f"test_{views.ids[k]:03d}_depth.png"),
                         depth_to_rgb(img["depth"].cpu(), img["opacity"].cpu()))
        return {
            "psnr": float(np.mean(psnrs)),
            "ssim": float(np.mean(ssims)),
            "lpips": None if any(v is None for v in lpips) else float(np.mean(lpips)),
            "psnr_per_view": psnrs,
            "eval_view_ids": views.ids,
            "render_seconds_per_view": float(np.mean(secs)),
            # mean |depth error| over ground-truth foreground pixels, scene units (built-in scenes)
            "depth_mae": float(np.mean(depth_errs)) if depth_errs else None,
            "eval_resolution": [views.height, views.width],
        }

    def render_turntable(self, path: str, frames: int, progress: bool = True) -> None:
        """A GIF orbiting the scene along the test path (Blender scenes) or the training cameras."""
        import imageio.v2 as imageio
        from tqdm.auto import tqdm

        src = self.scene.test if len(self.scene.test) >= frames else self.scene.train
        pick = np.linspace(0, len(src) - 1, frames).round().astype(int)
        weights = self.level_weights(self.cfg.iters)
        images = []
        for k in tqdm(pick, desc="video", disable=not progress, dynamic_ncols=True):
            c2w = src.c2w[k].to(self.device)
            img = self.renderer.render_image(c2w, src.height, src.width, src.focal, src.cx, src.cy, weights)
            images.append((img["rgb"].clamp(0, 1).cpu().numpy() * 255).astype(np.uint8))
        imageio.mimsave(path, images, duration=0.08, loop=0)

    # --- checkpoints ------------------------------------------------------------------------

    def state_dict(self) -> dict:
        state = {"field": self.field.state_dict(), "occ_density": self.occupancy.density,
                 "occ_bitfield": self.occupancy.bitfield}
        if hasattr(self.task, "correction"):
            state["pose_correction"] = self.task.correction.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.occupancy.density.copy_(state["occ_density"])
        self.occupancy.bitfield.copy_(state["occ_bitfield"])
        if "pose_correction" in state and hasattr(self.task, "correction"):
            self.task.correction.load_state_dict(state["pose_correction"])


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (0 where the platform does not say)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return 0.0
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def camera_z_scale(height: int, width: int, focal: float, cx: float, cy: float) -> torch.Tensor:
    """(H, W) factor turning distance along a pixel's unit ray into camera-z depth."""
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return 1.0 / torch.sqrt(((u - cx) / focal) ** 2 + ((v - cy) / focal) ** 2 + 1.0)


def save_png(path: str, img: torch.Tensor) -> None:
    import imageio.v2 as imageio

    imageio.imwrite(path, (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))


def depth_to_rgb(depth: torch.Tensor, opacity: torch.Tensor) -> torch.Tensor:
    """Grey-scale depth (near = bright) on a white background, (H, W, 3)."""
    valid = opacity > 0.5
    if valid.any():
        lo, hi = depth[valid].min(), depth[valid].max()
        g = 1.0 - (depth - lo) / (hi - lo).clamp_min(1e-6)
    else:
        g = torch.zeros_like(depth)
    g = torch.where(valid, g * 0.9, torch.ones_like(g))
    return g[..., None].expand(*g.shape, 3)


def write_json(path: str, data: dict) -> None:
    with open(path, "w") as fh:
        json.dump(data, fh, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
