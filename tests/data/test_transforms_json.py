"""Distortion (round trip, undistorting images), per-frame intrinsics of transforms.json, and
bad capture input as one clear line naming the file."""

import json
import os

import numpy as np
import pytest
from PIL import Image as PILImage

from warpnerf.cli import main
from warpnerf.data import DatasetError
from warpnerf.data import colmap as cm
from warpnerf.data.colmap import load_colmap
from warpnerf.data.distortion import Intrinsics, distort_pixels, undistort_pixels
from warpnerf.data.transforms_json import load_transforms_json

W, H = 64, 48
CAMS = {
    "SIMPLE_RADIAL": Intrinsics(W, H, 50.0, 50.0, 31.0, 25.0, k1=-0.18),
    "RADIAL": Intrinsics(W, H, 50.0, 50.0, 32.5, 23.0, k1=-0.2, k2=0.05),
    "OPENCV": Intrinsics(W, H, 52.0, 49.0, 33.0, 24.5, k1=-0.25, k2=0.07, p1=0.004, p2=-0.003),
}


@pytest.mark.parametrize("model", list(CAMS))
def test_distortion_round_trip_below_1e4th_px(model):
    cam = CAMS[model]
    v, u = np.meshgrid(np.linspace(0, H, 49), np.linspace(0, W, 65), indexing="ij")  # corners included
    ud, vd = distort_pixels(u, v, cam)
    assert np.abs(ud - u).max() > 1.0  # the distortion is not negligible
    uu, vv = undistort_pixels(ud, vd, cam)
    assert max(np.abs(uu - u).max(), np.abs(vv - v).max()) <= 1e-4
    # and the other way round, from observed pixels
    ui, vi = undistort_pixels(u, v, cam)
    u2, v2 = distort_pixels(ui, vi, cam)
    assert max(np.abs(u2 - u).max(), np.abs(v2 - v).max()) <= 1e-4


def pattern(x, y):
    """A smooth colour pattern over ideal normalised image coordinates, (..., 3) in [0, 1]."""
    return np.stack([0.5 + 0.4 * np.sin(3.0 * x + 1.0), 0.5 + 0.4 * np.cos(2.5 * y), 0.5 + 0.3 * np.sin(2.0 * (x + y))], -1)


def photo(cam):
    """What ``cam`` records of the pattern: each observed pixel shows the pattern at its ideal ray."""
    v, u = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    ui, vi = undistort_pixels(u, v, cam)
    return pattern((ui - cam.cx) / cam.fx, (vi - cam.cy) / cam.fy)


def save(path, img):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    PILImage.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8), "RGB").save(path)


def expected_pinhole(width, height, f, cx, cy):
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return pattern((u - cx) / f, (v - cy) / f)


def poses(n):
    """(n, 4, 4) OpenGL cameras on a circle looking at the origin."""
    from warpnerf.data.builtin import look_at

    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c2w = look_at(np.stack([3 * np.cos(a), 3 * np.sin(a), np.full(n, 1.0)], -1)).astype(np.float64)
    return np.concatenate([c2w, np.tile([[[0, 0, 0, 1.0]]], (n, 1, 1))], 1)


def test_transforms_json_undistorts_images_and_uses_per_frame_intrinsics(tmp_path):
    opencv = CAMS["OPENCV"]
    plain = Intrinsics(W, H, 50.0, 50.0, 32.0, 24.0)
    frames = []
    for k, c2w in enumerate(poses(3)):
        cam = opencv if k == 1 else plain
        save(str(tmp_path / "images" / f"f{k}.png"), photo(cam))
        fr = {"file_path": f"images/f{k}.png", "transform_matrix": c2w.tolist()}
        if k == 1:  # per-frame intrinsics override the top level
            fr.update(fl_x=cam.fx, fl_y=cam.fy, cx=cam.cx, cy=cam.cy, k1=cam.k1, k2=cam.k2, p1=cam.p1, p2=cam.p2)
        frames.append(fr)
    meta = {"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": W, "h": H, "frames": frames,
            "train_filenames": ["images/f0.png", "images/f1.png"], "test_filenames": ["images/f2.png"]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = load_transforms_json(str(tmp_path))
    assert (scene.train.focal, scene.train.cx, scene.train.cy) == (50.0, 32.0, 24.0)
    assert scene.train.ids == [0, 1] and scene.test.ids == [2]
    want = expected_pinhole(W, H, 50.0, 32.0, 24.0)
    got0, got1 = scene.train.images[0].numpy(), scene.train.images[1].numpy()
    assert np.abs(got0 - want).max() <= 0.5 / 255 + 1e-6  # the undistorted camera: read as is
    # the distorted frame, resampled: bilinear interpolation of 8-bit pixels on a smooth pattern;
    # the frame edge may map outside the source (clamped), so compare the inner part
    inner = (slice(6, H - 6), slice(6, W - 6))
    err = np.abs(got1[inner] - want[inner])
    assert err.max() < 0.03 and err.mean() < 0.006, (err.max(), err.mean())
    # without the resampling the distorted photo is far off: the test has teeth
    assert np.abs(photo(opencv)[inner] - want[inner]).mean() > 5 * err.mean()


def write_colmap(folder, camera, qt=None, names=("a.png", "b.png"), make_images=True, ext=".txt"):
    cams = {1: camera}
    imgs = {}
    for i, (name, c2w) in enumerate(zip(names, poses(len(names))), start=1):
        q, t = cm.c2w_to_colmap(c2w[:3])
        if qt is not None and i == 1:
            q, t = qt
        imgs[i] = cm.Image(i, q, t, 1, name)
        if make_images:
            save(os.path.join(folder, "images", name), np.full((camera.height, camera.width, 3), 0.5))
    cm.write_model(os.path.join(folder, "sparse", "0"), cams, imgs, {}, ext)


def test_colmap_opencv_camera_is_undistorted(tmp_path):
    cam = CAMS["OPENCV"]
    camera = cm.intrinsics_camera(1, cam)
    assert camera.model == "OPENCV"
    write_colmap(str(tmp_path), camera, ext=".bin")
    for name in ("a.png", "b.png"):
        save(str(tmp_path / "images" / name), photo(cam))
    scene = load_colmap(str(tmp_path), holdout=2)
    assert scene.train.focal == cam.fx and (scene.train.cx, scene.train.cy) == (cam.cx, cam.cy)
    want = expected_pinhole(W, H, cam.fx, cam.cx, cam.cy)
    inner = (slice(6, H - 6), slice(6, W - 6))
    err = np.abs(scene.train.images[0].numpy()[inner] - want[inner])
    assert err.max() < 0.03 and err.mean() < 0.006
    # no points: fallback bounds
    assert scene.aabb == (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)


@pytest.mark.parametrize("model,params", [("SIMPLE_PINHOLE", [40.0, 32, 24]), ("PINHOLE", [40.0, 41.0, 32, 24]),
                                          ("RADIAL", [40.0, 32, 24, 0.01, -0.002]), ("SIMPLE_RADIAL", [40.0, 32, 24, 0.01])])
def test_colmap_models_map_to_intrinsics(model, params):
    k = cm.camera_intrinsics(cm.Camera(1, model, W, H, np.array(params, float)), "cameras.txt")
    assert (k.fx, k.cx, k.cy) == (40.0, 32.0, 24.0)
    back = cm.intrinsics_camera(1, k)
    assert back.model == model and np.allclose(back.params, params)


# ---- bad input: one line naming the file, exit code 2 in the CLI -----------------------------------


def check_one_line(exc_info, *needles):
    msg = str(exc_info.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, (n, msg)


def test_missing_sparse_folder(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "no COLMAP sparse model", str(tmp_path), "warpnerf process")


def test_unsupported_camera_model(tmp_path):
    write_colmap(str(tmp_path), cm.Camera(1, "OPENCV_FISHEYE", W, H, np.array([40.0, 40, 32, 24, 0, 0, 0, 0])), ext=".bin")
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "OPENCV_FISHEYE", os.path.join(str(tmp_path), "sparse", "0", "cameras.bin"), "image_undistorter")


def test_listed_image_absent(tmp_path):
    write_colmap(str(tmp_path), cm.intrinsics_camera(1, CAMS["RADIAL"]))
    os.remove(tmp_path / "images" / "b.png")
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "missing image", os.path.join("images", "b.png"), "images.txt")


def test_non_finite_pose(tmp_path):
    write_colmap(str(tmp_path), cm.intrinsics_camera(1, CAMS["RADIAL"]), qt=(np.array([1.0, 0, 0, 0]), np.array([np.nan, 0, 0])))
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "non-finite pose", "a.png", "images.txt")
    # the same in a transforms.json
    meta = {"fl_x": 40.0, "w": W, "h": H, "frames": [{"file_path": "images/a.png", "transform_matrix": [[float("nan")] * 4] * 4}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as e:
        load_transforms_json(str(tmp_path))
    check_one_line(e, "non-finite values", "frame 0", "transforms.json")  # caught while reading the file


def test_no_registered_image(tmp_path):
    write_colmap(str(tmp_path), cm.intrinsics_camera(1, CAMS["RADIAL"]), names=(), make_images=False)
    (tmp_path / "images").mkdir()
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "no registered image", "images.txt")
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 40.0, "frames": []}))
    with pytest.raises(DatasetError) as e:
        load_transforms_json(str(tmp_path))
    check_one_line(e, "no registered image", "transforms.json")


def test_truncated_binary_model(tmp_path):
    write_colmap(str(tmp_path), cm.intrinsics_camera(1, CAMS["OPENCV"]), ext=".bin")
    path = tmp_path / "sparse" / "0" / "images.bin"
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(DatasetError) as e:
        load_colmap(str(tmp_path))
    check_one_line(e, "truncated", str(path))


def test_cli_prints_one_line_and_exits_2(tmp_path, capsys):
    scene = tmp_path / "root" / "mycapture"
    write_colmap(str(scene), cm.Camera(1, "FOV", W, H, np.array([40.0, 40, 32, 24, 0.9])))
    code = main(["train", "--scene", "mycapture", "--data-root", str(tmp_path / "root"), "--iters", "1",
                 "--out", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("warpnerf: error")]
    assert len(lines) == 1 and "FOV" in lines[0] and "cameras.txt" in lines[0], err
