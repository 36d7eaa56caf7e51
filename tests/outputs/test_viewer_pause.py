"""Pause and resume of a live training from ``warpnerf view`` (issue #65): ``RUN/PAUSE`` holds the
training between two steps (checkpoint saved, the wait not counted as training time), and the
viewer's panel presses it, shows it, and draws the pose task's estimated, initial and true cameras."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from test_viewer import _wait_until
from warpnerf.train.pause import PAUSE_FILE, wait_while_paused


def test_wait_while_paused_holds_until_the_file_goes_or_a_stop(tmp_path):
    assert wait_while_paused(str(tmp_path), 3) == 0.0  # no file: at once
    pause = tmp_path / PAUSE_FILE
    pause.write_text("")
    saved = []
    timer = threading.Timer(0.6, pause.unlink)
    timer.start()
    waited = wait_while_paused(str(tmp_path), 3, on_pause=lambda: saved.append(1), poll=0.05)
    timer.join()
    assert saved == [1] and 0.5 <= waited < 10 and not pause.exists()
    # Ctrl-C (the run's stop flag) ends a pause; the file stays
    pause.write_text("")
    stop = threading.Event()
    timer = threading.Timer(0.3, stop.set)
    timer.start()
    waited = wait_while_paused(str(tmp_path), 3, should_stop=stop.is_set, poll=0.05)
    timer.join()
    assert 0.25 <= waited < 10 and pause.exists()


TINY = """
occ_resolution = 32
occ_warmup = 8
occ_update_every = 4
march_steps = 128
levels = 8
log2_table_size = 14
max_resolution = 256
batch_rays = 256
target_samples = 4096
eval_max_views = 1
pose_refine_steps = 2
"""


def test_the_viewer_pauses_and_resumes_a_live_training(tmp_path):
    pytest.importorskip("viser")
    from warpnerf.outputs.viewer import RunViewer, serve, viser_from_c2w, wait_for_checkpoint

    (tmp_path / "tiny.toml").write_text(TINY)
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "warpnerf.cli", "train", "--quiet", "--task", "pose", "--scene", "chair",
         "--builtin-resolution", "40", "--iters", "2000", "--checkpoint-every", "5", "--threads", "1",
         "--video-frames", "0", "--config", str(tmp_path / "tiny.toml"), "--out", str(run)],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stop, apps = threading.Event(), []
    thread = None
    try:
        assert wait_for_checkpoint(str(run), 300), "the training never saved a checkpoint"
        viewer = RunViewer(str(run), "cpu", preview_height=16)
        state = viewer.training_state()
        assert state.live and not state.pause_file and not state.finished and state.text == "training"
        thread = threading.Thread(target=serve, args=(viewer, "127.0.0.1", 0, 0.2, stop),
                                  kwargs=dict(ready=apps.append), daemon=True)
        thread.start()
        assert _wait_until(lambda: apps, 60)
        app = apps[0]
        assert app.pause.label == "Pause training" and not app.pause.disabled

        app.pause.value = True  # the button's click
        assert (run / PAUSE_FILE).exists() and app.pause.label == "Resume training"
        assert _wait_until(lambda: app.training.paused, 120), app.status.content
        paused_at = viewer.step
        assert f"paused at step {paused_at}" in app.status.content
        at_pause = torch.load(run / "checkpoint.pt", weights_only=True)
        assert at_pause["step"] == paused_at  # saved on pausing: the viewer shows the step it waits at
        mtime = os.path.getmtime(run / "checkpoint.pt")
        time.sleep(4.0)
        assert proc.poll() is None and os.path.getmtime(run / "checkpoint.pt") == mtime  # waiting, not training

        # the pose task's cameras: estimated (moved by training), initial (noisy) and true, one frustum each
        sets = viewer.camera_sets()
        n_train = len(viewer.trainer.train_c2w)
        assert set(sets) == {"train", "test", "initial", "true"}
        assert all(len(app.frustums[k]) == n_train for k in ("train", "initial", "true"))
        assert sets["train"].c2w.shape == sets["initial"].c2w.shape == (n_train, 3, 4)
        assert (sets["train"].c2w - sets["initial"].c2w).abs().max() > 1e-6

        app.pause.value = True  # Resume
        assert not (run / PAUSE_FILE).exists() and app.pause.label == "Pause training"
        assert _wait_until(lambda: viewer.step > paused_at, 120), "the training did not resume"
        after = torch.load(run / "checkpoint.pt", weights_only=True)
        # the pause (over 4 s) is not training time: counted, the 5 steps since would add more than 4 s
        assert after["train_seconds"] - at_pause["train_seconds"] < 4.0, (at_pause["train_seconds"],
                                                                          after["train_seconds"])
        # the frustums follow the new checkpoint's estimated poses
        assert _wait_until(lambda: np.allclose(app.frustums["train"][0].position,
                                          viser_from_c2w(viewer.camera_sets()["train"].c2w[0])[0], atol=1e-5), 10)
        assert "training" in app.status.content and app.training.live
    finally:
        stop.set()
        if thread is not None:
            thread.join(30)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=300)
    assert f"paused after step {paused_at}: {run / PAUSE_FILE} exists" in out, out
    assert "resumed after" in out, out
    assert not viewer.training_state().live
