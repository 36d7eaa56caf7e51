"""The tiny trainer the training tests share: a small hash grid and batch on the tiny analytic scene."""

from tiny_scene import tiny_scene
from warpnerf.train.config import build_config
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer

TINY = dict(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128, hidden=32, target_samples=16384,
            batch_rays=512, occ_resolution=32, occ_warmup=32, occ_update_every=8, log_every=20, lr=2e-2,
            video_frames=0)


def make_trainer(task="full", size=32, **kw):
    cfg = build_config(task, overrides={**TINY, **kw})
    return Trainer(cfg, tiny_scene(size=size), make_task(cfg), "cpu")
