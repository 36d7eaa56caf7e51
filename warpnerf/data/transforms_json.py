"""The single ``transforms.json`` layout of nerfstudio (``ns-process-data``) and instant-ngp (``colmap2nerf.py``).

::

    {"camera_model": "OPENCV",                      # optional; OPENCV (default) or PINHOLE
     "fl_x": 1200.0, "fl_y": 1198.5,                # pixels (or "camera_angle_x", radians)
     "cx": 640.0, "cy": 360.0, "w": 1280, "h": 720, # principal point default: the image centre
     "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0,   # OpenCV distortion, optional
     "aabb_scale": 4,                               # optional: box half-side when nothing else bounds the scene
     "train_filenames": [...], "val_filenames": [...], "test_filenames": [...],   # optional split
     "frames": [{"file_path": "images/frame_00001.jpg",
                 "transform_matrix": [[...4...] x 4],   # camera-to-world, OpenGL axes
                 "fl_x": ..., "k1": ...}, ...]}         # any intrinsic may be given per frame

Per-frame intrinsics override the top-level ones. Images are resampled to one shared pinhole
camera (:mod:`warpnerf.data.distortion`), the world is normalised as documented in
:mod:`warpnerf.data.normalize` (there are no points, so an object rig is centred on the point its
cameras look at: :func:`warpnerf.data.capture.build_scene`), and without split lists every 8th image
(sorted by path) is a test view. The folder must not also hold ``transforms_train.json`` (that is the Blender layout).
"""

from __future__ import annotations

import math
import os

import numpy as np

from warpnerf.data.capture import Frame, build_scene
from warpnerf.data.distortion import Intrinsics
from warpnerf.data.errors import DatasetError, check_frames, json_number, read_json_object
from warpnerf.data.images import IMAGE_SUFFIXES, image_header
from warpnerf.data.scene import Scene

TRANSFORMS_FILE = "transforms.json"
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "camera_angle_x", "camera_angle_y")
SUPPORTED_CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def read_transforms_json(path: str) -> dict:
    """Parse and check ``transforms.json``; DatasetError naming the file and key at fault."""
    meta = read_json_object(path)
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if model not in SUPPORTED_CAMERA_MODELS:
        raise DatasetError(f"{path}: camera_model {model} is not supported (supported: {', '.join(SUPPORTED_CAMERA_MODELS)})")
    check_frames(path, meta.get("frames"), " (no registered image)")
    return meta


def frame_intrinsics(meta: dict, fr: dict, image_path: str, source: str) -> Intrinsics:
    """Intrinsics of one frame: its own keys over the top-level ones; size from the image's header if absent."""
    def where(k: str) -> str:
        return f"{source} (frame {fr['file_path']})" if k in fr else source

    def get(k: str, **kw):
        value = fr.get(k, meta.get(k))
        return None if value is None else json_number(where(k), k, value, **kw)

    w, h = get("w", positive=True, integer=True), get("h", positive=True, integer=True)
    if w is None or h is None:
        h, w = image_header(image_path)[:2]
    w, h = int(w), int(h)
    if get("k4"):
        raise DatasetError(f"{source}: frame {fr['file_path']} has k4 (fisheye distortion), which is not supported")
    fx, fy = get("fl_x", positive=True), get("fl_y", positive=True)
    if fx is None:
        ax = get("camera_angle_x")
        if ax is None:
            raise DatasetError(f"{source}: no focal length for frame {fr['file_path']} (need 'fl_x' or 'camera_angle_x')")
        if not 0.0 < ax < math.pi:
            raise DatasetError(f"{where('camera_angle_x')}: key 'camera_angle_x' must be in (0, pi) radians, got {ax}")
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None:
        ay = get("camera_angle_y")
        if ay is not None and not 0.0 < ay < math.pi:
            raise DatasetError(f"{where('camera_angle_y')}: key 'camera_angle_y' must be in (0, pi) radians, got {ay}")
        fy = 0.5 * h / math.tan(0.5 * ay) if ay is not None else fx
    cx, cy = get("cx"), get("cy")
    return Intrinsics(w, h, float(fx), float(fy), float(cx if cx is not None else w / 2),
                      float(cy if cy is not None else h / 2),
                      k1=get("k1") or 0.0, k2=get("k2") or 0.0, k3=get("k3") or 0.0,
                      p1=get("p1") or 0.0, p2=get("p2") or 0.0)


def _image_path(root: str, file_path: str) -> str:
    p = os.path.normpath(os.path.join(root, file_path))
    if os.path.splitext(p)[1].lower() in IMAGE_SUFFIXES:
        return p
    return p + ".png"  # Blender/instant-ngp style paths without a suffix


def read_transforms_poses(root: str) -> np.ndarray:
    """(N, 3, 4) OpenGL camera-to-world of the frames of ``root/transforms.json``, read from the file alone
    (:func:`warpnerf.data.resolve.capture_rig`); DatasetError for a malformed file or pose."""
    path = os.path.join(root, TRANSFORMS_FILE)
    meta = read_transforms_json(path)  # checks every frame's matrix
    return np.stack([np.asarray(fr["transform_matrix"], np.float64)[:3, :4] for fr in meta["frames"]])


def load_transforms_json(
    root: str,
    downscale: int = 1,
    holdout: int = 8,
    white_background: bool = True,
    normalize: bool = True,
    name: str | None = None,
    unbounded: bool | None = None,
    ndc: bool | None = None,
    pixels: bool = True,
) -> Scene:
    """Load a single-``transforms.json`` scene folder (module docstring) into a Scene (kind "transforms").

    Args: as :func:`warpnerf.data.colmap.load_colmap`.

    Raises:
        DatasetError naming the file: missing/malformed JSON, unsupported camera model, missing
            image, non-finite pose, no frame.
    """
    if not os.path.isdir(root):
        raise DatasetError(f"scene folder not found: {root}")
    path = os.path.join(root, TRANSFORMS_FILE)
    meta = read_transforms_json(path)
    frames = []
    for fr in meta["frames"]:
        img_path = _image_path(root, str(fr["file_path"]))
        if not os.path.isfile(img_path):
            raise DatasetError(f"missing image {img_path} (listed in {path})")
        m = np.asarray(fr["transform_matrix"], np.float64)[:3, :4]
        if not np.all(np.isfinite(m)):
            raise DatasetError(f"{path}: non-finite pose for image {fr['file_path']}")
        name_ = str(fr["file_path"])
        frames.append(Frame(name_[2:] if name_.startswith("./") else name_, img_path, m, frame_intrinsics(meta, fr, img_path, path)))
    lists = None
    if meta.get("train_filenames"):
        lists = {s: list(meta.get(f"{s}_filenames") or []) for s in ("train", "val", "test")}
        lists = {k: v for k, v in lists.items() if v}
    aabb_scale = meta.get("aabb_scale")
    if aabb_scale not in (None, 0):  # 0: unset, as before
        aabb_scale = json_number(path, "aabb_scale", aabb_scale, positive=True)
    return build_scene(frames, None, root, "transforms", path, name=name, split_lists=lists, holdout=holdout,
                       downscale=downscale, white_background=white_background,
                       aabb_scale=float(aabb_scale) if aabb_scale else None, normalize=normalize,
                       unbounded=unbounded, ndc=ndc, pixels=pixels)
