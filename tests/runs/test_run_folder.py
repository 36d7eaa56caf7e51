"""warpnerf.runs.folder, the one reader of run folders, and the checkpoint it never unpickles blindly.

Every command that reads a run's ``checkpoint.pt`` (eval, render, export, view, bench render, --resume)
reads it through ``folder.read_checkpoint`` -> ``train.checkpoint.load_checkpoint``, which passes
``weights_only=True`` explicitly. A checkpoint crafted to run code when unpickled is refused by each of
them and its code never runs, also with ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1``: that variable flips only
torch.load's *default* to a full unpickle (what the bare ``torch.load`` calls of the render loader and
the viewer did), never an explicit ``weights_only=True``.
"""

import json
import os
import shutil
import time

import pytest
import torch

from warpnerf.cli import main
from warpnerf.outputs.viewer import RunViewer
from warpnerf.runs import folder
from warpnerf.train.checkpoint import FORMAT, CheckpointError, load_checkpoint
from warpnerf.train.config import build_config


class _RunsCode:
    """Unpickling this calls ``os.mkdir(marker)``: a stand-in for whatever code a crafted pickle could run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def _crafted_checkpoint(path, marker) -> None:
    # a well-formed warpnerf checkpoint in every other respect: the format tag and a step
    torch.save({"format": FORMAT, "step": 1, "payload": _RunsCode(marker)}, str(path))


def _run_folder(path, marker, finished: bool = True) -> None:
    """A run folder as 'warpnerf train' writes it (config.toml, metrics.json) around the crafted checkpoint."""
    cfg = build_config("full", overrides={"out": str(path), "iters": 2, "video_frames": 0})
    os.makedirs(path)
    folder.write_config(os.path.join(path, folder.CONFIG), cfg)
    if finished:
        with open(os.path.join(path, folder.METRICS), "w") as f:
            json.dump({"psnr": 1.0, "ssim": 0.5, "config_hash": folder.config_hash(cfg)}, f)
    _crafted_checkpoint(os.path.join(path, folder.CHECKPOINT), marker)


@pytest.fixture(params=["torch default", "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1"])
def torch_load_env(request, monkeypatch):
    monkeypatch.delenv("TORCH_FORCE_WEIGHTS_ONLY_LOAD", raising=False)
    if request.param.startswith("TORCH_FORCE"):
        monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    else:
        monkeypatch.delenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", raising=False)


def test_the_crafted_checkpoint_runs_code_when_unpickled(tmp_path, monkeypatch):
    """The control: a bare torch.load under TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 runs the payload, so the
    tests below would notice a reader that does not go through load_checkpoint."""
    marker = tmp_path / "ran"
    _crafted_checkpoint(tmp_path / "c.pt", marker)
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    with pytest.warns(UserWarning, match="TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"):
        torch.load(tmp_path / "c.pt")
    assert marker.exists()


def test_load_checkpoint_refuses_it(tmp_path, torch_load_env):
    marker = tmp_path / "ran"
    _crafted_checkpoint(tmp_path / "c.pt", marker)
    with pytest.raises(CheckpointError, match="c.pt is not a readable warpnerf checkpoint"):
        load_checkpoint(str(tmp_path / "c.pt"))
    assert not marker.exists()


def test_load_run_refuses_it_before_loading_the_scene(tmp_path, torch_load_env):
    """load_run: what render, export and bench render load a finished run with."""
    marker = tmp_path / "ran"
    _run_folder(tmp_path / "run", marker)
    with pytest.raises(CheckpointError, match="checkpoint.pt"):
        folder.load_run(str(tmp_path / "run"), device="cpu")
    assert not marker.exists()


@pytest.mark.parametrize("argv", [["eval", "--quiet"], ["render", "--quiet", "--frames", "1"], ["export", "--quiet"]],
                         ids=["eval", "render", "export"])
def test_commands_on_a_finished_run_refuse_it(tmp_path, capsys, torch_load_env, argv):
    marker = tmp_path / "ran"
    _run_folder(tmp_path / "run", marker)
    assert main([argv[0], "--run", str(tmp_path / "run"), *argv[1:]]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt is not a readable warpnerf checkpoint" in err and "Traceback" not in err
    assert not marker.exists()
    assert not (tmp_path / "run" / "eval").exists()


def test_resume_refuses_it(tmp_path, capsys, torch_load_env):
    marker = tmp_path / "ran"
    _run_folder(tmp_path / "run", marker, finished=False)
    assert main(["train", "--quiet", "--resume", str(tmp_path / "run")]) == 2
    assert "checkpoint.pt is not a readable warpnerf checkpoint" in capsys.readouterr().err
    assert not marker.exists()


def test_viewer_refuses_it(tmp_path, torch_load_env):
    marker = tmp_path / "ran"
    _run_folder(tmp_path / "run", marker)
    with pytest.raises(CheckpointError, match="checkpoint.pt"):
        RunViewer(str(tmp_path / "run"), "cpu", preview_height=16)
    assert not marker.exists()


def test_viewer_does_not_reload_it(chair_run, tmp_path, torch_load_env):
    """A training run's checkpoint replaced by the crafted file: the viewer keeps the field it shows."""
    run = tmp_path / "run"
    shutil.copytree(chair_run, run, ignore=shutil.ignore_patterns("renders", "*.mp4", "*.gif"))
    viewer = RunViewer(str(run), "cpu", preview_height=16)
    step = viewer.step
    marker = tmp_path / "ran"
    time.sleep(0.05)  # a new modification time
    _crafted_checkpoint(run / "checkpoint.pt", marker)
    assert not viewer.reload_if_changed()
    assert viewer.step == step
    assert not marker.exists()


def test_folder_reads_back_what_a_run_wrote(chair_run):
    cfg = folder.read_run_config(str(chair_run))
    assert cfg.out == str(chair_run) and cfg.scene == "chair"
    assert folder.folder_state(str(chair_run)) == "finished"
    assert folder.finished_metrics(cfg) == folder.read_metrics(str(chair_run))
    state = folder.read_checkpoint(str(chair_run), map_location="cpu")
    assert state["format"] == FORMAT and state["config_hash"] == folder.config_hash(cfg)
