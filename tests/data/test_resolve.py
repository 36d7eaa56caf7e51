"""Scene resolution (dataset before built-in), scene listing, and the real data (slow)."""

import os

import numpy as np
import pytest
from fake_scenes import random_rotations, write_blender, write_llff

from warpnerf.data import DatasetError, describe_scenes, list_scenes, load_scene


@pytest.fixture
def data_root(tmp_path):
    """A data root holding a Blender scene named like a built-in, plus one in each standard subfolder."""
    write_blender(tmp_path / "chair", n=2, size=4)
    write_blender(tmp_path / "nerf_synthetic" / "mic", n=1, size=4)
    write_llff(tmp_path / "nerf_llff_data" / "leaves", random_rotations(3), np.zeros((3, 3)) + [[0], [1], [2]], np.full((3, 2), [1.0, 5.0]))
    os.makedirs(tmp_path / "not_a_scene")
    return str(tmp_path)


def test_dataset_wins_over_builtin(data_root):
    scene = load_scene("chair", data_root=data_root)
    assert (scene.source, scene.kind) == ("dataset", "blender")
    assert scene.train.images.shape == (2, 4, 4, 3)


def test_standard_subfolders_and_layout_detection(data_root):
    assert load_scene("mic", data_root=data_root).kind == "blender"
    leaves = load_scene("leaves", data_root=data_root, llff_factor=4, llff_holdout=2)
    assert (leaves.kind, leaves.ray_space.kind, leaves.test.ids) == ("llff", "ndc", [0, 2])


def test_data_root_from_env(data_root, monkeypatch):
    monkeypatch.setenv("WARPNERF_DATA", data_root)
    assert load_scene("mic").source == "dataset"


def test_unknown_scene_lists_builtins_and_datasets(data_root):
    with pytest.raises(DatasetError) as err:
        load_scene("sofa", data_root=data_root)
    msg = str(err.value)
    assert "unknown scene 'sofa'" in msg and "chair, lamp, vase" in msg and "chair, leaves, mic" in msg
    assert "not_a_scene" not in msg and "\n" not in msg


def test_missing_data_root_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match=r"data root .*nowhere.* is not a folder"):
        load_scene("chair", data_root=str(tmp_path / "nowhere"))


def test_list_and_describe(data_root, tmp_path, monkeypatch):
    builtins, datasets = list_scenes(data_root)
    assert builtins == ["chair", "lamp", "vase", "stand", "garden", "yard"] and datasets == ["chair", "leaves", "mic"]
    text = describe_scenes(data_root, cache_dir=str(tmp_path / "cache"))
    assert "lamp" in text and "leaves  llff" in text and "overrides the built-in scene" in text
    monkeypatch.delenv("WARPNERF_DATA", raising=False)
    assert "no data root" in describe_scenes(None, cache_dir=str(tmp_path / "cache"))


@pytest.mark.slow
def test_real_lego_and_fern():
    root = os.environ.get("WARPNERF_DATA")
    if not root:
        pytest.skip("set WARPNERF_DATA to the folder holding nerf_synthetic/ and nerf_llff_data/")
    lego = load_scene("lego", data_root=root, splits=("train", "test"))
    assert lego.source == "dataset" and lego.train.images.shape == (100, 400, 400, 3) and len(lego.test) == 200
    assert lego.train.focal == pytest.approx(555.555, abs=1e-2)
    fern = load_scene("fern", data_root=root)
    assert fern.kind == "llff" and fern.test.ids == [0, 8, 16] and fern.train.images.shape == (17, 378, 504, 3)
    assert fern.train.focal == pytest.approx(407.566, abs=1e-2)


def test_builtin_fallback_with_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv("WARPNERF_DATA", raising=False)
    scene = load_scene("vase", builtin_resolution=8, cache_dir=str(tmp_path), progress=False, splits=("train", "test"))
    assert scene.source == "builtin" and scene.train.images.shape == (100, 8, 8, 3) and len(scene.test) == 200
