"""The space a scene's rays are marched in: :class:`RaySpace` (docs/design.md §6).

Every :class:`~warpnerf.data.scene.Scene` carries one, made by its loader. The renderer maps the
world rays of the cameras through ``ray_space.apply`` and marches the result between
``ray_space.near`` and ``ray_space.far`` inside ``ray_space.aabb``; the field, the occupancy grid
and the marching step live in that space too. Nothing outside this module and the loaders needs
to know which kind of space a scene uses: callers ask the ray space (``apply``, ``to_world``,
``box_is_world``, ``forward_facing``) instead.

Kinds:

* ``"euclidean"``: world rays as they are (Blender, COLMAP, transforms.json, built-in scenes);
  ``near``/``far`` are distances along the unit world ray.
* ``"ndc"``: normalised device coordinates of forward-facing LLFF scenes (original NeRF). A
  world ray (o, d) of the recentred scene (content along -z) is moved to the plane
  z = -``ndc_near`` and projected by a pinhole camera with ``focal``, ``width``, ``height`` at the
  origin:

      o' = ( -f/(W/2) * o_x/o_z,   -f/(H/2) * o_y/o_z,   1 + 2 near / o_z )
      d' = ( -f/(W/2) * (d_x/d_z - o_x/o_z),  -f/(H/2) * (d_y/d_z - o_y/o_z),  -2 near / o_z )

  so o' + s d' with s in [0, 1] runs from the near plane (z' = -1) to infinity (z' = 1), and
  x', y' in [-1, 1] cover the frustum of the average camera. The other views look past that
  frustum's sides (fern: 12 % of the training rays leave it before z' = 0.9, and their far
  background was lost), so the box is [-e_x, e_x] x [-e_y, e_y] x [-1, 1] with the half-widths
  of :func:`ndc_extent` over the training views (fern: 1.47 x 1.34). ``apply`` returns d'
  normalised (the marcher wants unit directions), so the marching bounds are [0, inf) and the
  box ends the ray at z' = 1. Uniform steps in NDC are uniform steps in inverse depth, which
  suits a far background.
* ``"contracted"``: unbounded (360°) scenes, MipNeRF-360's scene contraction
  (:mod:`warpnerf.geometry.contraction`). ``apply`` only normalises, o' = (o - ``center``) * ``scale``,
  d' = d, so the part of the scene that matters most lies in the unit ball; rays stay straight
  and are marched from ``near`` to ``far`` (normalised units, ``far`` finite) with steps growing
  as |x|^2 beyond the ball (``march_rays(contract=True)``). The *samples* are contracted:
  ``to_field`` maps a marched point into the ball of radius 2, which is the field's and the
  occupancy grid's box [-2, 2]^3. Everything out to ``far`` is part of the field (the distant
  background too); the renderer's background only shows through where the field is empty.

The field and the occupancy grid always see ``to_field(x)`` of a marched point ``x``
(the identity except for the contracted kind); ``to_world`` inverts both maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from warpnerf.geometry.contraction import contract, uncontract

KINDS = ("euclidean", "ndc", "contracted")
NDC_AABB = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
CONTRACTED_AABB = (-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)


@dataclass(frozen=True)
class RaySpace:
    """How a scene's world rays become the rays the marcher sees (module doc, docs/design.md §6).

    Attributes:
        kind: ``"euclidean"``, ``"ndc"`` or ``"contracted"`` (module doc).
        aabb: the scene box (x0, y0, z0, x1, y1, z1) in the field's space (``to_field``): the
            field's and the occupancy grid's domain.
        near, far: marching bounds along the (unit) rays ``apply`` returns.
        focal, width, height, ndc_near: the NDC projection (pixels, and the world depth of the
            near plane); unused by the other kinds.
        center, scale: the contracted kind's normalisation (x' = (x - center) * scale).
    """

    kind: str = "euclidean"
    aabb: tuple[float, float, float, float, float, float] = (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5)
    near: float = 2.0
    far: float = 6.0
    focal: float = 0.0
    width: int = 0
    height: int = 0
    ndc_near: float = 1.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown ray space kind '{self.kind}'; expected one of {', '.join(KINDS)}")
        if self.kind == "ndc" and not (self.focal > 0 and self.width > 0 and self.height > 0):
            raise ValueError(f"an NDC ray space needs focal, width, height > 0, got {self.focal}, {self.width}, "
                             f"{self.height}")
        if self.kind == "contracted" and not (self.scale > 0 and math.isfinite(self.far) and self.far > self.near):
            raise ValueError(f"a contracted ray space needs scale > 0 and a finite far > near, got scale {self.scale}, "
                             f"near {self.near}, far {self.far}")

    @classmethod
    def euclidean(cls, aabb, near: float, far: float) -> "RaySpace":
        """World rays marched from ``near`` to ``far`` inside ``aabb`` (world units)."""
        return cls("euclidean", tuple(float(a) for a in aabb), float(near), float(far))

    @classmethod
    def ndc(cls, focal: float, width: int, height: int, ndc_near: float = 1.0,
            extent: tuple[float, float] = (1.0, 1.0)) -> "RaySpace":
        """LLFF's NDC for views with these intrinsics (pixels); bounds [0, inf), box
        [-e_x, e_x] x [-e_y, e_y] x [-1, 1] for ``extent`` (e_x, e_y) (:func:`ndc_extent`)."""
        ex, ey = (float(e) for e in extent)
        if not (math.isfinite(ex) and math.isfinite(ey) and ex > 0 and ey > 0):
            raise ValueError(f"an NDC box needs finite half-widths > 0, got {extent}")
        aabb = (-ex, -ey, NDC_AABB[2], ex, ey, NDC_AABB[5])
        return cls("ndc", aabb, 0.0, math.inf, float(focal), int(width), int(height), float(ndc_near))

    @classmethod
    def contracted(cls, near: float, far: float = 1000.0, center=(0.0, 0.0, 0.0), scale: float = 1.0) -> "RaySpace":
        """Unbounded scene: world x -> (x - center) * scale, contracted into the ball of radius 2;
        ``near``/``far`` in normalised units (far 1000: contracted radius 1.999)."""
        return cls("contracted", CONTRACTED_AABB, float(near), float(far),
                   center=tuple(float(c) for c in center), scale=float(scale))

    @property
    def is_contracted(self) -> bool:
        """True for unbounded scenes: samples go through :meth:`to_field` and the marcher's growing steps."""
        return self.kind == "contracted"

    @property
    def box_is_world(self) -> bool:
        """True when the box (so the field's input) is in world coordinates, e.g. for mesh export."""
        return self.kind == "euclidean"

    @property
    def forward_facing(self) -> bool:
        """True when the space only holds what lies in front of one average camera (NDC): camera
        paths should stay near the training cameras (spiral) rather than circle the scene."""
        return self.kind == "ndc"

    def apply(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) world rays (unit directions) -> the (..., 3) rays the marcher sees, with unit
        directions; the identity (the same tensors) for the euclidean kind. Differentiable."""
        if self.kind == "euclidean":
            return rays_o, rays_d
        if self.kind == "contracted":
            return (rays_o - rays_o.new_tensor(self.center)) * self.scale, rays_d
        o, d = ndc_rays(rays_o, rays_d, self.focal, self.width, self.height, near=self.ndc_near)
        return o, torch.nn.functional.normalize(d, dim=-1)

    def to_field(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) marched points (``o + t d`` of the rays ``apply`` returns) -> the field's input:
        the contraction for the contracted kind, else the identity (the same tensor). Differentiable."""
        if self.kind != "contracted":
            return x
        return contract(x)

    def to_world(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) points of the field's space -> world points (NDC's far plane z' = 1 and the
        contracted radius 2 map to infinity)."""
        if self.kind == "euclidean":
            return x
        if self.kind == "contracted":
            return uncontract(x) / self.scale + x.new_tensor(self.center)
        return world_from_ndc(x, self.focal, self.width, self.height, self.ndc_near)


def ndc_rays(
    rays_o: torch.Tensor, rays_d: torch.Tensor, focal: float, width: int, height: int, near: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Map world rays of a recentred forward-facing scene to NDC (see the module docstring).

    Args:
        rays_o: (..., 3) origins, world units (recentred frame, scene along -z).
        rays_d: (..., 3) directions (need not be unit; must have d_z != 0, i.e. not parallel
            to the image plane).
        focal, width, height: intrinsics of the views, pixels.
        near: depth of the NDC near plane (1.0 with the default bd_factor).

    Returns (o', d'), each (..., 3): the NDC ray is o' + t d' for t in [0, 1] (near plane ->
    infinity). Plain torch ops: differentiable w.r.t. both inputs (poses in the pose task).

    Example::

        o, d = ndc_rays(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]]), 400.0, 504, 378)
        # o = [[0, 0, -1]], d = [[0, 0, 2]]
    """
    # Move origins to the near plane so that t = 0 is z = -near for every ray.
    t = -(near + rays_o[..., 2]) / rays_d[..., 2]
    rays_o = rays_o + t[..., None] * rays_d
    ox, oy, oz = rays_o.unbind(-1)
    dx, dy, dz = rays_d.unbind(-1)
    sx = -2.0 * focal / width
    sy = -2.0 * focal / height
    o_ndc = torch.stack([sx * ox / oz, sy * oy / oz, 1.0 + 2.0 * near / oz], -1)
    d_ndc = torch.stack([sx * (dx / dz - ox / oz), sy * (dy / dz - oy / oz), -2.0 * near / oz], -1)
    return o_ndc, d_ndc


def ndc_extent(
    c2w: torch.Tensor, focal: float, width: int, height: int, near: float = 1.0, margin: float = 1.02
) -> tuple[float, float]:
    """Half-widths (e_x, e_y) of an NDC box that holds every pixel ray of these views from the
    near plane (z' = -1) to infinity (z' = 1): at least 1 (the average camera's frustum), times
    ``margin``, rounded up to 1/32.

    NDC rays are straight and x', y' are projective in the pixel position on any plane z' = c,
    so the extremes are reached by the four image corners at z' = -1 or z' = 1.

    Args:
        c2w: (N, 3, 4) camera-to-world of the views (recentred frame, OpenGL axes).
        focal, width, height: intrinsics in pixels (the NDC projection's too).
        near: depth of the NDC near plane.
        margin: relative slack beyond the outermost ray.
    """
    c2w = torch.as_tensor(c2w, dtype=torch.float64)
    u = torch.tensor([0.0, width, 0.0, width], dtype=torch.float64)
    v = torch.tensor([0.0, 0.0, height, height], dtype=torch.float64)
    cam = torch.stack([(u - width / 2) / focal, -(v - height / 2) / focal, -torch.ones(4, dtype=torch.float64)], -1)
    d = torch.einsum("nij,cj->nci", c2w[:, :, :3], cam).reshape(-1, 3)
    o = c2w[:, None, :, 3].expand(-1, 4, -1).reshape(-1, 3)
    o_ndc, d_ndc = ndc_rays(o, d, focal, width, height, near=near)
    ends = torch.cat([o_ndc, o_ndc + d_ndc])  # s = 0: z' = -1; s = 1: z' = 1
    half = ends[:, :2].abs().amax(0).clamp_min(1.0) * margin
    ex, ey = (math.ceil(float(h) * 32.0) / 32.0 for h in half)
    return ex, ey


def world_from_ndc(x: torch.Tensor, focal: float, width: int, height: int, near: float = 1.0) -> torch.Tensor:
    """Invert :func:`ndc_rays`' map: (..., 3) NDC points -> world points.
    z' = 1 + 2 near / z  =>  z = 2 near / (z' - 1); x' = -f/(W/2) x / z  =>  x = -x' z W / (2 f)."""
    z = 2.0 * near / (x[..., 2] - 1.0)
    return torch.stack([-x[..., 0] * z * width / (2 * focal), -x[..., 1] * z * height / (2 * focal), z], -1)
