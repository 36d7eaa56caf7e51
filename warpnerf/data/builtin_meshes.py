"""Geometry and materials of the built-in scenes, built in code with numpy.

World is z-up like Blender; every scene fits inside |x|, |y|, |z| <= 1.2 (the NeRF box is
±1.5). Lengths are scene units (the cameras sit at radius ~4.03).

Each primitive computes its own vertex normals, so hard edges stay hard between primitives
(a box face never averages its normal with its neighbour) while curved primitives shade
smoothly. Materials are rows of a small table interpreted by ``kernels/raytrace.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Mirrors the PATTERN_* constants of kernels/raytrace.py (kept here so that building a scene
# never imports Warp).
SOLID, WOOD, WEAVE, STRIPES, ANGULAR, GLAZE, MARBLE = range(7)


@dataclass
class Material:
    """One row of the material table (see kernels/raytrace.py for each pattern's parameters)."""

    pattern: int
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    freq: float = 1.0  # features per scene unit (per turn for ANGULAR)
    axis: int = 2  # 0/1/2 = x/y/z
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class SceneMesh:
    """A triangle mesh with per-vertex normals and per-face material ids."""

    points: np.ndarray  # (V, 3) float32, scene units
    normals: np.ndarray  # (V, 3) float32, unit
    faces: np.ndarray  # (F, 3) int32
    face_material: np.ndarray  # (F,) int32 rows of `materials`
    materials: list[Material] = field(default_factory=list)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the axis-aligned bounding box, each (3,)."""
        return self.points.min(axis=0), self.points.max(axis=0)


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def smooth_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, welding vertices at the same position.

    Welding matters for parametric grids, whose seam and pole vertices are duplicated: without
    it the seam would show as a crease.
    """
    key = np.round(points / 1e-6).astype(np.int64)
    _, weld = np.unique(key, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    p0, p1, p2 = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    face_n = np.cross(p1 - p0, p2 - p0)  # length = 2 * area: the area weighting for free
    acc = np.zeros((weld.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, weld[faces[:, k]], face_n)
    return _normalize(acc[weld])


class MeshBuilder:
    """Collects primitives (each with one material) into one :class:`SceneMesh`."""

    def __init__(self):
        self._points, self._normals, self._faces, self._mats = [], [], [], []
        self._count = 0
        self.materials: list[Material] = []

    def material(self, mat: Material) -> int:
        """Register a material; returns its id."""
        self.materials.append(mat)
        return len(self.materials) - 1

    def add(self, points, faces, mat: int, normals=None) -> None:
        """Append a primitive; ``normals`` default to smooth area-weighted normals."""
        points = np.asarray(points, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if normals is None:
            normals = smooth_normals(points, faces)
        self._points.append(points)
        self._normals.append(np.asarray(normals, dtype=np.float64))
        self._faces.append(faces + self._count)
        self._mats.append(np.full(len(faces), mat, dtype=np.int32))
        self._count += len(points)

    def build(self) -> SceneMesh:
        return SceneMesh(
            points=np.concatenate(self._points).astype(np.float32),
            normals=_normalize(np.concatenate(self._normals)).astype(np.float32),
            faces=np.concatenate(self._faces).astype(np.int32),
            face_material=np.concatenate(self._mats),
            materials=list(self.materials),
        )

    # ---- primitives -------------------------------------------------------------------------

    def box(self, lo, hi, mat: int) -> None:
        """Axis-aligned box between corners ``lo`` and ``hi``; flat-shaded (4 vertices per side)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        pts, nrm, fcs = [], [], []
        for axis in range(3):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            for side, value in ((-1.0, lo[axis]), (1.0, hi[axis])):
                quad = np.zeros((4, 3))
                quad[:, axis] = value
                quad[:, u] = [lo[u], hi[u], hi[u], lo[u]]
                quad[:, v] = [lo[v], lo[v], hi[v], hi[v]]
                n = np.zeros(3)
                n[axis] = side
                base = len(pts) * 4
                tri = [[0, 1, 2], [0, 2, 3]] if side > 0 else [[0, 2, 1], [0, 3, 2]]
                fcs.extend([[base + a, base + b, base + c] for a, b, c in tri])
                pts.append(quad)
                nrm.append(np.tile(n, (4, 1)))
        self.add(np.concatenate(pts), fcs, mat, np.concatenate(nrm))

    def grid(self, fn, nu: int, nv: int, mat: int, close_u: bool = False) -> None:
        """Parametric surface: ``fn(u, v) -> (..., 3)`` for u, v in [0, 1] on an (nu+1, nv+1) grid."""
        u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
        pts = fn(u, v).reshape(-1, 3)
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
        a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        # Drop triangles collapsed at poles: they have no area and confuse nothing but BVH build time.
        p = pts[faces]
        area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        self.add(pts, faces[area > 1e-12], mat)

    def revolve(self, r, z, mat: int, segments: int = 64, center=(0.0, 0.0)) -> None:
        """Surface of revolution about the vertical line through ``center`` of the profile (r(s), z(s))."""
        r, z = np.asarray(r, float), np.asarray(z, float)

        def fn(u, v):
            ang = u * 2 * np.pi
            k = np.round(v * (len(r) - 1)).astype(int)
            rr, zz = r[k], z[k]
            return np.stack([center[0] + rr * np.cos(ang), center[1] + rr * np.sin(ang), zz], -1)

        self.grid(fn, segments, len(r) - 1, mat)

    def cylinder(self, p0, p1, radius: float, mat: int, segments: int = 24, caps: bool = True) -> None:
        """Cylinder from point ``p0`` to ``p1`` (any direction); smooth sides, flat caps."""
        self.frustum(p0, p1, radius, radius, mat, segments, caps)

    def frustum(self, p0, p1, r0: float, r1: float, mat: int, segments: int = 24, caps: bool = True) -> None:
        """Truncated cone from ``p0`` (radius r0) to ``p1`` (radius r1); open when ``caps`` is False."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        axis = _normalize(p1 - p0)
        helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = _normalize(np.cross(axis, helper))
        e2 = np.cross(axis, e1)
        ang = np.linspace(0, 2 * np.pi, segments + 1)
        ring = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2  # (S+1, 3) radial unit vectors
        length = np.linalg.norm(p1 - p0)
        slope = (r0 - r1) / length  # tilts the side normal of a cone towards its narrow end
        pts = np.concatenate([p0 + r0 * ring, p1 + r1 * ring])
        side_n = _normalize(ring + slope * axis)
        nrm = np.concatenate([side_n, side_n])
        n = segments + 1
        faces = [[i, i + 1, n + i + 1] for i in range(segments)] + [[i, n + i + 1, n + i] for i in range(segments)]
        self.add(pts, faces, mat, nrm)
        if caps:
            for centre, rad, sign in ((p0, r0, -1.0), (p1, r1, 1.0)):
                disk = np.concatenate([centre[None], centre + rad * ring[:-1]])
                fan = [[0, 1 + i, 1 + (i + 1) % segments] for i in range(segments)]
                self.add(disk, fan, mat, np.tile(sign * axis, (len(disk), 1)))

    def sphere(self, center, radius: float, mat: int, segments: int = 32) -> None:
        center = np.asarray(center, float)

        def fn(u, v):
            th, ph = u * 2 * np.pi, (v - 0.5) * np.pi
            d = np.stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), np.sin(ph)], -1)
            return center + radius * d

        self.grid(fn, segments, segments // 2, mat)

    def superellipsoid(self, center, radii, e_vert: float, e_horiz: float, mat: int, segments: int = 48) -> None:
        """Superquadric: exponents < 1 give a rounded box (a cushion), 1 gives an ellipsoid."""
        center, radii = np.asarray(center, float), np.asarray(radii, float)

        def spow(x, e):
            return np.sign(x) * np.abs(x) ** e

        def fn(u, v):
            th, ph = u * 2 * np.pi - np.pi, (v - 0.5) * np.pi
            x = spow(np.cos(ph), e_vert) * spow(np.cos(th), e_horiz)
            y = spow(np.cos(ph), e_vert) * spow(np.sin(th), e_horiz)
            z = spow(np.sin(ph), e_vert)
            return center + radii * np.stack([x, y, z], -1)

        self.grid(fn, segments, segments // 2, mat)

    def tube(self, path: np.ndarray, radius: float, mat: int, segments: int = 8) -> None:
        """A tube of constant radius along a polyline ``path`` (P, 3), normals radial."""
        path = np.asarray(path, float)
        tangent = _normalize(np.gradient(path, axis=0))
        helper = np.where(np.abs(tangent[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
        e1 = _normalize(np.cross(tangent, helper))
        e2 = np.cross(tangent, e1)

        def fn(u, v):
            k = np.round(v * (len(path) - 1)).astype(int)
            ang = u * 2 * np.pi
            radial = np.cos(ang)[..., None] * e1[k] + np.sin(ang)[..., None] * e2[k]
            return path[k] + radius * radial

        self.grid(fn, segments, len(path) - 1, mat)


# ---- scenes --------------------------------------------------------------------------------


def chair_mesh() -> SceneMesh:
    """A wooden chair: four legs, apron, stretchers, slatted backrest and a woven cushion."""
    mb = MeshBuilder()
    oak_light, oak_dark = (0.78, 0.55, 0.32), (0.45, 0.27, 0.13)
    # One wood material per grain direction: the grain runs along each part's long axis.
    wood = [mb.material(Material(WOOD, oak_light, oak_dark, freq=22.0, axis=a, origin=(0.31, -0.17, 0.23))) for a in range(3)]
    wood_x, wood_y, wood_z = wood
    fabric = mb.material(Material(WEAVE, (0.62, 0.13, 0.12), (0.85, 0.62, 0.30), freq=18.0))

    leg, x0, y0 = 0.09, 0.55, 0.48  # leg width; leg centres at (±x0, ±y0)
    z_floor, z_seat = -1.12, -0.16
    for sx in (-1, 1):
        mb.box((sx * x0 - leg / 2, -y0 - leg / 2, z_floor), (sx * x0 + leg / 2, -y0 + leg / 2, z_seat), wood_z)
        # Rear legs continue up as the backrest posts.
        mb.box((sx * x0 - leg / 2, y0 - leg / 2, z_floor), (sx * x0 + leg / 2, y0 + leg / 2, 1.12), wood_z)
        # Side stretcher between front and rear leg.
        mb.box((sx * x0 - 0.025, -y0, -0.78), (sx * x0 + 0.025, y0, -0.72), wood_y)
    # Seat: apron rails then the seat board.
    mb.box((-x0, -y0 - leg / 2, z_seat - 0.12), (x0, -y0 + leg / 2 - 0.04, z_seat + 0.02), wood_x)
    mb.box((-x0, y0 - leg / 2 + 0.04, z_seat - 0.12), (x0, y0 + leg / 2, z_seat + 0.02), wood_x)
    for sx in (-1, 1):
        mb.box((sx * x0 - 0.035, -y0, z_seat - 0.12), (sx * x0 + 0.035, y0, z_seat + 0.02), wood_y)
    mb.box((-x0 - 0.06, -y0 - 0.08, z_seat + 0.02), (x0 + 0.06, y0 + 0.06, z_seat + 0.07), wood_x)
    # Cushion: a rounded box, the smooth part of the scene under a high-frequency weave.
    mb.superellipsoid((0.0, -0.02, z_seat + 0.14), (0.58, 0.52, 0.08), 0.35, 0.25, fabric, segments=72)
    # Backrest: lower rail, top rail and five vertical slats (thin, regularly spaced structure).
    yb = y0 - 0.005
    mb.box((-x0, yb - 0.03, 0.18), (x0, yb + 0.03, 0.28), wood_x)
    mb.box((-x0 - 0.04, yb - 0.04, 0.92), (x0 + 0.04, yb + 0.04, 1.1), wood_x)
    for k in range(5):
        xc = -0.36 + 0.18 * k
        mb.box((xc - 0.035, yb - 0.015, 0.28), (xc + 0.035, yb + 0.015, 0.92), wood_z)
    return mb.build()


def lamp_mesh() -> SceneMesh:
    """A desk lamp: heavy marble base, thin stem and arm, striped shade, coiled cord."""
    mb = MeshBuilder()
    marble = mb.material(Material(MARBLE, (0.92, 0.91, 0.88), (0.25, 0.27, 0.33), freq=3.0))
    brass = mb.material(Material(SOLID, (0.80, 0.62, 0.25)))
    cord = mb.material(Material(SOLID, (0.08, 0.08, 0.09)))
    bulb = mb.material(Material(SOLID, (1.0, 0.96, 0.80)))
    shade_c = (0.45, 0.0)
    shade = mb.material(
        Material(ANGULAR, (0.12, 0.32, 0.58), (0.95, 0.93, 0.86), freq=24.0, axis=2, origin=(shade_c[0], shade_c[1], 0.0))
    )
    stripes = mb.material(Material(STRIPES, (0.15, 0.15, 0.15), (0.85, 0.85, 0.85), freq=20.0, axis=2))

    base_c = (-0.15, 0.0)
    mb.frustum((*base_c, -1.12), (*base_c, -1.02), 0.52, 0.46, marble, segments=64)
    mb.cylinder((*base_c, -1.02), (*base_c, -0.96), 0.12, stripes, segments=32)
    top = np.array([base_c[0], base_c[1], 0.42])
    mb.cylinder((*base_c, -0.96), top, 0.028, brass, segments=16)
    mb.sphere(top, 0.06, brass, segments=24)
    elbow = np.array([shade_c[0], shade_c[1], 0.78])
    mb.cylinder(top, elbow, 0.022, brass, segments=16)
    mb.sphere(elbow, 0.045, brass, segments=20)
    # The shade hangs from the elbow; open at the bottom so its lining and the bulb show.
    mb.frustum((*shade_c, 0.78), (*shade_c, 0.30), 0.10, 0.40, shade, segments=96, caps=False)
    mb.sphere((*shade_c, 0.42), 0.09, bulb, segments=24)
    # A cord coiled round the stem: about one pixel wide at 200x200, the thinnest feature here.
    s = np.linspace(0.0, 1.0, 600)
    helix = np.stack(
        [base_c[0] + 0.07 * np.cos(s * 2 * np.pi * 7), base_c[1] + 0.07 * np.sin(s * 2 * np.pi * 7), -0.93 + 1.25 * s], -1
    )
    mb.tube(helix, 0.012, cord, segments=6)
    return mb.build()


def vase_mesh() -> SceneMesh:
    """A glazed vase: one smooth surface of revolution with a slowly varying colour."""
    mb = MeshBuilder()
    glaze = mb.material(Material(GLAZE, (0.16, 0.40, 0.56), (0.86, 0.90, 0.80), freq=1.5, axis=2))
    inner = mb.material(Material(SOLID, (0.35, 0.30, 0.25)))
    z = np.linspace(-1.1, 1.0, 140)
    r = 0.2 + 0.36 * np.exp(-(((z + 0.35) / 0.45) ** 2)) + 0.12 * (1 / (1 + np.exp(-(z - 0.8) / 0.06)))
    mb.revolve(r, z, glaze, segments=128)
    mb.revolve(np.linspace(0.0, r[0], 8), np.full(8, z[0]), glaze, segments=128)  # foot
    # Wall thickness 0.03: a rim ring plus an inner wall down to a hidden floor.
    mb.revolve([r[-1], r[-1] - 0.03], [z[-1], z[-1]], glaze, segments=128)
    zi = np.linspace(z[-1], 0.2, 40)
    ri = np.interp(zi, z, r) - 0.03
    mb.revolve(ri, zi, inner, segments=128)
    mb.revolve(np.linspace(ri[-1], 0.0, 4), np.full(4, zi[-1]), inner, segments=128)
    return mb.build()


def stand_mesh() -> SceneMesh:
    """A studio microphone on a stand (mic- and ficus-like): a thin pole and boom, a grille head
    woven from wires about a pixel wide at 200x200, and a cable. Most of every view is background,
    the case where a field can collapse to empty space and the occupancy grid with it."""
    mb = MeshBuilder()
    steel = mb.material(Material(SOLID, (0.55, 0.57, 0.60)))
    black = mb.material(Material(SOLID, (0.07, 0.07, 0.08)))
    gold = mb.material(Material(STRIPES, (0.80, 0.62, 0.25), (0.35, 0.25, 0.10), freq=30.0, axis=2))
    wire = mb.material(Material(SOLID, (0.85, 0.85, 0.82)))

    mb.frustum((0.0, 0.0, -1.12), (0.0, 0.0, -1.08), 0.42, 0.38, black, segments=48)
    mb.cylinder((0.0, 0.0, -1.08), (0.0, 0.0, 0.10), 0.018, steel, segments=12)
    joint = np.array([0.0, 0.0, 0.10])
    mb.sphere(joint, 0.04, black, segments=16)
    head = np.array([0.38, 0.0, 0.55])
    mb.cylinder(joint, head - np.array([0.08, 0.0, 0.10]), 0.014, steel, segments=12)
    # body under the head, then the grille: latitude rings and meridians of thin wire
    mb.frustum(head - np.array([0.0, 0.0, 0.42]), head - np.array([0.0, 0.0, 0.16]), 0.07, 0.10, gold, segments=32)
    r = 0.16
    t = np.linspace(0.0, 2 * np.pi, 97)
    for lat in np.linspace(-0.8, 0.8, 7):
        ring = np.stack([r * np.cos(lat) * np.cos(t), r * np.cos(lat) * np.sin(t), np.full_like(t, r * np.sin(lat))], -1)
        mb.tube(head + ring, 0.006, wire, segments=6)
    ph = np.linspace(-np.pi / 2, np.pi / 2, 49)
    for lon in np.linspace(0.0, np.pi, 6, endpoint=False):
        arc = np.stack([r * np.cos(ph) * np.cos(lon), r * np.cos(ph) * np.sin(lon), r * np.sin(ph)], -1)
        full = np.concatenate([arc, (arc * np.array([-1.0, -1.0, 1.0]))[::-1]])
        mb.tube(head + full, 0.006, wire, segments=6)
    # the cable hangs from the body down to the base in a loose curve
    s = np.linspace(0.0, 1.0, 80)
    start, end = head - np.array([0.0, 0.0, 0.42]), np.array([0.25, 0.2, -1.05])
    cable = start[None] * (1 - s[:, None]) + end[None] * s[:, None]
    cable[:, 0] += 0.25 * np.sin(np.pi * s)
    cable[:, 1] += 0.15 * np.sin(2 * np.pi * s)
    mb.tube(cable, 0.01, black, segments=6)
    return mb.build()


# name -> (builder, one-line description); the order is the order users see.
SCENES = {
    "chair": (chair_mesh, "wooden chair with a woven cushion: smooth shapes, wood grain and a fine fabric weave"),
    "lamp": (lamp_mesh, "desk lamp: thin stem and coiled cord, finely striped shade, marble base (high frequency)"),
    "vase": (vase_mesh, "glazed vase: one smooth surface of revolution, slowly varying colour (low frequency)"),
    "stand": (stand_mesh, "microphone on a stand: thin pole, wire grille and cable over mostly empty views (thin structures)"),
}


# ---- an unbounded scene: the chair on a textured ground inside a distant textured environment ----

GARDEN_GROUND_HALF = 8.0  # the ground is the square |x|, |y| <= 8 at the chair's floor
GARDEN_ENV_RADIUS = 15.0  # the environment is a sphere of this radius around the origin


def garden_mesh() -> SceneMesh:
    """The chair standing on a large veined stone ground (the foreground layer; casts shadows).

    Rendered together with :func:`garden_environment` by ``builtin.render_garden``: the
    environment is a separate layer because a shadow ray would always hit the enclosing sphere.
    """
    chair = chair_mesh()
    mb = MeshBuilder()
    mb.materials = list(chair.materials)
    mb._points.append(chair.points.astype(np.float64))
    mb._normals.append(chair.normals.astype(np.float64))
    mb._faces.append(chair.faces.astype(np.int64))
    mb._mats.append(chair.face_material.astype(np.int32))
    mb._count = len(chair.points)
    stone = mb.material(Material(MARBLE, (0.72, 0.66, 0.55), (0.12, 0.16, 0.22), freq=1.7))
    z = float(chair.points[:, 2].min()) - 1e-3  # just below the legs: no z-fighting
    h = GARDEN_GROUND_HALF
    n = 16  # a grid, not one quad: long thin triangles lose precision in the ray query
    g = np.linspace(-h, h, n + 1)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], -1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    mb.add(pts, faces, stone, normals=np.tile([0.0, 0.0, 1.0], (len(pts), 1)))
    return mb.build()


def garden_environment() -> SceneMesh:
    """A distant sphere (radius GARDEN_ENV_RADIUS) with a large-scale marbled pattern: the background layer."""
    mb = MeshBuilder()
    sky = mb.material(Material(MARBLE, (0.55, 0.70, 0.85), (0.20, 0.28, 0.18), freq=0.35))
    mb.sphere((0.0, 0.0, 0.0), GARDEN_ENV_RADIUS, sky, segments=96)
    return mb.build()
