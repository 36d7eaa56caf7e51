"""warpnerf.data.blender: compositing, intrinsics, poses, downscale, depth, and clear errors."""

import json
import math
import os

import numpy as np
import pytest
from fake_scenes import blender_matrix, write_blender
from PIL import Image

from warpnerf.data import DatasetError, load_blender


def test_loads_composited_images_intrinsics_and_poses(tmp_path):
    root = write_blender(tmp_path / "s", n=3, size=4, angle=0.7)
    scene = load_blender(root)
    assert (scene.kind, scene.source, scene.name) == ("blender", "dataset", "s")
    assert scene.train.images.shape == (3, 4, 4, 3) and scene.val is not None and len(scene.test) == 3
    img = scene.train.images[0].numpy()
    np.testing.assert_allclose(img[0, 0], 1.0)  # transparent -> white background
    a = 128 / 255
    np.testing.assert_allclose(img[0, 1], [a + (1 - a), 1 - a, 1 - a], atol=1e-6)  # half red on white
    np.testing.assert_allclose(img[2, 2], 128 / 255, atol=1e-6)
    np.testing.assert_allclose(scene.train.alpha[0, 0, :2].numpy(), [0.0, a], atol=1e-6)
    assert scene.train.focal == pytest.approx(0.5 * 4 / math.tan(0.35))
    assert (scene.train.cx, scene.train.cy) == (2.0, 2.0)
    np.testing.assert_allclose(scene.train.c2w[2].numpy(), np.asarray(blender_matrix(2))[:3], atol=1e-6)
    assert scene.train.ids == [0, 1, 2] and scene.train.depth is None
    assert (scene.near, scene.far, scene.aabb) == (2.0, 6.0, (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5))


def test_black_background_and_downscale(tmp_path):
    root = write_blender(tmp_path / "s", n=1, size=4, depth=True)
    scene = load_blender(root, downscale=2, white_background=False, splits=("train", "test"))
    assert scene.background == (0.0, 0.0, 0.0) and scene.val is None
    assert scene.train.images.shape == (1, 2, 2, 3)
    a = 128 / 255
    # Top-left 2x2 block: transparent, half red, two opaque grey pixels, composited on black.
    expected = (np.array([0.0, 0.0, 0.0]) + np.array([a, 0.0, 0.0]) + 2 * 128 / 255) / 4
    np.testing.assert_allclose(scene.train.images[0, 0, 0].numpy(), expected, atol=1e-6)
    assert scene.train.focal == pytest.approx(0.5 * 4 / math.tan(0.35) / 2)
    assert scene.train.cx == 1.0
    np.testing.assert_allclose(scene.train.depth.numpy(), 3.0)


def test_missing_val_split_is_optional(tmp_path):
    root = write_blender(tmp_path / "s", n=1, splits=("train", "test"))
    assert load_blender(root).val is None


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="scene folder not found"):
        load_blender(str(tmp_path / "nope"))


def test_missing_test_split_names_file(tmp_path):
    root = write_blender(tmp_path / "s", n=1, splits=("train",))
    with pytest.raises(DatasetError, match="transforms_test.json"):
        load_blender(root)


def test_malformed_json_names_file(tmp_path):
    root = write_blender(tmp_path / "s", n=1)
    with open(os.path.join(root, "transforms_train.json"), "w") as f:
        f.write('{"camera_angle_x": 0.7, "frames": [')
    with pytest.raises(DatasetError, match=r"malformed JSON in .*transforms_train.json"):
        load_blender(root)


@pytest.mark.parametrize("key", ["camera_angle_x", "transform_matrix", "file_path"])
def test_missing_key_is_named(tmp_path, key):
    root = write_blender(tmp_path / "s", n=2)
    path = os.path.join(root, "transforms_test.json")
    meta = json.load(open(path))
    if key == "camera_angle_x":
        del meta[key]
    else:
        del meta["frames"][1][key]
    json.dump(meta, open(path, "w"))
    with pytest.raises(DatasetError, match=key) as err:
        load_blender(root)
    assert "transforms_test.json" in str(err.value) and "\n" not in str(err.value)


def test_bad_matrix_shape(tmp_path):
    root = write_blender(tmp_path / "s", n=1)
    path = os.path.join(root, "transforms_train.json")
    meta = json.load(open(path))
    meta["frames"][0]["transform_matrix"] = [[1, 0], [0, 1]]
    json.dump(meta, open(path, "w"))
    with pytest.raises(DatasetError, match="frame 0 'transform_matrix'"):
        load_blender(root)


def test_missing_image_names_file(tmp_path):
    root = write_blender(tmp_path / "s", n=3)
    os.remove(os.path.join(root, "train", "r_2.png"))
    with pytest.raises(DatasetError, match=r"missing image .*r_2\.png"):
        load_blender(root)


def test_corrupt_image_names_file(tmp_path):
    root = write_blender(tmp_path / "s", n=3)
    with open(os.path.join(root, "val", "r_1.png"), "wb") as f:
        f.write(b"\x89PNG not really")
    with pytest.raises(DatasetError, match=r"cannot read image .*r_1\.png"):
        load_blender(root)


def test_size_mismatch_names_file(tmp_path):
    root = write_blender(tmp_path / "s", n=3, size=4)
    Image.fromarray(np.zeros((5, 4, 4), np.uint8), "RGBA").save(os.path.join(root, "train", "r_1.png"))
    with pytest.raises(DatasetError, match=r"image size mismatch: .*r_1\.png is 4x5, expected 4x4"):
        load_blender(root)
