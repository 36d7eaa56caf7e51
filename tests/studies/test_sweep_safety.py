"""Sweep safety (issue #64): a rerun with a changed spec never replaces finished runs without
``--overwrite``; scene names cannot write outside ``out``; ``out`` reaches workers as an absolute path."""

from __future__ import annotations

import json
import os

import pytest

import warpnerf.studies.sweep as sweep_mod
from warpnerf.cli import main
from warpnerf.studies.sweep import expand, load_spec, run_sweep
from warpnerf.train.config import ConfigError
from door import tree, one_line_error

SPEC = """out = "{out}"
scenes = {scenes}
tasks = ["fewshot"]
arms = ["nog2fr"]
retries = 0
[overrides]
builtin_resolution = 16
iters = {iters}
video_frames = 0
"""


def write_spec(path, out, scenes=("chair",), iters=20):
    path.write_text(SPEC.format(out=out, scenes=json.dumps(list(scenes)), iters=iters))
    return str(path)


def finished_run(spec_path):
    """The spec's run folder holding a finished run of it (as a sweep leaves it)."""
    from warpnerf.runs.folder import MARKER, config_hash, write_config

    (run,) = expand(load_spec(spec_path))
    os.makedirs(run.cfg.run_dir())
    write_config(os.path.join(run.cfg.run_dir(), "config.toml"), run.cfg)
    with open(os.path.join(run.cfg.run_dir(), "metrics.json"), "w") as f:
        json.dump({"psnr": 20.0, "ssim": 0.5, "config_hash": config_hash(run.cfg)}, f)
    open(os.path.join(run.cfg.run_dir(), MARKER), "w").close()
    return run


def test_a_changed_spec_does_not_replace_finished_runs(tmp_path, capsys):
    out = tmp_path / "out"
    finished_run(write_spec(tmp_path / "old.toml", out, iters=20))
    changed = write_spec(tmp_path / "new.toml", out, iters=30)
    before = tree(tmp_path)
    assert main(["sweep", changed, "--quiet"]) == 2
    one_line_error(capsys, "chair_fewshot_ngp_nog2fr_s0", "finished run", "iters", "--overwrite")
    assert tree(tmp_path) == before


def test_the_worker_refuses_too(tmp_path):
    """A run that finished between the driver's check and the worker's start is not lost either."""
    out = tmp_path / "out"
    finished_run(write_spec(tmp_path / "old.toml", out, iters=20))
    (run,) = expand(load_spec(write_spec(tmp_path / "new.toml", out, iters=30)))
    before = tree(tmp_path)
    with pytest.raises(ConfigError, match="iters"):
        sweep_mod._continue_or_replace(run.cfg)
    result = sweep_mod.execute_run(run.cfg.to_dict())
    assert result["status"] == "failed" and "iters" in result["error"]
    assert tree(tmp_path) == before


def test_the_same_spec_still_skips_finished_runs(tmp_path, monkeypatch):
    out = tmp_path / "out"
    spec_path = write_spec(tmp_path / "s.toml", out)
    finished_run(spec_path)
    monkeypatch.setattr(sweep_mod, "execute_run", lambda *a, **k: pytest.fail("a finished run was run again"))
    res = run_sweep(load_spec(spec_path), progress=False)
    assert [r.status for r in res["results"]] == ["skipped"]


@pytest.mark.parametrize("scene", ["../../x", "../x", "a/b", "..", "/abs/path", "a\\\\b"])
def test_a_scene_name_cannot_write_outside_out(tmp_path, capsys, monkeypatch, scene):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "deep" / "er").mkdir(parents=True)
    spec = write_spec(tmp_path / "s.toml", "deep/er/out", scenes=[scene])
    before = tree(tmp_path)
    assert main(["sweep", spec, "--quiet"]) == 2
    one_line_error(capsys, "outside out")
    assert tree(tmp_path) == before


def test_out_reaches_workers_as_an_absolute_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    seen = []

    def fake_execute(cfg_values, threads=None, log_path=None, stream=False, overwrite=False):
        seen.append((cfg_values["out"], cfg_values.get("data_root"), log_path))
        return {"status": "failed", "error": "not run in this test", "machine": "test"}

    monkeypatch.setattr(sweep_mod, "execute_run", fake_execute)
    spec = load_spec(write_spec(tmp_path / "s.toml", "rel/out"))
    spec.data_root = "data"
    run_sweep(spec, progress=False)
    ((out, data_root, log_path),) = seen
    assert os.path.isabs(out) and out == str(tmp_path / "rel" / "out" / "chair_fewshot_ngp_nog2fr_s0")
    assert data_root == str(tmp_path / "data") and os.path.isabs(log_path)
    assert log_path.startswith(str(tmp_path / "rel" / "out"))


def test_table_replaces_finished_runs_only_with_overwrite(tmp_path, capsys, monkeypatch):
    """`warpnerf table` is a sweep too: other --iters are refused, and --overwrite retrains both arms."""
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("builtin_resolution = 16\nvideo_frames = 0\neval_max_views = 1\n")
    out = tmp_path / "table"
    args = ["table", "--scenes", "chair", "--tasks", "fewshot", "--config", str(cfg), "--out", str(out), "--quiet"]
    assert main([*args, "--iters", "5"]) == 0
    capsys.readouterr()
    before = tree(out)
    assert main([*args, "--iters", "6"]) == 2
    one_line_error(capsys, "finished run", "iters", "--overwrite")
    assert tree(out) == before
    assert main([*args, "--iters", "6", "--overwrite"]) == 0
    for arm in ("g2fr", "nog2fr"):
        assert json.loads((out / f"chair_fewshot_ngp_{arm}_s0" / "metrics.json").read_text())["iters"] == 6
