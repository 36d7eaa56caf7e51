"""``warpnerf doctor``: runs on this machine, and names the usual misconfigurations."""

import torch

from warpnerf import openmp

from warpnerf.cli import doctor
from warpnerf.cli import main


def test_doctor_prints_one_screen_and_exits_0(capsys):
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert len(lines) <= 24  # one screen
    for key in ("torch ", "warp ", "device ", "cpu ", "kernels "):
        assert any(line.startswith(key) for line in lines), f"no '{key.strip()}' line in:\n{out}"
    assert torch.__version__ in out
    build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU build"
    assert build in out
    if not torch.cuda.is_available():
        assert "no CUDA device" in out or "sm_" in out
    assert "problem" in out  # "problems  none found" or one "problem" line each
    assert f"OpenMP wait {openmp.describe()}" in out


def _info(**kw):
    base = dict(torch_cuda_build=None, torch_cuda_available=False, cuda_devices=[], warp_toolkit=(13, 4),
                warp_driver=None, device_compiled={}, kernel_modules=80, compile_failures=[])
    base.update(kw)
    return base


GPU = dict(name="cuda:0", gpu="A100", arch=80, memory_gb=40.0, compile_arch=80)


def test_clean_cpu_machine_has_no_problem():
    assert doctor.problems(_info()) == []


def test_openmp_wait_policies_slower_than_the_short_spin_are_named():
    (line,) = doctor.problems(_info(omp_wait_policy="active"))
    assert line.startswith("OMP_WAIT_POLICY=ACTIVE") and "short spin" in line
    (line,) = doctor.problems(_info(omp_wait_policy="PASSIVE"))
    assert line.startswith("OMP_WAIT_POLICY=PASSIVE") and "GOMP_SPINCOUNT" in line
    assert doctor.problems(_info(openmp_wait="GOMP_SPINCOUNT=10000 KMP_BLOCKTIME=0")) == []


def test_cuda_torch_without_a_driver_is_named():
    (line,) = doctor.problems(_info(torch_cuda_build="12.8"))
    assert line.startswith("CUDA torch without a usable driver") and "12.8" in line


def test_cpu_torch_on_a_gpu_machine_is_named():
    lines = doctor.problems(_info(cuda_devices=[GPU], warp_driver=(13, 0), device_compiled={"cuda:0": 80}))
    assert lines == [lines[0]] and lines[0].startswith("CPU torch on a GPU machine")


def test_mismatched_cuda_versions_and_old_drivers_are_named():
    lines = doctor.problems(_info(torch_cuda_build="12.8", torch_cuda_available=True, cuda_devices=[GPU],
                                  warp_driver=(12, 8), device_compiled={"cuda:0": 80}))
    assert any(line.startswith("driver too old for Warp") and "13.4" in line for line in lines)
    assert any(line.startswith("mismatched CUDA versions") for line in lines)
    lines = doctor.problems(_info(torch_cuda_build="13.0", torch_cuda_available=True, cuda_devices=[GPU],
                                  warp_driver=(12, 4), warp_toolkit=(12, 8), device_compiled={"cuda:0": 80}))
    assert any(line.startswith("driver too old for torch") for line in lines)


def test_uncompiled_kernels_on_a_gpu_are_named():
    lines = doctor.problems(_info(torch_cuda_build="13.0", torch_cuda_available=True, cuda_devices=[GPU],
                                  warp_driver=(13, 0), device_compiled={"cuda:0": 70}))
    assert lines == ["cuda:0: 10 of 80 kernel modules not compiled yet (the first training step compiles them; "
                     "'warpnerf doctor --compile' does it now)"]


def test_bad_arch_is_a_user_error(capsys):
    assert main(["doctor", "--arch", "ampere"]) == 2
    assert "--arch" in capsys.readouterr().err
