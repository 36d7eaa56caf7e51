"""Built-in scenes: Blender-layout round trip, cameras, depth, and the cache protocol."""

import json
import math
import os

import numpy as np
import pytest

from warpnerf.data import DatasetError, builtin_scenes, load_blender, load_builtin
from warpnerf.data import builtin

COUNTS = (4, 2, 3)  # tiny splits keep the round trip under a second


@pytest.fixture(scope="module")
def chair_dir(tmp_path_factory):
    cache = str(tmp_path_factory.mktemp("cache"))
    return cache, builtin.ensure_builtin("chair", 32, cache, COUNTS, progress=False)


def test_round_trip_through_blender_loader(chair_dir):
    cache, folder = chair_dir
    scene = load_builtin("chair", 32, cache, counts=COUNTS, progress=False)
    assert (scene.source, scene.kind, scene.name) == ("builtin", "blender", "chair")
    assert scene.train.images.shape == (4, 32, 32, 3)
    assert len(scene.val) == 2 and len(scene.test) == 3
    meta = json.load(open(os.path.join(folder, "transforms_train.json")))
    assert meta["camera_angle_x"] == builtin.CAMERA_ANGLE_X
    assert scene.train.focal == pytest.approx(16 / math.tan(builtin.CAMERA_ANGLE_X / 2))
    cams = builtin.split_cameras(COUNTS)
    for split in ("train", "val", "test"):
        np.testing.assert_array_equal(getattr(scene, split).c2w.numpy(), cams[split])  # float32 survives JSON exactly
    centres = scene.train.c2w[:, :, 3].numpy()
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), builtin.CAMERA_RADIUS, rtol=1e-6)
    assert np.all(centres[:, 2] >= 0)  # upper hemisphere
    test_el = np.degrees(np.arcsin(scene.test.c2w[:, 2, 3].numpy() / builtin.CAMERA_RADIUS))
    np.testing.assert_allclose(test_el, builtin.TEST_ELEVATION_DEG, atol=1e-4)
    # Exact alpha: depth > 0 exactly where alpha is 1, background exactly white elsewhere.
    alpha, depth = scene.train.alpha.numpy(), scene.train.depth.numpy()
    assert set(np.unique(alpha)) == {0.0, 1.0}
    assert np.array_equal(depth > 0, alpha == 1.0)
    assert np.all(scene.train.images.numpy()[alpha == 0] == 1.0)
    assert 0.1 < alpha.mean() < 0.6  # the chair fills a sensible part of the frame


def test_depth_back_projects_onto_the_mesh_box(chair_dir):
    cache, folder = chair_dir
    scene = load_blender(folder, splits=("train", "test"))
    v = scene.train
    rows, cols = np.meshgrid(np.arange(v.height), np.arange(v.width), indexing="ij")
    lo, hi = builtin.scene_mesh("chair").bounds()
    for k in range(len(v)):
        z = v.depth[k].numpy()
        m = z > 0
        # OpenGL camera: x right, y up, looking down -z; depth is the distance along -z.
        cam = np.stack([(cols[m] + 0.5 - v.cx) / v.focal * z[m], -(rows[m] + 0.5 - v.cy) / v.focal * z[m], -z[m]], 1)
        c2w = v.c2w[k].numpy()
        world = cam @ c2w[:, :3].T + c2w[:, 3]
        # 16-bit depth quantisation is 1e-4 units; allow 2e-3 for float32 and rounding.
        assert np.all(world >= lo - 2e-3) and np.all(world <= hi + 2e-3)


def test_half_written_cache_is_regenerated(tmp_path):
    cache = str(tmp_path)
    counts = (1, 1, 1)
    folder = builtin.ensure_builtin("vase", 16, cache, counts, progress=False)
    # Simulate an interrupted copy/generation: no marker and a truncated image.
    os.remove(os.path.join(folder, ".complete"))
    open(os.path.join(folder, "train", "r_0.png"), "wb").close()
    # ...and a temp folder left behind by a process that no longer exists (pids stop below 2^22).
    stale = os.path.join(os.path.dirname(folder), f".tmp-{builtin.cache_key('vase', 16, counts)}-{2**22 + 7}-dead")
    os.makedirs(stale)
    assert not builtin.is_complete(folder)
    again = builtin.ensure_builtin("vase", 16, cache, counts, progress=False)
    assert again == folder and builtin.is_complete(folder)
    assert not os.path.exists(stale)
    assert load_builtin("vase", 16, cache, counts=counts, progress=False).train.images.shape == (1, 16, 16, 3)


def test_complete_cache_is_reused(chair_dir):
    cache, folder = chair_dir
    marker = os.path.join(folder, ".complete")
    before = os.stat(marker).st_mtime_ns
    assert builtin.ensure_builtin("chair", 32, cache, COUNTS, progress=False) == folder
    assert os.stat(marker).st_mtime_ns == before


def test_unwritable_cache_names_path_and_env_var(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(DatasetError, match=r"a_file.*WARPNERF_CACHE"):
        load_builtin("chair", 16, str(blocker / "cache"), progress=False)


def test_cache_location_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("WARPNERF_CACHE", str(tmp_path / "c"))
    assert builtin.cache_root() == str(tmp_path / "c" / "scenes")
    monkeypatch.delenv("WARPNERF_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert builtin.cache_root() == str(tmp_path / "x" / "warpnerf" / "scenes")


def test_unknown_builtin_lists_names():
    with pytest.raises(DatasetError, match="built-in scenes: chair, lamp, vase, stand"):
        load_builtin("sofa")


def test_every_builtin_has_a_description():
    scenes = builtin_scenes()
    assert len(scenes) >= 3 and "chair" in scenes
    assert all(isinstance(d, str) and 10 < len(d) < 120 and "\n" not in d for d in scenes.values())


def test_forward_facing_builtin_is_an_llff_capture(tmp_path):
    """The built-in 'yard' is a forward-facing capture written in the LLFF layout: it loads through
    load_llff (NDC ray space, every 8th view held out, opaque photos), and poses_bounds.npy decodes
    back to the cameras it was rendered from, with each view's depth bounds."""
    from warpnerf.data.llff import llff_to_opengl

    cache = str(tmp_path)
    scene = load_builtin("yard", 32, cache, counts=(10,), progress=False)
    assert (scene.source, scene.kind, scene.name) == ("builtin", "llff", "yard")
    assert scene.ray_space.kind == "ndc" and scene.val is None
    assert scene.train.images.shape == (8, 24, 32, 3) and scene.test.ids == [0, 8]
    assert bool((scene.train.alpha == 1).all())
    pb = np.load(os.path.join(builtin.ensure_builtin("yard", 32, cache, (10,)), "poses_bounds.npy"))
    poses = pb[:, :15].reshape(-1, 3, 5)
    np.testing.assert_allclose(llff_to_opengl(poses[:, :, :4]), builtin.forward_facing_cameras(10), atol=1e-6)
    np.testing.assert_allclose(poses[:, :, 4], np.tile([24.0, 32.0, builtin.focal_from_angle(32)], (10, 1)))
    near, far = pb[:, 15], pb[:, 16]
    # the chair is ~4.8 units away, the environment sphere 15 units from the origin
    assert (near > 3.0).all() and (near < 5.0).all() and (far > 15.0).all() and (far < 21.0).all()
    # forward-facing: recentred, every camera looks down -z (its back axis is ~ +z)
    assert float(scene.train.c2w[:, 2, 2].min()) > 0.99
    # the test views are spread over the patch of camera centres, not along one edge
    centres = np.concatenate([scene.train.c2w[:, :2, 3].numpy(), scene.test.c2w[:, :2, 3].numpy()])
    test_x = scene.test.c2w[:, 0, 3].numpy()
    assert test_x.max() - test_x.min() > 0.3 * (centres[:, 0].max() - centres[:, 0].min())


def test_builtin_view_counts_are_checked(tmp_path):
    with pytest.raises(DatasetError, match=r"'yard' takes view counts \(views,\)"):
        load_builtin("yard", 16, str(tmp_path), counts=(4, 2, 3), progress=False)
    with pytest.raises(DatasetError, match=r"'chair' takes view counts \(train, val, test\)"):
        load_builtin("chair", 16, str(tmp_path), counts=(4,), progress=False)
    with pytest.raises(DatasetError, match="already a capture in the LLFF layout"):
        builtin.export_builtin("yard", str(tmp_path / "out"), "transforms", 16, str(tmp_path), (9,), progress=False)
