"""Loader for forward-facing LLFF scenes (``poses_bounds.npy`` + ``images_<factor>/``).

``poses_bounds.npy`` is (N, 17) float: per image a 3x5 matrix flattened row-major, then the
near/far depth bounds of its content. The 3x5 matrix is [R | t | hwf]: rotation columns in
LLFF order [down, right, back], the camera centre t, and (height, width, focal) in pixels of
the full-resolution image. Processing follows the original NeRF code:

1. rotation columns -> OpenGL [right, up, back] = [c1, -c0, c2];
2. intrinsics rescaled to the images actually read (``images_8`` = 1/8 of full resolution);
3. scale the world so that the nearest bound becomes 1 / bd_factor (bd_factor 0.75: content
   starts at depth 1.33, safely behind the NDC near plane at 1.0);
4. recenter: express every pose in the frame of the "average pose" (mean centre, summed back
   and up axes), so the cameras look down -z around the origin;
5. test views (``test``): every ``holdout``-th image (i % holdout == 0, NeRF's "llffhold"), or the
   last 10 % by file name (BARF's and GARF's LLFF protocol: fern's images 18 and 19).

The scene's ray space is LLFF's NDC (:meth:`RaySpace.ndc <warpnerf.geometry.rayspace.RaySpace.ndc>`,
formula in :mod:`warpnerf.geometry.rayspace`, docs/design.md §6): world rays of the recentred scene are
projected by the views' pinhole camera at the origin; the box holds every training ray from the
near plane to infinity (:func:`~warpnerf.geometry.rayspace.ndc_extent`: x', y' slightly beyond
[-1, 1], z' in [-1, 1]), and uniform steps are uniform in inverse depth, which suits
forward-facing scenes with a far background.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from warpnerf.data.errors import DatasetError, check_c2w, check_camera_spread
from warpnerf.data.images import (IMAGE_SUFFIXES, area_downscale, downscaled_size, image_headers, load_parallel,
                                  read_image)
from warpnerf.data.scene import Scene, Views, stand_in
from warpnerf.geometry.rayspace import RaySpace, ndc_extent

LLFF_BD_FACTOR = 0.75
# which images are test views (load_llff's ``test``; config key llff_test)
LLFF_TESTS = ("every8", "last10")


def load_llff(
    root: str,
    factor: int = 8,
    holdout: int = 8,
    downscale: int = 1,
    bd_factor: float = LLFF_BD_FACTOR,
    recenter: bool = True,
    name: str | None = None,
    test: str = "every8",
    pixels: bool = True,
) -> Scene:
    """Load an LLFF scene folder into a :class:`Scene` (source "dataset", kind "llff", NDC ray space).

    Args:
        root: folder holding ``poses_bounds.npy`` and ``images_<factor>/`` (``images/`` for factor 1).
        factor: which pre-downsampled image folder to read (LLFF convention; fern ships ``images_8``).
        holdout: every ``holdout``-th image (ids 0, holdout, 2 holdout, ...) is a test view.
        downscale: extra integer block-average downscale applied after reading.
        bd_factor: the nearest bound is mapped to depth 1 / bd_factor.
        recenter: express poses relative to the average pose (required for NDC to make sense;
            False only for inspecting the raw converted poses).
        name: scene name (default: the folder name).
        test: "every8": every ``holdout``-th image is a test view (ids 0, holdout, ...; NeRF);
            "last10": the last ``int(0.1 * N)`` images (at least one) by file name (BARF, GARF).
        pixels: False: a cameras-only load (:mod:`warpnerf.data.scene`): image sizes from the file headers
            (the same checks), no pixel decoded, stand-ins for the images and alpha.

    Returns a scene whose ``train``/``test`` views hold (N, H, W, 3) images, OpenGL c2w, and
    ``val`` None, and an NDC ray space for the views' intrinsics (box around the training rays; module doc).

    Raises:
        DatasetError: missing folder/file, wrong array shape, image count or size that does
            not match the poses.
    """
    if not os.path.isdir(root):
        raise DatasetError(f"scene folder not found: {root}")
    if holdout < 1 or factor < 1 or downscale < 1:
        raise DatasetError(f"factor, holdout and downscale must be >= 1, got {factor}, {holdout}, {downscale}")
    if test not in LLFF_TESTS:
        raise DatasetError(f"test must be one of {', '.join(LLFF_TESTS)}, got {test!r}")
    pb_path = os.path.join(root, "poses_bounds.npy")
    try:
        pb = np.load(pb_path)
    except FileNotFoundError:
        raise DatasetError(f"missing {pb_path}") from None
    except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty (0-byte) file
        raise DatasetError(f"cannot read {pb_path}: {exc or 'empty file'}") from None
    if pb.ndim != 2 or pb.shape[1] != 17 or len(pb) == 0:
        raise DatasetError(f"{pb_path}: expected an (N, 17) array, got shape {pb.shape}")
    pb = pb.astype(np.float64)
    poses = pb[:, :15].reshape(-1, 3, 5)
    bounds = pb[:, 15:17]
    hwf = poses[0, :, 4]
    # before recentring: one NaN would spread to every pose and the marcher would never stop
    for i in range(len(poses)):
        check_c2w(poses[i, :, :4], f"{pb_path}: pose {i}")
    check_camera_spread(pb_path, poses[:, :, 3])
    if not np.all(np.isfinite(bounds)) or not np.all(bounds > 0):
        bad = int(np.nonzero(~(np.isfinite(bounds) & (bounds > 0)).all(1))[0][0])
        raise DatasetError(f"{pb_path}: bounds of pose {bad} must be finite and positive, got {bounds[bad].tolist()}")
    if not np.all(np.isfinite(hwf)) or not np.all(hwf > 0):
        raise DatasetError(f"{pb_path}: height, width, focal of pose 0 must be positive, got {hwf.tolist()}")

    paths = _image_paths(root, factor, len(poses))
    if pixels:
        first = read_image(paths[0])
        h_img, w_img = first.shape[:2]
    else:
        heads = image_headers(paths)
        h_img, w_img = heads[0][:2]
    if abs(h_img - hwf[0] / factor) > 1.0 or abs(w_img - hwf[1] / factor) > 1.0:
        raise DatasetError(
            f"{paths[0]} is {w_img}x{h_img} but poses_bounds.npy says {hwf[1]:.0f}x{hwf[0]:.0f} / {factor} "
            f"= {hwf[1] / factor:.0f}x{hwf[0] / factor:.0f}"
        )
    h, w = h_img // downscale, w_img // downscale

    def check_size(path: str, shape) -> None:
        if tuple(shape[:2]) != (h_img, w_img):
            raise DatasetError(
                f"image size mismatch: {path} is {shape[1]}x{shape[0]}, expected {w_img}x{h_img} like {paths[0]}"
            )

    if pixels:
        images = np.empty((len(paths), h, w, 3), np.float32)

        def load_one(i: int, path: str) -> None:
            img = first if i == 0 else read_image(path)
            check_size(path, img.shape)
            rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, -1)
            images[i] = area_downscale(rgb, downscale)

        load_parallel(paths, load_one)
    else:
        for path, shape in zip(paths, heads):
            check_size(path, shape)
        h, w = downscaled_size(h_img, w_img, downscale)

    c2w = llff_to_opengl(poses[:, :, :4])
    scale = 1.0 / (bounds.min() * bd_factor)
    c2w[:, :, 3] *= scale
    if recenter:
        c2w = recenter_poses(c2w)
    # Scale focal by the actual width: folders made by percentage resizes may round the size.
    focal = hwf[2] * (w_img / hwf[1]) / downscale

    ids = np.arange(len(paths))
    if test == "last10":  # _image_paths sorts by name, as BARF's loader does
        is_test = ids >= len(ids) - max(int(0.1 * len(ids)), 1)
    else:
        is_test = ids % holdout == 0
    test_ids, train_ids = ids[is_test], ids[~is_test]
    if len(train_ids) == 0:
        raise DatasetError(f"{root}: no training views left with holdout {holdout} and {len(ids)} images")

    def views(sel: np.ndarray) -> Views:
        return Views(
            images=torch.from_numpy(images[sel]) if pixels else stand_in((len(sel), h, w, 3)),
            c2w=torch.from_numpy(c2w[sel].astype(np.float32)),
            focal=float(focal),
            cx=w / 2.0,
            cy=h / 2.0,
            ids=[int(i) for i in sel],
            # photos are opaque everywhere: with random training backgrounds (the default) the
            # targets stay as they are and transmittance left at a ray's end is penalised, so the
            # field becomes opaque instead of rendering dark regions as see-through (instant-ngp;
            # the capture loader does the same). fern full: +0.8 dB test PSNR (docs/studies/2026-12-07-forward-facing-preset.md)
            alpha=torch.ones(len(sel), h, w) if pixels else stand_in((len(sel), h, w)),
        )

    return Scene(
        name=name or os.path.basename(os.path.normpath(root)),
        source="dataset",
        kind="llff",
        train=views(train_ids),
        test=views(test_ids),
        val=None,
        # the NDC near plane at world depth 1: content starts at 1 / bd_factor behind it
        ray_space=RaySpace.ndc(focal, w, h, ndc_near=1.0,
                               extent=ndc_extent(c2w[train_ids], focal, w, h, near=1.0)),
        # Real photos have no background: whatever transmittance is left at infinity is black
        # when rendering (the original NeRF LLFF setup); training with random backgrounds
        # leaves little of it.
        background=(0.0, 0.0, 0.0),
        root=os.path.abspath(root),
        pixels=pixels,
    )


def _image_paths(root: str, factor: int, n_poses: int) -> list[str]:
    folder = os.path.join(root, "images" if factor == 1 else f"images_{factor}")
    if not os.path.isdir(folder):
        found = sorted(d for d in os.listdir(root) if d.startswith("images") and os.path.isdir(os.path.join(root, d)))
        hint = f"; found {', '.join(found)}: pick the factor to match" if found else ""
        raise DatasetError(f"missing image folder {folder}{hint}")
    names = sorted(f for f in os.listdir(folder) if os.path.splitext(f)[1].lower() in IMAGE_SUFFIXES)
    if len(names) != n_poses:
        raise DatasetError(f"{folder} holds {len(names)} images but poses_bounds.npy has {n_poses} poses")
    return [os.path.join(folder, f) for f in names]


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """(N, 3, 4) LLFF [down, right, back | t] -> OpenGL [right, up, back | t] = [c1, -c0, c2 | t]."""
    poses = np.asarray(poses, np.float64)
    return np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:4]], axis=2)


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """(3, 4) "average" camera of (N, 3, 4) OpenGL poses: mean centre, back = normalised sum of
    back axes, right/up made orthonormal from the summed up axes."""
    centre = c2w[:, :, 3].mean(0)
    back = _unit(c2w[:, :, 2].sum(0))
    right = _unit(np.cross(c2w[:, :, 1].sum(0), back))
    up = _unit(np.cross(back, right))
    return np.stack([right, up, back, centre], axis=1)


def recenter_poses(c2w: np.ndarray) -> np.ndarray:
    """(N, 3, 4) poses expressed in the frame of their :func:`average_pose`."""
    avg = np.eye(4)
    avg[:3] = average_pose(c2w)
    full = np.concatenate([c2w, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(c2w), 1, 1))], axis=1)
    return (np.linalg.inv(avg) @ full)[:, :3]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)

