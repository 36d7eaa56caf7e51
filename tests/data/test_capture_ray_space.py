"""Captures get the ray space and preset of what they are, whatever the layout (#63): a forward-facing rig
written as a COLMAP model or a transforms.json trains in NDC with the forward-facing preset, as the LLFF
loader's scenes do; a 360° rig is contracted; ``--ndc`` / ``--unbounded`` and their ``--no-`` forms override."""

import json
import os
import shutil

import numpy as np
import pytest
from PIL import Image

from warpnerf.data import colmap as cm
from warpnerf.data import load_llff
from warpnerf.data.errors import DatasetError
from warpnerf.data.llff import LLFF_BD_FACTOR
from warpnerf.data.normalize import normalization_from_cameras
from warpnerf.data.resolve import load_scene
from warpnerf.train import config as C

FERN = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data", "nerf_llff_data", "fern")
needs_fern = pytest.mark.skipif(not os.path.isdir(FERN), reason="reference data ../shared/data not available")

# an SfM world: its own rotation, scale and origin (COLMAP's are arbitrary)
WORLD_ROT = np.array([[0.0, -0.6, 0.8], [0.0, 0.8, 0.6], [-1.0, 0.0, 0.0]])
WORLD_SCALE, WORLD_SHIFT = 3.7, np.array([2.0, -1.0, 5.0])


def to_world(c2w):
    rot = np.einsum("ij,njk->nik", WORLD_ROT, c2w[:, :, :3])
    return np.concatenate([rot, (WORLD_SCALE * c2w[:, :, 3] @ WORLD_ROT.T + WORLD_SHIFT)[:, :, None]], 2)


def fern_cameras():
    """(LLFF load of fern, its (20, 3, 4) cameras in image order)."""
    ll = load_llff(FERN)
    c2w = np.zeros((len(ll.train) + len(ll.test), 3, 4))
    for v in (ll.train, ll.test):
        c2w[v.ids] = v.c2w.numpy()
    return ll, c2w


def write_fern_colmap(root):
    """fern's images_8 as a COLMAP text model without points, its cameras the LLFF loader's moved into
    an SfM world; the capture every test here loads."""
    ll, c2w = fern_cameras()
    names = sorted(os.listdir(os.path.join(FERN, "images_8")))
    os.makedirs(os.path.join(root, "images"))
    for name in names:
        shutil.copy(os.path.join(FERN, "images_8", name), os.path.join(root, "images", name))
    h, w, f = ll.train.height, ll.train.width, ll.train.focal
    cams = {1: cm.Camera(1, "PINHOLE", w, h, np.array([f, f, w / 2, h / 2]))}
    imgs = {i + 1: cm.Image(i + 1, *cm.c2w_to_colmap(m), 1, n) for i, (n, m) in enumerate(zip(names, to_world(c2w)))}
    cm.write_model(os.path.join(root, "sparse", "0"), cams, imgs, {}, ".txt")
    return ll


@pytest.fixture(scope="module")
def fern_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    ll = write_fern_colmap(str(root / "fernc"))
    return str(root), ll


@needs_fern
def test_fern_as_colmap_trains_in_ndc_as_the_llff_loader_does(fern_capture):
    root, ll = fern_capture
    scene = load_scene("fernc", root)
    assert scene.kind == "colmap" and scene.ray_space.kind == "ndc" and scene.ray_space.forward_facing
    assert scene.normalization.rig == "forward_facing" and "NDC" in scene.normalization.framing
    assert (scene.near, scene.far) == (0.0, float("inf"))
    # the same test views, orientations and recentring as the LLFF loader, up to the world's scale
    assert scene.test.ids == ll.test.ids
    np.testing.assert_allclose(scene.train.c2w[:, :, :3], ll.train.c2w[:, :, :3], atol=1e-5)
    ratio = scene.train.c2w[:, :, 3].numpy() / ll.train.c2w[:, :, 3].numpy()
    k = float(np.median(ratio))
    np.testing.assert_allclose(ratio, k, rtol=1e-4)
    # without points the depth scale comes from the cameras: fern's nearest bound (poses_bounds.npy, which the
    # capture does not have) lands at k / LLFF_BD_FACTOR, behind the NDC near plane at 1 and not far off LLFF's 1.33
    nearest = k / LLFF_BD_FACTOR
    assert 1.05 < nearest < 2.0, nearest
    # the box holds every training ray from the near plane on (as the LLFF loader's does)
    x0, y0, z0, x1, y1, z1 = scene.aabb
    assert (z0, z1) == (-1.0, 1.0) and min(x1, y1) >= 1.0


@needs_fern
def test_no_ndc_keeps_the_box_and_the_camera_normalisation(fern_capture):
    root, _ = fern_capture
    scene = load_scene("fernc", root, ndc=False)
    assert scene.ray_space.kind == "euclidean" and "box" in scene.normalization.framing
    assert "--no-ndc" in scene.normalization.framing
    _, c2w = fern_cameras()
    ref = normalization_from_cameras(to_world(c2w))
    np.testing.assert_allclose(scene.normalization.matrix(), ref.matrix(), atol=1e-5)  # the text model rounds
    assert load_scene("fernc", root, unbounded=True).ray_space.kind == "contracted"
    with pytest.raises(DatasetError, match="one ray space"):
        load_scene("fernc", root, unbounded=True, ndc=True)
    with pytest.raises(DatasetError, match="LLFF layout.*NDC only"):
        load_scene("fern", os.path.dirname(os.path.dirname(FERN)), ndc=False)


@needs_fern
def test_the_forward_facing_preset_follows_the_capture_rig(fern_capture):
    root, _ = fern_capture
    ff = C.load_toml(C.preset_path("full" + C.FORWARD_FACING_SUFFIX))
    full = C.load_toml(C.preset_path("full"))
    assert ff["march_steps"] != full["march_steps"]
    cfg = C.build_config("full", overrides={"scene": "fernc", "data_root": root})
    assert {k: getattr(cfg, k) for k in ff} == ff
    for flags in ({"ndc": False}, {"unbounded": True}):
        cfg = C.build_config("full", overrides={"scene": "fernc", "data_root": root, **flags})
        assert cfg.march_steps == full["march_steps"] and cfg.distortion_weight == full.get("distortion_weight", 0.0)
    with pytest.raises(C.ConfigError, match="ndc and unbounded"):
        C.build_config("full", overrides={"scene": "fernc", "data_root": root, "ndc": True, "unbounded": True})


@needs_fern
def test_the_run_says_which_ray_space_and_preset_and_a_flag_overrides_them(fern_capture, tmp_path, capsys):
    from warpnerf.cli.app import main

    root, _ = fern_capture
    base = ["train", "--scene", "fernc", "--data-root", root, "--iters", "2", "--downscale", "4", "--video-frames", "0",
            "--eval-max-views", "1", "--quiet", "--threads", "1"]
    assert main([*base, "--out", str(tmp_path / "auto")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert any("preset configs/full.toml + full_forward_facing.toml" in line for line in out), out
    framing = [line for line in out if line.startswith("framing: ")]
    assert len(framing) == 1 and framing[0].startswith("framing: forward-facing: ") and "NDC" in framing[0]
    assert main([*base, "--no-ndc", "--out", str(tmp_path / "box")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert any("(preset configs/full.toml)" in line for line in out), out
    assert any(line.startswith("framing: forward-facing: ") and "box" in line for line in out)


# ---- synthetic rigs: the depth scale from points, and 360° rigs --------------------------------------------

SIZE, FOCAL = 16, 20.0


def write_transforms(root, c2w):
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    frames = []
    for k, m in enumerate(c2w):
        Image.fromarray(np.full((SIZE, SIZE, 3), 90, np.uint8)).save(os.path.join(root, "images", f"{k:03d}.png"))
        frames.append({"file_path": f"images/{k:03d}.png", "transform_matrix": np.vstack([m, [0, 0, 0, 1]]).tolist()})
    with open(os.path.join(root, "transforms.json"), "w") as f:
        json.dump({"camera_model": "PINHOLE", "fl_x": FOCAL, "fl_y": FOCAL, "w": SIZE, "h": SIZE, "frames": frames}, f)
    return root


def test_sparse_points_put_the_nearest_content_at_llffs_depth(tmp_path):
    """Parallel cameras (all looking down -z, on a 4 x 3 patch) and points of which a third lie on the plane
    z = -7 and the rest farther: the nearest content, depth 7, is mapped to 1 / bd_factor as LLFF maps its
    nearest bound."""
    xs, ys = np.meshgrid(np.linspace(-1, 1, 4), np.linspace(-0.5, 0.5, 3))
    c2w = np.zeros((12, 3, 4))
    c2w[:, :, :3] = np.eye(3)
    c2w[:, 0, 3], c2w[:, 1, 3] = xs.ravel(), ys.ravel()
    rng = np.random.default_rng(1)
    near = np.concatenate([rng.uniform(-3, 3, (100, 2)), np.full((100, 1), -7.0)], 1)
    far = np.concatenate([rng.uniform(-6, 6, (200, 2)), rng.uniform(-30, -8, (200, 1))], 1)
    pts = np.concatenate([near, far])
    world = to_world(c2w)
    world_pts = WORLD_SCALE * pts @ WORLD_ROT.T + WORLD_SHIFT
    root = str(tmp_path / "cap")
    os.makedirs(os.path.join(root, "images"))
    names = [f"{k:03d}.png" for k in range(len(c2w))]
    for n in names:
        Image.fromarray(np.full((SIZE, SIZE, 3), 90, np.uint8)).save(os.path.join(root, "images", n))
    cams = {1: cm.Camera(1, "PINHOLE", SIZE, SIZE, np.array([FOCAL, FOCAL, SIZE / 2, SIZE / 2]))}
    imgs = {i + 1: cm.Image(i + 1, *cm.c2w_to_colmap(m), 1, n) for i, (n, m) in enumerate(zip(names, world))}
    points = {i + 1: cm.Point3D(i + 1, x, np.array([9, 9, 9], np.uint8), 0.5, np.array([1]), np.array([0]))
              for i, x in enumerate(world_pts)}
    cm.write_model(os.path.join(root, "sparse", "0"), cams, imgs, points, ".txt")
    scene = cm.load_colmap(root)
    assert scene.ray_space.kind == "ndc" and "from the sparse points" in scene.normalization.framing
    assert scene.normalization.scale * WORLD_SCALE * 7.0 == pytest.approx(1.0 / LLFF_BD_FACTOR, rel=1e-6)
    # recentred: the cameras' mean is the origin, they look down -z
    cams_n = np.concatenate([scene.train.c2w.numpy(), scene.test.c2w.numpy()])
    np.testing.assert_allclose(cams_n[:, :, 3].mean(0), 0.0, atol=1e-5)
    np.testing.assert_allclose(cams_n[:, :, :3], np.broadcast_to(np.eye(3), cams_n[:, :, :3].shape), atol=1e-5)


def test_an_outward_ring_is_contracted_unless_told_otherwise(tmp_path):
    """Cameras on a ring looking outwards (a 360° rig): contracted beyond the cameras by default, a box with
    --no-unbounded, and the framing line says which."""
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    c2w = np.zeros((16, 3, 4))
    for k, a in enumerate(ang):
        back = -np.array([np.cos(a), np.sin(a), 0.0])  # looks outwards: -z points away from the centre
        up = np.array([0.0, 0.0, 1.0])
        c2w[k, :, 0], c2w[k, :, 1], c2w[k, :, 2] = np.cross(up, back), up, back
        c2w[k, :, 3] = 2.0 * np.array([np.cos(a), np.sin(a), 0.0])
    write_transforms(str(tmp_path / "data" / "ring"), to_world(c2w))
    scene = load_scene("ring", str(tmp_path / "data"))
    assert scene.normalization.rig == "360" and scene.ray_space.kind == "contracted"
    assert "contracted" in scene.normalization.framing and "--no-unbounded" in scene.normalization.framing
    box = load_scene("ring", str(tmp_path / "data"), unbounded=False)
    assert box.ray_space.kind == "euclidean" and "--unbounded would contract" in box.normalization.framing
    assert C.build_config("full", overrides={"scene": "ring", "data_root": str(tmp_path / "data")}).march_steps == \
        C.load_toml(C.preset_path("full"))["march_steps"]
