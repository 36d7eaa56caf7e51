"""A trained run's cameras in the frame its field was trained in.

For the pose task that frame is the one of the *optimised* training cameras: test cameras are
mapped into it by the training cameras' Sim(3) alignment (no photometric refinement). The held-out
PSNR (:mod:`warpnerf.train.monitor`), the videos (:mod:`warpnerf.runs.video`), the viewer and the
point-cloud export all place their cameras with these two functions.
"""

from __future__ import annotations

import torch

from warpnerf.geometry.cameras import map_gt_poses_to_estimate_frame


def training_cameras(trainer) -> torch.Tensor:
    """(N, 3, 4) training cameras in the field's frame (the optimised ones for the pose task)."""
    if hasattr(trainer.task, "current_c2w"):
        with torch.no_grad():
            return trainer.task.current_c2w().detach().cpu().float()
    return trainer.train_c2w.detach().cpu().float()


def test_cameras(trainer, split: str = "test") -> torch.Tensor:
    """(N, 3, 4) cameras of a held-out ``split`` (test or val) in the field's frame (pose task: mapped by
    the Sim(3) alignment)."""
    c2w = getattr(trainer.scene, split).c2w
    task = trainer.task
    if hasattr(task, "current_c2w"):
        c2w = map_gt_poses_to_estimate_frame(c2w.to(task.gt_c2w.device).double(), task.evaluate()["sim3"]).float()
    return c2w.detach().cpu().float()
