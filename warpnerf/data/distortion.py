"""Camera intrinsics with lens distortion, and resampling images to one shared pinhole camera.

The renderer knows one pinhole camera per split (``Views.focal``, ``cx``, ``cy``, square
pixels). Captures bring per-image cameras with distortion, so the loaders resample every image
once, at load time, onto a shared undistorted pinhole camera; the renderer stays untouched.

Distortion model (OpenCV / COLMAP ``OPENCV``; ``SIMPLE_RADIAL`` and ``RADIAL`` are the special
cases p1 = p2 = 0 and k2 = 0): for normalised image coordinates (x, y) = ((u - cx) / fx,
(v - cy) / fy) of an ideal pinhole, r^2 = x^2 + y^2,

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p2 x y + p1 (r^2 + 2 y^2)

and the observed pixel is (fx x_d + cx, fy y_d + cy). Pixel centres are at (i + 0.5, j + 0.5),
as in COLMAP and the rest of warpnerf.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """One camera: size in pixels, focal lengths and principal point in pixels, distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def distorted(self) -> bool:
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.p1, self.p2))

    def pinhole(self) -> "Intrinsics":
        """The same camera without distortion."""
        return replace(self, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0)

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel sizes multiply by 1 / factor)."""
        return replace(self, width=int(round(self.width * factor)), height=int(round(self.height * factor)),
                       fx=self.fx * factor, fy=self.fy * factor, cx=self.cx * factor, cy=self.cy * factor)


def distort(x: np.ndarray, y: np.ndarray, cam: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised coordinates -> distorted normalised coordinates (module docstring)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    xy = x * y
    xd = x * radial + 2.0 * cam.p1 * xy + cam.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + 2.0 * cam.p2 * xy + cam.p1 * (r2 + 2.0 * y * y)
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, cam: Intrinsics, iters: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates -> ideal ones, by Newton's method on :func:`distort`.

    Converges to ~1e-12 within a few iterations for the distortions cameras have (|k| < 1 over the
    image); float64 throughout.
    """
    xd = np.asarray(xd, np.float64)
    yd = np.asarray(yd, np.float64)
    x, y = xd.copy(), yd.copy()
    k1, k2, k3, p1, p2 = cam.k1, cam.k2, cam.k3, cam.p1, cam.p2
    for _ in range(iters):
        fx_, fy_ = distort(x, y, cam)
        ex, ey = fx_ - xd, fy_ - yd
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        # Jacobian of (x_d, y_d) w.r.t. (x, y)
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = 2.0 * x * y * dradial + 2.0 * p2 * y + 2.0 * p1 * x
        j22 = radial + 2.0 * y * y * dradial + 2.0 * p2 * x + 6.0 * p1 * y
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        dx = (j22 * ex - j12 * ey) / det
        dy = (-j21 * ex + j11 * ey) / det
        x, y = x - dx, y - dy
        if max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) < 1e-14:
            break
    return x, y


def distort_pixels(u: np.ndarray, v: np.ndarray, cam: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the ideal pinhole ``cam.pinhole()`` -> where ``cam`` (with distortion) sees them."""
    xd, yd = distort((np.asarray(u, np.float64) - cam.cx) / cam.fx, (np.asarray(v, np.float64) - cam.cy) / cam.fy, cam)
    return xd * cam.fx + cam.cx, yd * cam.fy + cam.cy


def undistort_pixels(u: np.ndarray, v: np.ndarray, cam: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Observed (distorted) pixels of ``cam`` -> pixels of the ideal pinhole ``cam.pinhole()``."""
    x, y = undistort((np.asarray(u, np.float64) - cam.cx) / cam.fx, (np.asarray(v, np.float64) - cam.cy) / cam.fy, cam)
    return x * cam.fx + cam.cx, y * cam.fy + cam.cy


def shared_pinhole(cams: list[Intrinsics]) -> tuple[int, int, float, float, float]:
    """(width, height, focal, cx, cy) of the undistorted square-pixel camera every view is resampled to.

    The first camera's size and principal point, focal = its fx (fy is matched by resampling).
    """
    c = cams[0]
    return c.width, c.height, float(c.fx), float(c.cx), float(c.cy)


def needs_resampling(cam: Intrinsics, target: tuple[int, int, float, float, float]) -> bool:
    w, h, f, cx, cy = target
    return cam.distorted or (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) != (w, h, f, f, cx, cy)


def resample_to_pinhole(img: np.ndarray, cam: Intrinsics, target: tuple[int, int, float, float, float]) -> np.ndarray:
    """Resample an (H, W, C) image taken by ``cam`` onto the pinhole camera ``target``.

    ``target`` = (width, height, focal, cx, cy), square pixels, same camera centre and
    orientation. Each target pixel centre is mapped through ``cam``'s distortion to a source
    position and sampled bilinearly; positions outside the source are clamped to its border.
    Returns (height, width, C) float32.
    """
    w, h, f, cx, cy = target
    v, u = np.meshgrid(np.arange(h, dtype=np.float64) + 0.5, np.arange(w, dtype=np.float64) + 0.5, indexing="ij")
    xd, yd = distort((u - cx) / f, (v - cy) / f, cam)
    su = xd * cam.fx + cam.cx - 0.5  # continuous index space: pixel i has its centre at i
    sv = yd * cam.fy + cam.cy - 0.5
    return bilinear(img, su, sv)


def bilinear(img: np.ndarray, su: np.ndarray, sv: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) ``img`` at continuous index positions (column ``su``, row ``sv``), clamped."""
    h0, w0 = img.shape[:2]
    su = np.clip(su, 0.0, w0 - 1.0)
    sv = np.clip(sv, 0.0, h0 - 1.0)
    i0 = np.minimum(np.floor(su).astype(np.int64), w0 - 2) if w0 > 1 else np.zeros(su.shape, np.int64)
    j0 = np.minimum(np.floor(sv).astype(np.int64), h0 - 2) if h0 > 1 else np.zeros(sv.shape, np.int64)
    a = (su - i0)[..., None].astype(np.float32)
    b = (sv - j0)[..., None].astype(np.float32)
    i1 = np.minimum(i0 + 1, w0 - 1)
    j1 = np.minimum(j0 + 1, h0 - 1)
    top = img[j0, i0] * (1 - a) + img[j0, i1] * a
    bottom = img[j1, i0] * (1 - a) + img[j1, i1] * a
    return (top * (1 - b) + bottom * b).astype(np.float32)
