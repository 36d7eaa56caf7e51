"""Captures without sparse points framed from their rig: an object rig is centred on the point its cameras
look at with a box the object fills (it used to fill a sixth of each axis: lego trained to 16 dB, not 30),
while captures with points, and forward-facing rigs in a box, keep the camera normalisation."""

import json
import math
import os

import numpy as np
import pytest
from PIL import Image

from trainer_helpers import short_run_psnr
from warpnerf.data import builtin, load_blender
from warpnerf.data import colmap as cm
from warpnerf.data.colmap import load_colmap
from warpnerf.data.normalize import bounds_from_points, every_nth_split, normalization_from_cameras
from warpnerf.data.transforms_json import load_transforms_json

SIZE = 16
FOCAL = builtin.focal_from_angle(SIZE)  # NeRF-synthetic's 40 deg field of view

# The capture's world: an SfM frame with its own rotation, scale and origin around the canonical rig.
WORLD_ROT = np.array([[0.0, -0.6, 0.8], [0.0, 0.8, 0.6], [-1.0, 0.0, 0.0]])  # up (+z) becomes +x-ish
WORLD_SCALE = 2.5
OBJECT_CENTRE = np.array([5.0, -3.0, 2.0])  # world; the object is a ball of radius WORLD_SCALE there
OBJECT_RADIUS = WORLD_SCALE


def to_world(c2w):
    """(N, 3, 4) canonical cameras -> the capture's world."""
    rot = np.einsum("ij,njk->nik", WORLD_ROT, c2w[:, :, :3])
    return np.concatenate([rot, (WORLD_SCALE * c2w[:, :, 3] @ WORLD_ROT.T + OBJECT_CENTRE)[:, :, None]], 2)


def object_rig(n=24):
    """Cameras 4 units from a unit ball at the origin (NeRF-synthetic's rig), in the capture's world."""
    return to_world(builtin.hemisphere_cameras(n, seed=5).astype(np.float64))


def write_capture(root, c2w, points=None, layout="colmap-text"):
    """``c2w`` (N, 3, 4) as a COLMAP text model (PINHOLE, ``points`` (P, 3) or none) or a transforms.json."""
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    names = [f"{k:03d}.png" for k in range(len(c2w))]
    for name in names:
        Image.fromarray(np.full((SIZE, SIZE, 3), 200, np.uint8)).save(os.path.join(root, "images", name))
    if layout == "transforms":
        frames = [{"file_path": f"images/{n}", "transform_matrix": np.vstack([m, [0, 0, 0, 1]]).tolist()}
                  for n, m in zip(names, c2w)]
        meta = {"camera_model": "PINHOLE", "fl_x": FOCAL, "fl_y": FOCAL, "w": SIZE, "h": SIZE, "frames": frames}
        with open(os.path.join(root, "transforms.json"), "w") as f:
            json.dump(meta, f)
        return str(root)
    cams = {1: cm.Camera(1, "PINHOLE", SIZE, SIZE, np.array([FOCAL, FOCAL, SIZE / 2, SIZE / 2]))}
    imgs = {i + 1: cm.Image(i + 1, *cm.c2w_to_colmap(m), 1, n) for i, (n, m) in enumerate(zip(names, c2w))}
    pts = {}
    for i, x in enumerate(points if points is not None else []):
        pts[i + 1] = cm.Point3D(i + 1, x, np.array([128, 128, 128], np.uint8), 0.5, np.array([1]), np.array([0]))
    cm.write_model(os.path.join(root, "sparse", "0"), cams, imgs, pts, ".txt")
    return str(root)


def test_object_rig_without_points_is_centred_on_the_object(tmp_path):
    scene = load_colmap(write_capture(str(tmp_path), object_rig()))
    norm = scene.normalization
    assert norm.rig == "object" and norm.framing.startswith("object-centric: ") and "\n" not in norm.framing
    lo, hi = np.array(scene.aabb[:3]), np.array(scene.aabb[3:])
    half = 0.5 * float((hi - lo).max())
    centre = norm.points(OBJECT_CENTRE[None])[0]
    # the camera cube put the object 0.5 half-sides off-centre (the cameras' mean is above it) at 0.25 of the box
    assert np.abs(centre - 0.5 * (lo + hi)).max() < 0.01 * half, centre
    ratio = OBJECT_RADIUS * norm.scale / half
    assert 0.4 < ratio < 0.9, ratio  # 1 / (1.1 * 4 * sin 20 deg) = 0.67
    # the box centre is on every optical axis, in front, and the box is the ball every camera sees, padded 10 %
    cams = np.concatenate([v.c2w.numpy() for v in (scene.train, scene.test)]).astype(np.float64)
    dist = np.linalg.norm(cams[:, :, 3], axis=1)
    assert np.all(np.einsum("nk,nk->n", cams[:, :, 2], cams[:, :, 3]) / dist > 1 - 1e-6)
    assert 1.1 * np.median(dist) * math.sin(0.5 * builtin.CAMERA_ANGLE_X) == pytest.approx(half, rel=1e-5)
    # up stays +z, as in the camera normalisation
    up = cams[:, :, 1].mean(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-6)


def test_transforms_json_frames_the_object_rig_as_colmap_does(tmp_path):
    c2w = object_rig()
    a = load_colmap(write_capture(str(tmp_path / "colmap"), c2w)).normalization
    b = load_transforms_json(write_capture(str(tmp_path / "json"), c2w, layout="transforms")).normalization
    assert b.rig == "object"
    np.testing.assert_allclose(b.matrix(), a.matrix(), atol=1e-9)


def test_points_and_forward_facing_rigs_keep_the_camera_normalisation(tmp_path):
    """What the loaders did before the rig framing: the map from the cameras, the box from the points."""
    c2w = object_rig()
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(300, 3))
    points = OBJECT_CENTRE + OBJECT_RADIUS * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    folder = write_capture(str(tmp_path / "points"), c2w, points)
    scene = load_colmap(folder)
    _, imgs, _ = cm.read_model(os.path.join(folder, "sparse", "0"))
    c2w = np.stack([cm.image_c2w(im) for im in sorted(imgs.values(), key=lambda im: im.name)])  # as read
    old = normalization_from_cameras(c2w)
    np.testing.assert_array_equal(scene.normalization.matrix(), old.matrix())
    train, _ = every_nth_split([f"{k:03d}.png" for k in range(len(c2w))])
    near, far, aabb = bounds_from_points(old.c2w(c2w)[train], old.points(points))
    assert (scene.near, scene.far, scene.aabb) == (near, far, aabb)
    assert scene.normalization.rig == "object" and "box from the sparse points" in scene.normalization.framing

    xs, ys = np.meshgrid(np.linspace(-1, 1, 4), np.linspace(-0.5, 0.5, 3))
    eyes = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], -1)
    ff = to_world(builtin.look_at(eyes, target=(0.0, 0.0, -12.0), up=(0.0, 1.0, 0.0)).astype(np.float64))
    # a forward-facing rig in a box (--no-ndc; by default it trains in NDC: tests/data/test_capture_ray_space.py)
    scene = load_transforms_json(write_capture(str(tmp_path / "ff"), ff, layout="transforms"), ndc=False)
    assert scene.normalization.rig == "forward_facing", scene.normalization.framing
    np.testing.assert_allclose(scene.normalization.matrix(), normalization_from_cameras(ff).matrix(), atol=1e-12)
    assert scene.aabb == (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)


# ---- training: the built-in chair as a COLMAP text model without points trains as its Blender load -------------

RES = 40
COUNTS = (10, 2, 4)


def test_chair_without_points_trains_as_its_blender_load(tmp_path):
    cache = str(tmp_path / "cache")
    blender = load_blender(builtin.ensure_builtin("chair", RES, cache, COUNTS, progress=False))
    folder = builtin.export_builtin("chair", str(tmp_path / "colmap"), "colmap-text", RES, cache, COUNTS,
                                    points_per_view=0, progress=False)
    assert os.path.getsize(os.path.join(folder, "sparse", "0", "points3D.txt")) < 300  # the header only
    scene = load_colmap(folder)
    assert scene.normalization.rig == "object"
    ref, psnr = short_run_psnr(blender), short_run_psnr(scene)
    assert ref > 12.0  # it learned something (the white background alone is ~10 dB)
    # measured 2026: Blender 14.13 dB, this capture 14.56; framed by the camera cube as before, 12.76 (fails)
    assert abs(psnr - ref) < 1.0, (psnr, ref)



def test_the_run_prints_the_framing_it_chose(tmp_path, capsys):
    from warpnerf.cli.app import main

    write_capture(str(tmp_path / "data" / "mycap"), object_rig())
    main(["train", "--scene", "mycap", "--data-root", str(tmp_path / "data"), "--iters", "2", "--video-frames", "0",
          "--eval-max-views", "1", "--pose-refine-steps", "0", "--out", str(tmp_path / "run"), "--quiet"])
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("framing: ")]
    assert len(lines) == 1 and lines[0].startswith("framing: object-centric: ") and "centred on it" in lines[0]
