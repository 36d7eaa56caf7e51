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


# a 40-step run on a loaded scene, for comparing one scene's loads (tests/data/test_colmap.py, test_rig_framing.py)
SHORT_RUN = dict(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128, hidden=32, target_samples=8192,
                 batch_rays=512, occ_resolution=32, occ_warmup=16, occ_update_every=8, log_every=20, lr=2e-2,
                 video_frames=0, iters=40, seed=0)


def short_run_psnr(scene):
    """Test PSNR of :data:`SHORT_RUN` trained on ``scene`` with one thread (identical float reductions
    in every run compared)."""
    from warpnerf import device
    from warpnerf.train.evaluate import evaluate

    before = device.num_threads()
    device.set_num_threads(1)
    try:
        cfg = build_config("full", overrides=SHORT_RUN)
        trainer = Trainer(cfg, scene, make_task(cfg), "cpu")
        trainer.fit(progress=False)
        return evaluate(trainer, None, progress=False)["psnr"]
    finally:
        device.set_num_threads(before)
