"""Warp's "Could not find or load the NVIDIA CUDA driver" line is not shown unless CUDA is asked for (#65)."""

import os
import subprocess
import sys

import pytest

from warpnerf import device
from warpnerf.device import CUDA_DRIVER_MISSING

TINY_BENCH = ("bench", "encoding", "--n", "1024", "--repeats", "1", "--levels", "4", "--log2-table-size", "10",
              "--no-roofline")


def _cli(*args):
    proc = subprocess.run([sys.executable, "-m", "warpnerf.cli", *args], capture_output=True, text=True,
                          env={**os.environ, "WARPNERF_THREADS": "1"}, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.mark.parametrize("dev", ["auto", "cpu"])
def test_no_cuda_driver_line_on_auto_or_cpu(dev):
    code, _, err = _cli(*TINY_BENCH, "--device", dev)
    assert code == 0, err[-2000:]
    assert CUDA_DRIVER_MISSING not in err


def test_asking_for_cuda_without_a_driver_names_it():
    wp = device.init_warp()
    if wp.is_cuda_available():
        pytest.skip("this machine has a CUDA device")
    code, _, err = _cli(*TINY_BENCH, "--device", "cuda")
    assert code == 2
    # one line, the error, naming Warp's reason when it had one (other Warp warnings, e.g. an old kernel cache, stay)
    line, = [x for x in err.splitlines() if "CUDA" in x]
    assert line.startswith("warpnerf: error: device 'cuda' requested but Warp sees no CUDA device")
    if device.held_back_warp_lines():  # this Warp build printed the driver line at init
        assert CUDA_DRIVER_MISSING in line


class _FakeWarp:
    """A Warp whose init prints, from below Python, the driver line between two other lines."""

    @staticmethod
    def init():
        os.write(2, b"Warp CUDA warning: " + CUDA_DRIVER_MISSING.encode() + b". GPU execution will not be available.\n")
        os.write(2, b"Warp error: something real\n")


def test_only_the_driver_line_is_held_back(capfd, monkeypatch):
    monkeypatch.setattr(device, "_HELD_BACK", [])
    print("before", file=sys.stderr)
    device._init_without_driver_line(_FakeWarp)
    err = capfd.readouterr().err
    assert err == "before\nWarp error: something real\n"
    assert device.held_back_warp_lines() == [f"Warp CUDA warning: {CUDA_DRIVER_MISSING}. GPU execution will not be "
                                             "available."]
