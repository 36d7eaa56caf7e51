"""Camera-pose maths in pure torch: SO(3)/SE(3) exp and log, BARF pose noise and correction,
Sim(3) Procrustes alignment and pose-error metrics.

Conventions
-----------
* A rigid transform is a (..., 3, 4) matrix ``[R | t]`` acting as ``x -> R x + t``. Camera poses
  are camera-to-world (``c2w``) in the OpenGL convention of :mod:`warpnerf.data.scene`; the
  camera centre is ``c2w[..., :, 3]`` and the viewing direction is ``-c2w[..., :, 2]``.
* ``compose(A, B)`` is the matrix product ``A @ B``: apply ``B`` first, then ``A``. (BARF's
  ``pose.compose([a, b])`` is the opposite order: ``a`` first, then ``b``.)
* An se(3) vector is ordered **rotation first**, as in BARF: ``xi = (w, u)`` with ``w = xi[..., :3]``
  the so(3) part (axis * angle, radians) and ``u = xi[..., 3:]`` the translation part (scene
  units). ``se3_exp(xi) = [exp(w^) | V(w) u]``, the exact exponential of the 4x4 twist matrix.

Pose noise and correction (BARF protocol)
-----------------------------------------
BARF stores world-to-camera poses and builds ``pose_noisy = compose([noise, pose])``, which in its
notation means "noise first, then pose": ``w2c_noisy = w2c @ exp(xi)``. The perturbation therefore
acts on *world* coordinates (it rotates about the world origin), and the learnable correction is
applied the same way: ``w2c_corrected = w2c_noisy @ exp(delta)``. In our c2w form that is

    c2w_noisy     = exp(xi)^-1    @ c2w
    c2w_corrected = exp(delta)^-1 @ c2w_noisy      (delta = -xi undoes the noise exactly)

Because the noise multiplies the world side, it does not depend on the camera-axis convention
(BARF's OpenCV camera frame and our OpenGL one give the same noisy poses for the same ``xi``).
``frame="camera"`` gives the other reading, ``w2c_noisy = exp(xi) @ w2c`` with ``xi`` expressed in
our OpenGL camera frame (rotation about the camera centre).

Everything is differentiable and works in float32 and float64; the small-angle branches use
Taylor series so that ``se3_exp`` has exact, finite gradients at ``xi = 0`` (pose corrections are
zero-initialised and trained by Adam).
"""

from __future__ import annotations

from typing import Optional

import torch

# Below this squared angle the closed forms (sin x / x, ...) are replaced by Taylor series, kept
# long enough to be exact in float64 (first dropped term < 1e-16 at theta = 0.5); just above it
# the float32 cancellation in the closed forms is ~ 1e-6 relative.
_SMALL_THETA2 = 0.25


# --------------------------------------------------------------------------------------------
# so(3) / SO(3)
# --------------------------------------------------------------------------------------------


def skew(w: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``w^`` of w (..., 3) -> (..., 3, 3), so that ``w^ v = w x v``."""
    w0, w1, w2 = w.unbind(-1)
    o = torch.zeros_like(w0)
    return torch.stack(
        [
            torch.stack([o, -w2, w1], -1),
            torch.stack([w2, o, -w0], -1),
            torch.stack([-w1, w0, o], -1),
        ],
        -2,
    )


def _vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`skew` applied to the antisymmetric part of m (..., 3, 3) -> (..., 3)."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def _exp_coeffs(theta2: torch.Tensor):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 as functions of t^2.

    The ``where`` trick feeds each branch only inputs it is safe on, so neither the Taylor branch
    (overflow for huge angles) nor the closed form (0/0 at t = 0) can leak NaN into gradients.
    """
    small = theta2 < _SMALL_THETA2
    x = torch.where(small, theta2, torch.zeros_like(theta2))
    # Horner forms of the series up to x^6 (t^12); the first dropped term is < 5e-17 at x = 0.25.
    a_s = 1 - x / 6 * (1 - x / 20 * (1 - x / 42 * (1 - x / 72 * (1 - x / 110 * (1 - x / 156)))))
    b_s = 0.5 * (1 - x / 12 * (1 - x / 30 * (1 - x / 56 * (1 - x / 90 * (1 - x / 132 * (1 - x / 182))))))
    c_s = (1 - x / 20 * (1 - x / 42 * (1 - x / 72 * (1 - x / 110 * (1 - x / 156 * (1 - x / 210)))))) / 6
    y = torch.where(small, torch.ones_like(theta2), theta2)
    t = y.sqrt()
    s, c = torch.sin(t), torch.cos(t)
    a_l = s / t
    b_l = (1 - c) / y
    c_l = (t - s) / (y * t)
    return torch.where(small, a_s, a_l), torch.where(small, b_s, b_l), torch.where(small, c_s, c_l)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) from an axis-angle vector w (..., 3), angle in radians
    (Rodrigues: ``R = I + A w^ + B w^2``)."""
    W = skew(w)
    A, B, _ = _exp_coeffs((w * w).sum(-1))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + A[..., None, None] * W + B[..., None, None] * (W @ W)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vector (..., 3), angle in [0, pi] radians, of rotation matrices R (..., 3, 3).

    Accurate over the whole range: near 0 it uses a series in sin^2, away from pi it uses
    ``theta / sin(theta) * vee(R)``, and for angles beyond 2*pi/3 (where sin -> 0 makes that
    ill-conditioned) it reads the axis from the symmetric part ``(R + R^T)/2 - cos I = (1 - cos) a a^T``
    and takes its sign from ``vee(R)``. At exactly pi the sign is arbitrary (both are valid logs).
    Differentiable except at exactly pi.
    """
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    v = _vee(R)  # sin(theta) * axis
    s2 = (v * v).sum(-1)

    # Branch 1 (cos > -1/2): theta / sin theta * v. With s = sin theta and theta < pi/2 the
    # factor asin(s)/s = 1 + s^2/6 + 3 s^4/40 + 5 s^6/112 + 35 s^8/1152 + ...; for cos < 0
    # (theta in (pi/2, 2pi/3)) atan2 handles it.
    small = (s2 < 1e-4) & (cos > 0)
    xs = torch.where(small, s2, torch.zeros_like(s2))
    f_small = 1 + xs * (1 / 6 + xs * (3 / 40 + xs * (5 / 112 + xs * 35 / 1152)))
    s2_safe = torch.where(small, torch.ones_like(s2), s2)
    s = s2_safe.sqrt()
    f_large = torch.atan2(s, torch.where(small, torch.ones_like(cos), cos)) / s
    w_main = torch.where(small, f_small, f_large)[..., None] * v

    # Branch 2 (cos <= -1/2): axis from the symmetric part, column with the largest diagonal
    # (that diagonal is >= 1/3 of the trace of a a^T = 1, so the division is well conditioned).
    near_pi = cos <= -0.5
    cos_np = torch.where(near_pi, cos, -torch.ones_like(cos))
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    S = (0.5 * (R + R.transpose(-1, -2)) - cos_np[..., None, None] * eye) / (1 - cos_np)[..., None, None]
    diag = torch.diagonal(S, dim1=-2, dim2=-1)
    k = diag.argmax(-1)
    col = torch.gather(S, -1, k[..., None, None].expand(*S.shape[:-1], 1))[..., 0]  # (..., 3)
    dk = torch.gather(diag, -1, k[..., None]).clamp_min(1e-12)
    axis = col / dk.sqrt()
    sign = torch.where((axis * v).sum(-1) < 0, -torch.ones_like(cos), torch.ones_like(cos))
    # atan2(sin, cos) rather than acos(cos): acos amplifies the rounding of cos by 1/sin near pi.
    s_np = torch.where(near_pi, s2, torch.ones_like(s2)).sqrt()
    theta_np = torch.atan2(s_np, cos_np)
    w_pi = (sign * theta_np)[..., None] * axis

    return torch.where(near_pi[..., None], w_pi, w_main)


# --------------------------------------------------------------------------------------------
# se(3) / SE(3)
# --------------------------------------------------------------------------------------------


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Rigid transform (..., 3, 4) from an se(3) vector xi (..., 6) = (w rotation, u translation).

    ``R = I + A w^ + B w^2``, ``t = V u`` with ``V = I + B w^ + C w^2`` (the exact matrix exponential).
    ``se3_exp(0)`` is the identity and its derivative there is the generator basis, computed
    without any 0/0 (Taylor branch).
    """
    w, u = xi[..., :3], xi[..., 3:]
    W = skew(w)
    W2 = W @ W
    A, B, C = _exp_coeffs((w * w).sum(-1))
    A, B, C = A[..., None, None], B[..., None, None], C[..., None, None]
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + A * W + B * W2
    V = eye + B * W + C * W2
    t = (V @ u[..., None])
    return torch.cat([R, t], -1)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """se(3) vector (..., 6) = (w, u) of rigid transforms T (..., 3, 4); inverse of :func:`se3_exp`
    for rotation angles in [0, pi).

    ``u = V^-1 t`` with ``V^-1 = I - w^/2 + D w^2``, ``D = (1 - (t/2) cot(t/2)) / t^2``; the
    cot form stays finite up to and including t = pi (where D = 1/pi^2).
    """
    R, t = T[..., :3], T[..., 3]
    w = so3_log(R)
    theta2 = (w * w).sum(-1)
    small = theta2 < _SMALL_THETA2
    x = torch.where(small, theta2, torch.zeros_like(theta2))
    # (t/2) cot(t/2) series; first dropped term ~ 3e-13 t^14, < 1e-17 at t^2 = 0.25.
    d_s = 1 / 12 + x * (1 / 720 + x * (1 / 30240 + x * (1 / 1209600 + x * (
        1 / 47900160 + x * (1382 / (638512875 * 4096) + x / 74724249600)))))
    y = torch.where(small, torch.ones_like(theta2), theta2)
    half = y.sqrt() / 2
    d_l = (1 - half * torch.cos(half) / torch.sin(half)) / y
    D = torch.where(small, d_s, d_l)[..., None, None]
    W = skew(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    Vinv = eye - 0.5 * W + D * (W @ W)
    u = (Vinv @ t[..., None])[..., 0]
    return torch.cat([w, u], -1)


def compose(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``A @ B`` for rigid transforms (..., 3, 4): x -> A(B(x)) (B is applied first). Broadcasts."""
    RA, tA = A[..., :3], A[..., 3:]
    RB, tB = B[..., :3], B[..., 3:]
    return torch.cat([RA @ RB, RA @ tB + tA], -1)


def invert(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms T (..., 3, 4): ``[R^T | -R^T t]``."""
    Rt = T[..., :3].transpose(-1, -2)
    return torch.cat([Rt, -(Rt @ T[..., 3:])], -1)


# --------------------------------------------------------------------------------------------
# BARF pose noise and learnable correction
# --------------------------------------------------------------------------------------------


def _apply_twist(c2w: torch.Tensor, E: torch.Tensor, frame: str) -> torch.Tensor:
    """c2w of the pose whose w2c is ``w2c @ E`` (frame="world", BARF) or ``E @ w2c`` ("camera")."""
    if frame == "world":
        return compose(invert(E), c2w)
    if frame == "camera":
        return compose(c2w, invert(E))
    raise ValueError(f"frame must be 'world' or 'camera', got {frame!r}")


def apply_correction(c2w: torch.Tensor, delta: torch.Tensor, frame: str = "world") -> torch.Tensor:
    """c2w (..., 3, 4) corrected by se(3) twists ``delta`` (..., 6) as :class:`PoseCorrection` does:
    ``w2c @ exp(delta)`` (frame="world") or ``exp(delta) @ w2c`` ("camera")."""
    return _apply_twist(c2w, se3_exp(delta.to(c2w.dtype)), frame)


def sample_se3_noise(
    n: int,
    sigma_rot: float,
    sigma_trans: float,
    generator: Optional[torch.Generator] = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """(n, 6) se(3) noise ~ N(0, diag(sigma_rot^2 x3, sigma_trans^2 x3)), rotation part first.

    sigma_rot in radians, sigma_trans in scene units. Drawn on the CPU in float64 from
    ``generator`` so the same seed gives the same noise for any dtype or device.
    """
    z = torch.randn(n, 6, generator=generator, dtype=torch.float64)
    scale = torch.tensor([sigma_rot] * 3 + [sigma_trans] * 3, dtype=torch.float64)
    return (z * scale).to(dtype)


def perturb_poses(
    c2w: torch.Tensor,
    sigma_rot: float = 0.15,
    sigma_trans: float = 0.15,
    generator: Optional[torch.Generator] = None,
    frame: str = "world",
    return_noise: bool = False,
):
    """BARF pose perturbation of camera-to-world poses c2w (N, 3, 4).

    Draws ``xi ~ N(0, sigma^2 I)`` per view (see :func:`sample_se3_noise`; BARF uses 0.15 for
    synthetic scenes, 0.01 for real ones) and returns ``c2w_noisy`` (N, 3, 4) whose world-to-camera
    pose is ``w2c @ exp(xi)`` (frame="world", BARF's code) or ``exp(xi) @ w2c`` (frame="camera").
    With ``return_noise=True`` also returns xi (N, 6). Reproducible from ``generator``'s seed.
    Not meant to be differentiated (the noise is a constant of the experiment).
    """
    xi = sample_se3_noise(c2w.shape[0], sigma_rot, sigma_trans, generator, dtype=torch.float64)
    E = se3_exp(xi).to(device=c2w.device)  # exp in float64, then cast with the result
    noisy = _apply_twist(c2w.to(torch.float64), E, frame).to(c2w.dtype)
    if return_noise:
        return noisy, xi.to(dtype=c2w.dtype, device=c2w.device)
    return noisy


class PoseCorrection(torch.nn.Module):
    """One learnable se(3) correction per training view, zero-initialised (BARF's ``se3_refine``).

    ``delta`` is an (N, 6) ``nn.Parameter`` ordered (rotation, translation). The correction is
    composed exactly like the noise of :func:`perturb_poses` with the same ``frame``:
    ``w2c_corrected = w2c_noisy @ exp(delta)`` for "world", so ``delta = -xi`` undoes the noise.
    Train it with its own optimiser (BARF: Adam, lr 1e-3 -> 1e-5 exponential).
    """

    def __init__(self, num_views: int, frame: str = "world"):
        super().__init__()
        if frame not in ("world", "camera"):
            raise ValueError(f"frame must be 'world' or 'camera', got {frame!r}")
        self.frame = frame
        self.delta = torch.nn.Parameter(torch.zeros(num_views, 6))

    def forward(self, c2w_noisy: torch.Tensor, idx: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Corrected c2w (..., 3, 4) for views ``idx``.

        c2w_noisy: (..., 3, 4) noisy poses *of the views idx* (already gathered, same leading
        shape as idx); idx: integer tensor of view indices, or None for all views (then c2w_noisy
        is (N, 3, 4)). Differentiable w.r.t. ``delta`` (and c2w_noisy). At initialisation the
        output equals the input exactly.
        """
        if idx is None:
            d = self.delta
        else:
            idx = torch.as_tensor(idx, device=self.delta.device)
            # index_select, not delta[idx]: its backward sums a camera's rays in a fixed order on
            # CPU (see warpnerf.model.renderer.gather_rows), so pose training is bit-reproducible
            d = self.delta.index_select(0, idx.reshape(-1)).reshape(*idx.shape, self.delta.shape[1])
        return apply_correction(c2w_noisy, d, self.frame)

    def for_rays(self, c2w_noisy: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Corrected c2w (B, 3, 4) of views ``idx`` (B,), e.g. one per ray, from the (N, 3, 4) noisy
        poses of *all* views: ``forward(c2w_noisy[idx], idx)`` with one exponential per distinct view
        instead of one per ray (a training step's ~5000 rays: 3.4 -> 1.2 ms forward + backward)."""
        views, inverse = torch.unique(torch.as_tensor(idx, device=self.delta.device), return_inverse=True)
        return self(c2w_noisy.index_select(0, views), views).index_select(0, inverse.reshape(-1))


# --------------------------------------------------------------------------------------------
# Sim(3) alignment and pose errors
# --------------------------------------------------------------------------------------------


def procrustes_sim3(src: torch.Tensor, dst: torch.Tensor, eps: float = 1e-12,
                    src_rot: Optional[torch.Tensor] = None, dst_rot: Optional[torch.Tensor] = None):
    """Similarity (s, R, t) with ``dst ~ s R src + t`` for point sets src, dst (N, 3).

    BARF / DESIGN §5: centre both sets, normalise each by its RMS distance to its centroid,
    rotation from the SVD of the 3x3 cross-covariance with a determinant fix (no reflections).
    The scale is the ratio of RMS radii (not Umeyama's least-squares scale), which makes the
    alignment exactly symmetric: swapping src and dst gives the inverse similarity.
    Computed in float64; returns s (python float), R (3, 3) and t (3,) in src's dtype.
    Needs N >= 3 non-collinear points for a unique rotation.

    With ``src_rot`` and ``dst_rot`` (N, 3, 3), the cameras' orientations, the rotation is fitted to
    them instead: it minimises ``sum_i ||R src_rot_i - dst_rot_i||_F^2`` (the same SVD, of
    ``sum_i src_rot_i dst_rot_i^T``), and scale and translation are the centres' as above. Where the
    centres barely span 3-D and their depths are estimated less well than the orientations
    (forward-facing captures: fern's centres spread 1.07 / 0.34 / 0.066) a depth error that grows
    across the rig cannot be told from a rotation, and the centres' rotation took it (6 deg on fern
    while every camera's orientation was within 1.4 deg of its ground truth). Weighting both kinds
    of term alike still turned a rig with a 3 deg depth tilt by 0.95 deg, hence orientations alone.
    """
    X = src.detach().to(torch.float64)
    Y = dst.detach().to(torch.float64)
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    rx = Xc.square().sum(-1).mean().sqrt().clamp_min(eps)
    ry = Yc.square().sum(-1).mean().sqrt().clamp_min(eps)
    if (src_rot is None) != (dst_rot is None):
        raise ValueError("procrustes_sim3: give both src_rot and dst_rot, or neither")
    if src_rot is None:
        H = (Xc / rx).T @ (Yc / ry)  # sum_i x_i y_i^T: R maximises tr(R H) = sum_i y_i^T R x_i
    else:  # sum_i tr(dst_rot_i^T R src_rot_i) = tr(R sum_i src_rot_i dst_rot_i^T)
        H = (src_rot.detach().to(torch.float64) @ dst_rot.detach().to(torch.float64).transpose(1, 2)).sum(0)
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.T
    fix = torch.ones(3, dtype=torch.float64)
    fix[2] = torch.sign(torch.linalg.det(V @ U.T))
    if fix[2] == 0:
        fix[2] = 1.0
    R = V @ torch.diag(fix) @ U.T
    s = ry / rx
    t = my - s * (R @ mx)
    return float(s), R.to(src.dtype), t.to(src.dtype)


def apply_sim3_to_poses(c2w: torch.Tensor, s: float, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Map camera poses c2w (N, 3, 4) through the similarity x -> s R x + t.

    Rotation becomes ``R @ R_c``, centre becomes ``s R c + t`` (the camera stays a rigid pose;
    the scale only moves its centre).
    """
    R = R.to(c2w)
    t = t.to(c2w)
    Rc, c = c2w[..., :3], c2w[..., 3]
    return torch.cat([R @ Rc, (s * (c @ R.T) + t)[..., None]], -1)


def invert_sim3(s: float, R: torch.Tensor, t: torch.Tensor):
    """Inverse similarity: x -> R^T (x - t) / s, returned as (1/s, R^T, -R^T t / s)."""
    return 1.0 / s, R.T, -(R.T @ t) / s


def map_gt_poses_to_estimate_frame(c2w_gt: torch.Tensor, sim3) -> torch.Tensor:
    """Bring ground-truth poses (e.g. test views) c2w_gt (N, 3, 4) into the frame of the
    estimated (optimised) training poses, using the inverse of the ``sim3 = (s, R, t)`` returned
    by :func:`evaluate_poses` (which maps estimate -> ground truth)."""
    return apply_sim3_to_poses(c2w_gt, *invert_sim3(*sim3))


def rotation_error_deg(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic rotation error per pair, degrees: ``arccos((tr(R1 R2^T) - 1) / 2)``.

    R1, R2: (..., 3, 3) (3x4 poses are accepted; the translation column is ignored).
    Evaluated in float64 (arccos near 1 loses ~0.02 deg of resolution in float32) and clamped
    to [-1, 1]. Returns (...,) in the input dtype. Not meant for gradients (arccos' at 1 is inf).
    """
    A = R1[..., :3, :3].to(torch.float64)
    B = R2[..., :3, :3].to(torch.float64)
    tr = (A * B).sum((-1, -2))  # tr(A B^T)
    ang = torch.acos(((tr - 1) / 2).clamp(-1.0, 1.0))
    return torch.rad2deg(ang).to(R1.dtype)


def translation_error(t1: torch.Tensor, t2: torch.Tensor) -> torch.Tensor:
    """Euclidean distance ``||t1 - t2||`` over the last axis (..., 3) -> (...), scene units
    (papers report it x 100)."""
    return (t1 - t2).norm(dim=-1)


def camera_frame_residuals(c2w: torch.Tensor, c2w_gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view pose residuals in each camera's own axes, for (N, 3, 4) poses in one frame:
    (N, 3) ``t_w2c - t_w2c_gt`` x 100 (BARF's translation error is its norm) and (N, 3) the
    rotation vector of ``R_gt^T R`` in degrees (float64)."""
    t_res = 100.0 * (invert(c2w)[:, :, 3] - invert(c2w_gt)[:, :, 3])
    rot_res = torch.rad2deg(so3_log(c2w_gt[:, :, :3].transpose(1, 2).double() @ c2w[:, :, :3].double()))
    return t_res, rot_res


UNCONVERGED_MIN_DEG = 1.0
UNCONVERGED_MEDIAN_RATIO = 5.0
UNCONVERGED_RULE = f"rot. err > {UNCONVERGED_MIN_DEG:g} deg and {UNCONVERGED_MEDIAN_RATIO:g}x the median"


def unconverged_views(rot_err_deg: torch.Tensor) -> list[int]:
    """Ids of views whose rotation error is above ``UNCONVERGED_MIN_DEG`` and above
    ``UNCONVERGED_MEDIAN_RATIO`` times the median: far outside the spread of the others."""
    bound = max(UNCONVERGED_MIN_DEG, UNCONVERGED_MEDIAN_RATIO * float(rot_err_deg.median()))
    return [int(i) for i in torch.nonzero(rot_err_deg > bound).flatten()]


def describe_unconverged(metrics: dict, max_ids: Optional[int] = None) -> Optional[str]:
    """One phrase for reports (the train summary, ``warpnerf table``) naming a pose run's
    ``unconverged_views`` with the medians, or None when every view converged. ``max_ids`` caps
    the ids listed."""
    stuck = metrics.get("unconverged_views") or []
    if not stuck:
        return None
    ids = ", ".join(map(str, stuck[:max_ids])) + (", ..." if max_ids is not None and len(stuck) > max_ids else "")
    return (f"{len(stuck)} view(s) not converged ({ids}; {UNCONVERGED_RULE}); median rot. err "
            f"{metrics['rot_err_deg_median']:.3f} deg, trans. err {metrics['trans_err_x100_median']:.3f}")


ALIGNMENTS = ("centres", "orientations")


def evaluate_poses(c2w_est: torch.Tensor, c2w_gt: torch.Tensor, align: str = "centres") -> dict:
    """Pose accuracy of estimated training poses after Sim(3) alignment (BARF protocol).

    c2w_est, c2w_gt: (N, 3, 4). The estimated camera centres are aligned to the ground-truth
    centres with :func:`procrustes_sim3`, the whole estimated poses are mapped through that
    similarity, and errors are measured per view. ``align``: "centres" is BARF's (the paper's
    tables); "orientations" fits the similarity's rotation to the cameras' orientations and its
    scale and translation to the centres (``procrustes_sim3``'s ``src_rot``), for cameras whose
    centres barely span 3-D (forward-facing captures), where the centres leave it ill-determined.

    Returns a dict with
      rot_err_deg: mean rotation error, degrees (float; unclamped float64 arccos, whereas BARF's
          float32 clamp floors its figure at ~0.026 deg);
      trans_err_x100: mean 100 * ||t_w2c_aligned - t_w2c_gt||, BARF's "trans" (its
          ``evaluate_camera_alignment``, which the paper's tables report): the translation of the
          aligned *world-to-camera* pose, scene units x 100;
      centre_err_x100: mean 100 * ||centre_aligned - centre_gt||, the camera-centre distance
          (differs from trans_err_x100 in either direction when rotations differ);
      rot_err_deg_per_view, trans_err_x100_per_view, centre_err_x100_per_view: lists of N floats;
      rot_err_deg_unaligned: mean rotation error without any alignment. Meaningful where the
          estimate shares the ground truth's frame (the pose task perturbs the ground truth); on
          fern (centre spread 1.07 / 0.34 / 0.066) the centres' alignment ("centres") is
          ill-determined and turned the cameras by 6 deg, which "orientations" avoids;
      rot_offset_cam_deg, trans_offset_cam_x100: the residual every camera shares, in its own frame:
          the mean over views of the rotation vector of R_gt^T R_aligned (degrees) and of
          t_w2c_aligned - t_w2c_gt (x100), 3 floats each (x, y, z camera axes). A systematic error
          shows here at the size of the per-view error; zero-mean scatter mostly averages out (100
          ring cameras with se(3) noise: 0.11 of the rotation error, 0.26 of the translation error);
      rot_err_deg_median, trans_err_x100_median: medians over views, which one view stuck in a
          wrong basin cannot move (mic: one view at 29 deg made the mean 0.55 deg, the median 0.25);
      unconverged_views: ids of views whose rotation error exceeds both ``UNCONVERGED_MIN_DEG`` and
          ``UNCONVERGED_MEDIAN_RATIO`` times the median: poses the optimisation did not bring in;
      sim3: (s, R (3, 3), t (3,)) mapping estimate -> ground truth (see
          :func:`map_gt_poses_to_estimate_frame` for test views);
      c2w_aligned: (N, 3, 4) aligned estimated poses (detached);
      alignment: ``align``.
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    est = c2w_est.detach()
    gt = c2w_gt.detach().to(est.dtype)
    rots = (est[:, :, :3], gt[:, :, :3]) if align == "orientations" else (None, None)
    s, R, t = procrustes_sim3(est[:, :, 3], gt[:, :, 3], src_rot=rots[0], dst_rot=rots[1])
    aligned = apply_sim3_to_poses(est, s, R, t)
    rot = rotation_error_deg(aligned, gt)
    centre = 100.0 * translation_error(aligned[:, :, 3], gt[:, :, 3])
    t_res, rot_res = camera_frame_residuals(aligned, gt)
    trans = t_res.norm(dim=-1)
    return {
        "rot_err_deg": float(rot.mean()),
        "rot_err_deg_unaligned": float(rotation_error_deg(est, gt).mean()),
        "trans_err_x100": float(trans.mean()),
        "centre_err_x100": float(centre.mean()),
        "rot_err_deg_median": float(rot.median()),
        "trans_err_x100_median": float(trans.median()),
        "unconverged_views": unconverged_views(rot),
        "rot_err_deg_per_view": [float(x) for x in rot],
        "trans_err_x100_per_view": [float(x) for x in trans],
        "centre_err_x100_per_view": [float(x) for x in centre],
        "rot_offset_cam_deg": [float(x) for x in rot_res.mean(0)],
        "trans_offset_cam_x100": [float(x) for x in t_res.mean(0)],
        "sim3": (s, R, t),
        "c2w_aligned": aligned,
        "alignment": align,
    }


def barf_pose_errors(c2w_est: torch.Tensor, c2w_gt: torch.Tensor) -> dict:
    """BARF's own pose metric (``prealign_cameras`` + ``evaluate_camera_alignment``), reproduced
    so that numbers can be set beside the paper's tables.

    c2w_est, c2w_gt: (N, 3, 4) camera-to-world poses in one axis convention (ours is OpenGL, BARF's
    OpenCV; the metric does not depend on it: flipping the camera axes turns R_al R_gt^T into
    F R_al R_gt^T F, same trace, and each w2c translation into F t, same norm).

    Alignment, estimate -> ground truth, from the camera centres only: with t0, t1 the gt / est
    centroids and s0, s1 their RMS radii, ``R = U Vh`` from the float64 SVD of
    ``sum_i (x0_i / s0)(x1_i / s1)^T`` (x = centred centres), then
    ``c_al = s0/s1 R (c_est - t1) + t0`` (BARF's row form ``(X1 - t1)/s1 @ R^T * s0 + t0``),
    ``R_al = R_est_w2c R^T`` and ``t_al = -R_al c_al``.

    Where this differs from :func:`evaluate_poses` (align="centres"), whose
    :func:`procrustes_sim3` uses the same centroids, the same RMS scale s0/s1 and the same rotation
    whenever ``det(U Vh) > 0``:
      * reflections: if ``det(U Vh) < 0`` BARF negates the *third row* of R (world z), not the
        direction of the smallest singular value (Kabsch). The two agree only when that direction
        is world z, e.g. a rig planar in z; elsewhere BARF's rotation is not the optimal one. This
        can happen where the centres are nearly planar (forward-facing captures);
      * if the SVD fails BARF falls back to the identity similarity (no centring, no scaling);
        here also when the centres give a non-finite matrix (all est centres equal: s1 = 0),
        where BARF's outcome depends on whether its torch's SVD raises on NaN;
      * rotation error: ``arccos(clamp((tr(R_al R_gt^T) - 1) / 2, -1 + 1e-7, 1 - 1e-7))`` in
        float32, so every view reads at least arccos(float32(1 - 1e-7)) = 0.0280 deg, and the
        next readable values are 0.0396, 0.0485, 0.0560 deg (the float32 trace lies in [2, 4],
        spaced 2^-22, so (tr - 1)/2 steps by 2^-23: a step of 2^-23 / sin(theta) rad, 0.0013 deg
        at 0.3 deg); evaluate_poses uses an unclamped float64 arccos. The mean is of these;
      * translation error: the same w2c ``||t_al - t_gt||`` as evaluate_poses' trans_err_x100
        (not the centre distance), x 100 as the paper reports it (BARF's code prints it raw).
    BARF runs the alignment in float32 (only the SVD in float64); here it is float64 and only the
    rotation distance is float32, so the results differ from BARF's code by its float32 rounding.
    Measured against BARF's functions on random rigs: translations by < 2e-4 (x 100), rotations per
    view by a few of the arccos steps above (up to 0.016 deg just above the floor, 0.002 deg at
    1 deg), means by < 0.004 deg. A perfect estimate reads the floor in both.

    Returns a dict with
      rot_err_deg_barf, rot_err_deg_barf_per_view: mean (float) and N floats, degrees;
      trans_err_x100_barf, trans_err_x100_barf_per_view: mean and N floats, scene units x 100;
      sim3_barf: (scale, R (3, 3), t (3,)) in c2w_est's dtype with ``gt_centre ~ scale R est_centre + t``,
          i.e. scale = s0/s1 and t = t0 - scale R t1 (the form :func:`apply_sim3_to_poses` and
          :func:`map_gt_poses_to_estimate_frame` take);
      barf_reflection_fixed: whether the third-row sign fix was applied;
      barf_svd_failed: whether the identity fallback was used.
    """
    est = c2w_est.detach().to(torch.float64)
    gt = c2w_gt.detach().to(device=est.device, dtype=torch.float64)
    c_est, c_gt = est[:, :, 3], gt[:, :, 3]
    eye = torch.eye(3, dtype=torch.float64, device=est.device)
    reflection = failed = False
    try:
        t0, t1 = c_gt.mean(0), c_est.mean(0)
        s0 = (c_gt - t0).square().sum(-1).mean().sqrt()
        s1 = (c_est - t1).square().sum(-1).mean().sqrt()
        H = ((c_gt - t0) / s0).T @ ((c_est - t1) / s1)  # sum_i x0_i x1_i^T: R = U Vh maximises sum_i x0_i^T R x1_i
        if not bool(torch.isfinite(H).all()):
            raise RuntimeError("non-finite cross-covariance")
        U, _, Vh = torch.linalg.svd(H)
        R = U @ Vh
        if torch.linalg.det(R) < 0:
            R = R.clone()
            R[2] = -R[2]
            reflection = True
        scale = s0 / s1
        t = t0 - scale * (R @ t1)
        scale = float(scale)
    except RuntimeError:  # BARF: "SVD did not converge" -> identity sim3
        failed, reflection = True, False
        scale, R, t = 1.0, eye, torch.zeros(3, dtype=torch.float64, device=est.device)
    c_al = scale * (c_est @ R.T) + t
    R_al = est[:, :, :3].transpose(1, 2) @ R.T  # w2c
    t_al = -(R_al @ c_al[..., None])[..., 0]
    R_gt = gt[:, :, :3].transpose(1, 2)
    t_gt = -(R_gt @ c_gt[..., None])[..., 0]
    # BARF's rotation_distance, in float32 as BARF computes it (this is what sets the floor)
    R_diff = R_al.float() @ R_gt.float().transpose(1, 2)
    trace = R_diff[:, 0, 0] + R_diff[:, 1, 1] + R_diff[:, 2, 2]
    rot = torch.rad2deg(((trace - 1) / 2).clamp(-1 + 1e-7, 1 - 1e-7).acos().double())
    trans = 100.0 * (t_al - t_gt).norm(dim=-1)
    return {
        "rot_err_deg_barf": float(rot.mean()),
        "rot_err_deg_barf_per_view": [float(x) for x in rot],
        "trans_err_x100_barf": float(trans.mean()),
        "trans_err_x100_barf_per_view": [float(x) for x in trans],
        "sim3_barf": (scale, R.to(c2w_est.dtype), t.to(c2w_est.dtype)),
        "barf_reflection_fixed": reflection,
        "barf_svd_failed": failed,
    }


def look_at(centres: torch.Tensor, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """c2w (N, 3, 4) of cameras at ``centres`` (N, 3) looking at ``target`` (OpenGL: the camera's
    -z axis points at the target, +y is as close to ``up`` as possible; Blender scenes use z up).
    A camera looking along ``up`` (no unique roll) gets its x axis from a perpendicular helper."""
    c = torch.as_tensor(centres)
    tgt = torch.as_tensor(target, dtype=c.dtype, device=c.device)
    upv = torch.as_tensor(up, dtype=c.dtype, device=c.device).expand_as(c)
    back = c - tgt
    z = back / back.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(upv, z)
    # Degenerate roll (view direction parallel to up): any x perpendicular to z will do.
    helper = torch.where(z[..., :1].abs() < 0.9, torch.tensor([1.0, 0.0, 0.0], dtype=c.dtype, device=c.device),
                         torch.tensor([0.0, 1.0, 0.0], dtype=c.dtype, device=c.device))
    x = torch.where(x.norm(dim=-1, keepdim=True) < 1e-6, torch.linalg.cross(helper.expand_as(z), z), x)
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z, c], -1)


def rotation_about_axis(axis, angle_rad: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(3, 3) rotation by angle_rad radians about ``axis`` (any non-zero 3-vector)."""
    a = torch.as_tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    return so3_exp(a * angle_rad).to(dtype)


__all__ = [
    "skew",
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "compose",
    "invert",
    "sample_se3_noise",
    "perturb_poses",
    "PoseCorrection",
    "procrustes_sim3",
    "apply_sim3_to_poses",
    "invert_sim3",
    "map_gt_poses_to_estimate_frame",
    "rotation_error_deg",
    "translation_error",
    "evaluate_poses",
    "barf_pose_errors",
    "look_at",
    "rotation_about_axis",
]
