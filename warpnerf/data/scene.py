"""The in-memory form every loader returns (Blender, LLFF, built-in scenes).

Conventions (shared by all loaders and the renderer):

* camera-to-world matrices ``c2w`` are (N, 3, 4) float32 in the OpenGL/Blender convention:
  x right, y up, the camera looks down its -z axis;
* images are (N, H, W, 3) float32 in [0, 1], already composited on the background;
* ``focal``, ``cx``, ``cy`` are in pixels of the loaded (possibly downscaled) images;
* a pixel (u, v) (column, row) has its centre at (u + 0.5, v + 0.5);
* ``ray_space`` (:mod:`warpnerf.geometry.rayspace`) says how world rays become the rays the marcher
  sees, and holds the scene box and marching bounds in that space (docs/design.md §6).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

from warpnerf.geometry.rayspace import RaySpace


@dataclass
class Views:
    """One split of a scene (train, val or test)."""

    images: torch.Tensor  # (N, H, W, 3) float32 in [0, 1], composited on the background
    c2w: torch.Tensor  # (N, 3, 4) float32, OpenGL convention
    focal: float  # pixels
    cx: float  # principal point, pixels
    cy: float
    ids: list[int] = field(default_factory=list)  # index of each view in its original split
    depth: Optional[torch.Tensor] = None  # (N, H, W) float32 ray distance along the camera z axis; 0 = background
    alpha: Optional[torch.Tensor] = None  # (N, H, W) float32 in [0, 1], when the source had one

    def __post_init__(self):
        if not self.ids:
            self.ids = list(range(self.images.shape[0]))

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def subset(self, idx: list[int]) -> "Views":
        """The views at positions ``idx`` (positions in this split, not original ids)."""
        pick = torch.as_tensor(idx, dtype=torch.long)
        return Views(
            images=self.images[pick],
            c2w=self.c2w[pick],
            focal=self.focal,
            cx=self.cx,
            cy=self.cy,
            ids=[self.ids[i] for i in idx],
            depth=None if self.depth is None else self.depth[pick],
            alpha=None if self.alpha is None else self.alpha[pick],
        )


@dataclass
class Scene:
    """A loaded scene: splits plus the geometry the renderer needs."""

    name: str
    source: str  # "dataset" or "builtin"
    kind: str  # "blender" (synthetic, built-in), "llff", "colmap" or "transforms"
    train: Views
    test: Views
    val: Optional[Views] = None
    ray_space: RaySpace = RaySpace()  # ray map, box and marching bounds (default: Blender's, world units)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    root: str = ""  # folder it was read from
    background_note: str = ""  # how the background was chosen, one line for the run (warpnerf.data.background)

    # The box and bounds are the ray space's: one place, so they cannot disagree with it.
    @property
    def aabb(self) -> tuple[float, float, float, float, float, float]:
        return self.ray_space.aabb

    @property
    def near(self) -> float:
        return self.ray_space.near

    @property
    def far(self) -> float:
        return self.ray_space.far
