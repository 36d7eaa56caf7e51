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
    for key in ("torch ", "warp ", "device ", "cpu ", "kernels ", "extras ", "data ", "lpips "):
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


def test_extras_are_read_from_the_package_metadata():
    reqs = ['numpy>=1.24', 'numpy>=1; extra == "have"', 'no-such-dist-warpnerf>=1; extra == "lack"',
            'torch>=2; python_version >= "3.8" and extra == "have"']
    assert doctor.extras_status(reqs) == {"have": [], "lack": ["no-such-dist-warpnerf"]}
    installed = doctor.extras_status()
    if installed is not None:  # an installed warpnerf: its extras are pyproject's
        import tomllib
        from pathlib import Path

        pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
        assert set(installed) == set(pyproject["project"]["optional-dependencies"])
    (line,) = doctor._extras_lines({"video": [], "log": ["tensorboard"]})
    assert line == "extras    installed: video; missing: log (pip install 'warpnerf[NAME]')"


def test_data_root_is_reported_and_a_bad_one_is_a_problem(tmp_path, monkeypatch):
    monkeypatch.delenv("WARPNERF_DATA", raising=False)
    data = doctor.data_root_status()
    assert data["value"] is None and "not set" in doctor._data_line(data)
    lego = tmp_path / "nerf_synthetic" / "lego"
    lego.mkdir(parents=True)
    (lego / "transforms_train.json").write_text("{}")
    monkeypatch.setenv("WARPNERF_DATA", str(tmp_path))
    data = doctor.data_root_status()
    assert data["scenes"] == ["lego"] and doctor._data_line(data).endswith("1 dataset scene(s) (lego)")
    assert doctor.problems(_info(data=data)) == []
    monkeypatch.setenv("WARPNERF_DATA", str(tmp_path / "nope"))
    data = doctor.data_root_status()
    (line,) = doctor.problems(_info(data=data))
    assert str(tmp_path / "nope") in line and "fix or unset $WARPNERF_DATA" in line


def test_lpips_line_names_what_is_missing(tmp_path):
    trunk = tmp_path / "alexnet-owt-7be5be79.pth"
    lp = {"trunk": str(trunk), "trunk_found": False, "lin": None, "lin_found": False}
    line = doctor._lpips_line(lp)
    assert line.startswith("lpips     weights not found: AlexNet trunk " + str(trunk))
    assert "warpnerf[metrics]" in line
    lp.update(trunk_found=True, lin="/x/alex.pth", lin_found=True)
    assert doctor._lpips_line(lp) == f"lpips     weights found: {trunk}, /x/alex.pth"
    from warpnerf.train.metrics import lpips_weight_files

    found = doctor.lpips_status()  # the same lookup evaluation uses
    assert (found["trunk_found"] and found["lin_found"]) == (lpips_weight_files("") is not None)


def test_kernel_cache_warmth_in_words():
    assert doctor._cache_warmth(81, 81).startswith("warm for the CPU")
    assert doctor._cache_warmth(0, 81).startswith("cold for the CPU (0/81")
    assert doctor._cache_warmth(8, 81).startswith("partly warm for the CPU (8/81")


def test_a_warning_while_probing_is_a_problem_never_beside_none_found():
    import warnings

    import warp
    from warp._src.logger import log_warning

    before = warp.get_logger()
    with doctor._recording_warnings() as caught:
        log_warning("stale kernel cache")
        warnings.warn("something odd", UserWarning, stacklevel=1)
    assert caught == ["Warp warns: stale kernel cache", "UserWarning: something odd"]
    assert warp.get_logger() is before  # Warp's own logger is back
    assert doctor.problems(_info(warnings=caught)) == caught
    info = doctor.collect()
    info["warnings"] = caught
    info["problems"] = doctor.problems(info)
    report = doctor.format_report(info)
    assert "none found" not in report
    assert "problem   Warp warns: stale kernel cache" in report.splitlines()
