"""Evaluation outside the training loop: test-view metrics and renders, BARF's test-time pose
refinement and the run folder's file helpers (the run's video: :mod:`warpnerf.runs.video`).

Every function takes a :class:`warpnerf.train.trainer.Trainer` and only reads it (field, renderer,
scene, config); none changes training state, so a checkpoint saved before evaluation resumes
to the same numbers.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import time
from typing import TYPE_CHECKING, Iterator, Optional

import numpy as np
import torch
from tqdm.auto import tqdm

from warpnerf.data.scene import Views
from warpnerf.geometry.cameras import PoseCorrection
from warpnerf.train import metrics as M
from warpnerf.train.checkpoint import atomic_write_text
from warpnerf.train.config import ConfigError, exp_decay

if TYPE_CHECKING:  # the trainer's modules import this one
    from warpnerf.train.trainer import Trainer

# whether the evaluation running now shows progress: evaluate() sets it around the task's eval_poses hook,
# whose signature has no progress argument, so that refine_poses called from there shows its bar
_PROGRESS: contextvars.ContextVar[bool] = contextvars.ContextVar("warpnerf_eval_progress", default=False)


@contextlib.contextmanager
def frozen(module: torch.nn.Module) -> Iterator[None]:
    """``module``'s parameters take no gradient inside the block (pose refinement against a fixed
    field: only the poses' graph is built) and take one again afterwards, also on an error."""
    for p in module.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in module.parameters():
            p.requires_grad_(True)


def refine_corrections(trainer: "Trainer", corr: "PoseCorrection", c2w: torch.Tensor, pixels, intrinsics,
                       weights, steps: int, lr: float, lr_final: float, progress: bool = False,
                       desc: str = "refine poses") -> None:
    """``steps`` Adam steps on ``corr``, the se(3) corrections of the (k, 3, 4) poses ``c2w``, against a
    frozen field (the caller freezes it). ``pixels(i)`` gives step i's rays as (row of ``c2w``, u, v,
    target rgb), the same number for every row; ``intrinsics`` is (focal, cx, cy). The loss is the sum
    over rows of each row's mean squared error, so rows are independent: each row's gradient is what
    refining it alone would see. The rate decays exponentially from ``lr`` to ``lr_final``: at a
    constant rate the last steps leave each pose jittering by about one rate. ``progress``: a bar
    named ``desc`` over the steps."""
    opt = torch.optim.Adam(corr.parameters(), lr=lr)
    for i in tqdm(range(steps), desc=desc, disable=not progress, dynamic_ncols=True, unit="step"):
        for g in opt.param_groups:
            g["lr"] = exp_decay(lr, lr_final, i / max(steps - 1, 1))
        idx, u, v, rgb = pixels(i)
        per_row = idx.shape[0] // c2w.shape[0]
        opt.zero_grad(set_to_none=True)
        # every ray rendered, in as many calls as the sample budget needs (one call for 25 lego views
        # x 1024 rays left the last views' rays unrendered, those poses drifting)
        chunks = trainer.renderer.render_pixels(lambda first, idx=idx: corr.for_rays(c2w, idx[first:]), u, v,
                                                intrinsics, weights)  # idx=idx: this step's pixels
        for first, out in chunks:
            loss = (out - rgb[first:first + out.shape[0]]).square().sum() / (3 * per_row)
            loss.backward()
        opt.step()


def refine_poses(trainer: "Trainer", c2w: torch.Tensor, views: Views, rays_per_step: int = 1024,
                 progress: Optional[bool] = None) -> torch.Tensor:
    """Photometric refinement of (N, 3, 4) poses against ``views``' images with the field frozen
    (BARF's test-time pose optimisation). Returns refined (N, 3, 4) poses.

    All views are refined together (:func:`refine_corrections`): every step renders
    ``rays_per_step`` random pixels of each view, ``pose_refine_steps`` steps from ``pose_lr`` to
    ``pose_lr_final`` as in training. ``progress`` (None: whatever the :func:`evaluate` calling the
    task's ``eval_poses`` was asked for) shows a bar over the steps."""
    if progress is None:
        progress = _PROGRESS.get()
    n_views = c2w.shape[0]
    corr = PoseCorrection(n_views).to(trainer.device)
    images = views.images.to(trainer.device)
    gen = torch.Generator(device=trainer.device).manual_seed(trainer.cfg.seed + 7)
    idx = torch.arange(n_views, device=trainer.device).repeat_interleave(rays_per_step)

    def pixels(_step):
        rows = torch.randint(0, views.height, idx.shape, generator=gen, device=trainer.device)
        cols = torch.randint(0, views.width, idx.shape, generator=gen, device=trainer.device)
        return idx, cols.float() + 0.5, rows.float() + 0.5, images[idx, rows, cols]

    with frozen(trainer.field):
        refine_corrections(trainer, corr, c2w, pixels, (views.focal, views.cx, views.cy),
                           trainer.level_weights(trainer.cfg.iters), trainer.cfg.pose_refine_steps,
                           trainer.cfg.pose_lr, trainer.cfg.pose_lr_final, progress=progress,
                           desc=f"refine {n_views} test pose{'s' if n_views != 1 else ''}")
    with torch.no_grad():
        return corr(c2w)

def _eval_pick(trainer: "Trainer") -> tuple[Views, list[int]]:
    test = getattr(trainer.scene, trainer.cfg.eval_split)
    if test is None:
        raise ConfigError(f"eval_split = '{trainer.cfg.eval_split}', but scene '{trainer.scene.name}' has no such split")
    pick = list(range(0, len(test), trainer.cfg.eval_view_stride))
    if trainer.cfg.eval_max_views:
        pick = pick[: trainer.cfg.eval_max_views]
    return test, pick


def eval_view_count(trainer: "Trainer") -> int:
    """How many views :func:`evaluate` renders (the run's banner announces it), without copying their images."""
    return len(_eval_pick(trainer)[1])


def eval_views(trainer: "Trainer") -> Views:
    """Every ``eval_view_stride``-th view of the ``eval_split`` (test unless settings are being chosen on val)."""
    test, pick = _eval_pick(trainer)
    return test.subset(pick)

def evaluate(trainer: "Trainer", out_dir: Optional[str] = None, progress: bool = True) -> dict:
    """Render the evaluation views (:func:`eval_views`) at the last step's level weights; PSNR, SSIM,
    LPIPS, timings and depth error. ``progress``: a bar over the views (and over the pose task's
    test-pose refinement steps before them)."""
    views = eval_views(trainer)
    token = _PROGRESS.set(progress)
    try:
        poses = trainer.task.eval_poses(trainer, views)
    finally:
        _PROGRESS.reset(token)
    weights = trainer.level_weights(trainer.cfg.iters)
    psnrs, ssims, lpips, secs, depth_errs = [], [], [], [], []
    if views.depth is not None:
        z_scale = camera_z_scale(views.height, views.width, views.focal, views.cx, views.cy)
    if out_dir:
        os.makedirs(os.path.join(out_dir, "renders"), exist_ok=True)
    for k in tqdm(range(len(views)), desc=f"evaluate {trainer.cfg.eval_split} views", disable=not progress,
                  dynamic_ncols=True, unit="view"):
        t0 = time.perf_counter()
        img = trainer.renderer.render_image(poses[k], views.height, views.width, views.focal, views.cx, views.cy,
                                         weights)
        secs.append(time.perf_counter() - t0)
        pred, gt = img["rgb"].clamp(0, 1).cpu(), views.images[k]
        psnrs.append(M.psnr(pred, gt))
        ssims.append(M.ssim(pred, gt))
        lpips.append(M.lpips_or_none(pred, gt))
        if views.depth is not None:
            # ground truth is camera-z depth (0 = background); ours is distance along the unit ray in
            # the ray space's units (a contracted space's are world units times its scale)
            fg = views.depth[k] > 0
            pred_z = img["depth"].cpu() * z_scale / trainer.scene.ray_space.scale
            depth_errs.append(float((pred_z[fg] - views.depth[k][fg]).abs().mean()) if fg.any() else 0.0)
        if out_dir:
            save_png(os.path.join(out_dir, "renders", f"test_{views.ids[k]:03d}.png"),
                     torch.cat([pred, gt], dim=1))
            save_png(os.path.join(out_dir, "renders", f"test_{views.ids[k]:03d}_depth.png"),
                     depth_to_rgb(img["depth"].cpu(), img["opacity"].cpu(),
                                  disparity=trainer.scene.ray_space.is_contracted))
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


def camera_z_scale(height: int, width: int, focal: float, cx: float, cy: float) -> torch.Tensor:
    """(H, W) factor turning distance along a pixel's unit ray into camera-z depth."""
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    return 1.0 / torch.sqrt(((u - cx) / focal) ** 2 + ((v - cy) / focal) ** 2 + 1.0)


def save_png(path: str, img: torch.Tensor) -> None:
    import imageio.v2 as imageio  # lazy: codecs stay out of --help (~0.08 s)

    imageio.imwrite(path, (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))


def depth_to_rgb(depth: torch.Tensor, opacity: torch.Tensor, disparity: bool = False) -> torch.Tensor:
    """Grey-scale depth (near = bright) on a white background, (H, W, 3). ``disparity``: shade
    1 / depth instead (unbounded scenes, whose far background would flatten everything else)."""
    valid = opacity > 0.5
    if disparity:
        depth = -1.0 / depth.clamp_min(1e-6)  # increasing with depth, like depth
    if valid.any():
        lo, hi = depth[valid].min(), depth[valid].max()
        g = 1.0 - (depth - lo) / (hi - lo).clamp_min(1e-6)
    else:
        g = torch.zeros_like(depth)
    g = torch.where(valid, g * 0.9, torch.ones_like(g))
    return g[..., None].expand(*g.shape, 3)


def write_json(path: str, data: dict) -> None:
    """JSON written atomically (temp file + fsync + rename): a crash never leaves half a file."""
    atomic_write_text(path, json.dumps(data, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
