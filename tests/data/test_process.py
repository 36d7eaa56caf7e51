"""`warpnerf process`: rendered photos of a textured built-in scene -> COLMAP -> poses that match
the rendering cameras; failures say how many images registered."""

import math
import os

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


def test_process_registers_every_rendered_photo_and_recovers_the_poses(tmp_path):
    pytest.importorskip("pycolmap")
    from warpnerf.geometry.cameras import evaluate_poses

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
