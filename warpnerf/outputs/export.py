"""Geometry out of a trained field: ``warpnerf export --what mesh|points``.

* **mesh**: the density is sampled on a regular grid over the scene box (cells the occupancy
  grid marks empty are set to 0, which removes floaters the renderer never samples), marching
  cubes (scikit-image) extracts the iso-surface ``sigma = threshold``, connected pieces (faces
  sharing a vertex) under ``min_component_faces`` faces are dropped (floaters; the largest piece
  always stays), and each vertex gets the colour the field emits towards a camera looking straight
  at the surface (view direction = the inward normal, i.e. the density gradient direction) and an
  outward unit normal (area-weighted mean of its faces' normals).
* **points**: every training view is rendered (optionally downscaled); each pixel with opacity
  above ``min_opacity`` becomes the point at the rendered depth along the marched ray, mapped
  back to world coordinates by the scene's ray space (``ray_space.to_world``, docs/design.md §6).

Files are binary PLY written with ``plyfile`` (vertex x, y, z, [nx, ny, nz,] red, green, blue; faces as
``vertex_indices``). These libraries and scipy (connected components) are the optional extra
``pip install 'warpnerf[export]'``.

Beside the PLY, ``warpnerf export`` writes ``<name>.export.json`` (:func:`info_path`): what was exported
with which settings, the mesh's counts before and after the floaters were removed (:attr:`Mesh.counts`),
the time and the peak memory. ``--record NAME`` puts the same into a results record.
"""

from __future__ import annotations

import os
from typing import NamedTuple, Optional

import numpy as np
import torch

from warpnerf.model.renderer import pixel_rays
from warpnerf.train.memory import mesh_bytes, over_budget, render_bytes
from warpnerf.train.views import training_cameras

# Iso-level of the exported surface, density per scene unit (1 - exp(-10 * 0.01) = 10 % of the light
# is blocked by 1/100 scene unit of it). Measured on the built-in chair after 150 steps: of the levels
# 5, 10, 25, 50 it gave the lowest Chamfer distance (0.033) and a bounding box within 2.5 %.
DEFAULT_THRESHOLD = 10.0

# Connected pieces of the mesh with fewer faces are floaters and are dropped (``--min-component-faces``).
# On the lego at 256^3 nearly every piece is under 100 faces (records lego_full_mesh and
# lego_full_mesh_keep_floaters, docs/results.md); a real part at that resolution (a stud of the lego)
# has hundreds. The largest piece is always kept.
DEFAULT_MIN_COMPONENT_FACES = 100


class ExportError(ValueError):
    """Export cannot proceed (missing optional package, empty surface, unsupported scene); one line."""


def _level_weights(trainer) -> torch.Tensor:
    return trainer.level_weights(trainer.cfg.iters)


@torch.no_grad()
def density_grid(trainer, resolution: int = 128, chunk: int = 1 << 17) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Density sampled at the (resolution,)*3 lattice spanning the scene box (corners included).

    Returns ``sigma`` (R, R, R) float32 indexed [ix, iy, iz] (per scene unit; 0 in cells the
    occupancy grid marks empty), ``lo`` (3,) and ``spacing`` (3,) in scene units."""
    field, occ = trainer.field, trainer.occupancy
    lo = np.asarray(occ.aabb[:3], np.float64)
    hi = np.asarray(occ.aabb[3:], np.float64)
    axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution, dtype=torch.float32) for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).to(trainer.device)
    w = _level_weights(trainer)
    sigma = torch.cat([field.density(pts[i:i + chunk], w) for i in range(0, pts.shape[0], chunk)])
    # occupancy cell of each lattice point (same layout as the marcher: flat (ix * res + iy) * res + iz)
    r = occ.resolution
    lo_t = torch.as_tensor(lo, dtype=torch.float32, device=pts.device)
    hi_t = torch.as_tensor(hi, dtype=torch.float32, device=pts.device)
    cell = ((pts - lo_t) / (hi_t - lo_t) * r).long().clamp(0, r - 1)
    occupied = occ.bitfield[(cell[:, 0] * r + cell[:, 1]) * r + cell[:, 2]].bool()
    sigma = torch.where(occupied, sigma, torch.zeros_like(sigma))
    spacing = (hi - lo) / (resolution - 1)
    return sigma.view(resolution, resolution, resolution).cpu().numpy(), lo, spacing


@torch.no_grad()
def vertex_colors(trainer, verts: np.ndarray, normals: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """(V, 3) uint8 colours of surface points ``verts`` (V, 3) seen along ``normals`` (V, 3):
    the field's colour for a ray travelling along the (unit) direction ``normals`` (inward)."""
    field = trainer.field
    w = _level_weights(trainer)
    out = []
    for i in range(0, len(verts), chunk):
        x = torch.as_tensor(verts[i:i + chunk], dtype=torch.float32, device=trainer.device)
        d = torch.nn.functional.normalize(torch.as_tensor(normals[i:i + chunk], dtype=torch.float32,
                                                          device=trainer.device), dim=-1)
        _, geo = field.geometry(x, w)
        out.append(field.color(geo, d).clamp(0, 1).cpu())
    rgb = torch.cat(out) if out else torch.zeros(0, 3)
    return (rgb.numpy() * 255 + 0.5).astype(np.uint8)


def face_components(faces: np.ndarray, n_verts: int) -> tuple[np.ndarray, int]:
    """Connected pieces of a triangle mesh, faces connected through shared vertices.

    Returns the piece label (F,) of each face, 0..n-1, and n. Memory is linear in the face count
    (a sparse vertex graph with two edges per face; scipy's connected components)."""
    from scipy.sparse import coo_matrix  # optional extra: warpnerf[export]
    from scipy.sparse.csgraph import connected_components  # optional extra: warpnerf[export]

    if len(faces) == 0:
        return np.zeros(0, np.int64), 0
    faces = np.asarray(faces, np.int64)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int32), (rows, cols)), shape=(n_verts, n_verts))
    _, vertex_label = connected_components(graph, directed=False)
    # vertices in no face are pieces of their own: number only the pieces that have faces
    _, label = np.unique(vertex_label[faces[:, 0]], return_inverse=True)
    label = label.reshape(-1)
    return label, int(label.max()) + 1


def remove_small_components(faces: np.ndarray, n_verts: int, min_faces: int):
    """Drop the connected pieces with fewer than ``min_faces`` faces (the largest piece always stays)
    and the vertices only they used.

    Returns ``keep`` (V',) old indices of the vertices kept, the faces (F', 3) int32 re-indexed into
    them, and the piece counts (before, after)."""
    label, n = face_components(faces, n_verts)
    if n == 0:
        return np.arange(n_verts), np.asarray(faces, np.int32).reshape(-1, 3), (0, 0)
    size = np.bincount(label, minlength=n)
    big = size >= min_faces
    big[np.argmax(size)] = True
    kept_faces = np.asarray(faces)[big[label]]
    keep = np.unique(kept_faces)
    new_index = np.full(n_verts, -1, np.int64)
    new_index[keep] = np.arange(len(keep))
    return keep, new_index[kept_faces].astype(np.int32), (n, int(big.sum()))


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the area-weighted mean of the normals of the faces around
    each vertex (faces counter-clockwise seen from outside give outward normals; 0 for a vertex in
    no face)."""
    tri = verts[faces].astype(np.float64)  # (F, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = twice the face's area
    acc = np.zeros((len(verts), 3))
    for k in range(3):
        for axis in range(3):
            acc[:, axis] += np.bincount(faces[:, k], weights=n[:, axis], minlength=len(verts))
    length = np.linalg.norm(acc, axis=-1, keepdims=True)
    return (acc / np.where(length > 0, length, 1.0)).astype(np.float32)


class Mesh(NamedTuple):
    """An exported mesh: vertices (V, 3) float32, faces (F, 3) int32 (CCW seen from outside),
    colours (V, 3) uint8, outward unit normals (V, 3) float32, the one-line ``summary`` of the
    vertex, face and piece counts before and after the floaters were removed, and those counts
    (``counts``: ``vertices_before``, ``faces_before``, ``pieces_before`` from marching cubes;
    ``vertices``, ``faces``, ``pieces`` written)."""
    verts: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    summary: str
    counts: dict


def info_path(ply_path: str) -> str:
    """The JSON file ``warpnerf export`` writes beside the PLY ``ply_path``: ``<name>.export.json``."""
    return os.path.splitext(ply_path)[0] + ".export.json"


def extract_mesh(trainer, resolution: int = 128, threshold: float = DEFAULT_THRESHOLD,
                 min_component_faces: int = DEFAULT_MIN_COMPONENT_FACES) -> Mesh:
    """Marching cubes on the density, then the connected pieces under ``min_component_faces`` faces
    removed (0 or 1: keep everything). Vertices are in scene units."""
    if not trainer.scene.ray_space.box_is_world:
        raise ExportError(f"mesh export needs a field in world coordinates (this scene's field lives in its "
                          f"{trainer.scene.ray_space.kind} ray space); use --what points")
    try:
        from skimage import measure  # optional extra: warpnerf[export]
        import scipy.sparse.csgraph  # noqa: F401  # optional extra: warpnerf[export]
    except ImportError:
        raise ExportError("mesh export needs scikit-image and scipy: pip install 'warpnerf[export]'") from None
    problem = over_budget(mesh_bytes(resolution), trainer.cfg.memory_budget_mb,
                          f"a {resolution}^3 density grid for marching cubes", "--resolution")
    if problem:
        raise ExportError(problem)
    sigma, lo, spacing = density_grid(trainer, resolution)
    if not (sigma.max() > threshold > sigma.min()):
        raise ExportError(f"the density never crosses the iso-level {threshold} (range {sigma.min():.3g}.."
                          f"{sigma.max():.3g}); pick --threshold inside it")
    # pad with empty space so surfaces touching the box boundary are closed
    padded = np.pad(sigma, 1, constant_values=0.0)
    verts, faces, normals, _ = measure.marching_cubes(padded, level=threshold, spacing=tuple(spacing))
    verts = verts - spacing + lo  # undo the one-cell pad, then move to world coordinates
    # skimage orders faces clockwise seen from the low-value side here; flip to CCW from outside
    faces = faces[:, ::-1]
    before = f"{len(verts):,} vertices, {len(faces):,} faces"
    counts = {"vertices_before": len(verts), "faces_before": len(faces)}
    keep, faces, (pieces_before, pieces) = remove_small_components(faces, len(verts), max(min_component_faces, 1))
    counts.update(pieces_before=pieces_before, vertices=len(keep), faces=len(faces), pieces=pieces)
    after = f"{len(keep):,} vertices, {len(faces):,} faces, {pieces:,} pieces"
    summary = (f"{after} (floaters kept)" if min_component_faces <= 1 else
               f"{after} (no piece under {min_component_faces} faces)" if pieces == pieces_before else
               f"{after} (from {before}, {pieces_before:,} pieces: {pieces_before - pieces:,} floaters under "
               f"{min_component_faces} faces removed)")
    verts, normals = verts[keep], normals[keep]
    # skimage's normals point down the density gradient (outwards); rays hit the surface going inwards
    colors = vertex_colors(trainer, verts, -normals)
    verts = verts.astype(np.float32)
    return Mesh(verts, faces, colors, vertex_normals(verts, faces), summary, counts)


@torch.no_grad()
def extract_points(trainer, scale: float = 0.5, min_opacity: float = 0.95, max_points: int = 1_000_000,
                   seed: int = 0, max_views: int = 0):
    """Coloured points from rendered depth of the training views (``scale``: resolution factor;
    ``max_views`` > 0: that many views, evenly spaced, instead of all).

    Returns points (P, 3) float32 in world units and colours (P, 3) uint8; at most
    ``max_points`` (a seeded random subset)."""
    views = trainer.views
    h, w = max(int(round(views.height * scale)), 1), max(int(round(views.width * scale)), 1)
    problem = over_budget(render_bytes(h, w, frames=0), trainer.cfg.memory_budget_mb,
                          f"rendering {w}x{h} views for points", "--scale")
    if problem:
        raise ExportError(problem)
    sx, sy = w / views.width, h / views.height
    focal, cx, cy = views.focal * sx, views.cx * sx, views.cy * sy
    c2ws = training_cameras(trainer)
    if 0 < max_views < len(c2ws):
        c2ws = c2ws[torch.linspace(0, len(c2ws) - 1, max_views).round().long()]
    weights = _level_weights(trainer)
    pts, cols = [], []
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32) + 0.5, torch.arange(w, dtype=torch.float32) + 0.5,
                          indexing="ij")
    u, v = u.reshape(-1).to(trainer.device), v.reshape(-1).to(trainer.device)
    for c2w in c2ws:
        c2w = c2w.to(trainer.device)
        img = trainer.renderer.render_image(c2w, h, w, focal, cx, cy, weights)
        keep = (img["opacity"].reshape(-1) > min_opacity)
        o, d = pixel_rays(c2w[None].expand(u.shape[0], 3, 4), u, v, focal, cx, cy)
        t = img["depth"].reshape(-1)
        # depth is measured along the rays the marcher saw: find the point there, then go back to the world
        space = trainer.scene.ray_space
        om, dm = space.apply(o, d)
        x = space.to_world(space.to_field(om + t[:, None] * dm))
        keep &= torch.isfinite(x).all(-1)  # points at infinity (the far end of an NDC ray)
        pts.append(x[keep].cpu())
        cols.append(img["rgb"].reshape(-1, 3)[keep].clamp(0, 1).cpu())
    points, colors = torch.cat(pts), torch.cat(cols)
    if points.shape[0] > max_points:
        pick = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(seed))[:max_points]
        points, colors = points[pick], colors[pick]
    return points.numpy().astype(np.float32), (colors.numpy() * 255 + 0.5).astype(np.uint8)


def write_ply(path: str, verts: np.ndarray, colors: np.ndarray, faces: Optional[np.ndarray] = None,
              normals: Optional[np.ndarray] = None) -> None:
    """Binary PLY: vertices (V, 3) float, optional normals (V, 3) float (nx, ny, nz), colours (V, 3)
    uint8, optional triangle faces (F, 3)."""
    try:
        from plyfile import PlyData, PlyElement  # optional extra: warpnerf[export]
    except ImportError:
        raise ExportError("writing PLY needs plyfile: pip install 'warpnerf[export]'") from None
    xyz = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    nxyz = [("nx", "f4"), ("ny", "f4"), ("nz", "f4")] if normals is not None else []
    v = np.empty(len(verts), dtype=xyz + nxyz + [("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = verts[:, 0], verts[:, 1], verts[:, 2]
    if normals is not None:
        v["nx"], v["ny"], v["nz"] = normals[:, 0], normals[:, 1], normals[:, 2]
    v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    elements = [PlyElement.describe(v, "vertex")]
    if faces is not None:
        f = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
        f["vertex_indices"] = faces
        elements.append(PlyElement.describe(f, "face"))
    PlyData(elements, text=False).write(path)


def read_ply(path: str):
    """(verts (V, 3) float32, colors (V, 3) uint8, faces (F, 3) int32 or None) of a PLY file."""
    from plyfile import PlyData  # optional extra: warpnerf[export]

    ply = PlyData.read(path)
    v = ply["vertex"].data
    verts = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float32)
    colors = np.stack([v["red"], v["green"], v["blue"]], -1).astype(np.uint8)
    faces = None
    if "face" in ply:
        faces = np.stack(ply["face"].data["vertex_indices"]).astype(np.int32)
    return verts, colors, faces


def read_ply_normals(path: str) -> Optional[np.ndarray]:
    """(V, 3) float32 vertex normals of a PLY file, None when it has none."""
    from plyfile import PlyData  # optional extra: warpnerf[export]

    v = PlyData.read(path)["vertex"].data
    if "nx" not in v.dtype.names:
        return None
    return np.stack([v["nx"], v["ny"], v["nz"]], -1).astype(np.float32)


# ---- comparing with a reference mesh --------------------------------------------------------------


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniformly distributed over a triangle mesh's area."""
    rng = np.random.default_rng(seed)
    tri = verts[faces].astype(np.float64)  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    pick = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)  # uniform barycentrics on a triangle
    a, b, c = tri[pick, 0], tri[pick, 1], tri[pick, 2]
    return ((1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c).astype(np.float32)


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean nearest-neighbour distances (a -> b, b -> a) between point sets (N, 3), (M, 3);
    the symmetric Chamfer distance is their mean (scene units)."""
    from scipy.spatial import cKDTree  # optional extra: warpnerf[export]

    return float(cKDTree(b).query(a)[0].mean()), float(cKDTree(a).query(b)[0].mean())
