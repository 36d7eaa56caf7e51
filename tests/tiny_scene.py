"""A tiny analytic scene for fast end-to-end tests: three colored spheres, rendered in torch."""

import math

import torch

from warpnerf.data.scene import Scene, Views
from warpnerf.geometry.cameras import look_at
from warpnerf.geometry.rayspace import RaySpace
from warpnerf.model.renderer import pixel_rays

SPHERES = [  # centre, radius, color
    ((0.0, 0.0, 0.0), 0.45, (0.9, 0.2, 0.2)),
    ((0.55, 0.25, 0.15), 0.25, (0.2, 0.8, 0.3)),
    ((-0.35, -0.45, 0.3), 0.3, (0.2, 0.3, 0.9)),
]


def render_spheres(c2w: torch.Tensor, size: int, focal: float) -> torch.Tensor:
    """(N, 3, 4) poses -> (N, size, size, 3) images on white, with a little diffuse shading."""
    v, u = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    images = []
    for pose in c2w:
        o, d = pixel_rays(pose[None].expand(size * size, 3, 4), u.reshape(-1), v.reshape(-1), focal, size / 2, size / 2)
        best_t = torch.full((o.shape[0],), math.inf)
        color = torch.ones(o.shape[0], 3)
        for centre, radius, rgb in SPHERES:
            c = torch.tensor(centre)
            oc = o - c
            b = (oc * d).sum(-1)
            disc = b * b - (oc * oc).sum(-1) + radius * radius
            t = -b - disc.clamp_min(0).sqrt()
            hit = (disc > 0) & (t > 0) & (t < best_t)
            normal = torch.nn.functional.normalize(o + t[:, None] * d - c, dim=-1)
            shade = 0.4 + 0.6 * (normal @ torch.tensor([0.3, 0.5, 0.8])).clamp_min(0)
            color = torch.where(hit[:, None], shade[:, None] * torch.tensor(rgb), color)
            best_t = torch.where(hit, t, best_t)
        images.append(color.view(size, size, 3))
    return torch.stack(images)


def tiny_scene(n_train: int = 24, n_test: int = 4, size: int = 32, seed: int = 0) -> Scene:
    gen = torch.Generator().manual_seed(seed)
    dirs = torch.nn.functional.normalize(torch.randn(n_train, 3, generator=gen), dim=-1)
    dirs[:, 2] = dirs[:, 2].abs() + 0.2  # upper hemisphere, like Blender scenes
    centres = torch.nn.functional.normalize(dirs, dim=-1) * 3.0
    angles = torch.linspace(0, 2 * math.pi, n_test + 1)[:-1] + 0.3
    test_centres = torch.stack([2.6 * torch.cos(angles), 2.6 * torch.sin(angles), torch.full_like(angles, 1.5)], -1)
    focal = size * 1.2
    train_c2w, test_c2w = look_at(centres), look_at(test_centres)
    mk = lambda c2w: Views(render_spheres(c2w, size, focal), c2w, focal, size / 2, size / 2)  # noqa: E731
    return Scene(name="spheres", source="builtin", kind="blender", train=mk(train_c2w), test=mk(test_c2w),
                 ray_space=RaySpace.euclidean((-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), near=1.0, far=5.0))
