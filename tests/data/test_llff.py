"""warpnerf.data.llff: axis order, scaling, recentring, holdout split, errors, and NDC rays."""

import math
import os

import numpy as np
import pytest
import torch
from fake_scenes import random_rotations, write_llff

from warpnerf.data import DatasetError, load_llff
from warpnerf.data.llff import average_pose
from warpnerf.geometry.rayspace import ndc_rays

N = 10


@pytest.fixture
def llff_scene(tmp_path):
    rot = random_rotations(N, seed=3)
    centres = np.random.default_rng(4).normal(size=(N, 3))
    bounds = np.stack([np.linspace(2.0, 3.0, N), np.linspace(10.0, 20.0, N)], 1)
    root = write_llff(tmp_path / "fake", rot, centres, bounds, hwf=(24, 32, 40.0), factor=4)
    return root, rot, centres


def _all_poses(scene):
    """(N, 3, 4) poses in original image order."""
    out = np.zeros((N, 3, 4))
    for views in (scene.train, scene.test):
        out[views.ids] = views.c2w.numpy()
    return out


def test_axis_order_and_scale_without_recentring(llff_scene):
    root, rot, centres = llff_scene
    scene = load_llff(root, factor=4, recenter=False)
    poses = _all_poses(scene)
    # The stored LLFF [down, right, back] columns must come back as the OpenGL rotation.
    np.testing.assert_allclose(poses[:, :, :3], rot, atol=1e-6)
    scale = 1.0 / (2.0 * 0.75)  # nearest bound 2.0 -> 1 / bd_factor
    np.testing.assert_allclose(poses[:, :, 3], centres * scale, atol=1e-5)


def test_recentring_keeps_relative_poses_and_centres_the_average(llff_scene):
    root, rot, centres = llff_scene
    scene = load_llff(root, factor=4)
    poses = _all_poses(scene)
    np.testing.assert_allclose(average_pose(poses), np.eye(3, 4), atol=1e-5)
    # Recentring is one rigid transform applied to all cameras: relative rotations survive.
    rel_expected = np.einsum("ji,njk->nik", rot[0], rot)
    rel_got = np.einsum("ji,njk->nik", poses[0, :, :3], poses[:, :, :3])
    np.testing.assert_allclose(rel_got, rel_expected, atol=1e-5)
    assert scene.ray_space.kind == "ndc" and scene.kind == "llff"
    # z' from the near plane to infinity; x', y' at least the average camera's frustum (tests/geometry/test_rayspace.py
    # checks that the box holds every training ray)
    x0, y0, z0, x1, y1, z1 = scene.aabb
    assert (z0, z1) == (-1.0, 1.0) and (x0, y0) == (-x1, -y1) and min(x1, y1) >= 1.0
    # NDC rays are marched with unit directions from the near plane until the box ends them at z' = 1
    assert (scene.near, scene.far) == (0.0, math.inf)
    assert (scene.ray_space.focal, scene.ray_space.width, scene.ray_space.height) == (10.0, 8, 6)


def test_holdout_split_and_intrinsics(llff_scene):
    root, _, _ = llff_scene
    scene = load_llff(root, factor=4, holdout=8)
    assert scene.test.ids == [0, 8]
    assert scene.train.ids == [1, 2, 3, 4, 5, 6, 7, 9]
    assert scene.train.images.shape == (8, 6, 8, 3)
    # photos are opaque: alpha 1 everywhere, so training uses random backgrounds (tests/train/test_trainer_loss.py)
    assert scene.train.alpha.shape == (8, 6, 8) and bool((scene.train.alpha == 1).all())
    assert scene.test.alpha.shape == (2, 6, 8)
    # Image k is uniformly 10 k / 255: checks that images follow their poses through the split.
    np.testing.assert_allclose(scene.test.images[1].numpy(), 80 / 255, atol=1e-6)
    assert (scene.train.focal, scene.train.cx, scene.train.cy) == (10.0, 4.0, 3.0)
    half = load_llff(root, factor=4, downscale=2)
    assert half.train.images.shape == (8, 3, 4, 3) and half.train.focal == 5.0


def test_barf_split_holds_out_the_last_tenth_by_name(llff_scene):
    """BARF's and GARF's LLFF protocol: the last int(0.1 N) images by file name are the test views
    (fern: 18 and 19 of 20); with fewer than ten images, still one."""
    root, _, _ = llff_scene
    scene = load_llff(root, factor=4, test="last10")
    assert scene.test.ids == [9] and scene.train.ids == list(range(9))
    np.testing.assert_allclose(scene.test.images[0].numpy(), 90 / 255, atol=1e-6)  # image k is 10 k / 255
    with pytest.raises(DatasetError, match="test must be one of every8, last10"):
        load_llff(root, factor=4, test="last")


def test_wrong_factor_lists_existing_folders(llff_scene):
    root, _, _ = llff_scene
    with pytest.raises(DatasetError, match=r"missing image folder .*images_8.*images_4"):
        load_llff(root, factor=8)


def test_image_count_and_size_mismatch(llff_scene):
    root, _, _ = llff_scene
    folder = os.path.join(root, "images_4")
    from PIL import Image

    Image.fromarray(np.zeros((7, 8, 3), np.uint8)).save(os.path.join(folder, "IMG_005.png"))
    with pytest.raises(DatasetError, match=r"IMG_005\.png is 8x7, expected 8x6"):
        load_llff(root, factor=4)
    os.remove(os.path.join(folder, "IMG_005.png"))
    with pytest.raises(DatasetError, match="holds 9 images but poses_bounds.npy has 10 poses"):
        load_llff(root, factor=4)


def test_ndc_rays_map_points_to_projective_coordinates():
    torch.manual_seed(0)
    focal, w, h, near = 30.0, 40, 30, 1.0
    o = torch.randn(64, 3, dtype=torch.float64) * 0.2
    d = torch.randn(64, 3, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    o_ndc, d_ndc = ndc_rays(o, d, focal, w, h, near)

    def project(x):  # NDC of world points in front of the camera (z < 0)
        return torch.stack([-2 * focal / w * x[:, 0] / x[:, 2], -2 * focal / h * x[:, 1] / x[:, 2], 1 + 2 * near / x[:, 2]], 1)

    for depth in (2.0, 5.0, 50.0):
        s = (-depth - o[:, 2]) / d[:, 2]  # ray parameter of the point at world z = -depth
        x = project(o + s[:, None] * d)
        t = (x[:, 2] - o_ndc[:, 2]) / d_ndc[:, 2]
        assert torch.all((t > 0) & (t < 1))  # between the near plane and infinity
        torch.testing.assert_close(o_ndc + t[:, None] * d_ndc, x)  # the world point lies on the NDC ray
    torch.testing.assert_close(o_ndc[:, 2], torch.full((64,), -1.0, dtype=torch.float64))  # starts at the near plane


def test_ndc_rays_are_differentiable():
    o = (torch.randn(4, 3, dtype=torch.float64) * 0.1).requires_grad_()
    d = (torch.randn(4, 3, dtype=torch.float64) * 0.1 + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: ndc_rays(a, b, 20.0, 32, 24), (o, d))
