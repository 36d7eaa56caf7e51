"""Training curves beyond the batch loss: held-out PSNR, G²fR state, pose error, TensorBoard.

A :class:`Monitor` is one of ``Trainer.callbacks``: ``fit`` calls it as ``monitor(trainer, step,
stats)`` after every step. It

* every ``cfg.heldout_every`` steps (and at the last step) renders ``cfg.heldout_views`` test
  views at half resolution and appends their mean PSNR to ``trainer.history["heldout"]`` as
  (step, dB) pairs, so ``history.json`` and ``training.png`` get the held-out curve; with
  ``progress`` a transient bar under the training bar shows each check (the last one runs after
  the training bar's final step and would otherwise be a silent pause);
* every ``cfg.log_every`` steps appends the encoding's L_Ψ to ``trainer.history["lipschitz"]``;
* with ``cfg.log == "tensorboard"`` writes scalars every ``cfg.log_every`` steps to
  ``<run>/tb`` (``pip install 'warpnerf[log]'``, view with ``tensorboard --logdir runs``).

TensorBoard scalar tags (:data:`TAGS`): ``train/loss`` (MSE), ``train/psnr`` (dB, training batch),
``heldout/psnr`` (dB), ``g2fr/active_levels``, ``g2fr/lipschitz`` (L_Ψ, paper eq. 17, see
:func:`lipschitz_bound`), ``pose/rot_err_deg`` and ``pose/trans_err_x100`` (pose task only,
after Sim(3) alignment), ``perf/samples_per_ray``, ``perf/step_seconds`` (wall time per step,
averaged since the previous log; includes the held-out renders of that interval), ``lr/grid`` and
``lr/mlp`` (the rates Adam used at that step, one per parameter group) and ``lr/pose`` (pose task:
the camera corrections' rate).

Images (:data:`IMAGE_TAGS`): ``g2fr/level_weights`` every ``log_every`` steps (one 8x8 block per
level, coarse to fine from the left, brightness w_m: black = masked, white = fully on);
``heldout/prediction`` and ``heldout/ground_truth`` at each held-out check (the held-out views side
by side, as the check renders them: half resolution from 64 px up).

Once evaluation is done, :meth:`Monitor.log_final` adds the final metrics at the last step
(:func:`final_tags`): ``test/psnr``, ``test/ssim`` and, when its weights are on disk, ``test/lpips``
(``val/...`` when ``eval_split = "val"``).
"""

from __future__ import annotations

import os
import time
from typing import Optional

import torch
from tqdm.auto import tqdm

from warpnerf.train import metrics as M
from warpnerf.train.config import ConfigError
from warpnerf.train.views import test_cameras

TAGS = ("train/loss", "train/psnr", "heldout/psnr", "g2fr/active_levels", "g2fr/lipschitz", "pose/rot_err_deg",
        "pose/trans_err_x100", "perf/samples_per_ray", "perf/step_seconds", "lr/grid", "lr/mlp", "lr/pose")
IMAGE_TAGS = ("g2fr/level_weights", "heldout/prediction", "heldout/ground_truth")
LEVEL_BLOCK = 8  # pixels per level (square) in the g2fr/level_weights image


def final_tags(split: str = "test") -> tuple[str, ...]:
    """The scalar tags :meth:`Monitor.log_final` writes: the final metrics measured on ``split``."""
    return tuple(f"{split}/{m}" for m in ("psnr", "ssim", "lpips"))


def level_weights_image(weights) -> torch.Tensor:
    """(1, 8, 8 L) uint8 image of the G²fR level weights: level m's block has brightness round(255 w_m)."""
    w = torch.tensor([float(v) for v in weights], dtype=torch.float32)
    row = (w * 255).round().to(torch.uint8).repeat_interleave(LEVEL_BLOCK)
    return row[None, None, :].expand(1, LEVEL_BLOCK, row.numel()).contiguous()


def _as_uint8(img: torch.Tensor) -> torch.Tensor:
    return (img.clamp(0, 1) * 255).round().to(torch.uint8)


def learning_rates(trainer) -> dict[str, float]:
    """``lr/<group>`` -> the rate each Adam group used at the step just taken (the trainer sets them
    before stepping), plus ``lr/pose`` for a task with its own optimizer (the pose corrections)."""
    out = {f"lr/{g.get('name', i)}": float(g["lr"]) for i, g in enumerate(trainer.optimizer.param_groups)}
    task_opt = getattr(trainer.task, "optimizer", None)
    if task_opt is not None:
        out["lr/pose"] = float(task_opt.param_groups[0]["lr"])
    return out


@torch.no_grad()
def lipschitz_bound(encoder, level_weights: Optional[torch.Tensor], n_pairs: int = 4096, eps: float = 1e-3,
                    seed: int = 0) -> float:
    """Monte-Carlo estimate of the encoding's Lipschitz constant L_Ψ (paper eq. 17), unit-box coordinates.

    L_Ψ = sup ||Ψ(x) - Ψ(y)||_2 / ||x - y||_2 with Ψ the level-weighted encoding, i.e.
    ||Ψ(x) - Ψ(y)||² = Σ_m w_m² <ψ_m(x) - ψ_m(y), ψ_m(x) - ψ_m(y)>; the encoders apply w_m to
    each level's features, so the weighted difference is the difference of their outputs. The
    sup is estimated by the max over ``n_pairs`` random pairs at distance ``eps`` (fixed
    ``seed``, so successive calls in a run use the same pairs and the curve is comparable):
    a lower bound of the true sup that approaches the largest local gradient norm.
    """
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n_pairs, 3, generator=gen) * (1 - 2 * eps) + eps
    u = torch.nn.functional.normalize(torch.randn(n_pairs, 3, generator=gen), dim=-1)
    dev = next(encoder.parameters()).device
    x, y = x.to(dev), (x + eps * u).to(dev)
    w = None if level_weights is None else level_weights.to(dev)
    diff = encoder(x.contiguous(), w) - encoder(y.contiguous(), w)
    return float((diff.norm(dim=-1) / (x - y).norm(dim=-1)).max())


def _area_downscale(img: torch.Tensor, f: int) -> torch.Tensor:
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    return img[:h, :w].reshape(h // f, f, w // f, f, -1).mean((1, 3))


def heldout_split(trainer) -> str:
    """The split the held-out PSNR reads: ``cfg.heldout_split``, or test when the scene has no val split."""
    split = trainer.cfg.heldout_split
    return split if getattr(trainer.scene, split, None) is not None else "test"


class HeldoutViews:
    """``k`` views of a held-out ``split`` (evenly spaced over it) at half resolution from 64 px up (4x cheaper
    renders), and their mean PSNR at a step (:meth:`check`): the held-out curve's views (:class:`Monitor`) and
    the val views the held-out G²fR schedule reads (``Trainer.fit``)."""

    def __init__(self, trainer, split: str, k: int):
        views = getattr(trainer.scene, split)
        if views is None:
            raise ConfigError(f"scene '{trainer.scene.name}' has no {split} split")
        self.split = split
        self.pick = torch.linspace(0, len(views) - 1, min(max(int(k), 1), len(views))).round().long()
        f = 2 if min(views.height, views.width) >= 64 else 1
        self.images = torch.stack([_area_downscale(views.images[i], f) for i in self.pick.tolist()])
        self.focal, self.cx, self.cy = views.focal / f, views.cx / f, views.cy / f

    def check(self, trainer, step: int, progress: bool = False) -> tuple[float, list[torch.Tensor]]:
        """(mean PSNR dB, the (h, w, 3) renders) of the views rendered with the field and level weights of
        ``step``; pose task: the ground-truth poses mapped by the current training-camera alignment, no refinement."""
        weights = trainer.level_weights(step)
        psnrs, preds = [], []
        # leave=False: the bar sits under the training bar while the check runs, then disappears
        bar = tqdm(zip(test_cameras(trainer, self.split)[self.pick], self.images), total=len(self.images),
                   desc=f"held-out check ({self.split}), step {step + 1}", disable=not progress, leave=False,
                   dynamic_ncols=True, unit="view")
        for c2w, gt in bar:
            out = trainer.renderer.render_image(c2w.to(trainer.device), gt.shape[0], gt.shape[1], self.focal, self.cx,
                                                self.cy, weights)
            preds.append(out["rgb"].clamp(0, 1).cpu())
            psnrs.append(M.psnr(preds[-1], gt))
        return float(sum(psnrs) / len(psnrs)), preds


class Monitor:
    """The ``Trainer.fit`` callback that records held-out PSNR and writes TensorBoard scalars."""

    def __init__(self, trainer, log_dir: Optional[str] = None, progress: bool = False):
        cfg = trainer.cfg
        self.progress = progress
        self.every = max(int(cfg.log_every), 1)
        self.heldout_every = int(cfg.heldout_every)
        self.writer = None
        if cfg.log == "tensorboard":
            try:
                from torch.utils.tensorboard import SummaryWriter  # optional extra: warpnerf[log]
            except ImportError:
                raise ConfigError("--log tensorboard needs the tensorboard package: "
                                  "pip install 'warpnerf[log]'") from None
            self.writer = SummaryWriter(log_dir or os.path.join(cfg.run_dir(), "tb"))
        elif cfg.log != "none":
            raise ConfigError(f"unknown --log '{cfg.log}': expected none or tensorboard")
        # the curve's split is heldout_split (val by default, so that settings chosen on the curve never saw a test view)
        self._heldout = (HeldoutViews(trainer, heldout_split(trainer), trainer.cfg.heldout_views)
                         if self.heldout_every > 0 else None)
        trainer.history.setdefault("heldout", [])  # (step, PSNR dB) pairs
        trainer.history.setdefault("heldout_epochs", [])  # the epochs (passes over the training pixels) at each
        trainer.history.setdefault("lipschitz", [])  # (step, L_Psi) pairs
        self._t_last, self._step_last = time.perf_counter(), -1
        self.heldout_seconds = 0.0

    def heldout_psnr(self, trainer, step: int) -> float:
        """Mean PSNR (dB) of the held-out views rendered with the field and level weights of ``step``."""
        return self._heldout.check(trainer, step)[0]

    def __call__(self, trainer, step: int, stats: dict) -> None:
        last = step == trainer.cfg.iters - 1
        values = {}
        if self._heldout is not None and ((step + 1) % self.heldout_every == 0 or last):
            t0 = time.perf_counter()
            value, preds = self._heldout.check(trainer, step, progress=self.progress)
            self.heldout_seconds += time.perf_counter() - t0
            trainer.history["heldout"].append((step, value))
            trainer.history["heldout_epochs"].append(trainer.epochs)
            values["heldout/psnr"] = value
            if self.writer is not None:  # the views side by side: (h, K w, 3)
                self.writer.add_image("heldout/prediction", _as_uint8(torch.cat(preds, dim=1)), step,
                                      dataformats="HWC")
                self.writer.add_image("heldout/ground_truth", _as_uint8(torch.cat(list(self._heldout.images), dim=1)),
                                      step, dataformats="HWC")
        if step % self.every == 0 or last:
            now = time.perf_counter()
            values.update({
                "train/loss": stats["loss"],
                "train/psnr": M.psnr_from_mse(stats["loss"]),
                "g2fr/active_levels": trainer.schedule.active_levels(step),
                "g2fr/lipschitz": lipschitz_bound(trainer.field.encoder, trainer.level_weights(step)),
                "perf/samples_per_ray": stats["samples_per_ray"],
                "perf/step_seconds": (now - self._t_last) / max(step - self._step_last, 1),
                **learning_rates(trainer),
            })
            if self.writer is not None:
                self.writer.add_image("g2fr/level_weights", level_weights_image(trainer.level_weights(step)), step,
                                      dataformats="CHW")
            self._t_last, self._step_last = now, step
            trainer.history["lipschitz"].append((step, values["g2fr/lipschitz"]))
            hist = getattr(trainer.task, "history", None)
            if hist and hist.get("rot_err_deg"):
                values["pose/rot_err_deg"] = hist["rot_err_deg"][-1]
                values["pose/trans_err_x100"] = hist["trans_err_x100"][-1]
        if self.writer is not None:
            for tag, v in values.items():
                self.writer.add_scalar(tag, float(v), step)

    def log_final(self, results: dict, step: int, split: str = "test") -> None:
        """The final metrics (``evaluate``'s psnr, ssim, lpips; lpips only when measured) as scalars at ``step``."""
        if self.writer is None:
            return
        for tag, key in zip(final_tags(split), ("psnr", "ssim", "lpips")):
            if results.get(key) is not None:
                self.writer.add_scalar(tag, float(results[key]), step)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
