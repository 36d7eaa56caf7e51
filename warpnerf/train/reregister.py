"""Re-registering training views that joint pose optimisation left in a wrong basin.

Not part of G²fR or BARF: an opt-in addition to the pose task (``pose_reregister_at``;
docs/studies/2026-12-07-mic-reregistration.md).

On mic, 1-4 of the 100 views of a run stay 5-30 deg off while the others converge to the paper's
level, and those few make the mean error (0.5-0.7 deg instead of ~0.05). By a third of the run their
photometric loss is 10-40x the median view's (a converged view: below 9x), so the loss finds them
without the ground truth (three of Mtrf's five stuck views on mic sat at 5-10x, hence the default
ratio of 5; a slow but converging view flagged at 5-9x comes in by step 1 below in a few seconds).
At ``pose_reregister_at`` of the run (and its multiples, ``pose_reregister_passes``: PoseTask) each
view above ``pose_reregister_ratio`` x the median is

1. refined where it is, the field frozen (``REFINE_STEPS`` Adam steps on ``PROBE_PIXELS`` pixels);
   a view this brings under ``pose_reregister_ratio`` x the median was slow, not lost, and stays;
2. otherwise, until its loss is below ``OK_RATIO`` x the median, searched for: poses drawn the way the noise
   was (a correction ~ N(0, s^2) per se(3) coordinate, s the spread of the other views' corrections,
   around the view's starting pose), the ``TOP`` best on ``SCREEN_PIXELS`` pixels refined as in 1,
   in two stages (successive halving): all ``TOP`` for ``HALVING_STEPS`` steps, then the ``KEEP``
   lowest on all probe pixels for the rest (a refinement's cost is linear in the poses refined).
   A round that lowers the best loss by 30 % narrows the next draw around it (``SHRINK``); a round
   that does not starts again from the whole spread. At most ``ROUNDS`` rounds.

The best pose found replaces the view's correction and that view's Adam moments are cleared. The
search never keeps a pose whose loss is higher than refining in place gave.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import torch

from warpnerf.geometry.cameras import PoseCorrection, apply_correction
from warpnerf.train.config import exp_decay
from warpnerf.train.evaluate import frozen, refine_corrections

if TYPE_CHECKING:  # the trainer's modules import this one
    from warpnerf.train.trainer import Trainer

PROBE_PIXELS = 1024  # pixels per view: the loss that flags a view, refinement and the final comparison
SCREEN_PIXELS = 128  # pixels per drawn pose in the search's first screening
DRAWS = 2000  # poses drawn per search round
TOP = 8  # drawn poses refined per round
REFINE_STEPS = 100  # Adam steps of each refinement (lr pose_lr -> pose_lr / 10)
HALVING_STEPS = 25  # a round refines all TOP poses this many steps, then only the KEEP best
KEEP = 2
OK_RATIO = 3.0  # a view is registered once its loss is below this x the median view's
ROUNDS = 16  # with successive halving a round costs ~0.4x what it did at 8 rounds
SHRINK = 0.4  # the draw's spread after a round that made progress


def probe_pixels(trainer: "Trainer", view: int, n: int, gen: torch.Generator):
    """(rows, cols, rgb) of ``n`` pixels of training view ``view``: where the view has an alpha
    channel, every other pixel from the object (a thin object such as mic covers a few % of the
    image, and uniform pixels would see mostly the background), the rest uniform."""
    img = trainer.images[view]
    h, w = img.shape[:2]
    rows = torch.randint(0, h, (n,), generator=gen)
    cols = torch.randint(0, w, (n,), generator=gen)
    alpha = trainer.views.alpha
    if alpha is not None:
        fg = (alpha[view] > 0.5).nonzero()
        if fg.shape[0] > 0:
            pick = fg[torch.randint(0, fg.shape[0], ((n + 1) // 2,), generator=gen)]
            rows[0::2], cols[0::2] = pick[:, 0], pick[:, 1]
    rows, cols = rows.to(trainer.device), cols.to(trainer.device)
    return rows, cols, img[rows, cols]


def _squared_errors(trainer: "Trainer", c2w_rays: torch.Tensor, rows, cols, target, weights) -> torch.Tensor:
    """(n,) mean squared colour error of each ray (no gradient), rendered within the sample budget."""
    views = trainer.views
    err = torch.empty(rows.shape[0], device=target.device)
    pixels = trainer.renderer.render_pixels(c2w_rays, cols.float() + 0.5, rows.float() + 0.5,
                                            (views.focal, views.cx, views.cy), weights)
    for first, rgb in pixels:
        n = rgb.shape[0]
        err[first:first + n] = (rgb - target[first:first + n]).square().mean(-1)
    return err


def _all_probe_pixels(trainer: "Trainer", n_views: int, seed: int) -> list:
    gen = torch.Generator().manual_seed(seed)
    return [probe_pixels(trainer, v, PROBE_PIXELS, gen) for v in range(n_views)]


@torch.no_grad()
def _losses_on(trainer: "Trainer", c2w: torch.Tensor, pixels: list, weights) -> torch.Tensor:
    """(N,) mean squared error of each pose in ``c2w`` (N, 3, 4) on its own ``PROBE_PIXELS`` pixels."""
    rows, cols, rgb = (torch.cat(p) for p in zip(*pixels))
    idx = torch.arange(c2w.shape[0], device=c2w.device).repeat_interleave(PROBE_PIXELS)
    err = _squared_errors(trainer, c2w.index_select(0, idx), rows, cols, rgb, weights)
    return err.view(c2w.shape[0], PROBE_PIXELS).mean(1)


def view_losses(trainer: "Trainer", c2w: torch.Tensor, weights, seed: int) -> torch.Tensor:
    """(N,) photometric loss of every training view at poses ``c2w`` (N, 3, 4): the mean squared
    error of ``PROBE_PIXELS`` probe pixels per view (drawn from ``seed``)."""
    return _losses_on(trainer, c2w, _all_probe_pixels(trainer, c2w.shape[0], seed), weights)


class _ViewSearch:
    """Poses of one view as se(3) corrections of its starting (noisy) pose, scored on fixed pixels."""

    def __init__(self, trainer: "Trainer", start_c2w: torch.Tensor, pixels, weights, frame: str):
        self.trainer, self.start, self.weights, self.frame = trainer, start_c2w, weights, frame
        self.rows, self.cols, self.rgb = pixels

    def poses(self, deltas: torch.Tensor) -> torch.Tensor:
        k = deltas.shape[0]
        return apply_correction(self.start.double().expand(k, 3, 4), deltas.double(), self.frame).float()

    @torch.no_grad()
    def losses(self, deltas: torch.Tensor, n_pixels: int, chunk: int = 256) -> torch.Tensor:
        """(k,) loss of each correction on the first ``n_pixels`` pixels."""
        rows, cols, rgb = self.rows[:n_pixels], self.cols[:n_pixels], self.rgb[:n_pixels]
        out = []
        for i in range(0, deltas.shape[0], chunk):
            c2w = self.poses(deltas[i:i + chunk])
            m = c2w.shape[0]
            err = _squared_errors(self.trainer, c2w.repeat_interleave(n_pixels, 0), rows.repeat(m), cols.repeat(m),
                                  rgb.repeat(m, 1), self.weights)
            out.append(err.view(m, n_pixels).mean(1))
        return torch.cat(out)

    def refine(self, deltas: torch.Tensor, steps: int, lr: float, lr_final: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Refine k corrections together on all pixels (rows are independent; the field must be
        frozen), the rate decaying from ``lr`` to ``lr_final``; returns the refined corrections and
        their losses."""
        k, n = deltas.shape[0], self.rows.shape[0]
        corr = PoseCorrection(k, frame=self.frame).to(deltas.device)
        with torch.no_grad():
            corr.delta.copy_(deltas)
        idx = torch.arange(k, device=deltas.device).repeat_interleave(n)
        rays = idx, (self.cols.float() + 0.5).repeat(k), (self.rows.float() + 0.5).repeat(k), self.rgb.repeat(k, 1)
        views = self.trainer.views
        refine_corrections(self.trainer, corr, self.start.expand(k, 3, 4).contiguous(), lambda _step: rays,
                           (views.focal, views.cx, views.cy), self.weights, steps, lr, lr_final)
        refined = corr.delta.detach().clone()
        return refined, self.losses(refined, n)


def _refine_halving(search: _ViewSearch, deltas: torch.Tensor, lr: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``search.refine`` over REFINE_STEPS steps (rate lr -> lr / 10) for the ``KEEP`` of ``deltas`` that
    are lowest after the first ``HALVING_STEPS`` (the others stop there); returns those KEEP."""
    def rate(step: int) -> float:  # one REFINE_STEPS schedule (refine_corrections'), split in two
        return exp_decay(lr, 0.1 * lr, step / (REFINE_STEPS - 1))

    early, early_loss = search.refine(deltas, HALVING_STEPS, rate(0), rate(HALVING_STEPS - 1))
    keep = torch.argsort(early_loss)[:KEEP]
    return search.refine(early[keep], REFINE_STEPS - HALVING_STEPS, rate(HALVING_STEPS), rate(REFINE_STEPS - 1))


def reregister_views(trainer: "Trainer", correction: "PoseCorrection", start_c2w: torch.Tensor,
                     optimizer: torch.optim.Optimizer, step: int, ratio: float, lr: float) -> list[dict]:
    """Find the views whose loss exceeds ``ratio`` x the median view's and register them again
    (module docstring). Changes ``correction`` and ``optimizer``'s moments of those views in place;
    returns one dict per flagged view: view, loss ratios before / after (on the pixels that flagged
    it), rounds searched, the best ratio on the search's own pixels after refining in place and after
    each round (``ratio_by_round``), seconds."""
    seed = trainer.cfg.seed * 1000 + step
    weights = trainer.level_weights(step)
    with torch.no_grad():
        current = correction(start_c2w)
    probes = _all_probe_pixels(trainer, current.shape[0], seed)
    losses = _losses_on(trainer, current, probes, weights)
    median = float(losses.median())
    flagged = [int(v) for v in torch.nonzero(losses > ratio * median).flatten()]
    if not flagged:
        return []
    deltas = correction.delta.detach()
    others = torch.ones(deltas.shape[0], dtype=torch.bool, device=deltas.device)
    others[flagged] = False
    # the spread of the other views' corrections: how far the noise moved a pose (with one view
    # left, fall back to the flagged views' own spread)
    spread = (deltas[others] if int(others.sum()) > 1 else deltas).std(0)
    gen = torch.Generator().manual_seed(seed + 1)
    results = []
    with frozen(trainer.field):
        for v in flagged:
            t0 = time.perf_counter()
            search = _ViewSearch(trainer, start_c2w[v:v + 1], probe_pixels(trainer, v, PROBE_PIXELS, gen), weights,
                                 correction.frame)
            best, best_loss = search.refine(deltas[v:v + 1].clone(), REFINE_STEPS, lr, 0.1 * lr)
            best, best_loss = best[0], float(best_loss[0])
            centre, scale, rounds = torch.zeros_like(spread), spread.clone(), 0
            trace = [best_loss / median]  # the best loss ratio after refining in place, then after each round
            # under the flag ratio after refining in place: slow, not lost (mic: such views, 3.4-3.8x,
            # gained nothing in 8 rounds and converged in training anyway)
            lost = best_loss > ratio * median
            while lost and best_loss > OK_RATIO * median and rounds < ROUNDS:
                rounds += 1
                draws = centre + torch.randn(DRAWS, 6, generator=gen).to(spread.device) * scale
                pick = torch.argsort(search.losses(draws, SCREEN_PIXELS))[:TOP]
                refined, refined_loss = _refine_halving(search, draws[pick], lr)
                i = int(torch.argmin(refined_loss))
                progress = float(refined_loss[i]) < 0.7 * best_loss
                if float(refined_loss[i]) < best_loss:
                    best, best_loss = refined[i], float(refined_loss[i])
                # progress: look closer around the new best; none: start again from the whole spread
                centre, scale = (best, scale * SHRINK) if progress else (torch.zeros_like(spread), spread.clone())
                trace.append(best_loss / median)
            with torch.no_grad():
                correction.delta[v] = best
                registered = correction(start_c2w[v:v + 1], torch.tensor([v]))
            # the ratio after on the pixels that flagged the view (the search scores its own pixels)
            after = float(_losses_on(trainer, registered, probes[v:v + 1], weights)[0])
            state = optimizer.state.get(correction.delta, {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key][v] = 0.0
            results.append({"view": v, "step": step, "loss_ratio_before": float(losses[v]) / median,
                            "loss_ratio_after": after / median, "rounds": rounds,
                            "ratio_by_round": trace, "seconds": time.perf_counter() - t0})
    return results
