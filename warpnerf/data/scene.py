"""The in-memory form every loader returns (Blender, LLFF, built-in scenes).

Conventions (shared by all loaders and the renderer):

* camera-to-world matrices ``c2w`` are (N, 3, 4) float32 in the OpenGL/Blender convention:
  x right, y up, the camera looks down its -z axis;
* images are (N, H, W, 3) float32 in [0, 1], already composited on the background;
* ``focal``, ``cx``, ``cy`` are in pixels of the loaded (possibly downscaled) images;
* a pixel (u, v) (column, row) has its centre at (u + 0.5, v + 0.5);
* ``ray_space`` (:mod:`warpnerf.geometry.rayspace`) says how world rays become the rays the marcher
  sees, and holds the scene box and marching bounds in that space (docs/design.md §6).

A cameras-only load (``load_scene(..., pixels=False)``, for a viewer, which renders and never trains) reads
no pixel: its images, alpha and depth are :func:`stand_in` tensors, of the right shape and no memory, and
``Scene.pixels`` is False.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

from warpnerf.geometry.rayspace import RaySpace


def stand_in(shape, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """A tensor of ``shape`` that holds no memory: a zero-stride view of one zero. It stands for the pixels of
    a cameras-only load (shapes and lengths are right, values are not)."""
    return torch.zeros((), dtype=dtype, device=device).expand(tuple(shape))


def stand_in_like(t: Optional[torch.Tensor], device=None) -> Optional[torch.Tensor]:
    """:func:`stand_in` of ``t``'s shape and dtype, on ``device`` (default ``t``'s); None for None."""
    return None if t is None else stand_in(t.shape, t.dtype, t.device if device is None else device)


def is_stand_in(t: Optional[torch.Tensor]) -> bool:
    """Whether ``t`` is a :func:`stand_in` (every stride 0; a real image tensor has none)."""
    return t is not None and t.dim() > 0 and all(st == 0 for st in t.stride())


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

        def take(t: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
            # indexing a stand-in would allocate the picked views in full: a stand-in of their shape instead
            if t is None:
                return None
            return stand_in((len(idx), *t.shape[1:]), t.dtype, t.device) if is_stand_in(t) else t[pick]

        return Views(
            images=take(self.images),
            c2w=self.c2w[pick],
            focal=self.focal,
            cx=self.cx,
            cy=self.cy,
            ids=[self.ids[i] for i in idx],
            depth=take(self.depth),
            alpha=take(self.alpha),
        )

    def drop_pixels(self, device=None) -> None:
        """Replace the images, alpha and depth by :func:`stand_in` tensors of their shapes (on ``device``,
        default their own), in place: their memory is given back once nothing else holds them."""
        self.images, self.alpha, self.depth = (stand_in_like(self.images, device), stand_in_like(self.alpha, device),
                                               stand_in_like(self.depth, device))


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
    pixels: bool = True  # False: a cameras-only load, the views' images, alpha and depth are stand-ins (module doc)

    def splits(self) -> list[Views]:
        """The loaded splits: train, val (when loaded), test."""
        return [v for v in (self.train, self.val, self.test) if v is not None]

    def drop_pixels(self, device=None) -> None:
        """Every split's :meth:`Views.drop_pixels` (stand-ins on ``device``, default their own); ``pixels`` False."""
        for views in self.splits():
            views.drop_pixels(device)
        self.pixels = False

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
