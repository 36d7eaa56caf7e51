"""`warpnerf process`: rendered photos of a textured built-in scene -> COLMAP -> poses that match
the rendering cameras; failures say how many images registered."""

import math
import os
import re

import numpy as np
import pytest
import torch
from PIL import Image

from warpnerf.cli import main
from warpnerf.data import DatasetError, builtin
from warpnerf.data.colmap import load_colmap

RES = 200


def garden_cameras():
    """36 cameras: two rings (15° and 40° elevation) of 18, 20° apart, looking at the chair."""
    az = np.radians(np.arange(0, 360, 20.0))
    eyes = []
    for el, r in ((15.0, 4.5), (40.0, 4.0)):
        e = math.radians(el)
        eyes += [[r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)] for a in az]
    return builtin.look_at(np.array(eyes), target=(0.0, 0.0, -0.3))


def write_photos(folder, c2w):
    rgb, _ = builtin.render_garden(c2w, RES, RES, builtin.focal_from_angle(RES))
    os.makedirs(folder, exist_ok=True)
    for k in range(len(c2w)):
        Image.fromarray(np.round(rgb[k] * 255).astype(np.uint8)).save(os.path.join(folder, f"v{k:02d}.png"))


def test_garden_render_is_textured_everywhere():
    c2w = garden_cameras()[:2]
    rgb, depth = builtin.render_garden(c2w, 48, 48, builtin.focal_from_angle(48))
    assert rgb.shape == (2, 48, 48, 3) and np.all(depth > 0)  # no pixel misses: ground or environment
    assert np.all(depth.max(axis=(1, 2)) > 5.0)  # the distant environment is visible
    assert rgb.std() > 0.1


def test_process_registers_every_rendered_photo_and_recovers_the_poses(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    from warpnerf.geometry.cameras import evaluate_poses
    from warpnerf.geometry.rig import classify_rig

    c2w = garden_cameras()
    assert len(c2w) >= 30
    write_photos(str(tmp_path / "photos"), c2w)
    out = tmp_path / "data" / "garden"
    # measured: ~22 s of CPU on this machine (SIFT on 36 x 200 px, exhaustive matching, mapping)
    code = main(["process", "--images", str(tmp_path / "photos"), "--out", str(out), "--quiet"])
    assert code == 0
    scene = load_colmap(str(out), normalize=False)  # the loader reads what process wrote
    pos = scene.train.ids + scene.test.ids
    assert len(pos) == len(c2w)  # every image registered
    est = torch.cat([scene.train.c2w, scene.test.c2w]).double()
    gt = torch.from_numpy(c2w[[int(scene.image_names[i][1:3]) for i in pos]]).double()
    ev = evaluate_poses(est, gt)
    print("rot", ev["rot_err_deg"], max(ev["rot_err_deg_per_view"]), "trans x100", ev["trans_err_x100"])
    # measured: mean 0.24°, worst view 0.40° with the focal length estimated by COLMAP
    assert ev["rot_err_deg"] <= 0.5
    assert max(ev["rot_err_deg_per_view"]) <= 1.0
    # the summary: how many registered, the mean reprojection error, and the rig of the registered cameras
    out_lines = capsys.readouterr().out.splitlines()
    summary = next(ln for ln in out_lines if ln.startswith("registered "))
    print(summary)
    assert summary.startswith(f"registered {len(c2w)} of {len(c2w)} images")
    err = float(re.search(r"mean reprojection error (\S+) px", summary).group(1))
    assert math.isfinite(err) and 0 < err < 2.0  # sub-pixel-ish on clean renders; NaN/0 would mean no points
    rig = classify_rig(est.numpy())  # the cameras the loader read back from what process wrote
    assert rig.kind == "object"  # two rings looking at the chair
    assert re.search(r"rig (\S+),", summary).group(1) == rig.kind
    assert any(ln.startswith("rig: object-centric:") for ln in out_lines)


def test_mapping_failure_says_how_many_registered(tmp_path):
    pytest.importorskip("pycolmap")
    from warpnerf.data.process import process_images

    rng = np.random.default_rng(0)
    photos = tmp_path / "noise"
    photos.mkdir()
    for k in range(4):  # unrelated random images: nothing matches
        Image.fromarray(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)).save(photos / f"n{k}.png")
    with pytest.raises(DatasetError) as e:
        process_images(str(photos), str(tmp_path / "out"), progress=False)
    msg = str(e.value)
    assert "\n" not in msg and "0 of 4 images" in msg and str(photos) in msg


def test_process_bad_input_is_one_line(tmp_path, capsys):
    assert main(["process", "--images", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "image folder not found" in err[0] and "nope" in err[0]
    (tmp_path / "empty").mkdir()
    assert main(["process", "--images", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "no images" in capsys.readouterr().err


# --- --out: new, empty, or an earlier process output re-made with --overwrite (issue #64) ---------------


class FakeColmap:
    """What the fake pycolmap did: ``calls`` [(matcher, extract)], and what each matcher registers
    (``registers[matcher]``: the fraction of the photos, the first ones by name)."""

    def __init__(self):
        self.calls = []
        self.registers = {"exhaustive": 1.0, "sequential": 1.0}


@pytest.fixture
def fake_colmap(monkeypatch):
    """Mapping that registers the photos (all by default; see FakeColmap) and writes a model of them as
    cameras on a ring looking at the origin, in no time."""
    import warpnerf.data.process as proc
    from warpnerf.data import colmap as cm

    fake = FakeColmap()

    class Rec:
        def __init__(self, names):
            self.names = names

        def num_reg_images(self):
            return len(self.names)

        def num_points3D(self):
            return 0

        def compute_mean_reprojection_error(self):
            return 0.5

        def write(self, folder):
            az = np.linspace(0, 2 * np.pi, len(self.names), endpoint=False)
            eyes = np.stack([4 * np.cos(az), 4 * np.sin(az), np.full_like(az, 1.5)], axis=1)
            cams = {1: cm.Camera(1, "PINHOLE", 8, 8, np.array([8.0, 8.0, 4.0, 4.0]))}
            imgs = {}
            for k, (name, pose) in enumerate(zip(self.names, builtin.look_at(eyes)), start=1):
                q, t = cm.c2w_to_colmap(pose)
                imgs[k] = cm.Image(k, q, t, 1, name)
            cm.write_model(folder, cams, imgs, {})

    def run(img_dir, db, models, names, camera_model, camera_params, single_camera, matcher, *a, extract=True):
        fake.calls.append((matcher, extract))
        return Rec(names[: int(fake.registers[matcher] * len(names))])

    monkeypatch.setattr(proc, "backend", lambda: "pycolmap")
    monkeypatch.setattr(proc, "_run_pycolmap", run)
    return fake


def photos(folder, names=("a.png", "b.png", "c.png")):
    os.makedirs(folder, exist_ok=True)
    for n in names:
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(os.path.join(folder, n))
    return str(folder)


def process(tmp_path, out, *extra, images=None):
    return main(["process", "--images", images or str(tmp_path / "photos"), "--out", str(out), "--quiet", *extra])


@pytest.mark.parametrize("overwrite", [False, True])
def test_process_refuses_a_folder_it_did_not_write(tmp_path, capsys, fake_colmap, overwrite):
    from door import one_line_error, tree

    photos(tmp_path / "photos")
    out = tmp_path / "mine"
    (out / "notes").mkdir(parents=True)
    (out / "notes.txt").write_text("keep me")
    before = tree(tmp_path)
    assert process(tmp_path, out, *(["--overwrite"] if overwrite else [])) == 2
    one_line_error(capsys, str(out), "not empty", "notes.txt", "not written by warpnerf process")
    assert tree(tmp_path) == before


def test_process_refuses_a_file_as_out(tmp_path, capsys, fake_colmap):
    from door import one_line_error, tree

    photos(tmp_path / "photos")
    (tmp_path / "f").write_text("x")
    before = tree(tmp_path)
    assert process(tmp_path, tmp_path / "f") == 2
    one_line_error(capsys, "is not a folder")
    assert tree(tmp_path) == before


def test_process_remakes_its_own_output_only_with_overwrite(tmp_path, capsys, fake_colmap):
    from door import one_line_error, tree
    from warpnerf.data.process import MARKER

    photos(tmp_path / "photos")
    out = tmp_path / "data" / "scene"
    assert process(tmp_path, out) == 0  # a new folder
    assert sorted(os.listdir(out)) == sorted([MARKER, "colmap", "images", "images_2", "images_4", "sparse"])
    capsys.readouterr()
    before = tree(tmp_path)
    assert process(tmp_path, out) == 2
    one_line_error(capsys, "earlier warpnerf process output", "--overwrite")
    assert tree(tmp_path) == before
    photos(tmp_path / "other", names=("x.png", "y.png", "z.png"))
    assert process(tmp_path, out, "--overwrite", images=str(tmp_path / "other")) == 0
    assert sorted(os.listdir(out / "images")) == ["x.png", "y.png", "z.png"]  # the earlier photos went with their model
    assert os.path.isfile(out / "sparse" / "0" / "images.bin")
    assert len(load_colmap(str(out), normalize=False).image_names) == 3


def test_process_in_place_and_into_an_empty_folder(tmp_path, fake_colmap):
    out = tmp_path / "scene"
    photos(out / "images")  # the photos already in DATASET/images
    assert process(tmp_path, out, images=str(out / "images")) == 0
    assert sorted(os.listdir(out / "images")) == ["a.png", "b.png", "c.png"]
    photos(tmp_path / "photos")
    (tmp_path / "empty").mkdir()
    assert process(tmp_path, tmp_path / "empty") == 0


# --- what process tells the user: the rig, the matching, a poor registration (issue #63) ------------------


@pytest.mark.parametrize("flag", ["--matching", "--matcher"])
def test_matching_flag_and_its_old_name_parse(flag):
    import argparse

    from warpnerf.data.process import add_parser

    p = add_parser(argparse.ArgumentParser().add_subparsers())
    assert p.parse_args(["--images", "x", "--out", "y", flag, "sequential"]).matcher == "sequential"
    assert p.parse_args(["--images", "x", "--out", "y"]).matcher is None
    with pytest.raises(SystemExit):
        p.parse_args(["--images", "x", "--out", "y", flag, "vocab"])
    assert "--matcher is the same flag" in " ".join(p.format_help().split())


def test_summary_names_the_rig_and_the_reprojection_error(tmp_path, capsys, fake_colmap):
    photos(tmp_path / "photos", names=[f"p{k}.png" for k in range(6)])
    assert process(tmp_path, tmp_path / "out") == 0
    cap = capsys.readouterr()
    assert fake_colmap.calls == [("exhaustive", True)]
    assert cap.err == ""  # everything registered: no warning
    lines = cap.out.splitlines()
    assert re.fullmatch(r"registered 6 of 6 images, 0 points, mean reprojection error 0\.50 px, rig object, "
                        r"[0-9.]+ s \(pycolmap, exhaustive matching\)", lines[0]), lines[0]
    assert lines[1].startswith("rig: object-centric: 6 cameras look at one point")


def test_poor_sequential_matching_falls_back_to_exhaustive(tmp_path, capsys, fake_colmap):
    from warpnerf.data.colmap import read_colmap_poses

    photos(tmp_path / "photos", names=[f"p{k}.png" for k in range(10)])
    fake_colmap.registers = {"sequential": 0.5, "exhaustive": 0.9}
    assert process(tmp_path, tmp_path / "out", "--matching", "sequential") == 0
    cap = capsys.readouterr()
    assert fake_colmap.calls == [("sequential", True), ("exhaustive", False)]  # the same features, matched again
    assert cap.err.splitlines() == [
        "warpnerf process: sequential matching registered 5 of 10 images (under 80 %): matching exhaustively once "
        "and keeping the better model",
        "warpnerf process: 9 of 10 images registered; the others are left out"]
    assert cap.out.startswith("registered 9 of 10 images") and "(pycolmap, exhaustive matching)" in cap.out
    assert len(read_colmap_poses(str(tmp_path / "out"))) == 9  # the exhaustive model was written


def test_fallback_keeps_the_better_model_and_warns_under_80_percent(tmp_path, capsys, fake_colmap):
    from warpnerf.data.colmap import read_colmap_poses

    photos(tmp_path / "photos", names=[f"p{k}.png" for k in range(10)])
    fake_colmap.registers = {"sequential": 0.6, "exhaustive": 0.4}  # exhaustive does worse: sequential's stays
    assert process(tmp_path, tmp_path / "out", "--matcher", "sequential") == 0
    cap = capsys.readouterr()
    assert fake_colmap.calls == [("sequential", True), ("exhaustive", False)]
    err = cap.err.splitlines()
    assert len(err) == 2 and "matching exhaustively once" in err[0]
    assert err[1].startswith("warpnerf process: warning: only 6 of 10 images registered (60 %, under 80 %)")
    assert "--matching exhaustive (tried after sequential)" in err[1] and "more overlap" in err[1]
    assert cap.out.startswith("registered 6 of 10 images") and "(pycolmap, sequential matching)" in cap.out
    assert len(read_colmap_poses(str(tmp_path / "out"))) == 6


def test_exhaustive_matching_is_not_rerun_and_warns(tmp_path, capsys, fake_colmap):
    photos(tmp_path / "photos", names=[f"p{k}.png" for k in range(10)])
    fake_colmap.registers["exhaustive"] = 0.7
    assert process(tmp_path, tmp_path / "out") == 0
    cap = capsys.readouterr()
    assert fake_colmap.calls == [("exhaustive", True)]
    err = cap.err.splitlines()
    assert len(err) == 1 and "only 7 of 10 images registered (70 %, under 80 %) with --matching exhaustive;" in err[0]
    assert "tried after" not in err[0] and "more overlap" in err[0]


# --- --video: the sharpest frame of each window, then the photo pipeline (issue #65) ----------------------


def _texture(seed, size=64):
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)


def _blur(img, r=3):
    """Box blur of radius r (wrapping at the borders)."""
    acc = np.zeros(img.shape, np.float64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            acc += np.roll(img, (dy, dx), axis=(0, 1))
    return (acc / (2 * r + 1) ** 2).round().astype(np.uint8)


def write_video(path, frames, fps=10):
    iio = pytest.importorskip("imageio.v2")
    pytest.importorskip("imageio_ffmpeg")  # the FFMPEG writer plugin
    with iio.get_writer(str(path), fps=fps, codec="libx264", quality=10, macro_block_size=16,
                        pixelformat="yuv420p") as w:
        for f in frames:
            w.append_data(f)
    return str(path)


def test_video_keeps_the_sharpest_frame_of_each_window(tmp_path):
    from warpnerf.data.process import extract_frames, sharpness

    sharp_at = {1, 7, 8}  # windows of 4 frames: 0-3, 4-7, 8-11
    frames = [_texture(i) if i in sharp_at else _blur(_texture(i)) for i in range(12)]
    video = write_video(tmp_path / "v.mp4", frames)
    res = extract_frames(video, str(tmp_path / "frames"), num_frames=3, progress=False)
    assert res == {"frames": 3, "video_frames": 12, "picked": [1, 7, 8]}
    written = sorted(os.listdir(tmp_path / "frames"))
    assert written == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    # what was written is the sharp frame, not a blurred one
    first = np.asarray(Image.open(tmp_path / "frames" / written[0]))
    assert sharpness(first) > 5 * sharpness(frames[0])


def test_video_frame_counts(tmp_path):
    from warpnerf.data.process import extract_frames

    video = write_video(tmp_path / "v.mp4", [_blur(_texture(i), 1 + i % 3) for i in range(30)])
    assert extract_frames(video, str(tmp_path / "a"), num_frames=7, progress=False)["frames"] == 7
    assert len(os.listdir(tmp_path / "a")) == 7
    res = extract_frames(video, str(tmp_path / "b"), num_frames=100, progress=False)  # fewer frames: every one
    assert res["frames"] == 30 and res["picked"] == list(range(30))


def test_process_video_runs_the_photo_pipeline(tmp_path, capsys, fake_colmap):
    from warpnerf.data.process import MARKER

    video = write_video(tmp_path / "v.mp4", [_blur(_texture(i), 1 + i % 3) for i in range(20)])
    out = tmp_path / "data" / "clip"
    assert main(["process", "--video", video, "--out", str(out), "--num-frames", "5", "--quiet"]) == 0
    assert "5 frames kept of 20" in capsys.readouterr().out
    assert sorted(os.listdir(out)) == sorted([MARKER, "colmap", "images", "images_2", "images_4", "sparse"])
    assert len(os.listdir(out / "images")) == 5
    for d, size in (("images", 64), ("images_2", 32), ("images_4", 16)):
        names = sorted(os.listdir(out / d))
        assert names == [f"frame_{k:05d}.png" for k in range(1, 6)]
        assert Image.open(out / d / names[0]).size == (size, size)
    # re-made only with --overwrite, like a photo folder's output
    assert main(["process", "--video", video, "--out", str(out), "--num-frames", "4", "--quiet"]) == 2
    assert main(["process", "--video", video, "--out", str(out), "--num-frames", "4", "--num-downscales", "0",
                 "--overwrite", "--quiet"]) == 0
    assert len(os.listdir(out / "images")) == 4 and not os.path.exists(out / "images_2")


def test_process_video_without_the_extra_is_one_line(tmp_path, capsys, monkeypatch, fake_colmap):
    import sys

    from door import one_line_error, tree

    (tmp_path / "v.mp4").write_bytes(b"not really a video")
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails as when the extra is missing
    before = tree(tmp_path)
    assert main(["process", "--video", str(tmp_path / "v.mp4"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    one_line_error(capsys, "imageio-ffmpeg", "pip install 'warpnerf[video]'")
    assert tree(tmp_path) == before
    assert main(["process", "--video", str(tmp_path / "nope.mp4"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    one_line_error(capsys, "video not found", "nope.mp4")
