"""From frames of a capture (COLMAP or transforms.json) to a :class:`Scene`.

Shared by :mod:`warpnerf.data.colmap` and :mod:`warpnerf.data.transforms_json`: check the poses,
normalise the world (:mod:`warpnerf.data.normalize`), read the images, resample them onto one
pinhole camera (:mod:`warpnerf.data.distortion`), split train/test and derive the bounds.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from warpnerf.data.distortion import Intrinsics, needs_resampling, resample_to_pinhole, shared_pinhole
from warpnerf.data.errors import DatasetError, check_camera_spread, check_intrinsics
from warpnerf.data.images import area_downscale, image_header, load_parallel, read_image
from warpnerf.data.normalize import Normalization, bounds_from_points, capture_normalization, every_nth_split, half_fov
from warpnerf.geometry.rig import classify_rig
from warpnerf.data.scene import Scene, Views, stand_in
from warpnerf.geometry.rayspace import RaySpace, ndc_extent


@dataclass
class Frame:
    """One registered image of a capture."""

    name: str  # name as the source files give it (split lists refer to it)
    path: str  # image file
    c2w: np.ndarray  # (3, 4) float64 OpenGL camera-to-world, capture world frame
    camera: Intrinsics


def check_frames(frames: list[Frame], source: str) -> None:
    """Raise DatasetError naming ``source`` when there is no frame or a pose is not finite."""
    if not frames:
        raise DatasetError(f"{source}: no registered image (the capture has no camera pose)")
    for fr in frames:
        if not np.all(np.isfinite(fr.c2w)):
            raise DatasetError(f"{source}: non-finite pose for image {fr.name}")
        rot = fr.c2w[:, :3]
        if abs(np.linalg.det(rot) - 1.0) > 1e-3 or np.abs(rot.T @ rot - np.eye(3)).max() > 1e-3:
            raise DatasetError(f"{source}: the pose of image {fr.name} is not a rotation (scaled or sheared matrix)")


def resolve_split(names: list[str], lists: dict[str, list[str]] | None, holdout: int, source: str):
    """{split: positions} from named lists (entries matched by full name, then by file name
    without folders, then without extension), else test = every ``holdout``-th image."""
    if not lists or not lists.get("train"):
        train, test = every_nth_split(names, holdout)
        if not train:
            raise DatasetError(f"{source}: no training image left with every {holdout}-th image held out of {len(names)}")
        return {"train": train, "test": test}
    keys = [
        {n: i for i, n in enumerate(names)},
        {os.path.basename(n): i for i, n in enumerate(names)},
        {os.path.splitext(os.path.basename(n))[0]: i for i, n in enumerate(names)},
    ]
    out = {}
    for split, entries in lists.items():
        pos = []
        for e in entries:
            e = str(e).strip()
            if e.startswith("./"):
                e = e[2:]
            hit = next((k[c] for k, c in zip(keys, (e, os.path.basename(e), os.path.splitext(os.path.basename(e))[0])) if c in k), None)
            if hit is None:
                raise DatasetError(f"{source}: {split} list names image '{e}', which is not among the registered images")
            pos.append(hit)
        out[split] = pos
    if not out.get("test"):
        rest = [i for i in range(len(names)) if i not in set(out["train"])]
        out["test"] = rest or out["train"][:1]  # a capture without test views still evaluates on something
    return out


def build_scene(
    frames: list[Frame],
    points: np.ndarray | None,
    root: str,
    kind: str,
    source: str,
    name: str | None = None,
    split_lists: dict[str, list[str]] | None = None,
    holdout: int = 8,
    downscale: int = 1,
    white_background: bool = True,
    aabb_scale: float | None = None,
    normalize: bool = True,
    unbounded: bool | None = None,
    ndc: bool | None = None,
    pixels: bool = True,
) -> Scene:
    """Assemble a Scene (source "dataset") from registered frames.

    Args:
        frames: every registered image (all splits).
        points: (P, 3) sparse points in the capture frame, or None.
        root: scene folder; kind: "colmap" or "transforms"; source: file named in errors.
        split_lists: {"train": [...], "val": [...], "test": [...]} image names, or None for
            every ``holdout``-th image (sorted by name) as test.
        downscale: integer block-average factor after resampling.
        white_background: composite images with alpha on white (else black); also the renderer's
            background.
        aabb_scale: fallback box half-side when there are no points (see normalize).
        normalize: map the world by :func:`~warpnerf.data.normalize.capture_normalization` (an object rig
            without points is centred on the point its cameras look at); False keeps the capture frame
            (the rig is still classified).
        unbounded: a 360° capture with a distant background: a contracted ray space
            (:mod:`warpnerf.geometry.rayspace`) around the normalised cameras, which lie in
            [-1, 1]^3, instead of a box; near from the points/cameras as for a box, far 1000.
            None: chosen from the rig (360° rigs; :func:`~warpnerf.data.normalize.choose_ray_space`).
        ndc: LLFF's NDC ray space (the world mapped as the LLFF loader maps it); None: chosen from the
            rig (forward-facing rigs). Without ``normalize`` the capture frame is kept and the ray space is
            a box, or contracted when ``unbounded`` is True.
        pixels: False: a cameras-only load (:mod:`warpnerf.data.scene`): each image's size is checked against
            its camera from the file header, nothing is decoded or resampled (the cameras are the shared
            pinhole either way), the images and alpha are stand-ins.

    The applied map is returned in ``scene.normalization`` (a :class:`Normalization`, whose ``framing``
    says which framing and ray space the rig got and why).
    """
    check_frames(frames, source)
    for fr in frames:  # COLMAP and transforms.json alike: a zero or NaN focal length is no camera
        k = fr.camera
        check_intrinsics(f"{source} (image {fr.name})", k.width, k.height, k.fx, k.fy, k.cx, k.cy)
    check_camera_spread(source, [fr.c2w[:3, 3] for fr in frames])  # before the normalisation divides by it
    if not isinstance(downscale, int) or downscale < 1:
        raise DatasetError(f"downscale must be a positive integer, got {downscale!r}")
    c2w = np.stack([fr.c2w for fr in frames])
    if normalize:  # the framing depends on the rig and the fields of view (warpnerf.data.normalize)
        fovs = [half_fov(fr.camera.width, fr.camera.height, fr.camera.fx, fr.camera.fy) for fr in frames]
        try:
            norm = capture_normalization(c2w, points, fovs, unbounded, ndc)
        except ValueError as e:  # --unbounded with --ndc
            raise DatasetError(f"{source}: {e}") from None
    else:
        rig = classify_rig(c2w)
        norm = Normalization(np.eye(3), np.zeros(3), 1.0, rig.kind, f"{rig.reason}; capture frame kept",
                             "contracted" if unbounded else "box")
    c2w_n = norm.c2w(c2w)
    pts_n = norm.points(points) if points is not None and len(points) else None

    target = shared_pinhole([fr.camera for fr in frames])
    w0, h0, f0, cx0, cy0 = target
    h, w = h0 // downscale, w0 // downscale
    if h == 0 or w == 0:
        raise DatasetError(f"downscale factor {downscale} is larger than the images ({w0}x{h0})")
    n = len(frames)
    bg = np.asarray((1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0), np.float32)

    def check_size(i: int, path: str, shape) -> None:
        cam = frames[i].camera
        if tuple(shape[:2]) != (cam.height, cam.width):
            raise DatasetError(f"image size mismatch: {path} is {shape[1]}x{shape[0]}, its camera says {cam.width}x{cam.height}")

    def load_one(i: int, path: str) -> None:
        cam = frames[i].camera
        img = read_image(path)
        check_size(i, path, img.shape)
        rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, -1)
        a = img[..., 3] if img.shape[-1] == 4 else np.ones(img.shape[:2], np.float32)
        # Composite first (linear in (rgb a, a), so resampling afterwards gives the same result).
        rgba = np.concatenate([rgb * a[..., None] + bg * (1.0 - a[..., None]), a[..., None]], -1)
        if needs_resampling(cam, target):
            rgba = resample_to_pinhole(rgba, cam, target)
        rgba = area_downscale(rgba, downscale)
        images[i] = rgba[..., :3]
        alpha[i] = rgba[..., 3]

    if pixels:
        images = np.empty((n, h, w, 3), np.float32)
        alpha = np.ones((n, h, w), np.float32)
        load_parallel([fr.path for fr in frames], load_one)
    else:
        load_parallel([fr.path for fr in frames], lambda i, path: check_size(i, path, image_header(path)))

    names = [fr.name for fr in frames]
    splits = resolve_split(names, split_lists, holdout, source)
    near, far, aabb = bounds_from_points(c2w_n[splits["train"]], pts_n, aabb_scale)
    if norm.ray_space == "ndc":  # as the LLFF loader: the box holds every training ray from the near plane at depth 1
        focal = f0 / downscale
        ray_space = RaySpace.ndc(focal, w, h, ndc_near=1.0,
                                 extent=ndc_extent(c2w_n[splits["train"]], focal, w, h, near=1.0))
    elif norm.ray_space == "contracted":
        ray_space = RaySpace.contracted(near)
    else:
        ray_space = RaySpace.euclidean(aabb, near, far)

    def views(sel: list[int]) -> Views:
        sel_t = torch.as_tensor(sel, dtype=torch.long)
        if not pixels:
            return Views(images=stand_in((len(sel), h, w, 3)), c2w=torch.from_numpy(c2w_n[sel].astype(np.float32)),
                         focal=f0 / downscale, cx=cx0 / downscale, cy=cy0 / downscale, ids=list(sel),
                         alpha=stand_in((len(sel), h, w)))
        return Views(
            images=torch.from_numpy(images)[sel_t],
            c2w=torch.from_numpy(c2w_n[sel].astype(np.float32)),
            focal=f0 / downscale,
            cx=cx0 / downscale,
            cy=cy0 / downscale,
            ids=list(sel),
            alpha=torch.from_numpy(alpha)[sel_t],
        )

    scene = Scene(
        name=name or os.path.basename(os.path.normpath(root)),
        source="dataset",
        kind=kind,
        train=views(splits["train"]),
        test=views(splits["test"]),
        val=views(splits["val"]) if splits.get("val") else None,
        ray_space=ray_space,
        background=tuple(float(b) for b in bg),
        root=os.path.abspath(root),
        pixels=pixels,
    )
    scene.normalization = norm  # not a dataclass field: only capture scenes have one
    scene.image_names = names
    return scene
