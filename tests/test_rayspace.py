"""warpnerf.data.rayspace: every scene owns its ray space; NDC is bit-identical to the formula the
trainer and renderer used before the ray space existed; the euclidean space leaves rays alone."""

import math

import numpy as np
import pytest
import torch
from fake_scenes import write_blender, write_llff

from warpnerf.data import RaySpace, load_blender, load_llff
from warpnerf.data.rayspace import NDC_AABB


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
    root = write_llff(tmp_path / "l", np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.tile([[1.0, 5.0]], (n, 1)))
    llff = load_llff(root, factor=4, downscale=2)
    space = llff.ray_space
    # the NDC camera is the one the training views were taken with
    assert (space.kind, space.focal, space.width, space.height, space.ndc_near) == (
        "ndc", llff.train.focal, llff.train.width, llff.train.height, 1.0)
    assert space.forward_facing and not space.box_is_world and llff.aabb == NDC_AABB


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
    with pytest.raises(Exception):  # frozen: the scene's space cannot drift from what the loader made
        RaySpace().near = 1.0
