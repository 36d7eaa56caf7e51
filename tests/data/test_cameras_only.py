"""Cameras-only scene loads (``load_scene(..., pixels=False)``, issue #65): the viewer's start-up reads the
image headers, not the pixels. Everything that does not depend on pixels (poses, intrinsics, normalisation,
bounds, ray space, splits, ids) is the full load's, the background is the one the full load settled (given:
detecting it needs the pixels), and no image is decoded."""

import glob
import json
import os

import numpy as np
import PIL.Image
import PIL.ImageFile
import pytest
import torch
from PIL import Image

from fake_scenes import write_blender
from warpnerf.data import builtin
from warpnerf.data import colmap as cm
from warpnerf.data.background import SettledBackground
from warpnerf.data.distortion import Intrinsics
from warpnerf.data.errors import DatasetError
from warpnerf.data.resolve import load_scene
from warpnerf.data.scene import Views, is_stand_in, stand_in

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data")
FERN = os.path.join(SHARED, "nerf_llff_data", "fern")
RES, COUNTS = 40, (10, 2, 4)  # the built-in chair, small: seconds to generate


def _refuse(*args, **kwargs):
    raise AssertionError("a cameras-only load decoded an image")


def refuse_decoding(m: pytest.MonkeyPatch) -> None:
    """Any pixel decoded (PIL, imageio) fails; opening a file for its header decodes nothing."""
    import imageio.v3 as iio

    m.setattr(PIL.ImageFile.ImageFile, "load", _refuse)
    m.setattr(PIL.Image.Image, "load", _refuse)
    m.setattr(iio, "imread", _refuse)


def full_and_cameras_only(monkeypatch, name, root, **kw):
    """(full load, cameras-only load given the full load's settled background) of scene ``name``; the second
    with every decoder refusing."""
    full = load_scene(name, root, progress=False, **kw)
    settled = SettledBackground.of(full, kw.get("background"))
    with monkeypatch.context() as m:
        refuse_decoding(m)
        cam = load_scene(name, root, progress=False, pixels=False, settled=settled, **kw)
    return full, cam


def assert_same_but_pixels(full, cam):
    assert full.pixels and not cam.pixels
    for attr in ("name", "source", "kind", "root", "ray_space", "background", "background_note", "aabb", "near", "far"):
        assert getattr(cam, attr) == getattr(full, attr), attr
    assert getattr(cam, "image_names", None) == getattr(full, "image_names", None)
    norm_full, norm_cam = getattr(full, "normalization", None), getattr(cam, "normalization", None)
    assert (norm_full is None) == (norm_cam is None)
    if norm_full is not None:
        for k, v in vars(norm_full).items():
            assert np.array_equal(v, getattr(norm_cam, k)) if isinstance(v, np.ndarray) else v == getattr(norm_cam, k), k
    assert (full.val is None) == (cam.val is None)
    for a, b in zip(full.splits(), cam.splits()):
        assert torch.equal(a.c2w, b.c2w) and a.c2w.dtype == b.c2w.dtype
        assert (a.focal, a.cx, a.cy, a.ids, a.height, a.width, len(a)) == (b.focal, b.cx, b.cy, b.ids, b.height,
                                                                            b.width, len(b))
        for t_full, t_cam in ((a.images, b.images), (a.alpha, b.alpha), (a.depth, b.depth)):
            assert (t_full is None) == (t_cam is None)
            if t_full is not None:
                assert t_cam.shape == t_full.shape and t_cam.dtype == t_full.dtype and is_stand_in(t_cam)


def rgb_on_white(path):
    """An RGBA PNG composited on white, as uint8 RGB (a render saved without alpha)."""
    a = np.asarray(Image.open(path)).astype(np.float64) / 255.0
    return np.round(255.0 * (a[..., :3] * a[..., 3:] + 1.0 - a[..., 3:])).astype(np.uint8)


@pytest.fixture(scope="module")
def chair_captures(tmp_path_factory):
    """The built-in chair as RGB-on-white captures (no alpha): COLMAP text, COLMAP binary with an OPENCV
    (distorted) camera, transforms.json without w/h (the sizes then come from the images); and its cache."""
    root = tmp_path_factory.mktemp("captures")
    cache = str(root / "cache")
    for name, layout in (("chairtxt", "colmap-text"), ("chairbin", "colmap-binary"), ("chairjson", "transforms")):
        folder = builtin.export_builtin("chair", str(root / name), layout, RES, cache, COUNTS, points_per_view=20,
                                        progress=False)
        for path in glob.glob(os.path.join(folder, "images", "*.png")):
            Image.fromarray(rgb_on_white(path)).save(path)
    sparse = str(root / "chairbin" / "sparse" / "0")
    cams, imgs, pts = cm.read_model(sparse, ".bin")
    k = cm.camera_intrinsics(cams[1], sparse)
    cams[1] = cm.intrinsics_camera(1, Intrinsics(k.width, k.height, k.fx, k.fx * 1.01, k.cx, k.cy, k1=0.02, p1=0.001))
    cm.write_model(sparse, cams, imgs, pts, ".bin")
    path = str(root / "chairjson" / "transforms.json")
    with open(path) as f:
        meta = json.load(f)
    del meta["w"], meta["h"]
    with open(path, "w") as f:
        json.dump(meta, f)
    return str(root)


def test_stand_ins_hold_no_memory_and_subsets_stay_stand_ins():
    t = stand_in((300, 400, 400, 3))
    assert t.shape == (300, 400, 400, 3) and set(t.stride()) == {0} and t.untyped_storage().nbytes() == 4
    assert is_stand_in(t) and not is_stand_in(torch.zeros(2, 3)) and not is_stand_in(None)
    views = Views(images=t, c2w=torch.zeros(300, 3, 4), focal=1.0, cx=0.5, cy=0.5, alpha=stand_in((300, 400, 400)))
    sub = views.subset([4, 7, 9])  # a few-shot task's training views: indexing would allocate them in full
    assert sub.images.shape == (3, 400, 400, 3) and is_stand_in(sub.images) and is_stand_in(sub.alpha)
    assert sub.ids == [4, 7, 9] and sub.depth is None


def test_the_blender_layout_reads_headers_only(tmp_path, monkeypatch):
    write_blender(str(tmp_path / "fake"), n=3, size=8, depth=True)
    for kw in ({}, {"downscale": 2}, {"splits": ("train", "test")}, {"background": "black"}):
        full, cam = full_and_cameras_only(monkeypatch, "fake", str(tmp_path), **kw)
        assert_same_but_pixels(full, cam)
        assert cam.train.depth is not None and cam.train.alpha is not None  # the layout's depth and alpha
    with monkeypatch.context() as m, pytest.raises(DatasetError, match="decoded an image"):
        refuse_decoding(m)  # the guard itself: a full load does decode (read_image names the file)
        load_scene("fake", str(tmp_path), progress=False)


def test_the_builtin_chair_and_yard_load_cameras_only(tmp_path, monkeypatch):
    """A built-in Blender-layout scene with depth PNGs, and the forward-facing (LLFF-layout, NDC) yard, whose
    photos have no uniform border: auto detects none and they stay opaque."""
    cache = str(tmp_path / "cache")
    monkeypatch.setenv("WARPNERF_CACHE", cache)
    builtin.ensure_builtin("chair", 16, cache, progress=False)  # generated (rendered, written) before decoding is refused
    builtin.ensure_builtin("yard", 32, cache, progress=False)
    full, cam = full_and_cameras_only(monkeypatch, "chair", None, builtin_resolution=16, splits=("train", "test"))
    assert_same_but_pixels(full, cam)
    assert cam.train.depth is not None and cam.background_note == ""
    full, cam = full_and_cameras_only(monkeypatch, "yard", None, builtin_resolution=32)
    assert_same_but_pixels(full, cam)
    assert cam.ray_space.forward_facing and cam.background == (0.0, 0.0, 0.0) and cam.background_note.startswith("none: ")
    assert cam.train.alpha is not None and cam.val is None


@pytest.mark.skipif(not os.path.isdir(FERN), reason="reference data ../shared/data not available")
def test_fern_loads_cameras_only(monkeypatch):
    for kw in ({}, {"llff_test": "last10", "downscale": 2}):
        full, cam = full_and_cameras_only(monkeypatch, "fern", SHARED, **kw)
        assert_same_but_pixels(full, cam)


@pytest.mark.parametrize("name", ["chairtxt", "chairbin", "chairjson"])
def test_rgb_on_white_captures_load_cameras_only_with_the_detected_white(chair_captures, monkeypatch, name):
    full, cam = full_and_cameras_only(monkeypatch, name, chair_captures)
    assert full.background == (1.0, 1.0, 1.0) and full.background_note.startswith("white: the border of ")
    assert full.train.alpha is None  # detected: alpha dropped, trained against the fixed white
    assert_same_but_pixels(full, cam)
    assert cam.val is not None and len(cam.train) == COUNTS[0]
    full, cam = full_and_cameras_only(monkeypatch, name, chair_captures, background="random", downscale=2)
    assert full.train.alpha is not None and "opaque" in full.background_note
    assert_same_but_pixels(full, cam)


def test_the_distorted_capture_gets_the_shared_pinhole(chair_captures, monkeypatch):
    full, cam = full_and_cameras_only(monkeypatch, "chairbin", chair_captures)
    assert_same_but_pixels(full, cam)
    k = cm.camera_intrinsics(cm.read_model(os.path.join(chair_captures, "chairbin", "sparse", "0"), ".bin")[0][1], "")
    assert k.distorted and (cam.train.focal, cam.train.cx, cam.train.cy) == (k.fx, k.cx, k.cy)


def test_the_checks_of_the_full_load_stay(tmp_path):
    root = write_blender(str(tmp_path / "fake"), n=2, size=8)
    settled = SettledBackground("auto", (1.0, 1.0, 1.0), True, "")
    Image.fromarray(np.zeros((6, 8, 4), np.uint8), "RGBA").save(os.path.join(root, "test", "r_1.png"))
    with pytest.raises(DatasetError, match=r"image size mismatch: .*r_1.png is 8x6, expected 8x8"):
        load_scene("fake", str(tmp_path), pixels=False, settled=settled)
    Image.fromarray(np.zeros((8, 8, 3), np.uint8), "RGB").save(os.path.join(root, "test", "r_1.png"))
    with pytest.raises(DatasetError, match=r"channel mismatch: .*r_1.png has 3 channels"):
        load_scene("fake", str(tmp_path), pixels=False, settled=settled)
    os.unlink(os.path.join(root, "test", "r_1.png"))
    with pytest.raises(DatasetError, match=r"missing image .*r_1.png"):
        load_scene("fake", str(tmp_path), pixels=False, settled=settled)
    write_blender(str(tmp_path / "fake"), n=2, size=8)
    with pytest.raises(DatasetError, match="downscale factor 16 is larger than the image"):
        load_scene("fake", str(tmp_path), pixels=False, settled=settled, downscale=16)


def test_a_cameras_only_load_needs_the_settled_background(tmp_path):
    write_blender(str(tmp_path / "fake"))
    with pytest.raises(ValueError, match="takes the settled background"):
        load_scene("fake", str(tmp_path), pixels=False)
    with pytest.raises(ValueError, match="takes the settled background"):
        load_scene("fake", str(tmp_path), settled=SettledBackground("auto", (1.0, 1.0, 1.0), True, ""))
    with pytest.raises(ValueError, match="chosen by --background auto, not black"):
        load_scene("fake", str(tmp_path), pixels=False, background="black",
                   settled=SettledBackground("auto", (1.0, 1.0, 1.0), True, ""))


def test_the_settled_background_round_trips_and_junk_is_no_record():
    rec = SettledBackground("learned", (0.25, 0.5, 1.0), False, "learned with the field, starting from rgb(...)")
    assert SettledBackground.from_dict(json.loads(json.dumps(rec.to_dict()))) == rec
    for junk in (None, "white", [], {}, {**rec.to_dict(), "mode": "green"}, {**rec.to_dict(), "colour": [1, 1]},
                 {**rec.to_dict(), "colour": [float("nan"), 0, 0]}, {**rec.to_dict(), "colour": [2, 0, 0]},
                 {**rec.to_dict(), "alpha": 1}, {**rec.to_dict(), "note": None}):
        assert SettledBackground.from_dict(junk) is None, junk
