"""What kind of camera rig a capture is, from its poses alone (numpy; no torch).

A capture without sparse points says nothing about where its content is, but its cameras do:

* ``"object"``: the cameras converge. Their optical axes pass near one point (:func:`optical_focus`,
  instant-ngp colmap2nerf's "look-at point"), which lies in front of nearly all of them, and their
  viewing directions spread wider than a forward-facing cone. NeRF-synthetic, product turntables,
  hand-held orbits, and also MipNeRF-360's inward-facing captures (the poses cannot tell a bounded
  object from a central object with a distant background: that needs the images or the points).
* ``"forward_facing"``: every camera looks within a small cone of one direction and the centres
  spread little compared with how far away the axes meet (LLFF: a hand-held patch, all looking
  ahead). NDC suits these.
* ``"360"``: neither: the directions spread widely without a common point in front, e.g.
  cameras looking outward from a ring, a walk through a room, a flythrough.

Thresholds (module constants) and why:

* :data:`FORWARD_CONE_DEG` = 30: LLFF captures keep every view within ~5-15 deg of the mean
  direction; an object orbit covers a far wider arc (NeRF-synthetic's hemisphere: 90 deg and more).
  A converging rig narrower than this (a 60 deg arc in front of an object) is, for framing, a
  forward-facing capture: one side of the scene, seen from in front.
* :data:`FORWARD_SPREAD` = 0.5 (about sin 30 deg): in a converging rig whose directions lie within a
  30 deg cone the centres lie within ~sin 30 deg of the distance to the focus. Cameras that look one
  way but spread farther than that (a flythrough along the view direction) are not one frustum's
  worth of scene, so they are not forward-facing.
* :data:`OBJECT_IN_FRONT` = 0.9: a few cameras may miss (a stray frame looking away) but the
  focus of an outward-looking ring sits behind all of them.
* :data:`OBJECT_MAX_MEAN_ANGLE_DEG` = 20: the mean angle between a camera's axis and the direction
  to the focus. Synthetic rigs aim exactly (0 deg); a hand-held orbit frames the object off-centre
  by up to about a third of a phone's field of view (~10-15 deg); cameras with no common target
  (random directions) give 60-80 deg.
* :data:`PARALLEL_EIGEN` = 1e-6: :func:`optical_focus` gives up when the smallest eigenvalue of its
  normal matrix, per camera, is below this: axes parallel to within ~1e-3 rad (0.06 deg), where the
  point along them is set by noise alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

RigKind = Literal["object", "forward_facing", "360"]

FORWARD_CONE_DEG = 30.0
FORWARD_SPREAD = 0.5
OBJECT_IN_FRONT = 0.9
OBJECT_MAX_MEAN_ANGLE_DEG = 20.0
PARALLEL_EIGEN = 1e-6


@dataclass(frozen=True)
class Rig:
    """The kind of a rig and the numbers it was decided on (module doc)."""

    kind: RigKind
    reason: str  # one line for a person, e.g. "object-centric: 100 cameras look at one point (...)"
    focus: Optional[np.ndarray]  # (3,) nearest point to all optical axes, world units; None: parallel axes
    cone_deg: float  # largest angle between a viewing direction and the mean direction, degrees
    in_front: float  # fraction of cameras with the focus in front of them (0 without a focus)
    focus_angle_deg: float  # mean angle between an optical axis and the direction to the focus, degrees


def optical_focus(c2w: np.ndarray) -> Optional[np.ndarray]:
    """(3,) least-squares nearest point to the optical axes of (N, 3, 4) OpenGL cameras, or None.

    Minimises sum_i |(I - d_i d_i^T)(p - c_i)|^2 (d_i = -z column, c_i = the centre), i.e. solves
    sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) c_i. None when the axes are parallel within
    :data:`PARALLEL_EIGEN` (a forward-facing rig: no point is nearer to all of them than another).
    """
    c2w = np.asarray(c2w, np.float64)
    d = -c2w[:, :, 2]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3) projections off each axis
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, c2w[:, :, 3])
    vals, vecs = np.linalg.eigh(a)
    if vals[0] < PARALLEL_EIGEN * len(c2w):
        return None
    return vecs @ ((vecs.T @ b) / vals)


def classify_rig(c2w: np.ndarray) -> Rig:
    """The :class:`Rig` of (N, 3, 4) OpenGL camera-to-world poses (module doc for the rules)."""
    c2w = np.asarray(c2w, np.float64)
    n = len(c2w)
    d = -c2w[:, :, 2]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    c = c2w[:, :, 3]
    mean = d.mean(0)
    norm = float(np.linalg.norm(mean))
    cone = 180.0 if norm < 1e-9 else float(np.degrees(np.arccos(np.clip(d @ (mean / norm), -1.0, 1.0))).max())
    focus = optical_focus(c2w)
    in_front, angle, reach = 0.0, 180.0, math.inf
    if focus is not None:
        to_focus = focus[None] - c
        dist = np.linalg.norm(to_focus, axis=1)
        cos = np.einsum("nk,nk->n", to_focus, d) / np.maximum(dist, 1e-12)
        in_front = float((cos > 0).mean())
        angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).mean())
        reach = float(np.linalg.norm(focus - c.mean(0)))
    spread = float(np.sqrt(((c - c.mean(0)) ** 2).sum(1).mean()))
    cams = f"{n} camera{'s' if n != 1 else ''}"
    if cone < FORWARD_CONE_DEG and spread <= FORWARD_SPREAD * reach:
        where = ("axes parallel" if focus is None else
                 f"centres spread {spread / reach:.2f} of the distance to the focus")
        return Rig("forward_facing", f"forward-facing: {cams} look within {cone:.1f} deg of one direction ({where})",
                   focus, cone, in_front, angle)
    if focus is not None and in_front >= OBJECT_IN_FRONT and angle < OBJECT_MAX_MEAN_ANGLE_DEG:
        return Rig("object", f"object-centric: {cams} look at one point (mean angle to the focus {angle:.1f} deg, "
                             f"views up to {cone:.0f} deg from their mean direction)", focus, cone, in_front, angle)
    if focus is None:
        why = "parallel axes"
    elif in_front < OBJECT_IN_FRONT:
        why = f"the point nearest to all axes is in front of {100 * in_front:.0f} % of them"
    else:
        why = f"mean angle to the point nearest to all axes {angle:.1f} deg"
    return Rig("360", f"360: {cams} look up to {cone:.0f} deg from their mean direction with no common point ({why})",
               focus, cone, in_front, angle)
