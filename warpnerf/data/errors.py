"""The one exception type of the data layer."""

import json
import math
import os

import numpy as np


class DatasetError(ValueError):
    """A scene cannot be found, read or generated.

    The message is a single line naming the file, folder or key at fault (and, where it helps,
    what to do), so the CLI can print it as is without a traceback.
    """


def check_c2w(m, where: str, tol: float = 1e-3) -> None:
    """Raise DatasetError unless ``m`` (3x4 or 4x4, any array-like) is a finite camera-to-world
    matrix whose 3x3 block is a proper rotation (orthonormal within ``tol``, det +1).

    A NaN pose is not just one bad view: LLFF recentring spreads it to every pose and the marcher
    then walks an infinite ray, so it has to be stopped here, before anything is written.
    """
    a = np.asarray(m, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{where} has non-finite values (NaN or inf)")
    r = a[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol:
        raise DatasetError(f"{where}: rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {tol})")
    det = float(np.linalg.det(r))
    if det < 0:
        raise DatasetError(f"{where}: rotation is a reflection (det = {det:.3f}, expected +1)")


def check_camera_spread(where: str, centres, rel_tol: float = 1e-6) -> None:
    """Raise DatasetError when two or more cameras all sit at one point (``centres``: (N, 3)).

    Identical poses (a copied matrix) or a rotation-only capture give no parallax: nothing fixes the
    depth of a point, the normalisation has no scale (every layout), and training fits a flat panorama.
    The tolerance is relative to the distance of the cameras from the origin (at least 1 unit)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    if len(c) < 2:
        return
    spread = float(np.abs(c - c.mean(0)).max())
    if spread <= rel_tol * max(1.0, float(np.abs(c).max())):
        at = ", ".join(f"{v:.4g}" for v in c[0])
        raise DatasetError(f"{where}: all {len(c)} camera centres coincide (at {at}): identical or rotation-only "
                           "poses give no parallax; a scene needs views from different places")


def read_json_object(path: str, missing: str = "") -> dict:
    """The JSON object in ``path``; DatasetError naming the file when it is missing, unreadable,
    malformed or not an object (``missing``: what to add to the missing-file message)."""
    if not os.path.isfile(path):
        raise DatasetError(f"missing {path}{missing}")
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"malformed JSON in {path}: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return meta


def check_frames(path: str, frames, empty: str = "") -> None:
    """Check a transforms file's ``frames``: a non-empty list whose entries have ``file_path`` and a
    finite, rotation-valued 4x4 (or 3x4) ``transform_matrix`` (``empty``: added to that message)."""
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: missing or empty key 'frames'{empty}")
    for i, fr in enumerate(frames):
        for key in ("file_path", "transform_matrix"):
            if not isinstance(fr, dict) or key not in fr:
                raise DatasetError(f"{path}: frame {i} has no '{key}'")
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: frame {i} 'transform_matrix' is not a numeric 4x4 matrix") from None
        if m.shape not in ((4, 4), (3, 4)):
            raise DatasetError(f"{path}: frame {i} 'transform_matrix' must be 4x4, got shape {m.shape}")
        check_c2w(m, f"{path}: frame {i} 'transform_matrix'")
    check_camera_spread(path, [np.asarray(fr["transform_matrix"], dtype=np.float64)[:3, 3] for fr in frames])


def json_number(where: str, key: str, value, positive: bool = False, integer: bool = False) -> float:
    """``value`` (read from a JSON file) as a finite float, or DatasetError naming ``where`` and ``key``:
    strings, booleans, lists and null are not numbers (``"wide"`` or ``"abc"`` where a number belongs).
    ``positive``: must be > 0; ``integer``: must be a whole number (an image size)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{where}: key '{key}' must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise DatasetError(f"{where}: key '{key}' must be finite, got {value!r}")
    if positive and not v > 0:
        raise DatasetError(f"{where}: key '{key}' must be positive, got {value!r}")
    if integer and v != int(v):
        raise DatasetError(f"{where}: key '{key}' must be a whole number, got {value!r}")
    return v


def check_intrinsics(where: str, w, h, fx, fy, cx, cy) -> None:
    """Image size and focal lengths positive and finite, principal point finite (every layout)."""
    for key, value in (("width", w), ("height", h), ("focal length fx", fx), ("focal length fy", fy)):
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
            raise DatasetError(f"{where}: {key} must be finite and positive, got {value!r}")
    for key, value in (("cx", cx), ("cy", cy)):
        if not (isinstance(value, (int, float, np.number)) and math.isfinite(value)):
            raise DatasetError(f"{where}: principal point {key} must be finite, got {value!r}")
