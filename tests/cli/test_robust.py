"""Bad input fails at the door: each case writes a broken file or folder, runs the CLI in
a subprocess, and checks exit code 2, one stderr line naming the culprit, and that nothing was written.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from door import error_lines
from fake_scenes import blender_matrix, write_blender, write_llff

TRAIN = ["-m", "warpnerf.cli", "train", "--quiet", "--threads", "1", "--iters", "2", "--video-frames", "0"]


def run_cli(args, cwd, timeout=300, env=None):
    e = dict(os.environ)
    e.update(env or {})
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=e)
    return p.returncode, p.stderr.strip(), time.perf_counter() - t0


def tree(path):
    """Every file under ``path`` with its size and mtime (to show nothing changed)."""
    out = {}
    for root, _, files in os.walk(path):
        for f in files:
            st = os.stat(os.path.join(root, f))
            out[os.path.join(root, f)] = (st.st_size, st.st_mtime_ns)
    return out


def assert_user_error(rc, err, *needles):
    assert rc == 2, err
    # Warp's own notices (no CUDA driver, old kernels in the cache) are not ours to silence
    lines = error_lines(err)
    assert len(lines) == 1, err
    assert lines[0].startswith("warpnerf: error: ")
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])


# --- Blender layout ---------------------------------------------------------------------------


def _edit_frame(root, split, k, matrix):
    path = os.path.join(root, f"transforms_{split}.json")
    with open(path) as f:
        meta = json.load(f)
    meta["frames"][k]["transform_matrix"] = matrix
    with open(path, "w") as f:
        json.dump(meta, f)
    return path


def _nan_matrix():
    m = blender_matrix(1)
    m[0][3] = float("nan")
    return m


def _inf_matrix():
    m = blender_matrix(1)
    m[1][1] = float("inf")
    return m


def _scaled_matrix():
    m = np.asarray(blender_matrix(1))
    m[:3, :3] *= 1.1
    return m.tolist()


def _reflection_matrix():
    m = np.asarray(blender_matrix(1))
    m[:3, 0] *= -1
    return m.tolist()


BAD_POSES = {
    "nan": (_nan_matrix, "non-finite"),
    "inf": (_inf_matrix, "non-finite"),
    "zero": (lambda: np.zeros((4, 4)).tolist(), "not orthonormal"),
    "scaled": (_scaled_matrix, "not orthonormal"),
    "reflection": (_reflection_matrix, "reflection"),
}


@pytest.mark.parametrize("case", sorted(BAD_POSES))
def test_blender_bad_pose(tmp_path, case):
    make, words = BAD_POSES[case]
    root = write_blender(str(tmp_path / "data" / "bad"), n=2, size=4)
    path = _edit_frame(root, "train", 1, make())
    # json writes NaN/Infinity literals, which Python's reader accepts: the loader must check them
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "bad", "--out", "run"], tmp_path)
    assert_user_error(rc, err, path, "frame 1", words)
    assert not (tmp_path / "run").exists()


def test_blender_rgb_images_refused_then_allowed_with_flag(tmp_path):
    from PIL import Image

    root = write_blender(str(tmp_path / "data" / "rgb"), n=2, size=4)
    for split in ("train", "val", "test"):
        for k in range(2):
            p = os.path.join(root, split, f"r_{k}.png")
            Image.open(p).convert("RGB").save(p)
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "rgb", "--out", "run"], tmp_path)
    assert_user_error(rc, err, "r_0.png", "alpha", "--allow-rgb")
    assert not (tmp_path / "run").exists()
    # with the flag the scene loads (one warning line per split); cut it short with a bad n_views
    # so the test stays quick: the error comes after loading, before any folder is written
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "rgb", "--out", "run",
                          "--allow-rgb", "--task", "fewshot", "--n-views", "5"], tmp_path)
    assert rc == 2
    assert "warning" in err and "no alpha channel" in err and "n_views" in err.splitlines()[-1]
    assert not (tmp_path / "run").exists()


def test_blender_missing_test_split(tmp_path):
    root = write_blender(str(tmp_path / "data" / "nosplit"), n=2, size=4, splits=("train",))
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "nosplit", "--out", "run"],
                         tmp_path)
    assert_user_error(rc, err, os.path.join(root, "transforms_test.json"))
    assert not (tmp_path / "run").exists()


def test_blender_malformed_json(tmp_path):
    root = write_blender(str(tmp_path / "data" / "badjson"), n=2, size=4)
    path = os.path.join(root, "transforms_train.json")
    with open(path, "w") as f:
        f.write('{"camera_angle_x": 0.7, "frames": [')
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "badjson", "--out", "run"],
                         tmp_path)
    assert_user_error(rc, err, path, "malformed JSON")
    assert not (tmp_path / "run").exists()


def test_blender_image_size_mismatch(tmp_path):
    from PIL import Image

    root = write_blender(str(tmp_path / "data" / "sizes"), n=2, size=4)
    p = os.path.join(root, "train", "r_1.png")
    Image.new("RGBA", (6, 6)).save(p)
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "sizes", "--out", "run"],
                         tmp_path)
    assert_user_error(rc, err, p, "size mismatch")
    assert not (tmp_path / "run").exists()


def test_blender_missing_image(tmp_path):
    root = write_blender(str(tmp_path / "data" / "noimg"), n=2, size=4)
    p = os.path.join(root, "test", "r_1.png")
    os.unlink(p)
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "noimg", "--out", "run"],
                         tmp_path)
    assert_user_error(rc, err, "r_1.png")
    assert not (tmp_path / "run").exists()


# --- LLFF layout ------------------------------------------------------------------------------


def _llff(tmp_path, name="ff", n=9, bounds=None):
    rot = np.tile(np.eye(3), (n, 1, 1))
    centres = np.stack([np.linspace(-0.2, 0.2, n), np.zeros(n), np.zeros(n)], 1)
    b = np.tile([[1.0, 10.0]], (n, 1)) if bounds is None else bounds
    return write_llff(str(tmp_path / "data" / name), rot, centres, b, hwf=(24, 32, 40.0), factor=8)


def _edit_poses_bounds(root, fn):
    path = os.path.join(root, "poses_bounds.npy")
    pb = np.load(path)
    fn(pb)
    np.save(path, pb)
    return path


def test_llff_nan_pose_fails_in_seconds(tmp_path):
    """The case that used to hang forever (NaN spread by recentring, infinite far bound)."""
    root = _llff(tmp_path)
    path = _edit_poses_bounds(root, lambda pb: pb.__setitem__((3, 3), np.nan))
    rc, err, secs = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff", "--out", "run"],
                            tmp_path)
    assert_user_error(rc, err, path, "pose 3", "non-finite")
    assert not (tmp_path / "run").exists()
    assert secs < 120  # import + load; the old behaviour never returned


@pytest.mark.parametrize("value", [-1.0, 0.0, np.inf])
def test_llff_bad_bounds(tmp_path, value):
    root = _llff(tmp_path)
    path = _edit_poses_bounds(root, lambda pb: pb.__setitem__((2, 15), value))
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff", "--out", "run"], tmp_path)
    assert_user_error(rc, err, path, "bounds of pose 2")
    assert not (tmp_path / "run").exists()


def test_llff_rotation_not_orthonormal(tmp_path):
    root = _llff(tmp_path)
    path = _edit_poses_bounds(root, lambda pb: pb.__setitem__((4, 0), 2.0))
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff", "--out", "run"], tmp_path)
    assert_user_error(rc, err, path, "pose 4", "orthonormal")
    assert not (tmp_path / "run").exists()


def test_llff_wrong_array_shape(tmp_path):
    root = _llff(tmp_path)
    path = os.path.join(root, "poses_bounds.npy")
    np.save(path, np.zeros((9, 16)))
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff", "--out", "run"], tmp_path)
    assert_user_error(rc, err, path, "(N, 17)")
    assert not (tmp_path / "run").exists()


def test_llff_image_count_mismatch(tmp_path):
    root = _llff(tmp_path)
    os.unlink(os.path.join(root, "images_8", "IMG_008.png"))
    rc, err, _ = run_cli([*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff", "--out", "run"], tmp_path)
    assert_user_error(rc, err, "images_8", "8 images", "9 poses")
    assert not (tmp_path / "run").exists()


# --- configuration and run folder ---------------------------------------------------------------

CONFIG_CASES = {
    "threads0": (["--threads", "0"], "thread"),
    "iters0": (["--iters", "0"], "iters"),
    "lr_negative": (["--lr", "-1"], "lr"),
    "checkpoint_every_negative": (["--checkpoint-every", "-1"], "checkpoint_every"),
    "n_views0": (["--task", "fewshot", "--n-views", "0"], "n_views"),
    "n_views_too_many": (["--task", "fewshot", "--n-views", "999", "--builtin-resolution", "16"], "n_views"),
    "unknown_device": (["--device", "tpu"], "device"),
    "unknown_model": (["--model", "nope"], "model"),
    "bad_mask": (["--g2fr-mask", "square"], "g2fr-mask"),  # argparse names the flag
}


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_bad_config_value(tmp_path, case):
    flags, key = CONFIG_CASES[case]
    rc, err, _ = run_cli([*TRAIN, "--out", "run", *flags], tmp_path)
    assert_user_error(rc, err, key)
    assert not (tmp_path / "run").exists()


def test_device_cuda_without_gpu(tmp_path):
    import warp as wp

    wp.config.quiet = True
    if wp.get_cuda_device_count() > 0:
        pytest.skip("a CUDA device is present")
    rc, err, _ = run_cli([*TRAIN, "--out", "run", "--device", "cuda"], tmp_path)
    assert_user_error(rc, err, "cuda")
    assert not (tmp_path / "run").exists()


def test_config_file_unknown_key_and_malformed(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("itres = 5\n")
    rc, err, _ = run_cli([*TRAIN, "--out", "run", "--config", str(bad)], tmp_path)
    assert_user_error(rc, err, str(bad), "itres")
    bad.write_text("iters = \n")
    rc, err, _ = run_cli([*TRAIN, "--out", "run", "--config", str(bad)], tmp_path)
    assert_user_error(rc, err, str(bad), "malformed TOML")
    assert not (tmp_path / "run").exists()


def test_out_under_a_file(tmp_path):
    (tmp_path / "afile").write_text("x")
    rc, err, _ = run_cli([*TRAIN, "--out", "afile/run"], tmp_path)
    assert_user_error(rc, err, "afile", "not a folder")


def test_out_is_foreign_folder(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("x")
    before = tree(tmp_path / "mine")
    rc, err, _ = run_cli([*TRAIN, "--out", "mine"], tmp_path)
    assert_user_error(rc, err, "mine", "not a warpnerf run folder")
    assert tree(tmp_path / "mine") == before


def _fake_run(folder, cfg_overrides=None, finished=True, checkpoint_bytes=None):
    """A run folder as train writes it (config.toml, metrics.json with the config hash)."""
    from warpnerf.train.config import build_config
    from warpnerf.runs.folder import config_hash, write_config

    os.makedirs(folder, exist_ok=True)
    cfg = build_config("full", overrides={"out": str(folder), "iters": 2, "video_frames": 0, "threads": 1,
                                          **(cfg_overrides or {})})
    write_config(os.path.join(folder, "config.toml"), cfg)
    if finished:
        with open(os.path.join(folder, "metrics.json"), "w") as f:
            json.dump({"psnr": 1.0, "config_hash": config_hash(cfg)}, f)
    if checkpoint_bytes is not None:
        with open(os.path.join(folder, "checkpoint.pt"), "wb") as f:
            f.write(checkpoint_bytes)
    return cfg


def test_finished_out_refused_without_overwrite(tmp_path):
    _fake_run(tmp_path / "run")
    before = tree(tmp_path / "run")
    rc, err, _ = run_cli([*TRAIN, "--out", "run"], tmp_path)
    assert_user_error(rc, err, "run", "finished run", "--overwrite")
    assert tree(tmp_path / "run") == before


def test_unfinished_out_refused_without_resume(tmp_path):
    _fake_run(tmp_path / "run", finished=False)
    before = tree(tmp_path / "run")
    rc, err, _ = run_cli([*TRAIN, "--out", "run"], tmp_path)
    assert_user_error(rc, err, "unfinished run", "--resume")
    assert tree(tmp_path / "run") == before


def test_resume_nothing(tmp_path):
    rc, err, _ = run_cli([*TRAIN, "--resume", "nowhere"], tmp_path)
    assert_user_error(rc, err, "nowhere")
    assert not (tmp_path / "nowhere").exists()


def test_resume_finished_run_does_nothing(tmp_path):
    _fake_run(tmp_path / "run")
    before = tree(tmp_path / "run")
    rc, out = None, None
    p = subprocess.run([sys.executable, "-m", "warpnerf.cli", "train", "--quiet", "--resume", "run"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    rc, out = p.returncode, p.stdout
    assert rc == 0 and "already finished" in out
    assert tree(tmp_path / "run") == before


def test_resume_changed_config_refused_without_force(tmp_path):
    _fake_run(tmp_path / "run", finished=False)
    before = tree(tmp_path / "run")
    rc, err, _ = run_cli([*TRAIN[:-4], "--resume", "run", "--lr", "0.5"], tmp_path)
    assert_user_error(rc, err, "config.toml", "lr", "--force")
    assert tree(tmp_path / "run") == before


@pytest.mark.parametrize("kind", ["truncated", "foreign", "pickle"])
def test_resume_bad_checkpoint(tmp_path, kind):
    import io

    import torch

    if kind == "truncated":
        buf = io.BytesIO()
        torch.save({"format": "warpnerf-checkpoint-1", "x": torch.zeros(1000)}, buf)
        data = buf.getvalue()[:700]
    elif kind == "foreign":
        buf = io.BytesIO()
        torch.save({"model": torch.zeros(3)}, buf)
        data = buf.getvalue()
    else:  # an arbitrary pickled object: weights_only must refuse it, not run it
        buf = io.BytesIO()
        import datetime

        torch.save({"format": "warpnerf-checkpoint-1", "obj": datetime.date(2020, 1, 1)}, buf)
        data = buf.getvalue()
    _fake_run(tmp_path / "run", finished=False, checkpoint_bytes=data)
    before = tree(tmp_path / "run")
    rc, err, _ = run_cli([*TRAIN[:-4], "--resume", "run"], tmp_path)
    assert_user_error(rc, err, "checkpoint.pt")
    assert tree(tmp_path / "run") == before


def test_eval_refuses_unfinished_and_truncated(tmp_path):
    _fake_run(tmp_path / "run", finished=False)
    rc, err, _ = run_cli(["-m", "warpnerf.cli", "eval", "--quiet", "--run", "run"], tmp_path)
    assert_user_error(rc, err, "not a finished run")
    _fake_run(tmp_path / "run2", checkpoint_bytes=b"PK\x03\x04 truncated")
    rc, err, _ = run_cli(["-m", "warpnerf.cli", "eval", "--quiet", "--run", "run2"], tmp_path)
    assert_user_error(rc, err, "checkpoint.pt")
    assert not (tmp_path / "run2" / "eval").exists()


# --- in-process units -------------------------------------------------------------------------


def test_config_toml_round_trips_quotes_and_backslashes(tmp_path):
    from warpnerf.runs.folder import config_hash, read_run_config, write_config
    from warpnerf.train.config import build_config

    out = str(tmp_path / 'we"ird\\run')
    cfg = build_config("full", overrides={"out": out, "data_root": 'C:\\data "x"'})
    os.makedirs(out)
    write_config(os.path.join(out, "config.toml"), cfg)
    back = read_run_config(out)
    assert back.data_root == cfg.data_root and back.out == out
    assert config_hash(back) == config_hash(cfg)


def test_checkpoint_is_atomic_and_keeps_previous(tmp_path):
    import torch

    from warpnerf.train.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

    path = str(tmp_path / "c.pt")
    save_checkpoint(path, {"a": torch.arange(3)})
    assert torch.equal(load_checkpoint(path)["a"], torch.arange(3))

    def boom(fh):
        fh.write(b"half")
        raise OSError("disk full")

    from warpnerf.train.checkpoint import atomic_write_bytes

    with pytest.raises(OSError):
        atomic_write_bytes(path, boom)
    assert torch.equal(load_checkpoint(path)["a"], torch.arange(3))  # previous one intact
    assert os.listdir(tmp_path) == ["c.pt"]  # no temp file left behind
    with open(path, "r+b") as f:
        f.truncate(50)
    with pytest.raises(CheckpointError, match="c.pt"):
        load_checkpoint(path)
