"""Run folders are safe (issue #64): ``--overwrite`` removes only folders warpnerf made (marker
``.warpnerf-run``), and one training at a time writes into a folder (lock ``.warpnerf-lock`` with the
owner's pid, taken with O_EXCL, removed at exit, stale locks taken over)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from warpnerf.cli import main
from warpnerf.runs.folder import LOCK, MARKER, RunLock
from warpnerf.train.config import ConfigError
from door import tree, one_line_error

TRAIN = ["train", "--quiet", "--scene", "chair", "--builtin-resolution", "16", "--iters", "2", "--threads", "1",
         "--video-frames", "0"]


def fake_run(folder, finished=True):
    """A folder that looks like a run (config.toml, metrics.json) but that warpnerf did not make."""
    from warpnerf.runs.folder import config_hash, write_config
    from warpnerf.train.config import build_config

    os.makedirs(folder, exist_ok=True)
    cfg = build_config("full", overrides={"out": str(folder), "iters": 2, "video_frames": 0, "threads": 1,
                                          "scene": "chair", "builtin_resolution": 16})
    write_config(os.path.join(folder, "config.toml"), cfg)
    if finished:
        with open(os.path.join(folder, "metrics.json"), "w") as f:
            json.dump({"psnr": 1.0, "config_hash": config_hash(cfg)}, f)
    return cfg


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("trained") / "run"
    assert main([*TRAIN, "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("finished", [True, False])
def test_overwrite_refuses_a_folder_warpnerf_did_not_make(tmp_path, capsys, finished):
    folder = tmp_path / "mine"
    fake_run(folder, finished)
    (folder / "notes.txt").write_text("do not lose me")
    (folder / "src").mkdir()
    (folder / "src" / "main.py").write_text("print(1)")
    before = tree(tmp_path)
    assert main([*TRAIN, "--out", str(folder), "--overwrite"]) == 2
    one_line_error(capsys, str(folder), MARKER, "--overwrite")
    assert tree(tmp_path) == before


def test_a_run_folder_carries_the_marker_and_no_lock_after_the_run(trained):
    assert (trained / MARKER).is_file() and (trained / "metrics.json").is_file()
    assert not (trained / LOCK).exists()


def test_overwrite_replaces_a_marked_run(trained, capsys):
    (trained / "stale.txt").write_text("from the old run")
    assert main([*TRAIN, "--out", str(trained), "--overwrite"]) == 0
    assert not (trained / "stale.txt").exists() and (trained / MARKER).is_file() and not (trained / LOCK).exists()


def test_an_old_unmarked_run_is_still_resumable(tmp_path):
    from warpnerf.runs.run import prepare_run

    cfg = fake_run(tmp_path / "old", finished=False)
    assert prepare_run(cfg, resume=True) == "resume"
    cfg = fake_run(tmp_path / "old2", finished=True)
    assert prepare_run(cfg, resume=True) == "finished"


def test_a_second_training_into_a_live_folder_exits_2(tmp_path, capsys):
    folder = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from warpnerf.runs.folder import RunLock\n"
        f"lock = RunLock({str(folder)!r}).acquire(); print('locked', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = tree(tmp_path)
        assert main([*TRAIN, "--out", str(folder)]) == 2
        one_line_error(capsys, str(folder), "in use", str(holder.pid))
        assert tree(tmp_path) == before
        with pytest.raises(ConfigError, match="in use"):  # the O_EXCL create itself refuses too
            RunLock(str(folder)).acquire()
        assert tree(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()


def test_a_stale_lock_is_taken_over_with_a_note(tmp_path, capsys):
    folder = tmp_path / "run"
    folder.mkdir()
    pid = dead_pid()
    (folder / LOCK).write_text(f"{pid} {os.uname().nodename}\n")
    lock = RunLock(str(folder)).acquire()
    try:
        assert lock.note and str(pid) in lock.note
        assert (folder / LOCK).read_text().split()[0] == str(os.getpid())
    finally:
        lock.release()
    assert not (folder / LOCK).exists()


def test_a_failed_start_leaves_nothing_behind(tmp_path, capsys):
    before = tree(tmp_path)
    assert main([*TRAIN[:3], "nosuchscene", *TRAIN[4:], "--data-root", str(tmp_path), "--out",
                 str(tmp_path / "run")]) == 2
    one_line_error(capsys, "nosuchscene")
    assert tree(tmp_path) == before


@pytest.mark.parametrize("point", ["step:1", "after_train"])
def test_sigterm_removes_the_lock(tmp_path, point):
    out = tmp_path / "run"
    env = dict(os.environ, WARPNERF_FAULT=point, WARPNERF_FAULT_SIGNAL="TERM")
    p = subprocess.run([sys.executable, "-m", "warpnerf.cli", *TRAIN, "--out", str(out)], env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode in (130, 128 + signal.SIGTERM), p.stderr
    assert out.is_dir() and not (out / LOCK).exists()


# --- a run folder is self-contained (its data root recorded) and refuses a scene that changed ---------


def test_the_data_root_from_the_environment_is_recorded(tmp_path, monkeypatch):
    from fake_scenes import write_blender

    from warpnerf.runs.folder import load_run, read_run_config

    data = tmp_path / "data"
    write_blender(str(data / "boxy"), n=3, size=16)
    monkeypatch.setenv("WARPNERF_DATA", str(data))
    out = tmp_path / "run"
    assert main(["train", "--quiet", "--scene", "boxy", "--iters", "2", "--threads", "1", "--video-frames", "0",
                 "--eval-max-views", "1", "--out", str(out)]) == 0
    assert read_run_config(str(out)).data_root == str(data)
    monkeypatch.delenv("WARPNERF_DATA")  # a fresh shell: the run folder alone reopens its scene
    trainer = load_run(str(out), "cpu")
    assert trainer.scene.source == "dataset" and trainer.scene.name == "boxy"


def test_a_run_whose_scene_now_resolves_elsewhere_is_refused_in_one_line(trained, tmp_path, monkeypatch, capsys):
    """The built-in chair run, opened in a shell whose data root holds a dataset named chair."""
    from fake_scenes import write_blender

    data = tmp_path / "data"
    write_blender(str(data / "chair"), n=3, size=16)
    monkeypatch.setenv("WARPNERF_DATA", str(data))
    before = tree(trained)
    for argv in (["export", "--what", "points", "--quiet"], ["render", "--frames", "1", "--quiet"],
                 ["eval", "--quiet"]):
        args = [argv[0], "--run", str(trained), *argv[1:]]
        assert main(args) == 2, args
        one_line_error(capsys, "builtin", "chair", "dataset")
    assert tree(trained) == before
