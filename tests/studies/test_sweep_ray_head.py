"""A sweep against a separately started Ray head (issue #64): `ray start --head` in one working
directory, the sweep driver in another with a relative `out`. The sweep is killed once a run has
finished and started again; the restart must find that run where the driver looks and leave it alone.

Before the fix, workers resolved the relative `out` in their own working directory: the restart saw
no finished run and the workers cut finished folders back to a lone config.toml.
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
