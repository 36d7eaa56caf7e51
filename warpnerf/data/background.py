"""Backgrounds of images without alpha: a uniform border colour is a background, not geometry (numpy; no torch).

A product shot on white, or a rendered scene saved as RGB, has no alpha channel, so a loader has to take
every pixel as opaque: the field must then paint the white surround with density inside the box, the
occupancy grid cannot prune it, and the object is lost in a haze (lego written as a COLMAP model of RGB
photos on white trained to 16 dB). instant-ngp and nerfstudio train such captures against the background
colour instead. :func:`detect_background` finds one:

* in each view, the border ring (the outermost :func:`ring_width` pixels) is taken; its colour is the
  per-channel median, and the view has a uniform border when at least :data:`BORDER_SHARE` of the ring's
  pixels lie within :data:`BORDER_TOL` (largest channel difference) of it;
* the scene has a background when at least :data:`VIEW_SHARE` of its views have a uniform border of one
  colour (each within :data:`BORDER_TOL` of one of them).

Why these numbers (measured on the reference data): NeRF-synthetic's lego composited on white has every
pixel of the border ring exactly 1.0 in 96 of its 100 training views and >= 95 % in all 100 (the model
reaches the border in the others); mic passes in 96 of 100. :data:`BORDER_TOL` = 0.04 (10/255) leaves room for
JPEG noise and a little shading on a studio sweep. A photograph's border holds no such colour: in LLFF's fern
at most 10 % of a view's ring lies within 0.04 of its median colour (median 7 %).

:func:`settle_background` applies the choice of ``background`` (:data:`BACKGROUNDS`, the ``--background``
flag) to a loaded scene (module-level doc of each mode there). What it decided depends on the pixels (the
border colours, and whether the alpha is 1 everywhere), so a run folder stores it (:class:`SettledBackground`,
the checkpoint's ``scene_background``) and a cameras-only load, which has no pixel, applies the stored one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

BORDER_SHARE = 0.95
BORDER_TOL = 0.04
VIEW_SHARE = 0.8
BACKGROUNDS = ("auto", "white", "black", "learned", "random")
FIXED = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
LEARNED_START = (0.5, 0.5, 0.5)  # a learned background with nothing detected starts at mid-grey


@dataclass(frozen=True)
class Detection:
    """What :func:`detect_background` found."""

    colour: Optional[tuple[float, float, float]]  # None: no uniform background
    views: int  # views looked at
    agreeing: int  # views whose border is uniform and of ``colour`` (of the most common colour when None)
    reason: str  # one line for a person


def ring_width(height: int, width: int) -> int:
    """Pixels of the border ring of an image: 2 % of its shorter side, at least 1 (400 x 400: 8)."""
    return max(1, min(height, width) // 50)


def border_pixels(image: np.ndarray) -> np.ndarray:
    """(K, C) pixels of the border ring (:func:`ring_width`) of an (H, W, C) image."""
    h, w = image.shape[:2]
    r = ring_width(h, w)
    if 2 * r >= min(h, w):
        return image.reshape(-1, image.shape[-1])
    return np.concatenate([image[:r].reshape(-1, image.shape[-1]), image[-r:].reshape(-1, image.shape[-1]),
                           image[r:-r, :r].reshape(-1, image.shape[-1]), image[r:-r, -r:].reshape(-1, image.shape[-1])])


def uniform_border(image: np.ndarray, tol: float = BORDER_TOL, share: float = BORDER_SHARE):
    """(colour, share of the ring within ``tol`` of it) of an (H, W, 3) float image in [0, 1]; colour is
    None when that share is below ``share``."""
    ring = np.asarray(border_pixels(np.asarray(image)[..., :3]), np.float64)
    colour = np.median(ring, axis=0)
    close = float((np.abs(ring - colour).max(axis=1) <= tol).mean())
    return (tuple(float(c) for c in colour) if close >= share else None), close


def colour_name(colour) -> str:
    """"white", "black" or "rgb(r, g, b)" (two decimals) of a colour in [0, 1]."""
    if min(colour) >= 1.0 - BORDER_TOL:
        return "white"
    if max(colour) <= BORDER_TOL:
        return "black"
    return "rgb(" + ", ".join(f"{c:.2f}" for c in colour) + ")"


def detect_background(images: Iterable[np.ndarray], tol: float = BORDER_TOL, share: float = BORDER_SHARE,
                      view_share: float = VIEW_SHARE) -> Detection:
    """The uniform background colour of views (each an (H, W, 3) float array in [0, 1]), as the module
    docstring says (the views that agree: the largest group within ``tol`` of one view's colour; the
    colour: their mean), or a :class:`Detection` with colour None and the reason."""
    colours, shares, n = [], [], 0
    for image in images:
        n += 1
        colour, close = uniform_border(image, tol, share)
        shares.append(close)
        if colour is not None:
            colours.append(colour)
    if n == 0:
        return Detection(None, 0, 0, "no image")
    agree = []
    if colours:  # the largest group of views whose colours lie within tol of one of them
        c = np.asarray(colours)
        near = np.abs(c[:, None, :] - c[None, :, :]).max(-1) <= tol
        agree = [colours[j] for j in np.nonzero(near[int(near.sum(1).argmax())])[0]]
    need = view_share * n
    if len(agree) < need:
        return Detection(None, n, len(agree),
                         f"none: {len(agree)} of {n} views share one uniform border colour (need {math.ceil(need)}; "
                         f"{len(colours)} have a uniform border); median share of a border ring within {tol:g} of "
                         f"its colour: {100 * float(np.median(shares)):.0f} %")
    colour = tuple(float(c) for c in np.asarray(agree).mean(0))
    return Detection(colour, n, len(agree),
                     f"{colour_name(colour)}: the border of {len(agree)} of {n} views is uniform (>= {100 * share:.0f} % "
                     f"of its pixels within {tol:g} of one colour)")


def _views(scene):
    return [v for v in (scene.train, scene.val, scene.test) if v is not None]


def is_opaque(scene) -> bool:
    """True when no view of ``scene`` carries transparency: no alpha, or alpha 1 everywhere (RGB images)."""
    return all(v.alpha is None or bool((v.alpha >= 1.0).all()) for v in _views(scene))


def settle_background(scene, mode: Optional[str] = None):
    """Apply background ``mode`` (:data:`BACKGROUNDS`; None = "auto") to a loaded scene, in place; returns it
    with ``background_note`` set (one line for the run to print, "" when there is nothing to say).

    Images with transparency were composited by their loader on white, or on black for "black"; for them
    "auto" and "random" change nothing (random training backgrounds where alpha is known). Opaque images
    (no alpha channel; LLFF and captured photos):

    * "auto": a uniform border colour (:func:`detect_background`) becomes the scene's fixed background and
      the views' alpha is dropped, so training composites the field on that colour instead of asking it to
      be opaque; without one the images stay opaque photos, as before;
    * "white" / "black": that colour is the fixed background;
    * "learned": the colour is learned with the field (:class:`~warpnerf.train.trainer.Trainer`), starting
      from the detected one, else :data:`LEARNED_START`; images with alpha too lose their random backgrounds;
    * "random": opaque photos, no detection (what "auto" did before detection existed).
    """
    mode = mode or "auto"
    if mode not in BACKGROUNDS:
        raise ValueError(f"unknown background '{mode}': expected one of {', '.join(BACKGROUNDS)}")
    opaque = is_opaque(scene)
    if mode == "random" or (mode == "auto" and not opaque):
        scene.background_note = "" if mode == "auto" else (
            "random while training where the images' alpha is known" + ("; none here: photos trained as opaque"
                                                                        if opaque else ""))
        return scene
    detection = None
    if mode in ("auto", "learned") and opaque:
        detection = detect_background(v.images[i].numpy() for v in _views(scene) for i in range(len(v)))
    if mode == "auto" and detection.colour is None:
        scene.background_note = f"{detection.reason}; the images are trained as opaque photos"
        return scene
    if mode in FIXED:
        colour = FIXED[mode]
        note = f"{mode} (--background {mode}), " + ("fixed" if opaque else "the images' alpha composited on it")
    elif mode == "learned":
        colour = detection.colour if detection is not None and detection.colour is not None else LEARNED_START
        note = f"learned with the field, starting from {colour_name(colour)}"
    else:
        colour, note = detection.colour, f"{detection.reason}; trained as a fixed background, not as geometry"
    scene.background = tuple(float(c) for c in colour)
    if opaque or mode == "learned":
        for v in _views(scene):
            v.alpha = None  # the trainer composites on scene.background instead of a random colour
    scene.background_note = note
    return scene


@dataclass(frozen=True)
class SettledBackground:
    """What :func:`settle_background` decided for a scene: the run folder keeps it (the checkpoint's and
    metrics.json's ``scene_background``, :meth:`to_dict`) so that a cameras-only load
    (``load_scene(..., pixels=False)``), which has no pixel to detect a background in, gets the background
    the run trained with (:meth:`apply`)."""

    mode: str  # the --background mode it was settled with (:data:`BACKGROUNDS`; "auto" for unset)
    colour: tuple[float, float, float]  # scene.background
    alpha: bool  # whether the views kept their alpha (False: dropped, training composites on ``colour``)
    note: str  # scene.background_note

    @classmethod
    def of(cls, scene, mode: Optional[str] = None) -> "SettledBackground":
        """The decision :func:`settle_background` (with ``mode``) made for the loaded ``scene``."""
        return cls(mode or "auto", tuple(float(c) for c in scene.background),
                   all(v.alpha is not None for v in _views(scene)), str(scene.background_note))

    def to_dict(self) -> dict:
        return {"mode": self.mode, "colour": list(self.colour), "alpha": self.alpha, "note": self.note}

    @classmethod
    def from_dict(cls, value) -> Optional["SettledBackground"]:
        """The record :meth:`to_dict` wrote, or None when ``value`` is not one (a run from before runs kept it,
        or a damaged file)."""
        if not isinstance(value, dict):
            return None
        mode, colour, alpha, note = (value.get(k) for k in ("mode", "colour", "alpha", "note"))
        if (mode not in BACKGROUNDS or not isinstance(alpha, bool) or not isinstance(note, str)
                or not isinstance(colour, (list, tuple)) or len(colour) != 3
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0.0 <= c <= 1.0 for c in colour)):
            return None
        return cls(mode, tuple(float(c) for c in colour), alpha, note)

    def apply(self, scene):
        """Settle ``scene`` (loaded, not settled) as this record says, in place, without looking at a pixel;
        returns it."""
        scene.background = self.colour
        if not self.alpha:
            for v in _views(scene):
                v.alpha = None
        scene.background_note = self.note
        return scene
