"""A full disk while a run writes its checkpoint or metrics (issue #64): one line, exit 2, the last good
checkpoint kept, and the run continues from it with ``--resume`` once there is space.

The disk fills inside the real atomic writer (``warpnerf.train.checkpoint.atomic_write_bytes``): the write
callback puts some bytes in the temp file, then raises OSError(ENOSPC) as a full file system does.
"""

from __future__ import annotations

import errno
import json
import os

import pytest
import torch

import warpnerf.train.checkpoint as ckpt_mod
from door import one_line_error
from warpnerf.cli import main

TINY = ["--builtin-resolution", "16", "--levels", "4", "--log2-table-size", "12", "--hidden", "16", "--batch-rays", "64",
        "--occ-resolution", "16", "--march-steps", "32", "--eval-max-views", "1", "--heldout-every", "0"]


def train_args(out):
    return ["train", "--quiet", "--task", "fewshot", "--iters", "6", "--checkpoint-every", "2", "--threads", "1",
            "--video-frames", "0", *TINY, "--out", str(out)]


def fill_disk_at(monkeypatch, name: str, nth: int) -> list:
    """From the ``nth`` atomic write of a file called ``name`` on, the disk is full; returns the write log."""
    real, seen = ckpt_mod.atomic_write_bytes, []

    def writer(path, write):
        if os.path.basename(path) == name:
            seen.append(path)
            if len(seen) >= nth:
                def write_then_fail(fh):
                    fh.write(b"the first bytes fit")
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

                return real(path, write_then_fail)
        return real(path, write)

    monkeypatch.setattr(ckpt_mod, "atomic_write_bytes", writer)
    return seen


@pytest.fixture(autouse=True)
def scene_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))


def leftovers(run):
    return [n for n in os.listdir(run) if n.startswith(".tmp-")]


def test_full_disk_at_a_checkpoint_keeps_the_last_one(tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    fill_disk_at(monkeypatch, "checkpoint.pt", nth=2)  # the step-2 checkpoint is written, the step-4 one is not
    assert main(train_args(run)) == 2
    one_line_error(capsys, f"cannot write {run / 'checkpoint.pt'}: No space left on device",
                   "previous checkpoint.pt (if any) is unchanged", f"warpnerf train --resume {run}")
    assert torch.load(run / "checkpoint.pt", weights_only=True)["step"] == 2  # the last good one, readable
    assert not leftovers(run) and not (run / "metrics.json").exists() and not (run / ".warpnerf-lock").exists()
    monkeypatch.undo()  # space again
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    assert main(["train", "--quiet", "--threads", "1", "--resume", str(run)]) == 0
    assert json.loads((run / "metrics.json").read_text())["iters"] == 6


def test_full_disk_at_metrics_json_leaves_the_run_resumable(tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    fill_disk_at(monkeypatch, "metrics.json", nth=1)
    assert main(train_args(run)) == 2
    one_line_error(capsys, "cannot write", "metrics.json: No space left on device", "--resume")
    assert torch.load(run / "checkpoint.pt", weights_only=True)["step"] == 6  # the final checkpoint
    assert not (run / "metrics.json").exists() and not leftovers(run)  # never looks finished
    monkeypatch.undo()
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    assert main(["train", "--quiet", "--threads", "1", "--resume", str(run)]) == 0
    assert (run / "metrics.json").exists()


def test_any_other_write_error_is_one_line(tmp_path, capsys, monkeypatch):
    """An OSError no command turned into a message (a plot, a render, a video) still ends as one line."""
    import warpnerf.cli.app as app

    def full(args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "renders" / "0.png"))

    monkeypatch.setattr(app, "cmd_scenes", full)
    assert main(["scenes"]) == 2
    one_line_error(capsys, "No space left on device", "0.png")
