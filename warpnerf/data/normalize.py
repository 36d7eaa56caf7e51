"""Scene normalisation for captures with arbitrary world frames (COLMAP, transforms.json).

A structure-from-motion world has an arbitrary origin, orientation and scale. Like nerfstudio's
``auto_orient_and_center_poses(method="up", center_method="poses")`` followed by its
``scale_factor = 1 / max |t|``, every such scene is mapped by one similarity

    x' = s * (R @ x + t)          (points; camera centres likewise)
    R_c2w' = R @ R_c2w            (camera orientations; directions d' = R @ d, still unit)

where ``R`` turns the mean camera up axis (OpenGL +y, averaged over all views) onto +z,
``t = -R @ mean(camera centres)`` and ``s = 1 / max |component of the centred, rotated camera
centres|``, so the cameras lie in [-1, 1]^3 with at least one on the boundary. The map is
:class:`Normalization`; loaders compute it from all views (every split) before splitting.

Object rigs without points (:func:`capture_normalization`): the cube around the cameras is
mostly empty there (NeRF-synthetic's lego filled a sixth of each axis and trained to 16 dB
instead of 30), so, like instant-ngp's colmap2nerf, the scene is centred on the point the
cameras look at (:func:`warpnerf.geometry.rig.optical_focus`) instead, with the same ``R``, and
scaled so that the cube of half-side 1 is the frustum intersection: the ball around the focus that
every camera sees whole (radius ``distance * sin(narrowest half field of view)``, median over the
cameras), padded by :data:`OBJECT_BOX_PAD`. NeRF-synthetic (cameras 4.03 from the centre, 40 deg
field of view) gets its own box, [-1.5, 1.5]^3, as the unit cube. Object rigs with points, and 360°
rigs in a box or contracted, keep the camera normalisation.

Ray space (:func:`choose_ray_space`): a forward-facing rig trains in LLFF's NDC, whatever the layout
(a COLMAP model from ``warpnerf process`` or a transforms.json as well as ``poses_bounds.npy``), a 360° rig
in a contracted space (MipNeRF-360), anything else in a box; ``ndc`` / ``unbounded`` given as True or
False override the rig. In NDC the world is mapped as the LLFF loader maps it
(:func:`normalization_forward_facing`): scaled so that the nearest content lies at depth
1 / ``LLFF_BD_FACTOR`` = 1.33, in front of the NDC near plane at 1, then expressed in the frame of the
average camera (:func:`warpnerf.data.llff.average_pose`). The nearest content is the 0.1th percentile of
the sparse points' depths (LLFF's imgs2poses), else half the depth at which the optical axes meet
(:data:`FF_FOCUS_NEAR`), else a multiple of the camera spread (:data:`FF_SPREAD_NEAR`).

Bounds: ``near``/``far`` come from the depths of the sparse points seen by the cameras (robust
percentiles), else from the camera spread; the box ``aabb`` from the points (robust bounding
cube), else the cube of half-side ``aabb_scale`` (instant-ngp's key, default 1: after the object
framing that is instant-ngp's own unit box, 1.5 units around the look-at point of cameras 4 away).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warpnerf.data.llff import LLFF_BD_FACTOR, average_pose
from warpnerf.geometry.rig import classify_rig

# Object framing: the box half-side over the radius every camera sees whole. 1.1 makes it NeRF-synthetic's
# box exactly (1.1 * 4.031 * sin(0.3456) = 1.50) and leaves room for an object framed slightly off-centre.
OBJECT_BOX_PAD = 1.1
MIN_POINTS = 8  # fewer sparse points than this bound nothing (bounds_from_points falls back too)
# Forward-facing rigs without points: the nearest content, as a fraction of the depth at which the optical axes
# meet. LLFF's fern: the axes meet 32 units in front of the cameras, its nearest bound is 17 (0.53); a smaller
# fraction only costs depth resolution (NDC's z' crowds towards 1), a larger one cuts the nearest content off.
FF_FOCUS_NEAR = 0.5
# ... and when the axes do not meet in front (parallel within optical_focus's tolerance): a multiple of the RMS
# distance of the centres from their mean (fern: nearest bound 17, centre spread 3.5, 4.8x).
FF_SPREAD_NEAR = 4.0
RAY_SPACES = ("box", "ndc", "contracted")


@dataclass
class Normalization:
    """The similarity x' = scale * (rotation @ x + translation) applied to a capture's world."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    scale: float
    rig: str = ""  # "object", "forward_facing" or "360" (warpnerf.geometry.rig); "" when not classified
    framing: str = ""  # one line: the rig and what the map does about it, for the run to print
    ray_space: str = "box"  # "box", "ndc" or "contracted" (:func:`choose_ray_space`)

    @staticmethod
    def identity() -> "Normalization":
        return Normalization(np.eye(3), np.zeros(3), 1.0)

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous form of the map."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.scale * self.translation
        return m

    def points(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> normalised points (float64)."""
        x = np.asarray(x, np.float64)
        return self.scale * (x @ self.rotation.T + self.translation)

    def c2w(self, c2w: np.ndarray) -> np.ndarray:
        """(N, 3, 4) OpenGL camera-to-world -> normalised (float64); rotations stay orthonormal."""
        c2w = np.asarray(c2w, np.float64)
        rot = np.einsum("ij,njk->nik", self.rotation, c2w[:, :, :3])
        return np.concatenate([rot, self.points(c2w[:, :, 3])[:, :, None]], axis=2)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation turning unit vector ``a`` onto unit vector ``b`` (shortest arc)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-10:
        # Opposite vectors: a half turn about any axis perpendicular to a.
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def normalization_from_cameras(c2w: np.ndarray, orient: bool = True, center: bool = True, rescale: bool = True) -> Normalization:
    """The documented normalisation (module docstring) of (N, 3, 4) OpenGL cameras.

    ``orient``/``center``/``rescale`` switch off each part (identity rotation, zero shift, unit scale).
    """
    c2w = np.asarray(c2w, np.float64)
    rot = rotation_between(c2w[:, :, 1].mean(0), [0.0, 0.0, 1.0]) if orient else np.eye(3)
    t = -rot @ c2w[:, :, 3].mean(0) if center else np.zeros(3)
    scale = 1.0
    if rescale:
        extent = np.abs(c2w[:, :, 3] @ rot.T + t).max()
        scale = 1.0 / extent if extent > 1e-12 else 1.0
    return Normalization(rot, t, float(scale))


def half_fov(width: float, height: float, fx: float, fy: float) -> float:
    """Narrowest half field of view of a pinhole camera, radians: the half-angle of the cone inside its
    frustum. The principal point is taken at the image centre (a calibrated one is within a few pixels)."""
    return float(min(math.atan2(0.5 * width, fx), math.atan2(0.5 * height, fy)))


def normalization_from_focus(c2w: np.ndarray, focus: np.ndarray, half_fovs) -> Normalization:
    """The object framing (module docstring) of (N, 3, 4) OpenGL cameras converging on ``focus`` (3,).

    ``half_fovs``: (N,) or one narrowest half field of view, radians (:func:`half_fov`).
    """
    c2w = np.asarray(c2w, np.float64)
    focus = np.asarray(focus, np.float64)
    rot = rotation_between(c2w[:, :, 1].mean(0), [0.0, 0.0, 1.0])
    dist = np.linalg.norm(c2w[:, :, 3] - focus, axis=1)
    seen = float(np.median(dist * np.sin(np.broadcast_to(np.asarray(half_fovs, np.float64), dist.shape))))
    half = OBJECT_BOX_PAD * seen
    if not half > 1e-12:
        raise ValueError(f"no room around the focus: the cameras see a ball of radius {seen:.3g} around it")
    return Normalization(rot, -rot @ focus, 1.0 / half)


def choose_ray_space(rig: str, unbounded: bool | None = None, ndc: bool | None = None) -> tuple[str, str]:
    """(ray space, why) for a rig of kind ``rig``: "ndc" for forward-facing rigs, "contracted" for 360° rigs,
    "box" otherwise; ``unbounded`` / ``ndc`` True or False (the ``--unbounded`` / ``--ndc`` flags and their
    ``--no-`` forms) override the rig. Raises ValueError when both are True.

    >>> choose_ray_space("forward_facing")
    ('ndc', 'NDC, as LLFF scenes (--no-ndc keeps a box)')
    >>> choose_ray_space("forward_facing", ndc=False)[0]
    'box'
    """
    if unbounded and ndc:
        raise ValueError("unbounded and ndc both on: a scene has one ray space (contracted or NDC); drop one")
    if unbounded:
        return "contracted", "contracted beyond the cameras (--unbounded)"
    if ndc:
        return "ndc", "NDC (--ndc)"
    if rig == "forward_facing" and ndc is None:
        return "ndc", "NDC, as LLFF scenes (--no-ndc keeps a box)"
    if rig == "360" and unbounded is None:
        return "contracted", "contracted beyond the cameras, for a distant background (--no-unbounded keeps a box)"
    why = "box"
    if rig == "forward_facing":
        why += " (--no-ndc)"
    elif rig == "360":
        why += " (--no-unbounded; --unbounded would contract a distant background)"
    return "box", why


def near_content_depth(c2w: np.ndarray, points: np.ndarray | None, focus: np.ndarray | None) -> tuple[float, str]:
    """(depth, where from) of the nearest content in front of (N, 3, 4) forward-facing cameras (module docstring):
    the 0.1th percentile of the sparse points' depths along the view axes, else :data:`FF_FOCUS_NEAR` times the
    mean depth of ``focus`` (the point nearest to the optical axes) when it lies in front, else
    :data:`FF_SPREAD_NEAR` times the RMS spread of the centres."""
    c2w = np.asarray(c2w, np.float64)
    axis = -c2w[:, :, 2] / np.linalg.norm(c2w[:, :, 2], axis=1, keepdims=True)
    if points is not None and len(points) >= MIN_POINTS:
        rel = np.asarray(points, np.float64)[None, :, :] - c2w[:, None, :, 3]
        z = np.einsum("npk,nk->np", rel, axis)
        z = z[z > 1e-9]
        if z.size >= MIN_POINTS:
            return float(np.percentile(z, 0.1)), "from the sparse points"
    if focus is not None:
        depth = float(np.einsum("nk,nk->n", np.asarray(focus, np.float64)[None] - c2w[:, :, 3], axis).mean())
        if depth > 0:
            return FF_FOCUS_NEAR * depth, f"taken at {FF_FOCUS_NEAR:g}x the depth where the optical axes meet"
    spread = float(np.sqrt(((c2w[:, :, 3] - c2w[:, :, 3].mean(0)) ** 2).sum(1).mean()))
    return FF_SPREAD_NEAR * spread, f"taken at {FF_SPREAD_NEAR:g}x the camera spread: the optical axes do not meet in front"


def normalization_forward_facing(c2w: np.ndarray, near_depth: float) -> Normalization:
    """The LLFF loader's map (module docstring) of (N, 3, 4) OpenGL cameras whose nearest content lies
    ``near_depth`` in front of them: scale so that it is at 1 / LLFF_BD_FACTOR, then the average camera's
    frame (rotation A^T, translation -A^T mean centre: recentring commutes with the scale)."""
    if not (near_depth > 0 and np.isfinite(near_depth)):
        raise ValueError(f"the nearest content must lie in front of the cameras, got depth {near_depth}")
    avg = average_pose(np.asarray(c2w, np.float64))
    rot = avg[:, :3].T
    return Normalization(rot, -rot @ avg[:, 3], 1.0 / (LLFF_BD_FACTOR * near_depth))


def capture_normalization(c2w: np.ndarray, points: np.ndarray | None, half_fovs,
                          unbounded: bool | None = None, ndc: bool | None = None) -> Normalization:
    """The map of a capture, chosen from its rig (module docstring), with ``rig``, ``framing`` and
    ``ray_space`` filled in.

    Args:
        c2w: (N, 3, 4) OpenGL cameras of all views, capture frame (checked: finite rotations, not all
            at one point).
        points: (P, 3) sparse points or None; with :data:`MIN_POINTS` or more the points bound the scene.
        half_fovs: (N,) or one narrowest half field of view, radians (:func:`half_fov`).
        unbounded, ndc: None: the ray space from the rig; True / False: contract (the cameras then lie in
            [-1, 1]^3) / NDC, or not (:func:`choose_ray_space`).
    """
    rig = classify_rig(c2w)
    space, why = choose_ray_space(rig.kind, unbounded, ndc)
    has_points = points is not None and len(points) >= MIN_POINTS
    if space == "ndc":
        depth, where = near_content_depth(c2w, points, rig.focus)
        norm = normalization_forward_facing(c2w, depth)
        how = f"{why}; nearest content ({where}) at depth {1.0 / LLFF_BD_FACTOR:.2f}"
    elif rig.kind == "object" and not has_points and space == "box":
        norm = normalization_from_focus(c2w, rig.focus, half_fovs)
        how = "centred on it, box = what every camera sees"
    else:
        norm = normalization_from_cameras(c2w)
        how = ("cameras in [-1, 1]^3, " + why if space == "contracted" else
               "box from the sparse points" if has_points else "box = the cube around the cameras")
        if space == "box" and why != "box":
            how += why[3:]
    norm.rig, norm.framing, norm.ray_space = rig.kind, f"{rig.reason}; {how}", space
    return norm


def bounds_from_points(c2w: np.ndarray, points: np.ndarray | None, aabb_scale: float | None = None):
    """(near, far, aabb) of a normalised scene.

    Args:
        c2w: (N, 3, 4) normalised OpenGL cameras (the training views).
        points: (P, 3) normalised sparse points, or None / empty.
        aabb_scale: half-side of the fallback cube (instant-ngp's ``aabb_scale``), default 1.

    With points: depths along each camera's view axis of the points in front of it give
    ``near = 0.5 * 1st percentile`` and ``far = 1.5 * 99th percentile`` (the marcher also clips
    to the box, so a generous far costs nothing); the box is the cube around the 0.5-99.5 %
    percentile bounds of the points, padded by 10 %. Without points: near 0.01, far = the
    diagonal of the fallback cube plus the camera spread, box the fallback cube.
    """
    half = float(aabb_scale) if aabb_scale else 1.0
    c2w = np.asarray(c2w, np.float64)
    if points is not None and len(points) >= MIN_POINTS:
        pts = np.asarray(points, np.float64)
        rel = pts[None, :, :] - c2w[:, None, :, 3]  # (N, P, 3)
        z = -np.einsum("npk,nk->np", rel, c2w[:, :, 2])  # depth along -z (OpenGL looks down -z)
        z = z[z > 1e-6]
        if z.size >= 8:
            near = 0.5 * float(np.percentile(z, 1.0))
            far = 1.5 * float(np.percentile(z, 99.0))
            lo = np.percentile(pts, 0.5, axis=0)
            hi = np.percentile(pts, 99.5, axis=0)
            centre = 0.5 * (lo + hi)
            r = 0.55 * float((hi - lo).max())  # half the largest extent, padded by 10 %
            r = max(r, 1e-3)
            aabb = tuple(float(x) for x in np.concatenate([centre - r, centre + r]))
            return near, far, aabb
    spread = float(np.linalg.norm(c2w[:, :, 3], axis=1).max())
    return 0.01, 2.0 * np.sqrt(3.0) * half + spread, (-half, -half, -half, half, half, half)


def every_nth_split(names: list[str], holdout: int = 8) -> tuple[list[int], list[int]]:
    """(train, test) positions with test = every ``holdout``-th name in sorted order (LLFF/MipNeRF-360).

    ``names`` need not be sorted; positions refer to the given order.
    """
    order = sorted(range(len(names)), key=lambda i: names[i])
    test = sorted(order[k] for k in range(0, len(order), holdout))
    test_set = set(test)
    return [i for i in range(len(names)) if i not in test_set], test
