"""Diagnose the camera-frame offset the pose task's errors share (README, "Pose within the 20-minute budget").

    python docs/analysis/pose_offset.py run RUN          # a finished pose run: shared offsets at the start and the end
    python docs/analysis/pose_offset.py noise RUN [--draws 20]  # the evaluation on mean-zero noise around the GT poses
    python docs/analysis/pose_offset.py refine RUN [--views 100] [--steps 200]  # a full-task run: refine GT poses

"Shared offset" = the mean over views of BARF's w2c translation error (x100) and of the rotation error
log(R_gt^T R), both in each camera's own frame, after the Sim(3) alignment of the camera centres
(:func:`warpnerf.geometry.cameras.evaluate_poses`). An analysis tool, not part of the package.
"""

import argparse
import os

import torch

from warpnerf import device as devmod
from warpnerf.geometry.cameras import camera_frame_residuals, evaluate_poses, perturb_poses
from warpnerf.runs.folder import load_scene_for, read_run_config
from warpnerf.train.checkpoint import load_checkpoint
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

def fmt(v: torch.Tensor) -> str:
    return "(" + ", ".join(f"{x:+.4f}" for x in v.tolist()) + ")"


def load_trainer(run: str) -> Trainer:
    cfg = read_run_config(run)
    trainer = Trainer(cfg, load_scene_for(cfg, False), make_task(cfg), devmod.resolve_device("cpu"))
    trainer.load_state_dict(load_checkpoint(os.path.join(run, "checkpoint.pt"), map_location="cpu"))
    return trainer


def report(name: str, est: torch.Tensor, gt: torch.Tensor) -> None:
    ev = evaluate_poses(est, gt)
    dt, w = camera_frame_residuals(ev["c2w_aligned"].double(), gt.double())
    print(f"{name}: rot {ev['rot_err_deg']:.4f} deg, trans x100 {ev['trans_err_x100']:.4f}; shared t {fmt(dt.mean(0))}, "
          f"without it {(dt - dt.mean(0)).norm(dim=1).mean():.4f}; shared rot {fmt(w.mean(0))} deg")
    # how t_y depends on the camera's elevation above the world's xy plane (+z up, Blender's frame)
    c = gt[:, :, 3].double()
    cos_el = c[:, :2].norm(dim=1) / c.norm(dim=1)
    a, b = torch.linalg.lstsq(torch.stack([cos_el, torch.ones_like(cos_el)], 1), dt[:, 1:2]).solution.flatten().tolist()
    print(f"       t_y ~ {a:+.4f} cos(elevation) {b:+.4f}")


def cmd_run(args) -> None:
    task = load_trainer(args.run).task
    with torch.no_grad():
        report("start", task.noisy_c2w, task.gt_c2w)
        report("end  ", task.current_c2w(), task.gt_c2w)


def cmd_noise(args) -> None:
    gt = load_scene_for(read_run_config(args.run), False).train.c2w.double()
    for sigma in (0.001, 0.003):
        ty = torch.tensor([evaluate_poses(perturb_poses(gt, sigma, sigma, torch.Generator().manual_seed(100 + k)), gt)
                           ["trans_offset_cam_x100"][1] for k in range(args.draws)])
        print(f"sigma {sigma}: shared t_y over {args.draws} draws: mean {ty.mean():+.4f}, sd {ty.std():.4f}")


def cmd_refine(args) -> None:
    from warpnerf.train.evaluate import refine_poses

    trainer = load_trainer(args.run)
    trainer.cfg.pose_refine_steps, trainer.cfg.pose_lr, trainer.cfg.pose_lr_final = args.steps, 1e-3, 1e-5
    views = trainer.scene.train
    views = views.subset(list(range(0, len(views), max(1, len(views) // args.views)))[: args.views])
    gt = views.c2w.to(trainer.device).float()
    dt, w = camera_frame_residuals(refine_poses(trainer, gt, views).double(), gt.double())
    n = dt.shape[0] ** 0.5
    print(f"{dt.shape[0]} GT poses refined: shared t {fmt(dt.mean(0))} +- {fmt(dt.std(0) / n)} (standard error); "
          f"shared rot {fmt(w.mean(0))} +- {fmt(w.std(0) / n)} deg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    sub.add_parser("run").add_argument("run")
    p = sub.add_parser("noise")
    p.add_argument("run")
    p.add_argument("--draws", type=int, default=20)
    p = sub.add_parser("refine")
    p.add_argument("run")
    p.add_argument("--views", type=int, default=100)
    p.add_argument("--steps", type=int, default=200)
    args = parser.parse_args()
    {"run": cmd_run, "noise": cmd_noise, "refine": cmd_refine}[args.cmd](args)


if __name__ == "__main__":
    main()
