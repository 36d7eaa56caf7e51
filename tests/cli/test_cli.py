"""The command line: errors are one line with exit code 2, no traceback; help works without CUDA."""

import json
import os
import subprocess
import sys

import pytest

from warpnerf.cli import main


def run_cli(*args, env=None):
    proc = subprocess.run([sys.executable, "-m", "warpnerf.cli", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


def test_help_lists_subcommands():
    code, out, _ = run_cli("--help")
    assert code == 0
    for cmd in ("train", "eval", "bench", "scenes", "table"):
        assert cmd in out


def test_unknown_scene_is_one_line_error(tmp_path):
    code, out, err = run_cli("train", "--scene", "nosuchscene", "--data-root", str(tmp_path), "--iters", "1")
    assert code == 2
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("warpnerf: error")]
    assert len(lines) == 1 and "nosuchscene" in lines[0] and "chair" in lines[0]


def test_unknown_config_key_is_one_line_error(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("iters = 5\nlearning_rate = 3\n")
    assert main(["train", "--config", str(cfg)]) == 2


def test_missing_run_folder_is_an_error(tmp_path, capsys):
    assert main(["eval", "--run", str(tmp_path / "nope")]) == 2
    assert "config.toml" in capsys.readouterr().err


def test_bench_render_needs_a_run(tmp_path, capsys):
    assert main(["bench", "render"]) == 2
    assert "needs --run" in capsys.readouterr().err
    assert main(["bench", "render", "--run", str(tmp_path / "nope")]) == 2
    assert "config.toml" in capsys.readouterr().err


def test_bad_device_is_an_error(capsys):
    assert main(["bench", "encoding", "--device", "tpu"]) == 2
    assert "unknown device" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["ngp", "mtrf"])
def test_bench_encoding_json_is_measured(model):
    code, out, err = run_cli("bench", "encoding", "--n", "2048", "--levels", "4", "--log2-table-size", "12",
                             "--repeats", "1", "--json", "--model", model)
    assert code == 0, err
    res = json.loads(out.strip().splitlines()[-1])
    for key in ("warp_fwd_pts_s", "warp_fwdbwd_pts_s", "torch_fwd_pts_s", "torch_fwdbwd_pts_s", "ratio_fwd",
                "ratio_fwdbwd", "threads", "device"):
        assert key in res
    assert res["warp_fwd_pts_s"] > 0 and res["device"] == "cpu"
    assert set(res["cases"]) == {"uniform", "rays", "g2fr_first4"} and res["model"] == model


def test_scenes_lists_builtins():
    code, out, _ = run_cli("scenes")
    assert code == 0
    for name in ("chair", "lamp", "vase", "stand"):
        assert name in out


def test_main_command_end_to_end_on_tiny_builtin(tmp_path):
    """`warpnerf train --scene chair --task fewshot`, shrunk: generation, training, eval, video, metrics."""
    out = tmp_path / "run"
    code, stdout, err = run_cli(
        "train", "--scene", "chair", "--task", "fewshot", "--builtin-resolution", "48", "--iters", "30",
        "--eval-max-views", "2", "--video-frames", "3", "--out", str(out), "--quiet",
        env={"WARPNERF_CACHE": str(tmp_path / "cache"), "WARPNERF_DATA": str(tmp_path)},  # a data root without the scene
    )
    assert code == 0, err[-2000:]
    assert "from builtin" in stdout
    m = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "iters", "train_seconds", "n_train_views", "scene", "scene_source", "task", "model",
                "g2fr", "device", "seed"):
        assert key in m, key
    assert m["scene_source"] == "builtin" and m["n_train_views"] == 10 and m["g2fr"] is True and m["iters"] == 30
    assert m["psnr"] > 8.0  # 30 steps: far from converged, but not garbage
    assert ((out / "turntable.mp4").exists() or (out / "turntable.gif").exists()) and (out / "config.toml").exists()
    assert len(list((out / "renders").glob("test_*.png"))) == 4  # 2 views x (rgb, depth)
    code, stdout, err = run_cli("eval", "--run", str(out), "--quiet", env={"WARPNERF_CACHE": str(tmp_path / "cache")})
    assert code == 0, err[-2000:]
    assert json.loads((out / "eval" / "metrics.json").read_text())["psnr"] == pytest.approx(m["psnr"], abs=1e-4)
    # `table --reuse` reads a finished run only when its configuration is identical
    from warpnerf.train.config import build_config, load_toml
    from warpnerf.runs.folder import finished_metrics

    values = load_toml(str(out / "config.toml"))
    cfg = build_config(values.pop("task"), overrides=values)
    assert finished_metrics(cfg)["psnr"] == pytest.approx(m["psnr"])
    cfg.iters += 1
    assert finished_metrics(cfg) is None


def test_threads_option_bounds_torch_too():
    """`--threads 1` must hold torch's intra-op pool to one thread as well: two runs started side by side
    with --threads 1 each otherwise kept four busy threads on two cores (each ran ~3x slower than half speed)."""
    import argparse

    import torch

    from warpnerf import device
    from warpnerf.cli import app as cli

    before = (device.num_threads(), torch.get_num_threads())
    try:
        assert cli._setup_device(argparse.Namespace(device="cpu", threads=1)) == "cpu"
        assert (device.num_threads(), torch.get_num_threads()) == (1, 1)
    finally:
        device.set_num_threads(before[0])
        torch.set_num_threads(before[1])


WAIT_POLICY_PROBE = """
import importlib.abc, os, sys
seen = []
class Probe(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" and not seen:
            seen.append([os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME")])
        return None
sys.meta_path.insert(0, Probe())
from warpnerf.cli import app
app.build_parser()
import torch
print(seen[0])
"""


@pytest.mark.parametrize("user", [{}, {"OMP_WAIT_POLICY": "PASSIVE"}, {"GOMP_SPINCOUNT": "0"}])
def test_cli_sets_a_short_openmp_spin_before_torch_loads(user):
    """The OpenMP runtime reads its wait settings once, when torch loads: the command line must set
    them before the first torch import (the config registry imports torch while the parser is
    built), and leave every wait setting alone when the user made one."""
    keys = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME")
    env = {k: v for k, v in os.environ.items() if k not in keys}
    env.update(user)
    proc = subprocess.run([sys.executable, "-c", WAIT_POLICY_PROBE], capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    expected = [user.get(k) for k in keys] if user else [None, "10000", "0"]
    assert proc.stdout.strip().splitlines()[-1] == str(expected)


def test_summary_names_unconverged_pose_views():
    from warpnerf.cli.app import _summary

    m = {"psnr": 33.1, "ssim": 0.98, "iters": 3000, "train_seconds": 300.0, "render_seconds_per_view": 0.3,
         "rot_err_deg": 0.447, "trans_err_x100": 0.722, "rot_err_deg_median": 0.229, "trans_err_x100_median": 0.61,
         "unconverged_views": [18]}
    line = _summary(m)
    assert "rot err 0.447 deg" in line
    assert line.endswith("; 1 view(s) not converged (18; rot. err > 1 deg and 5x the median); "
                         "median rot. err 0.229 deg, trans. err 0.610")
    m["unconverged_views"] = list(range(10))  # the summary lists eight ids
    assert "(0, 1, 2, 3, 4, 5, 6, 7, ...; rot. err" in _summary(m)
    m["unconverged_views"] = []
    assert "not converged" not in _summary(m)


def test_summary_names_reregistered_views():
    from warpnerf.cli.app import _summary

    m = {"psnr": 33.1, "ssim": 0.98, "iters": 3000, "train_seconds": 300.0, "render_seconds_per_view": 0.3,
         "rot_err_deg": 0.066, "trans_err_x100": 0.462, "unconverged_views": [],
         "reregistered": [{"view": 14, "step": 1000}, {"view": 79, "step": 1000}]}
    assert _summary(m).endswith("; re-registered view(s) 14, 79 at step 1000")
    m["reregistered"].append({"view": 43, "step": 2000})  # a second pass
    assert _summary(m).endswith("; re-registered view(s) 14, 79 at step 1000; 43 at step 2000")
    m["reregistered"] = []
    assert "re-registered" not in _summary(m)


def test_eval_prints_pose_errors(monkeypatch, capsys):
    """``warpnerf eval`` on a pose run prints the re-evaluated pose errors, not only PSNR / SSIM."""
    import warpnerf.runs.run
    from warpnerf.cli import main

    res = {"psnr": 21.29, "ssim": 0.587, "rot_err_deg": 0.398, "trans_err_x100": 1.32, "unconverged_views": [],
           "pose_alignment": "orientations"}
    monkeypatch.setattr(warpnerf.runs.run, "evaluate_run", lambda run, progress=True, device=None: res)
    assert main(["eval", "--run", "R", "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line == ("PSNR 21.29 dB; SSIM 0.587; rot err 0.398 deg (orientations aligned); "
                    "trans err (BARF) x100 1.320; written to R/eval/metrics.json")
    res = {"psnr": 30.0, "ssim": 0.95}  # another task: no pose figures
    assert main(["eval", "--run", "R", "--quiet"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "PSNR 30.00 dB; SSIM 0.950; written to R/eval/metrics.json"
