"""warpnerf.geometry.rayspace: every scene owns its ray space; NDC is bit-identical to the formula the
trainer and renderer used before the ray space existed; the euclidean space leaves rays alone."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from fake_scenes import write_blender, write_llff

from warpnerf.data import load_blender, load_llff
from warpnerf.geometry.rayspace import NDC_AABB, RaySpace, ndc_extent, ndc_rays
from warpnerf.model.renderer import pixel_rays


def previous_ndc(rays_o, rays_d, focal, width, height, near=1.0):
    """The NDC map as the trainer (ndc_rays in data/llff.py, near=1.0) and the renderer (normalise
    the direction) applied it before RaySpace, copied verbatim."""
    t = -(near + rays_o[..., 2]) / rays_d[..., 2]
    rays_o = rays_o + t[..., None] * rays_d
    ox, oy, oz = rays_o.unbind(-1)
    dx, dy, dz = rays_d.unbind(-1)
    sx = -2.0 * focal / width
    sy = -2.0 * focal / height
    o_ndc = torch.stack([sx * ox / oz, sy * oy / oz, 1.0 + 2.0 * near / oz], -1)
    d_ndc = torch.stack([sx * (dx / dz - ox / oz), sy * (dy / dz - oy / oz), -2.0 * near / oz], -1)
    return o_ndc, torch.nn.functional.normalize(d_ndc, dim=-1)


def random_rays(n, seed, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.3
    d = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.3 + torch.tensor([0.0, 0.0, -1.0], dtype=dtype)
    return o, torch.nn.functional.normalize(d, dim=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ndc_is_bit_identical_to_the_previous_formula(dtype):
    o, d = random_rays(4096, seed=1, dtype=dtype)
    for focal, w, h in ((407.5648, 504, 378), (10.0, 8, 6), (float(np.float64(52.3)), 63, 47)):
        space = RaySpace.ndc(focal, w, h)
        got_o, got_d = space.apply(o, d)
        want_o, want_d = previous_ndc(o, d, focal, w, h)
        assert torch.equal(got_o, want_o) and torch.equal(got_d, want_d)
    assert (space.near, space.far, space.aabb) == (0.0, math.inf, NDC_AABB)


def test_ndc_to_world_inverts_apply():
    o, d = random_rays(256, seed=2, dtype=torch.float64)
    space = RaySpace.ndc(30.0, 40, 30)
    on, dn = space.apply(o, d)
    for s in (0.1, 0.5, 1.2):  # points along the marched (unit) NDC ray, before z' reaches 1
        x = space.to_world(on + s * dn)
        # the world point lies on the world ray: (x - o) is parallel to d
        torch.testing.assert_close(torch.linalg.cross(x - o, d), torch.zeros_like(x), atol=1e-9, rtol=0)
    torch.testing.assert_close(space.to_world(on)[:, 2], torch.full((256,), -1.0, dtype=torch.float64))  # near plane


def test_ndc_apply_is_differentiable():
    o, d = random_rays(4, seed=3, dtype=torch.float64)
    space = RaySpace.ndc(20.0, 32, 24)
    assert torch.autograd.gradcheck(space.apply, (o.requires_grad_(), d.requires_grad_()))


def test_euclidean_leaves_rays_unchanged():
    o, d = random_rays(1000, seed=4)
    o0, d0 = o.clone(), d.clone()
    space = RaySpace.euclidean((-1.5, -1.5, -1.5, 1.5, 1.5, 1.5), 2.0, 6.0)
    got_o, got_d = space.apply(o, d)
    assert got_o is o and got_d is d and torch.equal(o, o0) and torch.equal(d, d0)
    x = torch.randn(10, 3)
    assert space.to_world(x) is x
    assert space.box_is_world and not space.forward_facing


def test_loaders_give_their_scene_its_ray_space(tmp_path):
    blender = load_blender(write_blender(tmp_path / "b", n=2, size=4))
    assert blender.ray_space == RaySpace.euclidean((-1.5, -1.5, -1.5, 1.5, 1.5, 1.5), 2.0, 6.0)
    assert (blender.near, blender.far, blender.aabb) == (2.0, 6.0, (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5))
    n = 4
    # cameras a hair apart around the origin (identical ones are refused: no parallax)
    centres = np.array([[1e-4, 0, 0], [-1e-4, 0, 0], [0, 1e-4, 0], [0, -1e-4, 0]])
    root = write_llff(tmp_path / "l", np.tile(np.eye(3), (n, 1, 1)), centres, np.tile([[1.0, 5.0]], (n, 1)))
    llff = load_llff(root, factor=4, downscale=2)
    space = llff.ray_space
    # the NDC camera is the one the training views were taken with
    assert (space.kind, space.focal, space.width, space.height, space.ndc_near) == (
        "ndc", llff.train.focal, llff.train.width, llff.train.height, 1.0)
    assert space.forward_facing and not space.box_is_world
    # cameras at the origin: the box is the average camera's frustum plus the margin (exactly so for
    # identical cameras; these move its sides by ~1e-4 / near)
    assert llff.aabb == pytest.approx((-1.03125, -1.03125, -1.0, 1.03125, 1.03125, 1.0), abs=1e-3)


def small_rotations(n, seed, angle=0.15):
    """(n, 3, 3) rotations by up to ``angle`` radians about random axes (forward-facing views)."""
    g = torch.Generator().manual_seed(seed)
    w = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * angle
    return torch.linalg.matrix_exp(torch.stack([
        torch.stack([torch.zeros(n, dtype=w.dtype), -w[:, 2], w[:, 1]], -1),
        torch.stack([w[:, 2], torch.zeros(n, dtype=w.dtype), -w[:, 0]], -1),
        torch.stack([-w[:, 1], w[:, 0], torch.zeros(n, dtype=w.dtype)], -1)], -2))


def test_ndc_box_holds_every_training_ray_to_infinity(tmp_path):
    """Forward-facing views that look past the average camera's frustum (as LLFF's do: fern's
    rays reach |x'| = 1.44): every pixel ray, anywhere from the near plane to z' = 1, lies in the
    loader's NDC box, and the box is no wider than the outermost ray plus the margin."""
    n = 6
    g = torch.Generator().manual_seed(5)
    centres = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([0.4, 0.3, 0.05],
                                                                                          dtype=torch.float64)
    rot = small_rotations(n, seed=6)
    root = write_llff(tmp_path / "l", rot.numpy(), centres.numpy(), np.tile([[2.0, 20.0]], (n, 1)))
    scene = load_llff(root, factor=4, holdout=1000)  # every view trains (view 0 is also the test view)
    space, views = scene.ray_space, scene.train
    x0, y0, z0, x1, y1, z1 = space.aabb
    assert (z0, z1) == (-1.0, 1.0) and x0 == -x1 and y0 == -y1
    assert x1 > 1.1 and y1 > 1.03  # these views see well past the frustum in x and in y
    h, w = views.height, views.width
    v, u = torch.meshgrid(torch.arange(h + 1.0), torch.arange(w + 1.0), indexing="ij")  # pixel corners
    u, v = u.flatten().double(), v.flatten().double()
    reach = torch.zeros(2, dtype=torch.float64)
    for c2w in views.c2w.double():
        # the renderer's own rays through every pixel corner
        o, d = pixel_rays(c2w[None].expand(len(u), 3, 4), u, v, views.focal, views.cx, views.cy)
        o_ndc, d_ndc = ndc_rays(o, d, space.focal, w, h, near=space.ndc_near)
        for s in torch.linspace(0, 1, 9, dtype=torch.float64):  # z' from -1 (s = 0) to 1 (s = 1)
            xy = (o_ndc + s * d_ndc)[:, :2].abs().amax(0)
            reach = torch.maximum(reach, xy)
    # float32 poses in the views, float64 in the loader: allow for the rounding of the c2w
    assert reach[0] <= x1 + 1e-5 and reach[1] <= y1 + 1e-5
    assert x1 <= reach[0] * 1.02 + 1 / 32 + 1e-5 and y1 <= reach[1] * 1.02 + 1 / 32 + 1e-5


def test_ndc_extent_is_symmetric_under_mirrored_views_and_rejects_bad_boxes():
    c2w = torch.cat([torch.eye(3, dtype=torch.float64), torch.tensor([[0.3], [0.0], [0.0]], dtype=torch.float64)], 1)
    mirrored = c2w.clone()
    mirrored[0, 3] = -0.3
    assert ndc_extent(c2w[None], 30.0, 40, 30) == ndc_extent(mirrored[None], 30.0, 40, 30)
    assert ndc_extent(c2w[None], 30.0, 40, 30) == ndc_extent(torch.stack([c2w, mirrored]), 30.0, 40, 30)
    # a camera shifted right sees past the frustum's side at the near plane: |x'| = 1 + 0.3 * 2f/W there
    assert ndc_extent(c2w[None], 30.0, 40, 30, margin=1.0)[0] == math.ceil((1 + 0.3 * 60 / 40) * 32) / 32
    for bad in ((0.0, 1.0), (1.0, math.inf), (-1.0, 1.0)):
        with pytest.raises(ValueError, match="half-widths"):
            RaySpace.ndc(30.0, 40, 30, extent=bad)


def test_contracted_space_normalises_contracts_and_inverts():
    """Unbounded scenes: apply only normalises (directions unchanged), to_field contracts into the
    ball of radius 2 (the box [-2, 2]^3), to_world undoes both."""
    space = RaySpace.contracted(0.05, far=500.0, center=(1.0, -2.0, 0.5), scale=0.25)
    assert space.is_contracted and not space.box_is_world and not space.forward_facing
    assert space.aabb == (-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)
    g = torch.Generator().manual_seed(0)
    o, d = torch.randn(64, 3, generator=g) * 10, torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    o2, d2 = space.apply(o, d)
    assert torch.equal(d2, d)
    torch.testing.assert_close(o2, (o - torch.tensor([1.0, -2.0, 0.5])) * 0.25)
    x = o2 + 3.0 * d2
    y = space.to_field(x)
    assert float(y.norm(dim=-1).max()) < 2.0
    inner = x.norm(dim=-1) <= 1.0
    assert torch.equal(y[inner], x[inner])
    torch.testing.assert_close(space.to_world(y), o + 12.0 * d, rtol=1e-4, atol=1e-4)
    # the other kinds keep the field's input as marched
    plain = RaySpace()
    assert plain.to_field(x) is x


def test_bad_ray_spaces_are_refused():
    with pytest.raises(ValueError, match="unknown ray space kind 'spherical'"):
        RaySpace(kind="spherical")
    with pytest.raises(ValueError, match="finite far"):
        RaySpace.contracted(0.1, far=math.inf)
    with pytest.raises(ValueError, match="scale > 0"):
        RaySpace.contracted(0.1, scale=0.0)
    with pytest.raises(ValueError, match="focal, width, height"):
        RaySpace(kind="ndc")
    # frozen: the scene's space cannot drift from what the loader made
    with pytest.raises(dataclasses.FrozenInstanceError):
        RaySpace().near = 1.0
