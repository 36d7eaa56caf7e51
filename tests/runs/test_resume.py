"""Kill tests: a run crashed (SIGKILL) or interrupted (SIGINT/SIGTERM) at any point and
then resumed ends bit-identical to an uninterrupted run: checkpoint tensors, history and metrics.

A tiny configuration keeps each subprocess to seconds; the pose task exercises both Adam states.
``WARPNERF_FAULT`` makes the run signal itself at an exact place (a step boundary, between a
checkpoint's fsync and its rename, between training and evaluation).
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

TINY = """
occ_resolution = 32
occ_warmup = 8
occ_update_every = 4
march_steps = 256
levels = 8
log2_table_size = 14
max_resolution = 256
batch_rays = 256
target_samples = 8192
eval_max_views = 1
pose_refine_steps = 3
log_every = 1
"""
ITERS, SAVE_EVERY = 30, 10


def train_args(out, config):
    return [sys.executable, "-m", "warpnerf.cli", "train", "--quiet", "--task", "pose", "--scene", "chair",
            "--builtin-resolution", "40", "--iters", str(ITERS), "--checkpoint-every", str(SAVE_EVERY), "--threads", "1",
            "--video-frames", "0", "--config", str(config), "--out", str(out)]


def resume_args(out):
    return [sys.executable, "-m", "warpnerf.cli", "train", "--quiet", "--threads", "1", "--resume", str(out)]


def run(args, cwd, fault=None, sig="KILL"):
    env = dict(os.environ)
    if fault:
        env.update(WARPNERF_FAULT=fault, WARPNERF_FAULT_SIGNAL=sig)
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=900, env=env)


def ckpt(run_dir):
    state = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=True)
    state.pop("train_seconds")
    return state


def metrics(run_dir):
    """metrics.json without the measurements of the process (timings, peak memory): those differ
    between any two runs, interrupted or not."""
    with open(os.path.join(run_dir, "metrics.json")) as f:
        m = json.load(f)
    return {k: v for k, v in m.items() if "seconds" not in k and k not in ("peak_rss_mb", "cpu")}


def assert_same(a, b, path="state"):
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), path
    elif isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    else:
        assert a == b, (path, a, b)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume")
    (d / "tiny.toml").write_text(TINY)
    p = run(train_args(d / "ref", d / "tiny.toml"), d)
    assert p.returncode == 0, p.stderr
    return d


def check_matches_reference(work, out):
    assert_same(ckpt(work / "ref"), ckpt(out))
    assert_same(metrics(work / "ref"), metrics(out))
    with open(work / "ref" / "history.json") as f1, open(out / "history.json") as f2:
        assert json.load(f1) == json.load(f2)
    assert not [n for n in os.listdir(out) if n.startswith(".tmp-")]


@pytest.mark.parametrize("fault", ["step:25", "before_replace:checkpoint.pt", "after_train"])
def test_sigkill_then_resume_is_bit_identical(work, fault):
    out = work / ("kill_" + fault.replace(":", "_").replace(".", "_"))
    p = run(train_args(out, work / "tiny.toml"), work, fault=fault)
    assert p.returncode == -signal.SIGKILL, p.stderr
    assert not (out / "metrics.json").exists()  # never looks finished
    p = run(resume_args(out), work)
    assert p.returncode == 0, p.stderr
    check_matches_reference(work, out)


def test_sigterm_at_step_boundary_saves_and_exits_130(work):
    out = work / "term"
    p = run(train_args(out, work / "tiny.toml"), work, fault="step:5", sig="TERM")
    assert p.returncode == 130, p.stderr
    assert "interrupted at step 5" in p.stderr and "--resume" in p.stderr
    assert torch.load(out / "checkpoint.pt", weights_only=True)["step"] == 5
    p = run(resume_args(out), work)
    assert p.returncode == 0, p.stderr
    check_matches_reference(work, out)


def test_external_sigint_then_resume_is_bit_identical(work):
    out = work / "int"
    proc = subprocess.Popen(train_args(out, work / "tiny.toml"), cwd=work, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 600
    while not (out / "checkpoint.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)  # somewhere after step 10, mid-step or mid-launch
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 130, err
    step = torch.load(out / "checkpoint.pt", weights_only=True)["step"]
    assert SAVE_EVERY <= step < ITERS
    p = run(resume_args(out), work)
    assert p.returncode == 0, p.stderr
    check_matches_reference(work, out)
    # a second resume of the now finished run does nothing and says so
    before = os.stat(out / "metrics.json").st_mtime_ns
    p = run(resume_args(out), work)
    assert p.returncode == 0 and "already finished" in p.stdout
    assert os.stat(out / "metrics.json").st_mtime_ns == before


def test_eval_with_device_override_reproduces_metrics(work):
    p = subprocess.run([sys.executable, "-m", "warpnerf.cli", "eval", "--quiet", "--threads", "1", "--device", "cpu",
                        "--run", str(work / "ref")], cwd=work, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    with open(work / "ref" / "eval" / "metrics.json") as f:
        ev = json.load(f)
    assert ev["psnr"] == metrics(work / "ref")["psnr"]


# schedules whose state moves with the run: levels open on loss plateaus (adaptive) or on val-PSNR plateaus
# (heldout; min_gain 100 dB: every check after the first is a plateau, so levels open on both sides of the kill;
# drop 100 dB: the guard never closes them, so where they open does not hang on the PSNR's noise)
SCHEDULE_CONFIGS = {
    "adaptive": 'g2fr_schedule = "adaptive"\ng2fr_plateau_window = 3\ng2fr_plateau_tol = 0.9\n',
    "heldout": 'g2fr_schedule = "heldout"\ng2fr_heldout_window = 4\ng2fr_heldout_min_gain = 100.0\n'
               'g2fr_heldout_drop = 100.0\ng2fr_heldout_views = 2\n',
}


@pytest.fixture(scope="module", params=sorted(SCHEDULE_CONFIGS))
def adaptive_work(request, tmp_path_factory):
    """A few-shot run whose G²fR levels open on a measured signal: the schedule's state must resume too."""
    d = tmp_path_factory.mktemp(f"resume_{request.param}")
    (d / "tiny.toml").write_text(TINY + SCHEDULE_CONFIGS[request.param])
    return d


def adaptive_args(out, config):
    args = train_args(out, config)
    args[args.index("pose")] = "fewshot"
    return args


def test_adaptive_schedule_resumes_bit_identical(adaptive_work):
    d = adaptive_work
    p = run(adaptive_args(d / "ref", d / "tiny.toml"), d)
    assert p.returncode == 0, p.stderr
    opened = json.loads((d / "ref" / "metrics.json").read_text())["g2fr_open_steps"]
    assert any(10 < s <= 25 for s in opened) and any(s > 25 for s in opened)  # levels open on both sides of the kill
    out = d / "kill"
    p = run(adaptive_args(out, d / "tiny.toml"), d, fault="step:25")
    assert p.returncode == -signal.SIGKILL, p.stderr
    p = run(resume_args(out), d)
    assert p.returncode == 0, p.stderr
    check_matches_reference(d, out)
