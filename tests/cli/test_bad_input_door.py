"""Validation at the door (issue #64): bad values fail before anything loads or is written, with
exit code 2 and one line naming the file or flag and key."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from PIL import Image

from fake_scenes import write_blender
from warpnerf.cli import main
from warpnerf.train.config import _FLOAT_FIELDS
from door import one_line_error, tree

TRAIN = ["train", "--quiet", "--iters", "2", "--threads", "1", "--video-frames", "0"]


def refused(tmp_path, capsys, argv, *needles):
    """``main(argv)`` exits 2 with one stderr line holding ``needles``, and changes nothing under tmp_path."""
    before = tree(tmp_path)
    assert main(argv) == 2, argv
    line = one_line_error(capsys, *needles)
    assert tree(tmp_path) == before
    return line


@pytest.mark.parametrize("name", _FLOAT_FIELDS)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_every_float_flag_refuses_non_finite_values(tmp_path, capsys, name, value):
    refused(tmp_path, capsys, [*TRAIN, f"--{name.replace('_', '-')}={value}", "--out", str(tmp_path / "run")],
            name)


def test_error_sampling_nan_in_a_config_file(tmp_path, capsys):
    (tmp_path / "c.toml").write_text("error_sampling = nan\n")
    refused(tmp_path, capsys, [*TRAIN, "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "run")],
            "error_sampling", "finite")


@pytest.mark.parametrize("res", ["0", "-3", "4"])
def test_builtin_resolution_out_of_range_is_refused(tmp_path, capsys, res):
    refused(tmp_path, capsys, [*TRAIN, "--builtin-resolution", res, "--out", str(tmp_path / "run")],
            "builtin_resolution")


def test_an_unknown_background_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main([*TRAIN, "--background", "purple", "--out", str(tmp_path / "run")])
    assert e.value.code == 2
    one_line_error(capsys, "--background", "purple", "white")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flags, needles", [
    (["--ndc", "--unbounded"], ("ndc and unbounded",)),
    (["--background", "random", "--no-random-background"], ("background random needs random_background",)),
])
def test_background_and_ray_space_flags_that_cannot_be(tmp_path, capsys, flags, needles):
    refused(tmp_path, capsys, [*TRAIN, *flags, "--out", str(tmp_path / "run")], *needles)


def test_ndc_on_a_scene_that_cannot_have_it(tmp_path, capsys):
    """--ndc chooses the ray space of captures; a Blender-layout scene trains in its box only."""
    write_blender(str(tmp_path / "data" / "scene"), n=2, size=16)
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "scene", "--ndc",
                               "--out", str(tmp_path / "run")], "Blender layout", "--ndc")


# --- data loaders: a non-numeric or non-positive value names the file and the key -------------------------


def _blender(tmp_path, **meta_changes):
    root = write_blender(str(tmp_path / "data" / "scene"), n=2, size=16)
    for split in ("train", "val", "test"):
        path = os.path.join(root, f"transforms_{split}.json")
        with open(path) as f:
            meta = json.load(f)
        for k, v in meta_changes.items():
            if v is None:
                meta.pop(k, None)
            else:
                meta[k] = v
        with open(path, "w") as f:
            json.dump(meta, f)
    return root


@pytest.mark.parametrize("changes, key", [
    ({"camera_angle_x": "wide"}, "camera_angle_x"),
    ({"camera_angle_x": None, "fl_x": "abc"}, "fl_x"),
    ({"camera_angle_x": None, "fl_x": 0}, "fl_x"),
    ({"camera_angle_x": None, "fl_x": -5.0}, "fl_x"),
    ({"camera_angle_x": None, "fl_x": 20.0, "cx": "middle"}, "cx"),
    ({"camera_angle_x": [0.7]}, "camera_angle_x"),
    ({"camera_angle_x": True}, "camera_angle_x"),
])
def test_blender_non_numeric_or_bad_focal(tmp_path, capsys, changes, key):
    _blender(tmp_path, **changes)
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "scene",
                               "--out", str(tmp_path / "run")], "transforms_train.json", key)


def _transforms(tmp_path, top=None, frame=None, n=4, size=16):
    root = tmp_path / "data" / "cap"
    (root / "images").mkdir(parents=True)
    frames = []
    for k in range(n):
        Image.fromarray(np.full((size, size, 3), 40 * k, np.uint8)).save(root / "images" / f"{k}.png")
        a = 0.4 * k
        m = [[np.cos(a), 0, np.sin(a), 3 * np.sin(a)], [0, 1, 0, 0.1 * k], [-np.sin(a), 0, np.cos(a), 3 * np.cos(a)],
             [0, 0, 0, 1]]
        frames.append({"file_path": f"images/{k}.png", "transform_matrix": m, **(frame or {})})
    meta = {"fl_x": 20.0, "fl_y": 20.0, "w": size, "h": size, "frames": frames, **(top or {})}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize("top, frame, key", [
    ({"w": "abc"}, None, "'w'"),
    ({"h": 0}, None, "'h'"),
    ({"w": 15.5}, None, "'w'"),
    ({"aabb_scale": "big"}, None, "aabb_scale"),
    ({"aabb_scale": -2}, None, "aabb_scale"),
    ({"fl_x": "wide"}, None, "fl_x"),
    ({"fl_x": 0.0}, None, "fl_x"),
    ({"fl_y": -1.0}, None, "fl_y"),
    (None, {"fl_x": "x"}, "fl_x"),
    ({"fl_x": None, "camera_angle_x": "wide"}, None, "camera_angle_x"),
    ({"fl_x": None, "camera_angle_x": 4.0}, None, "camera_angle_x"),
    ({"k1": "small"}, None, "k1"),
])
def test_transforms_json_non_numeric_values(tmp_path, capsys, top, frame, key):
    if top and top.get("fl_x", 1) is None:
        top = {k: v for k, v in top.items() if k != "fl_x"}
        root = _transforms(tmp_path, top)
        meta = json.loads((root / "transforms.json").read_text())
        meta.pop("fl_x")
        meta.pop("fl_y")
        (root / "transforms.json").write_text(json.dumps(meta))
    else:
        _transforms(tmp_path, top, frame)
    line = refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "cap",
                                      "--out", str(tmp_path / "run")], "transforms.json", key)
    assert "frame" in line if frame else True


def test_a_zero_byte_poses_bounds_is_one_line(tmp_path, capsys):
    root = tmp_path / "data" / "ff"
    (root / "images_8").mkdir(parents=True)
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(root / "images_8" / "0.png")
    (root / "poses_bounds.npy").write_bytes(b"")
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff",
                               "--out", str(tmp_path / "run")], "poses_bounds.npy")


def test_llff_focal_must_be_positive(tmp_path, capsys):
    from fake_scenes import random_rotations, write_llff

    n = 4
    rng = np.random.default_rng(0)
    write_llff(str(tmp_path / "data" / "ff"), random_rotations(n) * 0 + np.eye(3), rng.normal(size=(n, 3)) * 0.1,
               np.tile([1.0, 10.0], (n, 1)), hwf=(64, 64, 0.0), factor=8)
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff",
                               "--out", str(tmp_path / "run")], "poses_bounds.npy", "focal")


@pytest.mark.parametrize("fx", [0.0, -3.0, float("nan"), float("inf")])
def test_every_capture_layout_refuses_a_bad_focal(tmp_path, fx):
    """COLMAP and transforms.json scenes both go through build_scene: a camera with a zero, negative
    or non-finite focal length is a DatasetError naming the source and image."""
    from warpnerf.data.capture import Frame, build_scene
    from warpnerf.data.distortion import Intrinsics
    from warpnerf.data.errors import DatasetError

    frames = [Frame(f"{k}.png", str(tmp_path / f"{k}.png"), np.eye(4)[:3], Intrinsics(16, 16, fx, 20.0, 8.0, 8.0))
              for k in range(3)]
    with pytest.raises(DatasetError, match=r"sparse/0/cameras.txt \(image 0.png\).*focal"):
        build_scene(frames, None, str(tmp_path), "colmap", "sparse/0/cameras.txt")


# --- sweep specs: a bad retries or resources value is one line, before anything is written ---------------


@pytest.mark.parametrize("line, needle", [
    ('retries = "abc"', "'retries' must be a whole number >= 0, got 'abc'"),
    ("retries = 1.5", "'retries' must be a whole number >= 0, got 1.5"),
    ("retries = true", "'retries' must be a whole number >= 0, got True"),
    ("retries = -1", "'retries' must be a whole number >= 0, got -1"),
    ('resources = "many"', "'resources' must be a table"),
    ('[resources]\nnum_cpus = "two"', "num_cpus must be a number > 0"),
    ("[resources]\nnum_cpus = 0", "num_cpus must be a number > 0"),
    ("[resources]\nnum_gpus = -1", "num_gpus must be a number >= 0"),
    ("[resources]\nnum_gpus = nan", "num_gpus must be a number >= 0"),
    ('overrides = 3', "'overrides' must be a table"),
])
def test_sweep_spec_bad_retries_and_resources(tmp_path, capsys, line, needle):
    spec = tmp_path / "s.toml"
    spec.write_text(f'out = "{tmp_path / "out"}"\nscenes = ["chair"]\n{line}\n')
    refused(tmp_path, capsys, ["sweep", str(spec), "--quiet"], "s.toml", needle)


# --- an output place that cannot be written: one line, even as root (os.access says yes to root) ----------

needs_proc = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")


@needs_proc
@pytest.mark.parametrize("out", ["/proc/x", "/proc/x/y", "/proc/self/x"])
def test_train_into_an_unwritable_out(tmp_path, capsys, monkeypatch, out):
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    refused(tmp_path, capsys, [*TRAIN, "--builtin-resolution", "16", "--out", out], f"run folder {out}")


@needs_proc
def test_sweep_into_an_unwritable_out(tmp_path, capsys):
    spec = tmp_path / "s.toml"
    spec.write_text('out = "/proc/x"\nscenes = ["chair"]\n')
    refused(tmp_path, capsys, ["sweep", str(spec), "--quiet"], "/proc/x", "cannot be created")


@needs_proc
def test_process_into_an_unwritable_out(tmp_path, capsys, monkeypatch):
    import warpnerf.data.process as proc

    monkeypatch.setattr(proc, "backend", lambda: "pycolmap")  # the check comes before COLMAP runs
    (tmp_path / "photos").mkdir()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "photos" / "a.png")
    refused(tmp_path, capsys, ["process", "--images", str(tmp_path / "photos"), "--out", "/proc/x", "--quiet"],
            "--out /proc/x", "cannot be written")


# --- identical camera centres: no parallax, no scale; refused by every layout, naming the file -----------


def test_blender_identical_poses(tmp_path, capsys):
    root = _blender(tmp_path)
    path = os.path.join(root, "transforms_train.json")
    meta = json.load(open(path))
    for fr in meta["frames"]:
        fr["transform_matrix"] = meta["frames"][0]["transform_matrix"]
    json.dump(meta, open(path, "w"))
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "scene",
                               "--out", str(tmp_path / "run")], "transforms_train.json", "2 camera centres coincide")


@pytest.mark.parametrize("rotate", [False, True])  # copied matrices; a camera turning on the spot
def test_transforms_json_identical_centres(tmp_path, capsys, rotate):
    root = _transforms(tmp_path)
    meta = json.loads((root / "transforms.json").read_text())
    for fr in meta["frames"]:
        if rotate:
            fr["transform_matrix"] = [row[:3] + [5.0 if i == 0 else 0.0] for i, row in
                                      enumerate(fr["transform_matrix"][:3])] + [[0, 0, 0, 1]]
        else:
            fr["transform_matrix"] = meta["frames"][1]["transform_matrix"]
    (root / "transforms.json").write_text(json.dumps(meta))
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "cap",
                               "--out", str(tmp_path / "run")], "transforms.json", "4 camera centres coincide")


def test_llff_identical_centres(tmp_path, capsys):
    from fake_scenes import random_rotations, write_llff

    n = 4
    write_llff(str(tmp_path / "data" / "ff"), random_rotations(n), np.tile([[0.5, -1.0, 2.0]], (n, 1)),
               np.tile([1.0, 10.0], (n, 1)), hwf=(64, 64, 50.0), factor=8)
    refused(tmp_path, capsys, [*TRAIN, "--data-root", str(tmp_path / "data"), "--scene", "ff",
                               "--out", str(tmp_path / "run")], "poses_bounds.npy", "coincide", "0.5, -1, 2")


def test_colmap_identical_centres(tmp_path):
    """COLMAP models go through build_scene like transforms.json: the check names the images file."""
    from warpnerf.data.capture import Frame, build_scene
    from warpnerf.data.distortion import Intrinsics
    from warpnerf.data.errors import DatasetError

    frames = [Frame(f"{k}.png", str(tmp_path / f"{k}.png"), np.eye(4)[:3], Intrinsics(16, 16, 20.0, 20.0, 8.0, 8.0))
              for k in range(3)]
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin: all 3 camera centres coincide"):
        build_scene(frames, None, str(tmp_path), "colmap", "sparse/0/images.bin")
    frames[1] = Frame("1.png", str(tmp_path / "1.png"), np.eye(4)[:3] + np.array([[0, 0, 0, 1e-3]] * 3),
                      frames[1].camera)  # a millimetre apart at unit distance: parallax, accepted past this check
    with pytest.raises(DatasetError, match="1.png|0.png"):  # now the missing images are the error
        build_scene(frames, None, str(tmp_path), "colmap", "sparse/0/images.bin")


# --- size flags whose tensors cannot fit memory_budget_mb: refused before anything loads --------------------


@pytest.mark.parametrize("flag, value, key", [
    ("--log2-table-size", "40", "log2_table_size"),
    ("--log2-table-size", "28", "log2_table_size"),
    ("--hidden", "1000000", "hidden"),
    ("--occ-resolution", "5000", "occ_resolution"),
    ("--batch-rays", "2000000000", "batch_rays"),
    ("--sample-budget", "10000000000", "sample_budget"),
])
def test_size_flags_beyond_the_memory_budget(tmp_path, capsys, flag, value, key):
    line = refused(tmp_path, capsys, [*TRAIN, flag, value, "--out", str(tmp_path / "run")],
                   "memory_budget_mb = 4096", f"lower {key}")
    assert "needs at least" in line


def test_a_bigger_memory_budget_lets_a_size_through(tmp_path):
    from warpnerf.train.config import build_config

    with pytest.raises(Exception, match="batch_rays"):
        build_config("full", None, {"batch_rays": 100_000_000})  # 6.1 GB of rays
    assert build_config("full", None, {"batch_rays": 100_000_000, "memory_budget_mb": 8192}).batch_rays == 100_000_000


# --- render, export and view of a run whose checkpoint is truncated or not ours: one line, nothing written ----


def _finished_run_with_checkpoint(folder, data: bytes):
    from warpnerf.runs.folder import MARKER, config_hash, write_config
    from warpnerf.train.config import build_config

    cfg = build_config("full", overrides={"out": str(folder), "builtin_resolution": 16, "video_frames": 0})
    os.makedirs(folder)
    write_config(os.path.join(folder, "config.toml"), cfg)
    with open(os.path.join(folder, "metrics.json"), "w") as f:
        json.dump({"psnr": 1.0, "config_hash": config_hash(cfg), "scene_source": "builtin"}, f)
    open(os.path.join(folder, MARKER), "w").close()
    with open(os.path.join(folder, "checkpoint.pt"), "wb") as f:
        f.write(data)


def _checkpoint_bytes(kind: str) -> bytes:
    import io

    import torch

    buf = io.BytesIO()
    if kind == "truncated":
        torch.save({"format": "warpnerf-checkpoint-1", "x": torch.zeros(1000)}, buf)
        return buf.getvalue()[:700]
    if kind == "foreign":  # another program's state dict: loads, but is not ours
        torch.save({"model": torch.zeros(3)}, buf)
        return buf.getvalue()
    if kind == "empty":
        return b""
    import datetime  # an arbitrary pickled object: weights_only refuses it instead of running it

    torch.save({"format": "warpnerf-checkpoint-1", "obj": datetime.date(2020, 1, 1)}, buf)
    return buf.getvalue()


@pytest.mark.parametrize("kind", ["truncated", "foreign", "empty", "pickle"])
@pytest.mark.parametrize("command", [["render", "--frames", "2"], ["export"], ["export", "--what", "points"],
                                     ["view"]])
def test_outputs_of_a_run_with_a_bad_checkpoint(tmp_path, capsys, monkeypatch, kind, command):
    if command[0] == "view":
        pytest.importorskip("viser")
        import warpnerf.outputs.viewer as viewer_mod

        monkeypatch.setattr(viewer_mod, "serve", lambda *a, **k: pytest.fail("served a bad checkpoint"))
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "cache"))
    _finished_run_with_checkpoint(tmp_path / "run", _checkpoint_bytes(kind))
    refused(tmp_path, capsys, [command[0], "--run", str(tmp_path / "run"), *command[1:], "--quiet"], "checkpoint.pt")
