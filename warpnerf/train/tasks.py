"""Tasks decide which views train, how cameras are posed, and how a run is evaluated.

A task is an object with a few hooks the :class:`warpnerf.train.trainer.Trainer` calls; the training
loop itself never asks which task it runs.

* ``full``    all training views, known poses;
* ``fewshot`` N views chosen by a deterministic rule (or a named list), known poses;
* ``pose``    all training views with BARF-style noisy poses, jointly optimised (DESIGN §5).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Optional

import torch
from tqdm.auto import tqdm

from warpnerf.data.scene import Scene, Views
from warpnerf.geometry.cameras import (PoseCorrection, barf_pose_errors, evaluate_poses, map_gt_poses_to_estimate_frame,
                                       perturb_poses)
from warpnerf.train import plots, reregister
from warpnerf.train.config import ConfigError, TrainConfig, exp_decay
from warpnerf.train.evaluate import refine_poses

if TYPE_CHECKING:
    from warpnerf.train.trainer import Trainer

# FreeNeRF's 8 NeRF-synthetic training views (ids in transforms_train.json)
NAMED_VIEW_LISTS = {"freenerf8": [26, 86, 2, 55, 75, 93, 16, 73]}


class Task:
    """Base task: every training view with its known pose."""

    name = "full"

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg

    def train_views(self, scene: Scene) -> Views:
        return scene.train

    def setup(self, trainer: "Trainer") -> None:
        """Create task state (e.g. pose parameters) once the trainer exists."""

    def caveat(self, scene: Scene) -> Optional[str]:
        """One line the run prints before training when this task has a known problem on ``scene``, else None."""
        return None

    def camera_poses(self, trainer: "Trainer", idx: torch.Tensor) -> torch.Tensor:
        """(B, 3, 4) c2w of training views ``idx`` (differentiable when poses are learned)."""
        return trainer.train_c2w[idx]

    def optimizer_step(self, trainer: "Trainer", step: int) -> None:
        """Step task-owned optimisers after the loss backward."""

    def after_step(self, trainer: "Trainer", step: int) -> dict:
        """Extra progress values to log (small dict)."""
        return {}

    def eval_poses(self, trainer: "Trainer", views: Views) -> torch.Tensor:
        """(N, 3, 4) poses to render the evaluation views from: their known poses, refined photometrically
        first with ``refine_test_poses`` (a capture's held-out photos carry COLMAP's errors too)."""
        c2w = views.c2w.to(trainer.device)
        if self.cfg.refine_test_poses and self.cfg.pose_refine_steps > 0:
            return refine_poses(trainer, c2w, views)
        return c2w

    def metrics(self, trainer: "Trainer") -> dict:
        return {}

    def artifacts(self, trainer: "Trainer", out_dir: str) -> None:
        """Task plots and files written after evaluation."""

    def state_dict(self) -> dict:
        """The task's own training state for checkpoints (tensors, numbers, lists, dicts)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned."""


class FullTask(Task):
    name = "full"


def farthest_view_order(c2w: torch.Tensor, n: int, start: int = 0) -> list[int]:
    """Greedy farthest-point sampling of camera centres: start at view ``start``, then repeatedly
    add the view farthest from all chosen ones. Deterministic and spreads views over the sphere."""
    centres = c2w[:, :, 3].double()
    chosen = [start]
    dist = (centres - centres[start]).norm(dim=-1)
    while len(chosen) < min(n, centres.shape[0]):
        nxt = int(torch.argmax(dist))
        chosen.append(nxt)
        dist = torch.minimum(dist, (centres - centres[nxt]).norm(dim=-1))
    return chosen


def random_view_order(n_total: int, n: int, seed: int) -> list[int]:
    """``n`` distinct positions of ``n_total``, drawn with their own generator seeded by ``seed``: the
    same set for both arms of a seed, another set for another seed, whatever else the run draws."""
    return torch.randperm(n_total, generator=torch.Generator().manual_seed(int(seed)))[:n].tolist()


class FewShotTask(Task):
    """Train on ``n_views`` views: ``view_set`` fps (farthest-point sampling over camera centres from
    view 0, the same for every seed) or random (drawn with the seed), or ``views`` (a named list such as
    ``freenerf8``, or comma-separated ids of transforms_train.json)."""

    name = "fewshot"

    def selected_ids(self, views: Views) -> list[int]:
        spec = self.cfg.views.strip()
        if not spec:
            if not 1 <= self.cfg.n_views <= len(views):
                raise ConfigError(f"n_views must be in [1, {len(views)}], got {self.cfg.n_views}")
            if self.cfg.view_set == "random":
                return [views.ids[i] for i in random_view_order(len(views), self.cfg.n_views, self.cfg.seed)]
            return [views.ids[i] for i in farthest_view_order(views.c2w, self.cfg.n_views)]
        if spec in NAMED_VIEW_LISTS:
            return list(NAMED_VIEW_LISTS[spec])
        try:
            return [int(s) for s in spec.split(",") if s.strip()]
        except ValueError:
            raise ConfigError(f"views must be one of {sorted(NAMED_VIEW_LISTS)} or comma-separated ids, got '{spec}'") from None

    def train_views(self, scene: Scene) -> Views:
        ids = self.selected_ids(scene.train)
        pos = {vid: i for i, vid in enumerate(scene.train.ids)}
        missing = [i for i in ids if i not in pos]
        if missing:
            raise ConfigError(f"views {missing} are not training views of '{scene.name}' (ids 0..{len(scene.train) - 1})")
        return scene.train.subset([pos[i] for i in ids])


NOISE_SIGMA_SYNTHETIC = 0.15  # BARF's / the paper's pose noise on synthetic scenes
NOISE_SIGMA_REAL = 0.01  # the paper's pose noise on real scenes (MipNeRF-360)


def identity_poses(n: int, dtype: torch.dtype, device) -> torch.Tensor:
    """(n, 3, 4) copies of [I | 0]: every camera at the origin looking down -z. In a recentred LLFF
    scene that is the average pose, BARF's start on LLFF ("identity")."""
    return torch.eye(3, 4, dtype=dtype, device=device).expand(n, 3, 4).clone()


class PoseTask(Task):
    """Joint camera-pose optimisation from BARF-perturbed poses (DESIGN §5)."""

    name = "pose"

    def __init__(self, cfg: TrainConfig):
        super().__init__(cfg)
        # trans_err_x100 is BARF's (aligned w2c translations), centre_err_x100 the camera-centre distance
        self.history: dict[str, list] = {"step": [], "rot_err_deg": [], "trans_err_x100": [], "centre_err_x100": [],
                                         "rot_err_deg_unaligned": []}
        self.initial: dict = {}
        self.final: dict = {}
        self.reregistered: list[dict] = []  # warpnerf.train.reregister's report, one dict per view searched for
        self.alignment = "centres"  # set from the scene in setup (alignment_for)

    def train_views(self, scene: Scene) -> Views:
        if self.cfg.pose_init == "identity" and not scene.ray_space.forward_facing:
            # every camera at one pose sees the same image: only a forward-facing rig, whose cameras
            # all look one way, can be registered from there (BARF does it on LLFF only)
            raise ConfigError(f"pose_init identity starts every camera at the average pose, which only suits a "
                              f"forward-facing (LLFF-layout) scene; '{scene.name}' is not one: use pose_init noise")
        return scene.train

    def caveat(self, scene: Scene) -> Optional[str]:
        # measured on fern (docs/studies/2026-12-07-pose-forward-facing.md): Procrustes on nearly planar
        # camera centres turned the cameras by 6 deg
        if scene.ray_space.forward_facing:
            return ("note: on forward-facing (NDC) scenes the pose errors take the alignment's rotation from the "
                    "cameras' orientations (BARF's, from camera centres that barely span 3-D, turned fern by 6 deg): "
                    "not comparable with BARF's LLFF figures")
        return None

    @staticmethod
    def alignment_for(scene: Scene) -> str:
        """How estimated poses are aligned to the ground truth (``cameras.evaluate_poses``' ``align``):
        BARF's centres, except on forward-facing scenes, whose centres leave the rotation ill-determined."""
        return "orientations" if scene.ray_space.forward_facing else "centres"

    def _barf_means(self, c2w: torch.Tensor) -> dict:
        """BARF's own figures (its evaluation code: centre alignment with its reflection fix, float32
        arccos clamped at ~0.028 deg per view), beside ours in every pose table."""
        with torch.no_grad():
            barf = barf_pose_errors(c2w, self.gt_c2w)
        return {"rot_err_deg_barf": barf["rot_err_deg_barf"], "trans_err_x100_barf": barf["trans_err_x100_barf"],
                "rot_err_deg_barf_per_view": barf["rot_err_deg_barf_per_view"]}

    def evaluate(self) -> dict:
        """:func:`warpnerf.geometry.cameras.evaluate_poses` of the current training poses (no gradient)."""
        with torch.no_grad():
            return evaluate_poses(self.current_c2w(), self.gt_c2w, self.alignment)

    def noise_sigmas(self, scene: Scene) -> tuple[float, float]:
        # the paper's settings: 0.15 on synthetic scenes, 0.01 on real captures (LLFF, COLMAP, transforms.json)
        default = NOISE_SIGMA_SYNTHETIC if scene.kind == "blender" else NOISE_SIGMA_REAL
        base = self.cfg.pose_noise if self.cfg.pose_noise is not None else default
        rot = self.cfg.pose_noise_rot if self.cfg.pose_noise_rot is not None else base
        trans = self.cfg.pose_noise_trans if self.cfg.pose_noise_trans is not None else base
        return rot, trans

    def setup(self, trainer: "Trainer") -> None:
        self.alignment = self.alignment_for(trainer.scene)
        gt = trainer.train_c2w
        rot, trans = self.noise_sigmas(trainer.scene)
        # its own generator: the same seed gives the same noise with and without G²fR
        gen = torch.Generator().manual_seed(self.cfg.seed + 1)
        self.gt_c2w = gt.detach().clone()
        if self.cfg.pose_init == "identity":
            self.noisy_c2w = identity_poses(gt.shape[0], gt.dtype, trainer.device)
            rot = trans = 0.0
        else:
            self.noisy_c2w = perturb_poses(gt.cpu(), rot, trans, generator=gen).to(trainer.device)
        self.sigmas = (rot, trans)
        self.correction = PoseCorrection(gt.shape[0]).to(trainer.device)
        # Adam moves each parameter by ~lr per step whatever the gradient's size, so a rate tuned for
        # sigma = 0.15 throws poses with sigma = 0.01 far off while the field is still blurry
        # (garden, 3e-3: 0.94 deg at step 0, 5.4 deg at step 130); scale it with the noise. From the
        # average pose the cameras start as far off as the rig is wide: BARF's rates, unscaled.
        # With no noise (--pose-noise 0: refining a capture's COLMAP poses, whose errors are unknown but
        # small), the rates are scaled as for the paper's real-scene sigma, not to zero (no refinement).
        by_noise = self.cfg.pose_lr_by_noise and self.cfg.pose_init == "noise"
        sigma = max(rot, trans) or NOISE_SIGMA_REAL
        self.lr_scale = min(sigma / NOISE_SIGMA_SYNTHETIC, 1.0) if by_noise else 1.0
        self.optimizer = torch.optim.Adam(self.correction.parameters(), lr=self.cfg.pose_lr * self.lr_scale)
        init = evaluate_poses(self.noisy_c2w, self.gt_c2w, self.alignment)
        self.initial = {k: init[k] for k in ("rot_err_deg", "trans_err_x100", "centre_err_x100", "rot_err_deg_unaligned")}
        self.initial.update(self._barf_means(self.noisy_c2w))
        self._record(0)

    def state_dict(self) -> dict:
        return {"correction": self.correction.state_dict(), "optimizer": self.optimizer.state_dict(),
                "history": self.history, "reregistered": self.reregistered}

    def load_state_dict(self, state: dict) -> None:
        self.correction.load_state_dict(state["correction"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.history = {k: list(v) for k, v in state["history"].items()}
        self.reregistered = list(state.get("reregistered", []))

    def current_c2w(self) -> torch.Tensor:
        return self.correction(self.noisy_c2w)

    def camera_poses(self, trainer: "Trainer", idx: torch.Tensor) -> torch.Tensor:
        return self.correction.for_rays(self.noisy_c2w, idx)

    def optimizer_step(self, trainer: "Trainer", step: int) -> None:
        lr = self.lr_scale * exp_decay(self.cfg.pose_lr, self.cfg.pose_lr_final, step / max(self.cfg.iters - 1, 1))
        for g in self.optimizer.param_groups:
            g["lr"] = lr
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def _record(self, step: int) -> dict:
        ev = self.evaluate()
        self.history["step"].append(step)
        self.history["rot_err_deg"].append(ev["rot_err_deg"])
        self.history["trans_err_x100"].append(ev["trans_err_x100"])
        self.history["centre_err_x100"].append(ev["centre_err_x100"])
        self.history.setdefault("rot_err_deg_unaligned", []).append(ev["rot_err_deg_unaligned"])
        # the part every camera shares (x100, camera axes): docs/studies/2026-12-07-pose-translation-offset.md
        self.history.setdefault("trans_offset_cam_x100", []).append(ev["trans_offset_cam_x100"])
        return ev

    def reregister_steps(self) -> list[int]:
        """The steps after which views are searched for again: at ``pose_reregister_at`` of the run
        and its multiples, ``pose_reregister_passes`` at most (a pass at or past the run's end is
        dropped: with 0.5, one pass); none when off."""
        at = self.cfg.pose_reregister_at
        if at <= 0:
            return []
        passes = [k * at for k in range(1, self.cfg.pose_reregister_passes + 1)]
        return [max(int(round(f * self.cfg.iters)) - 1, 0) for f in passes if f < 1.0]

    def after_step(self, trainer: "Trainer", step: int) -> dict:
        if step in self.reregister_steps():
            self._reregister(trainer, step + 1)
        # same cadence as the trainer's progress line, so the bar shows the errors
        if step % max(self.cfg.log_every, 1) == 0 or step + 1 == self.cfg.iters:
            ev = self._record(step + 1)
            return {"rot": f"{ev['rot_err_deg']:.3f}", "trans": f"{ev['trans_err_x100']:.2f}"}
        return {}

    def _reregister(self, trainer: "Trainer", step: int) -> None:
        found = reregister.reregister_views(trainer, self.correction, self.noisy_c2w, self.optimizer, step,
                                 self.cfg.pose_reregister_ratio, self.cfg.pose_lr * self.lr_scale)
        self.reregistered.extend(found)
        if found:
            tqdm.write(f"step {step}: re-registered {len(found)} view(s) whose loss was > "
                       f"{self.cfg.pose_reregister_ratio:g}x the median view's: "
                       + ", ".join(f"{r['view']} ({r['loss_ratio_before']:.1f}x -> {r['loss_ratio_after']:.1f}x)"
                                   for r in found)
                       + f" in {sum(r['seconds'] for r in found):.0f} s")
        else:
            tqdm.write(f"step {step}: no view's loss is > {self.cfg.pose_reregister_ratio:g}x the median view's; "
                       "nothing to re-register")

    def eval_poses(self, trainer: "Trainer", views: Views) -> torch.Tensor:
        """Test poses mapped into the optimised frame by the training-camera Sim(3) alignment, then
        refined photometrically (``pose_refine_steps`` Adam steps per view, field frozen)."""
        ev = self.evaluate()
        self.final = {**ev, **self._barf_means(self.current_c2w())}
        # on forward-facing scenes the alignment's rotation is the orientations' (alignment_for): the
        # centres' was ill-determined, and test views mapped by it started 6 deg off (fern: 12.83 dB)
        mapped = map_gt_poses_to_estimate_frame(views.c2w.to(trainer.device).double(), ev["sim3"]).float()
        if self.cfg.pose_refine_steps <= 0:
            return mapped
        return refine_poses(trainer, mapped, views)

    def metrics(self, trainer: "Trainer") -> dict:
        ev = self.final
        return {
            "rot_err_deg": ev["rot_err_deg"],
            "trans_err_x100": ev["trans_err_x100"],
            "rot_err_deg_median": ev["rot_err_deg_median"],
            "trans_err_x100_median": ev["trans_err_x100_median"],
            "unconverged_views": ev["unconverged_views"],
            "rot_err_deg_per_view": ev["rot_err_deg_per_view"],
            "trans_err_x100_per_view": ev["trans_err_x100_per_view"],
            "centre_err_x100": ev["centre_err_x100"],
            "centre_err_x100_per_view": ev["centre_err_x100_per_view"],
            "rot_err_deg_unaligned": ev["rot_err_deg_unaligned"],
            "initial_rot_err_deg_unaligned": self.initial["rot_err_deg_unaligned"],
            "rot_offset_cam_deg": ev["rot_offset_cam_deg"],
            "trans_offset_cam_x100": ev["trans_offset_cam_x100"],
            "rot_err_deg_barf": ev["rot_err_deg_barf"],
            "trans_err_x100_barf": ev["trans_err_x100_barf"],
            "rot_err_deg_barf_per_view": ev["rot_err_deg_barf_per_view"],
            "initial_rot_err_deg_barf": self.initial["rot_err_deg_barf"],
            "initial_trans_err_x100_barf": self.initial["trans_err_x100_barf"],
            "pose_init": self.cfg.pose_init,
            "initial_rot_err_deg": self.initial["rot_err_deg"],
            "initial_trans_err_x100": self.initial["trans_err_x100"],
            "initial_centre_err_x100": self.initial["centre_err_x100"],
            "pose_noise_rot": self.sigmas[0],
            "pose_noise_trans": self.sigmas[1],
            "pose_error_history": self.history,
            "reregistered": self.reregistered,
            "pose_alignment": self.alignment,
        }

    def artifacts(self, trainer: "Trainer", out_dir: str) -> None:
        plots.plot_cameras(os.path.join(out_dir, "cameras.png"), self.gt_c2w.cpu(), self.noisy_c2w.cpu(),
                           self.final["c2w_aligned"].cpu(), title=f"{trainer.scene.name}: camera poses")
        plots.plot_pose_error_curve(os.path.join(out_dir, "pose_error.png"), self.history["step"],
                                    self.history["rot_err_deg"], self.history["trans_err_x100"],
                                    rot_label=("rotation error, orientations aligned (degrees)"
                                               if self.alignment == "orientations" else None),
                                    events=self.reregistration_events())

    def reregistration_events(self) -> dict[int, str]:
        """Step -> "N view(s) re-registered" for each pass that searched for views (the pose-error
        plot's markers; which views: metrics.json, the run's summary)."""
        counts: dict[int, int] = {}
        for r in self.reregistered:
            counts[r["step"]] = counts.get(r["step"], 0) + 1
        return {step: f"{n} view{'s' if n > 1 else ''} re-registered" for step, n in counts.items()}


TASKS = {cls.name: cls for cls in (FullTask, FewShotTask, PoseTask)}


def make_task(cfg: TrainConfig) -> Task:
    try:
        return TASKS[cfg.task](cfg)
    except KeyError:
        raise ConfigError(f"unknown task '{cfg.task}': expected one of {sorted(TASKS)}") from None
