"""A sweep against a separately started Ray head (issue #64): `ray start --head` in one working
directory, the sweep driver in another with a relative `out`. The sweep is killed once a run has
finished and started again; the restart must find that run where the driver looks and leave it alone.

Before the fix, workers resolved the relative `out` in their own working directory: the restart saw
no finished run and the workers cut finished folders back to a lone config.toml.

SIGINT or SIGTERM to the driver of such a sweep stops it as a local one stops: the running Ray task's
training saves its checkpoint at the step it had reached, the queued task never starts, the driver exits 130,
and the same command resumes the stopped run and skips the finished one.
"""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

from test_sweep import write_spec
from test_sweep_interrupt import SPEC as TINY_SPEC
from test_sweep_interrupt import ckpt_step

pytestmark = pytest.mark.skipif(shutil.which("ray") is None and not os.path.exists(
    os.path.join(os.path.dirname(sys.executable), "ray")), reason="ray is not installed (warpnerf[cluster])")


# Ray >= 2.5x turns token authentication on for `ray start`; a test cluster on one machine opts out (a real
# cluster keeps it and gives every node the token: docs/sweep.md)
RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray(*args, cwd, env) -> subprocess.CompletedProcess:
    exe = shutil.which("ray") or os.path.join(os.path.dirname(sys.executable), "ray")
    return subprocess.run([exe, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture
def ray_head(tmp_path):
    """A local Ray head started from its own folder, stopped after the test."""
    head_dir = tmp_path / "head"
    head_dir.mkdir()
    port = _free_port()
    env = {**os.environ, **RAY_ENV}
    try:
        p = _ray("start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                 "--disable-usage-stats", cwd=head_dir, env=env)
    except subprocess.TimeoutExpired:
        _ray("stop", "--force", cwd=head_dir, env=env)
        pytest.skip("ray start --head did not finish in 300 s on this host")
    if p.returncode != 0:
        _ray("stop", "--force", cwd=head_dir, env=env)
        pytest.skip(f"ray start --head failed on this host: {p.stderr.strip().splitlines()[-1:]}")
    try:
        yield "auto"  # the command: the cluster started last on this machine
    finally:
        _ray("stop", "--force", cwd=head_dir, env=env)


def test_restarted_sweep_on_a_ray_head_keeps_its_finished_runs(tmp_path, ray_head):
    driver = tmp_path / "driver"
    driver.mkdir()
    write_spec(driver / "spec.toml", "out", ["chair"])  # a relative out, as the shipped specs have
    env = {**os.environ, "WARPNERF_CACHE": str(tmp_path / "cache"), **RAY_ENV}
    cmd = [sys.executable, "-m", "warpnerf.cli", "sweep", "spec.toml", "--backend", "ray", "--ray-address", ray_head,
           "--quiet"]
    out = driver / "out"
    proc = subprocess.Popen(cmd, cwd=driver, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    finished = None
    try:
        deadline = time.time() + 900
        while time.time() < deadline and proc.poll() is None and finished is None:
            done = [p for p in out.glob("*/metrics.json") if "total_seconds" in p.read_text()]
            finished = done[0].parent if done else None
            time.sleep(0.2)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
    assert finished is not None, f"no run finished before the kill: {err[-2000:]}"
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in finished.iterdir() if p.is_file()}
    assert not (tmp_path / "head" / "out").exists()  # nothing was written where the head was started

    p = subprocess.run(cmd, cwd=driver, env=env, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    after = {q.name: (q.stat().st_mtime_ns, q.read_bytes()) for q in finished.iterdir() if q.is_file()}
    assert after == before  # the finished run's folder is untouched, byte for byte
    status = {r["run"]: r["status"] for r in json.loads((out / "sweep.json").read_text())["runs"]}
    assert status[finished.name] == "skipped"
    assert set(status.values()) <= {"skipped", "done"} and len(status) == 2
    assert not (tmp_path / "head" / "out").exists()


# three runs of the tiny chair, one at a time (each takes the head's 2 CPUs); a checkpoint every 20 steps
STOP_SPEC = TINY_SPEC.replace('arms = ["g2fr", "nog2fr"]', 'arms = ["g2fr", "nog2fr", "adaptive"]').replace(
    "num_cpus = 1", "num_cpus = 2").replace("iters = 8", "iters = 400\ncheckpoint_every = 20")


@pytest.mark.parametrize("sig", ["INT", "TERM"])
def test_a_signal_stops_a_ray_sweep_after_its_training_checkpoints(tmp_path, ray_head, sig):
    """Once one run has finished and the next has saved its first periodic checkpoint (step 20), the driver
    alone gets the signal (as from `kill`). The stopped run's checkpoint is the one of the step it reports,
    past 20: saved at the stop, not a periodic one the Ray task was cancelled after."""
    out = tmp_path / "out"
    spec = tmp_path / "spec.toml"
    spec.write_text(STOP_SPEC.format(out=out))
    env = {k: v for k, v in os.environ.items() if not k.startswith("WARPNERF_FAULT")}
    env.update(RAY_ENV, WARPNERF_CACHE=str(tmp_path / "cache"))
    cmd = [sys.executable, "-m", "warpnerf.cli", "sweep", str(spec), "--backend", "ray", "--ray-address", ray_head,
           "--quiet"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    finished = training = None
    try:
        deadline = time.time() + 600
        while time.time() < deadline and proc.poll() is None and not (finished and training):
            finished = next((p.parent for p in out.glob("*/metrics.json") if "total_seconds" in p.read_text()), None)
            training = next((p.parent for p in out.glob("*/checkpoint.pt")
                             if not (p.parent / "metrics.json").exists()), None)
            time.sleep(0.05)
        proc.send_signal(getattr(signal, "SIG" + sig))
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert finished and training, f"no run was training after a finished one: {err[-2000:]}"
    assert proc.returncode == 130, err[-2000:]
    ours = [ln for ln in err.splitlines() if ln.startswith("warpnerf:")]
    assert len(ours) == 1 and ours[0].startswith("warpnerf: sweep interrupted: ") and "continue with" in ours[0], err
    runs = {r["run"]: r for r in json.loads((out / "sweep.json").read_text())["runs"]}
    stopped = runs[training.name]
    assert stopped["status"] == "interrupted" and stopped["error"].endswith(", checkpoint saved"), stopped
    step = int(stopped["error"].split("stopped at step ")[1].split(",")[0])
    assert 20 < step < 400 and ckpt_step(training) == step and not (training / "metrics.json").exists()
    assert runs[finished.name]["status"] == "done"
    (queued,) = set(runs) - {finished.name, training.name}
    assert runs[queued]["status"] == "interrupted" and not (out / queued).exists()  # cancelled before it started
    if sig == "TERM":
        return  # the restart is the same after either signal

    before = {q.name: (q.stat().st_mtime_ns, q.read_bytes()) for q in finished.iterdir() if q.is_file()}
    p = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    assert {q.name: (q.stat().st_mtime_ns, q.read_bytes()) for q in finished.iterdir() if q.is_file()} == before
    status = {r["run"]: r["status"] for r in json.loads((out / "sweep.json").read_text())["runs"]}
    assert status == {finished.name: "skipped", training.name: "done", queued: "done"}
    assert f"resumed at step {step}" in (out / "logs" / f"{training.name}.log").read_text()
