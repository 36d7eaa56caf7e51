"""Writers of tiny on-disk scenes for the data tests (a helper module, not a test file)."""

from __future__ import annotations

import json
import os

import numpy as np
from PIL import Image


def blender_matrix(k: int) -> list[list[float]]:
    """A distinct, valid 4x4 camera-to-world matrix for frame ``k``."""
    a = 0.3 * k
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    m[:3, 3] = [4.0 * np.sin(a), 0.5 * k, 4.0 * np.cos(a)]
    return m.tolist()


def write_blender(root, n: int = 2, size: int = 4, splits=("train", "val", "test"), depth: bool = False, angle=0.7):
    """A Blender-layout scene of ``n`` RGBA frames per split; pixel (0, 0) transparent,
    (0, 1) half-transparent red, the rest opaque grey. Returns ``root``."""
    os.makedirs(root, exist_ok=True)
    for split in splits:
        os.makedirs(os.path.join(root, split), exist_ok=True)
        frames = []
        for k in range(n):
            img = np.full((size, size, 4), 128, np.uint8)
            img[..., 3] = 255
            img[0, 0] = [10, 20, 30, 0]
            img[0, 1] = [255, 0, 0, 128]
            Image.fromarray(img, "RGBA").save(os.path.join(root, split, f"r_{k}.png"))
            frame = {"file_path": f"./{split}/r_{k}", "rotation": 0.0, "transform_matrix": blender_matrix(k)}
            if depth:
                np.save(os.path.join(root, split, f"r_{k}_depth.npy"), np.full((size, size), 3.0 + k, np.float32))
                frame["depth_path"] = f"./{split}/r_{k}_depth.npy"
            frames.append(frame)
        with open(os.path.join(root, f"transforms_{split}.json"), "w") as f:
            json.dump({"camera_angle_x": angle, "frames": frames}, f)
    return str(root)


def write_llff(root, gl_rot: np.ndarray, centres: np.ndarray, bounds: np.ndarray, hwf=(24, 32, 40.0), factor=4):
    """An LLFF scene whose OpenGL camera rotations are ``gl_rot`` (N, 3, 3), centres (N, 3) and
    bounds (N, 2); images of hwf / factor pixels in ``images_<factor>``. Returns ``root``."""
    n = len(gl_rot)
    # OpenGL [right, up, back] -> LLFF [down, right, back] = [-up, right, back].
    llff_rot = np.stack([-gl_rot[:, :, 1], gl_rot[:, :, 0], gl_rot[:, :, 2]], axis=2)
    hwf_col = np.tile(np.asarray(hwf, np.float64)[None, :, None], (n, 1, 1))
    poses = np.concatenate([llff_rot, centres[:, :, None], hwf_col], axis=2)  # (N, 3, 5)
    os.makedirs(os.path.join(root, f"images_{factor}"), exist_ok=True)
    np.save(os.path.join(root, "poses_bounds.npy"), np.concatenate([poses.reshape(n, 15), bounds], 1))
    h, w = int(hwf[0]) // factor, int(hwf[1]) // factor
    for k in range(n):
        img = np.full((h, w, 3), 10 * k, np.uint8)
        Image.fromarray(img, "RGB").save(os.path.join(root, f"images_{factor}", f"IMG_{k:03d}.png"))
    return str(root)


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3, 3) proper rotations from QR of Gaussian matrices."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q
