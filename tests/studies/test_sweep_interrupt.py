"""Signals stop a sweep (issue #64): SIGINT or SIGTERM during ``warpnerf sweep`` / ``warpnerf table`` let the
running training save its checkpoint, then the sweep stops (no retry, nothing else starts) and exits 130 with
one line naming the command that continues it; that command resumes the stopped run and skips finished ones
without touching them.

``WARPNERF_FAULT=step:N`` makes the process signal itself at the end of step N of every run it trains (the
mechanism of tests/runs/test_resume.py); a resumed run starts past step N, so the fault stops the next run.
The sweeps run in this process (the signal reaches the training loop's handler); one test sends a real
SIGTERM to a sweep process from outside.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from door import error_lines, one_line_error, tree
from warpnerf.cli import main

SPEC = """out = "{out}"
scenes = ["chair"]
tasks = ["fewshot"]
arms = ["g2fr", "nog2fr"]
retries = 1
[resources]
num_cpus = 1
[overrides]
builtin_resolution = 16
iters = 8
eval_max_views = 1
video_frames = 0
heldout_every = 0
levels = 4
log2_table_size = 12
base_resolution = 8
max_resolution = 64
hidden = 16
target_samples = 2048
batch_rays = 64
occ_resolution = 16
occ_warmup = 4
occ_update_every = 4
march_steps = 32
"""
FIRST, SECOND = "chair_fewshot_ngp_g2fr_s0", "chair_fewshot_ngp_nog2fr_s0"


@pytest.fixture
def spec(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("WARPNERF_THREADS", "1")
    path = tmp_path / "spec.toml"
    path.write_text(SPEC.format(out=tmp_path / "out"))
    return path


def stopped_line(capsys, *needles) -> str:
    return one_line_error(capsys, *needles, prefix="warpnerf: sweep interrupted: ")


def status(out) -> dict:
    return {r["run"]: (r["status"], r["attempts"]) for r in json.loads((out / "sweep.json").read_text())["runs"]}


def ckpt_step(run_dir) -> int:
    return torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"]


@pytest.mark.parametrize("sig", ["INT", "TERM"])
def test_a_signal_stops_the_sweep_and_the_same_command_continues(spec, tmp_path, capsys, monkeypatch, sig):
    out = tmp_path / "out"
    argv = ["sweep", str(spec), "--quiet"]
    monkeypatch.setenv("WARPNERF_FAULT", "step:3")
    monkeypatch.setenv("WARPNERF_FAULT_SIGNAL", sig)

    # 1. the first run stops at step 3 with its checkpoint; not retried; the second never starts
    assert main(argv) == 130
    stopped_line(capsys, f"{FIRST} stopped at step 3, checkpoint saved", "0 of 2 runs finished",
                 f"continue with: warpnerf sweep {spec} --quiet")
    assert ckpt_step(out / FIRST) == 3 and not (out / FIRST / "metrics.json").exists()
    assert not (out / SECOND).exists() and not (out / "table.md").exists()
    assert status(out) == {FIRST: ("interrupted", 1), SECOND: ("pending", 0)}

    # 2. the same command: the first run resumes at step 3 and finishes; the second stops at its step 3
    assert main(argv) == 130
    stopped_line(capsys, f"{SECOND} stopped at step 3", "1 of 2 runs finished")
    assert "resumed at step 3" in (out / "logs" / f"{FIRST}.log").read_text()
    assert json.loads((out / FIRST / "metrics.json").read_text())["iters"] == 8
    assert ckpt_step(out / SECOND) == 3 and not (out / SECOND / "metrics.json").exists()
    assert status(out) == {FIRST: ("done", 1), SECOND: ("interrupted", 1)}

    # 3. without the signal: the finished run is skipped untouched, the stopped one resumes and finishes
    monkeypatch.delenv("WARPNERF_FAULT")
    finished = tree(out / FIRST)
    assert main(argv) == 0
    assert tree(out / FIRST) == finished
    assert status(out) == {FIRST: ("skipped", 0), SECOND: ("done", 1)}
    assert (out / "logs" / f"{SECOND}.log").read_text().count("resumed at step 3") == 1
    assert (out / "table.md").exists()


def test_table_stops_on_sigterm_and_continues(tmp_path, capsys, monkeypatch):
    """`warpnerf table` is a sweep: the same stop, and the same command continues."""
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("builtin_resolution = 16\nvideo_frames = 0\neval_max_views = 1\nlevels = 4\n"
                   "log2_table_size = 12\nhidden = 16\nbatch_rays = 64\nocc_resolution = 16\nmarch_steps = 32\n")
    out = tmp_path / "table"
    argv = ["table", "--scenes", "chair", "--tasks", "fewshot", "--config", str(cfg), "--out", str(out), "--quiet",
            "--iters", "4", "--threads", "1"]
    monkeypatch.setenv("WARPNERF_FAULT", "step:2")
    monkeypatch.setenv("WARPNERF_FAULT_SIGNAL", "TERM")
    assert main(argv) == 130
    stopped_line(capsys, f"{FIRST} stopped at step 2", "continue with: warpnerf table --scenes chair")
    assert not (out / SECOND).exists()
    monkeypatch.delenv("WARPNERF_FAULT")
    assert main(argv) == 0
    assert status(out) == {FIRST: ("done", 1), SECOND: ("done", 1)}
    assert "resumed at step 2" in (out / "logs" / f"{FIRST}.log").read_text()


def test_an_external_sigterm_stops_a_sweep_process(spec, tmp_path):
    """A real SIGTERM from outside, mid-training: the run checkpoints, the process exits 130 with one line."""
    out = tmp_path / "out"
    # long enough to be hit mid-training: the signal comes once the first periodic checkpoint exists
    spec.write_text(spec.read_text().replace("iters = 8", "iters = 100000\ncheckpoint_every = 20"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("WARPNERF_FAULT")}
    proc = subprocess.Popen([sys.executable, "-m", "warpnerf.cli", "sweep", str(spec), "--quiet"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 600
    while proc.poll() is None and time.time() < deadline and not (out / FIRST / "checkpoint.pt").exists():
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=600)
    lines = error_lines(err)
    assert proc.returncode == 130, err
    assert len(lines) == 1 and lines[0].startswith("warpnerf: sweep interrupted: ") and "continue with" in lines[0]
    assert 20 <= ckpt_step(out / FIRST) < 100000 and not (out / FIRST / "metrics.json").exists()
    assert not (out / SECOND).exists()
    assert status(out)[FIRST] == ("interrupted", 1)


def test_sigterm_to_the_driver_stops_worker_processes(spec, tmp_path):
    """--workers 2: the driver forwards the stop to its worker processes; each running training checkpoints."""
    out = tmp_path / "out"
    spec.write_text(spec.read_text().replace("iters = 8", "iters = 100000\ncheckpoint_every = 20"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("WARPNERF_FAULT")}
    proc = subprocess.Popen([sys.executable, "-m", "warpnerf.cli", "sweep", str(spec), "--quiet", "--workers", "2"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 600
    while proc.poll() is None and time.time() < deadline and not all(
            (out / name / "checkpoint.pt").exists() for name in (FIRST, SECOND)):
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)  # the driver only, as `kill` does
    _, err = proc.communicate(timeout=600)
    lines = error_lines(err)
    assert proc.returncode == 130, err
    assert len(lines) == 1 and lines[0].startswith("warpnerf: sweep interrupted: "), lines
    assert "--workers 2" in lines[0]
    assert status(out) == {FIRST: ("interrupted", 1), SECOND: ("interrupted", 1)}
    for name in (FIRST, SECOND):
        assert 20 <= ckpt_step(out / name) < 100000 and not (out / name / "metrics.json").exists()


@pytest.mark.parametrize("then", ["second signal", "grace over"])
def test_a_ray_sweep_kills_tasks_that_do_not_stop(spec, monkeypatch, then):
    """The Ray driver's stop without Ray (a stand-in module): the first SIGINT cancels every task gently
    (force=False: Ray raises SIGINT in it, the training checkpoints); a second one, or RAY_STOP_GRACE s without
    their results, kills them (force=True). tests/studies/test_sweep_ray_head.py stops real Ray tasks."""
    import types

    from warpnerf.studies import sweep

    cancels, signals = [], [KeyboardInterrupt] * (2 if then == "second signal" else 1)

    def wait(refs, num_returns, timeout):
        if signals:
            raise signals.pop()
        return [], refs

    task = types.SimpleNamespace(options=lambda **kw: task, remote=lambda *args: object())
    fake = types.SimpleNamespace(is_initialized=lambda: True, remote=lambda fn: task, wait=wait,
                                 cancel=lambda ref, force: cancels.append(force))
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setattr(sweep, "RAY_STOP_GRACE", 0.0 if then == "grace over" else 600.0)
    pending = [sweep.RunResult(r) for r in sweep.expand(sweep.load_spec(str(spec)))]
    sweep._run_ray(pending, sweep.load_spec(str(spec)), 1, None, sweep._Progress(2, 0, enabled=False))
    assert cancels == [False, False, True, True]
    assert [(r.status, r.attempts) for r in pending] == [("interrupted", 1)] * 2
    assert all("killed" in r.error for r in pending)
