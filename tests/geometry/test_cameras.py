"""Tests for warpnerf.geometry.cameras: Lie-group maps, BARF noise / correction, Sim(3) alignment, errors."""

import math
import numpy as np

import pytest
import torch

from warpnerf.geometry import cameras as C

DTYPES = [torch.float32, torch.float64]
# Round-trip tolerances per dtype; measured max errors over the cases below were 7.2e-7 (float32)
# and 1.4e-15 (float64) for se(3), 7.2e-7 and 8.9e-16 for so(3) near 0 and pi.
TOL = {torch.float32: 5e-6, torch.float64: 1e-12}


def _random_axes(n, dtype, gen):
    a = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return (a / a.norm(dim=-1, keepdim=True)).to(dtype)


def _ring_cameras(n=12, radius=4.0, seed=0, dtype=torch.float32):
    """Blender-like rig: cameras on a sphere around the origin looking at it (z up). Built in
    float64 so that the float64 variant is orthonormal to machine precision."""
    g = torch.Generator().manual_seed(seed)
    az = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    el = torch.rand(n, generator=g, dtype=torch.float64) * 1.2 + 0.1
    centres = radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1)
    return C.look_at(centres).to(dtype)


# ------------------------------------------------------------------ exp / log


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("max_angle", [1e-7, 1e-3, 0.4, 0.6, 2.0, 3.1])
def test_se3_exp_log_round_trip(dtype, max_angle):
    g = torch.Generator().manual_seed(1)
    n = 500
    angles = torch.rand(n, 1, generator=g, dtype=torch.float64).to(dtype) * max_angle
    xi = torch.cat([_random_axes(n, dtype, g) * angles, torch.randn(n, 3, generator=g).to(dtype)], -1)
    T = C.se3_exp(xi)
    R = T[..., :3]
    eye = torch.eye(3, dtype=dtype)
    assert (R @ R.transpose(-1, -2) - eye).abs().max() < TOL[dtype]
    assert (torch.linalg.det(R) - 1).abs().max() < TOL[dtype]
    assert (C.se3_log(T) - xi).abs().max() < TOL[dtype]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.5, 2.0, 2.2, math.pi - 1e-2, math.pi - 1e-6, math.pi])
def test_so3_log_near_zero_and_pi(dtype, angle):
    g = torch.Generator().manual_seed(2)
    w = _random_axes(200, dtype, g) * angle
    R = C.so3_exp(w)
    w_back = C.so3_log(R)
    # The angle is recovered everywhere (atan2 keeps it accurate next to pi)...
    assert (w_back.norm(dim=-1) - angle).abs().max() < TOL[dtype]
    # ...and the vector itself, except at exactly pi where -w is an equally valid logarithm.
    if angle < math.pi - 1e-7:
        assert (w_back - w).abs().max() < TOL[dtype]
    assert (C.so3_exp(w_back) - R).abs().max() < TOL[dtype]


def test_so3_exp_known_rotation():
    R = C.rotation_about_axis([0, 0, 1], math.pi / 2, torch.float64)
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(R, expected, atol=1e-15)


@pytest.mark.parametrize("dtype", DTYPES)
def test_se3_exp_at_zero_is_identity_with_generator_jacobian(dtype):
    xi = torch.zeros(6, dtype=dtype)
    T = C.se3_exp(xi)
    assert torch.equal(T, torch.eye(3, 4, dtype=dtype))
    J = torch.autograd.functional.jacobian(C.se3_exp, xi)  # (3, 4, 6)
    assert torch.isfinite(J).all()
    # d exp / d w_k at 0 is the rotation generator skew(e_k) (no translation), and
    # d exp / d u_k is the translation e_k.
    expected = torch.zeros(3, 4, 6, dtype=dtype)
    for k in range(3):
        e = torch.zeros(3, dtype=dtype)
        e[k] = 1
        expected[:, :3, k] = C.skew(e)
        expected[k, 3, 3 + k] = 1
    assert torch.equal(J, expected)


@pytest.mark.gradcheck
def test_se3_exp_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    at_zero = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    # 0.3 keeps some angles in the Taylor branch (< 0.5) and some in the closed form.
    small = (torch.randn(4, 6, generator=g, dtype=torch.float64) * 0.3).requires_grad_()
    large = (torch.randn(4, 6, generator=g, dtype=torch.float64) * 1.5).requires_grad_()
    for xi in (at_zero, small, large):
        assert torch.autograd.gradcheck(C.se3_exp, (xi,))
    assert torch.autograd.gradcheck(C.se3_log, (C.se3_exp(small).detach().requires_grad_(),))


def test_compose_invert():
    g = torch.Generator().manual_seed(4)
    A = C.se3_exp(torch.randn(5, 6, generator=g, dtype=torch.float64))
    B = C.se3_exp(torch.randn(5, 6, generator=g, dtype=torch.float64))
    eye = torch.eye(3, 4, dtype=torch.float64).expand(5, 3, 4)
    assert torch.allclose(C.compose(A, C.invert(A)), eye, atol=1e-14)
    # compose(A, B) applies B first: x -> A(B(x)).
    x = torch.randn(5, 3, generator=g, dtype=torch.float64)
    apply = lambda T, p: (T[..., :3] @ p[..., None])[..., 0] + T[..., 3]  # noqa: E731
    assert torch.allclose(apply(C.compose(A, B), x), apply(A, apply(B, x)), atol=1e-13)


def test_look_at_convention():
    c2w = _ring_cameras()
    centres = c2w[:, :, 3]
    view_dir = -c2w[:, :, 2]  # OpenGL: the camera looks down its -z axis
    assert torch.allclose(view_dir, -centres / centres.norm(dim=-1, keepdim=True), atol=1e-6)
    assert (torch.linalg.det(c2w[:, :, :3]) - 1).abs().max() < 1e-6
    # A camera straight above the target (view direction parallel to up) still gets a valid frame.
    top = C.look_at(torch.tensor([[0.0, 0.0, 3.0]]))
    assert torch.allclose(-top[0, :, 2], torch.tensor([0.0, 0.0, -1.0]))
    assert torch.allclose(top[0, :, :3] @ top[0, :, :3].T, torch.eye(3), atol=1e-6)


# ------------------------------------------------------------------ BARF noise and correction


def test_noise_reproducible_by_seed():
    c2w = _ring_cameras()
    a = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(7))
    b = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(7))
    c = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(8))
    assert torch.equal(a, b)
    assert not torch.allclose(a, c)
    # The same seed gives the same noise in float64 too (drawn in float64 on the CPU).
    d = C.perturb_poses(c2w.double(), 0.15, 0.15, torch.Generator().manual_seed(7))
    assert d.dtype == torch.float64 and torch.allclose(d.float(), a, atol=1e-6)


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_noise_composition_and_scale(frame):
    n = 4000
    c2w = _ring_cameras(n, seed=5, dtype=torch.float64)
    sigma_rot, sigma_trans = 0.15, 0.05
    noisy, xi = C.perturb_poses(c2w, sigma_rot, sigma_trans, torch.Generator().manual_seed(9), frame=frame,
                                return_noise=True)
    # Recover the perturbation from the poses alone:
    #   world:  w2c_noisy = w2c @ E   <=>  E = c2w @ c2w_noisy^-1
    #   camera: w2c_noisy = E @ w2c   <=>  E = c2w_noisy^-1 @ c2w
    if frame == "world":
        E = C.compose(c2w, C.invert(noisy))
    else:
        E = C.compose(C.invert(noisy), c2w)
    xi_back = C.se3_log(E)
    assert (xi_back - xi).abs().max() < 1e-12
    # Empirical std per part; 12000 samples per group -> relative std error ~0.65 %, so 4 % is
    # comfortably above chance (measured: -0.74 % rotation, -0.18 % translation).
    std_rot = xi_back[:, :3].std().item()
    std_trans = xi_back[:, 3:].std().item()
    assert abs(std_rot / sigma_rot - 1) < 0.04
    assert abs(std_trans / sigma_trans - 1) < 0.04
    assert xi_back.mean(0).abs().max() < 4 * sigma_rot / math.sqrt(n)


def test_world_frame_noise_does_not_depend_on_camera_axes():
    # BARF perturbs w2c in its OpenCV camera frame (c2w_cv = c2w_gl @ diag(1,-1,-1)); because the
    # noise multiplies the world side, the perturbed OpenGL poses are the same.
    c2w = _ring_cameras(dtype=torch.float64)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    c2w_cv = torch.cat([c2w[:, :, :3] @ flip, c2w[:, :, 3:]], -1)
    noisy_gl = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(3))
    noisy_cv = C.perturb_poses(c2w_cv, 0.15, 0.15, torch.Generator().manual_seed(3))
    back_to_gl = torch.cat([noisy_cv[:, :, :3] @ flip, noisy_cv[:, :, 3:]], -1)
    assert torch.allclose(back_to_gl, noisy_gl, atol=1e-14)


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_pose_correction_identity_at_init_and_exact_undo(frame):
    c2w = _ring_cameras(8)
    noisy, xi = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(1), frame=frame,
                                return_noise=True)
    corr = C.PoseCorrection(8, frame=frame)
    assert torch.equal(corr(noisy), noisy)
    idx = torch.tensor([5, 2])
    assert torch.equal(corr(noisy[idx], idx), noisy[idx])
    with torch.no_grad():
        corr.delta.copy_(-xi)
    # float32 exp/compose chain; measured max error 2.4e-7.
    assert (corr(noisy) - c2w).abs().max() < 1e-5


def test_pose_correction_gradient_only_reaches_indexed_views():
    c2w = _ring_cameras(6)
    corr = C.PoseCorrection(6)
    idx = torch.tensor([1, 4])
    out = corr(c2w[idx], idx)
    out.square().sum().backward()
    grad = corr.delta.grad
    assert torch.isfinite(grad).all()
    assert grad[idx].abs().sum() > 0
    rest = torch.tensor([0, 2, 3, 5])
    assert torch.equal(grad[rest], torch.zeros(4, 6))


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_pose_correction_for_rays_equals_one_exponential_per_ray(frame):
    """for_rays (one exponential per distinct view, gathered to the rays) gives the per-ray forward's
    poses and the same gradient on every view's correction, for unsorted indices with repeats."""
    c2w = _ring_cameras(7)
    corr = C.PoseCorrection(7, frame=frame)
    with torch.no_grad():
        corr.delta.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(1))
    idx = torch.tensor([5, 1, 1, 3, 5, 5, 0, 3, 1])
    weights = torch.randn(len(idx), 3, 4, generator=torch.Generator().manual_seed(2))
    grads = []
    for poses in (lambda: corr(c2w[idx], idx), lambda: corr.for_rays(c2w, idx)):
        corr.delta.grad = None
        out = poses()
        (out * weights).sum().backward()
        grads.append((out.detach(), corr.delta.grad.clone()))
    torch.testing.assert_close(grads[1][0], grads[0][0], rtol=0, atol=1e-6)
    torch.testing.assert_close(grads[1][1], grads[0][1], rtol=1e-5, atol=1e-6)
    assert torch.equal(grads[1][1][[2, 4, 6]], torch.zeros(3, 6))  # views without rays get no gradient
    assert grads[1][1][[0, 1, 3, 5]].abs().sum(dim=1).min() > 0


def test_pose_correction_recovers_perturbation_by_adam():
    n = 10
    c2w = _ring_cameras(n)
    noisy = C.perturb_poses(c2w, 0.15, 0.15, torch.Generator().manual_seed(11))
    corr = C.PoseCorrection(n)
    opt = torch.optim.Adam(corr.parameters(), lr=1e-2)
    # A world-frame rotation of d radians moves a camera at radius 4 by about 4 d, so the rotation
    # term gets weight 4^2 = 16 to balance the two; unweighted, Adam needs ~800 steps.
    for _ in range(300):
        opt.zero_grad()
        est = corr(noisy)
        loss = (est[:, :, 3] - c2w[:, :, 3]).square().sum(-1).mean() + \
            16.0 * (est[:, :, :3] - c2w[:, :, :3]).square().sum((-1, -2)).mean()
        loss.backward()
        opt.step()
    est = corr(noisy).detach()
    before = C.rotation_error_deg(noisy, c2w).mean().item()
    after = C.rotation_error_deg(est, c2w).max().item()
    centre_err = (est[:, :, 3] - c2w[:, :, 3]).norm(dim=-1).max().item()
    assert before > 5.0  # the start is far off (about 14 degrees mean)
    # Measured after 300 steps: 0.024 degrees (the arccos floor for float32 matrices) and
    # 5.5e-6 scene units.
    assert after < 0.1
    assert centre_err < 1e-3


# ------------------------------------------------------------------ Sim(3) and errors


@pytest.mark.parametrize("dtype", DTYPES)
def test_procrustes_recovers_known_sim3(dtype):
    g = torch.Generator().manual_seed(12)
    src = torch.randn(30, 3, generator=g, dtype=torch.float64) * 2
    s_true = 0.37
    R_true = C.so3_exp(torch.tensor([0.4, -1.1, 2.0], dtype=torch.float64))
    t_true = torch.tensor([1.5, -0.3, 4.0], dtype=torch.float64)
    dst = s_true * src @ R_true.T + t_true
    s, R, t = C.procrustes_sim3(src.to(dtype), dst.to(dtype))
    # Measured errors: float64 4e-16; float32 inputs 3e-8 (rounding of the inputs themselves).
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    assert abs(s - s_true) < tol
    assert (R.double() - R_true).abs().max() < tol
    assert (t.double() - t_true).abs().max() < 10 * tol
    assert abs(torch.linalg.det(R.double()).item() - 1) < tol


def test_procrustes_rejects_reflection():
    # A mirrored copy must still give a proper rotation (det +1), not the reflection.
    g = torch.Generator().manual_seed(13)
    src = torch.randn(20, 3, generator=g, dtype=torch.float64)
    dst = src * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    _, R, _ = C.procrustes_sim3(src, dst)
    assert abs(torch.linalg.det(R).item() - 1) < 1e-12


def _forward_facing_rig(n=20, seed=3):
    """fern-like rig: centres spread 1.0 / 0.3 / 0.02 in a plane facing the scene, every camera
    looking along -z at a point far in front (float64)."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([1.0, 0.3, 0.02], dtype=torch.float64)
    return C.look_at(centres, target=(0.0, 0.0, -8.0), up=(0.0, 1.0, 0.0))


def test_pose_alignment_recovers_a_known_sim3_and_is_symmetric():
    """With the rotation fitted to the orientations (align="orientations") an exact similarity is
    still recovered exactly, and swapping the two pose sets gives its inverse."""
    gt = _forward_facing_rig()
    s0, R0 = 0.6, C.so3_exp(torch.tensor([0.3, -0.7, 1.1], dtype=torch.float64))
    t0 = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    est = C.apply_sim3_to_poses(gt, s0, R0, t0)
    s, R, t = C.procrustes_sim3(est[:, :, 3], gt[:, :, 3], src_rot=est[:, :, :3], dst_rot=gt[:, :, :3])
    si, Ri, ti = C.invert_sim3(s0, R0, t0)
    assert abs(s - si) < 1e-12 and (R - Ri).abs().max() < 1e-12 and (t - ti).abs().max() < 1e-11
    s2, R2, t2 = C.procrustes_sim3(gt[:, :, 3], est[:, :, 3], src_rot=gt[:, :, :3], dst_rot=est[:, :, :3])
    assert abs(s2 - s0) < 1e-12 and (R2 - R0).abs().max() < 1e-12 and (t2 - t0).abs().max() < 1e-11
    with pytest.raises(ValueError, match="both src_rot and dst_rot"):
        C.procrustes_sim3(est[:, :, 3], gt[:, :, 3], src_rot=est[:, :, :3])
    with pytest.raises(ValueError, match="align must be one of"):
        C.evaluate_poses(est, gt, align="poses")


def test_pose_alignment_pins_the_rotation_where_centres_are_nearly_planar():
    """fern's case (docs/studies/2026-12-07-pose-forward-facing.md): every orientation is right but the
    centres' depths carry an error that grows across the rig (a tilt of 3 deg, which nearly planar
    centres cannot tell from a rotation). Aligning the centres alone turns every camera by about that
    much; fitting the rotation to the orientations keeps them where they are, with the centres'
    scale."""
    gt = _forward_facing_rig()
    est = gt.clone()
    est[:, 2, 3] += math.tan(math.radians(3.0)) * gt[:, 0, 3]  # depth error along the rig's long axis
    centres = C.evaluate_poses(est, gt, align="centres")
    poses = C.evaluate_poses(est, gt, align="orientations")
    assert centres["alignment"] == "centres" and poses["alignment"] == "orientations"
    assert centres["rot_err_deg"] > 2.0  # the centres' fit rotates the cameras by ~the tilt
    assert poses["rot_err_deg"] < 1e-6
    assert poses["rot_err_deg_unaligned"] == centres["rot_err_deg_unaligned"] == pytest.approx(0.0, abs=1e-6)
    assert poses["sim3"][0] == pytest.approx(centres["sim3"][0], rel=1e-12)  # the scale is the centres'
    # on a rig without errors both recover it
    ring = _ring_cameras(15, dtype=torch.float64)
    a, b = C.evaluate_poses(ring, ring, align="centres"), C.evaluate_poses(ring, ring, align="orientations")
    assert a["rot_err_deg"] == pytest.approx(0.0, abs=1e-5) and b["rot_err_deg"] == pytest.approx(0.0, abs=1e-5)


def test_rotation_error_known_angles():
    I = torch.eye(3)
    Rz10 = C.rotation_about_axis([0, 0, 1], math.radians(10.0))
    Rx90 = C.rotation_about_axis([1, 0, 0], math.radians(90.0))
    R180 = C.rotation_about_axis([1, 1, 0], math.pi)
    err = C.rotation_error_deg(torch.stack([Rz10, Rx90, R180, I]), torch.stack([I, I, I, I]))
    # float32 rotation matrices, error evaluated in float64; measured max deviation 7.6e-6 degrees.
    assert torch.allclose(err, torch.tensor([10.0, 90.0, 180.0, 0.0]), atol=1e-4)
    # Symmetric, and relative: R2 = Rz10 @ R1 is 10 degrees from R1 whatever R1 is.
    assert abs(C.rotation_error_deg(Rx90, Rz10 @ Rx90).item() - 10.0) < 1e-4
    assert C.translation_error(torch.tensor([1.0, 2.0, 2.0]), torch.zeros(3)).item() == 3.0


def test_evaluate_poses_invariant_to_similarity_and_maps_test_views():
    gt = _ring_cameras(15, dtype=torch.float64)
    s0 = 0.6
    R0 = C.rotation_about_axis([1.0, -2.0, 0.5], 1.3, torch.float64)
    t0 = torch.tensor([2.0, 0.5, -1.0], dtype=torch.float64)
    est = C.apply_sim3_to_poses(gt, s0, R0, t0)  # perfect poses in another frame
    ev = C.evaluate_poses(est, gt)
    # float64 throughout; measured 0.0 degrees and 1.3e-12 (x100 units).
    assert ev["rot_err_deg"] < 1e-5
    assert ev["trans_err_x100"] < 1e-10
    assert len(ev["rot_err_deg_per_view"]) == 15
    # The returned similarity maps estimate -> gt, so it is the inverse of (s0, R0, t0) ...
    s, R, t = ev["sim3"]
    assert abs(s * s0 - 1) < 1e-12
    # ... and test views in gt coordinates land where the estimate frame puts them.
    test_gt = _ring_cameras(5, seed=99, dtype=torch.float64)
    mapped = C.map_gt_poses_to_estimate_frame(test_gt, ev["sim3"])
    assert torch.allclose(mapped, C.apply_sim3_to_poses(test_gt, s0, R0, t0), atol=1e-12)


def test_evaluate_poses_per_view_errors():
    gt = _ring_cameras(10, dtype=torch.float64)
    est = gt.clone()
    # Rotate camera 3 by 5 degrees about its own centre: centres are unchanged, so the alignment
    # is the identity and only that view has a rotation error.
    est[3, :, :3] = C.rotation_about_axis([0, 1, 0], math.radians(5.0), torch.float64) @ est[3, :, :3]
    ev = C.evaluate_poses(est, gt)
    rot = torch.tensor(ev["rot_err_deg_per_view"])
    assert abs(rot[3].item() - 5.0) < 1e-6
    # The other views sit at the arccos-near-1 floor (measured 2.1e-6 degrees at most).
    assert rot[torch.arange(10) != 3].max() < 1e-4
    assert ev["centre_err_x100"] < 1e-10
    # BARF's translation is the w2c one, t = -R^T c: rotating a camera about its centre moves it
    trans = torch.tensor(ev["trans_err_x100_per_view"], dtype=torch.float64)
    c = gt[3, :, 3]
    expect = 100 * (est[3, :, :3].T @ c - gt[3, :, :3].T @ c).norm()
    assert abs(trans[3] - expect) < 1e-8 and expect > 1.0
    assert trans[torch.arange(10) != 3].max() < 1e-8
    assert abs(ev["rot_err_deg"] - 0.5) < 1e-4
    # one view 5 degrees off among exact ones: not converged, and the median does not see it
    assert ev["unconverged_views"] == [3]
    assert ev["rot_err_deg_median"] < 1e-4 and ev["trans_err_x100_median"] < 1e-8


def test_unconverged_views_needs_both_bounds():
    # errors of 0.3-0.5 deg with one at 1.2 deg: under 5x the median (2 deg), so converged;
    # one at 3 deg is over both bounds; where every view is off (median 4 deg) none stands out
    assert C.unconverged_views(torch.tensor([0.3, 0.4, 0.5, 0.4, 1.2])) == []
    assert C.unconverged_views(torch.tensor([0.3, 0.4, 0.5, 0.4, 3.0])) == [4]
    assert C.unconverged_views(torch.tensor([4.0, 3.5, 4.5, 4.2, 6.0])) == []
    # a tiny median does not flag sub-degree scatter: the 1 degree floor holds
    assert C.unconverged_views(torch.tensor([0.01, 0.02, 0.01, 0.9])) == []


def test_evaluate_poses_separates_a_shared_offset_from_scatter():
    gt = _ring_cameras(100, seed=3, dtype=torch.float64)
    # every camera pitched by 0.1 deg about its own x axis (centres unchanged: the alignment is the identity)
    Rx = C.rotation_about_axis([1.0, 0.0, 0.0], math.radians(0.1), torch.float64)
    est = gt.clone()
    est[:, :, :3] = gt[:, :, :3] @ Rx
    ev = C.evaluate_poses(est, gt)
    f64 = dict(dtype=torch.float64)
    expect = torch.tensor([0.1, 0.0, 0.0], **f64)
    assert torch.allclose(torch.tensor(ev["rot_offset_cam_deg"], **f64), expect, atol=1e-9)
    t_res = 100 * (C.invert(est)[:, :, 3] - C.invert(gt)[:, :, 3])
    assert torch.allclose(torch.tensor(ev["trans_offset_cam_x100"], **f64), t_res.mean(0), atol=1e-9)
    # a shared pitch moves t the same way in every camera: the mean is the whole error
    assert abs(torch.tensor(ev["trans_offset_cam_x100"]).norm() - ev["trans_err_x100"]) < 1e-6 * ev["trans_err_x100"]
    # zero-mean per-camera noise: the shared part is a small fraction of the per-view error
    noisy = C.perturb_poses(gt, 0.01, 0.01, generator=torch.Generator().manual_seed(5))
    ev = C.evaluate_poses(noisy, gt)
    # measured 0.11 / 0.26 of the mean per-view errors (a shared offset: 1.0, above)
    assert torch.tensor(ev["rot_offset_cam_deg"]).norm() < 0.5 * ev["rot_err_deg"]
    assert torch.tensor(ev["trans_offset_cam_x100"]).norm() < 0.5 * ev["trans_err_x100"]


def _barf_camera_alignment(c2w_est: np.ndarray, c2w_gt: np.ndarray):
    """BARF's evaluate_camera_alignment written from its definition, in numpy: align the estimated
    camera centres to the ground truth (centroid, RMS scale, SVD rotation with det fix), rebuild
    each aligned pose as world-to-camera [R_w2c R^T | -R_aligned c_aligned] and report the
    geodesic rotation error (degrees) and ||t_w2c_aligned - t_w2c_gt|| x 100, mean over views."""
    def w2c(c2w):
        R = c2w[:, :, :3].transpose(0, 2, 1)
        return R, -np.einsum("nij,nj->ni", R, c2w[:, :, 3])

    ce, cg = c2w_est[:, :, 3], c2w_gt[:, :, 3]
    t0, t1 = cg.mean(0), ce.mean(0)
    X0, X1 = cg - t0, ce - t1
    s0, s1 = np.sqrt((X0 ** 2).sum(-1).mean()), np.sqrt((X1 ** 2).sum(-1).mean())
    X0, X1 = X0 / s0, X1 / s1
    U, _, Vt = np.linalg.svd((X0.T @ X1).astype(np.float64))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    centre_aligned = (ce - t1) / s1 @ R.T * s0 + t0
    Re, _ = w2c(c2w_est)
    Ra = Re @ R.T
    ta = -np.einsum("nij,nj->ni", Ra, centre_aligned)
    Rg, tg = w2c(c2w_gt)
    cos = ((np.einsum("nij,nij->n", Ra, Rg)) - 1) / 2
    rot = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return rot.mean(), 100 * np.linalg.norm(ta - tg, axis=-1).mean()


@pytest.mark.parametrize("noise", [0.0005, 0.05, 0.15])
def test_trans_err_is_barfs_quantity(noise):
    # synthetic camera set, a known similarity, per-camera se(3) noise
    gt = _ring_cameras(100, seed=3, dtype=torch.float64)
    noisy = C.perturb_poses(gt, noise, noise, generator=torch.Generator().manual_seed(5))
    R0 = C.rotation_about_axis([0.3, 1.0, -0.2], 0.7, torch.float64)
    est = C.apply_sim3_to_poses(noisy, 1.7, R0, torch.tensor([0.4, -2.0, 1.0], dtype=torch.float64))
    ev = C.evaluate_poses(est, gt)
    rot_ref, trans_ref = _barf_camera_alignment(est.numpy(), gt.numpy())
    # float64 on both sides: measured differences below 1e-9
    assert abs(ev["rot_err_deg"] - rot_ref) <= 1e-5
    assert abs(ev["trans_err_x100"] - trans_ref) <= 1e-5
    assert ev["centre_err_x100"] != pytest.approx(ev["trans_err_x100"], rel=1e-3)


def test_camera_frame_residuals_recover_a_shared_offset():
    gt = _ring_cameras(16, dtype=torch.float64)
    # every camera moved by -0.01 along its own y axis in w2c terms, and pitched by 0.02 degrees
    w2c = C.invert(gt)
    pitch = C.rotation_about_axis((1.0, 0.0, 0.0), math.radians(0.02), dtype=torch.float64)
    shifted = torch.cat([pitch @ w2c[:, :, :3], pitch @ w2c[:, :, 3:] + torch.tensor([0.0, -0.01, 0.0],
                                                                                   dtype=torch.float64)[:, None]], -1)
    dt, w = C.camera_frame_residuals(C.invert(shifted), gt)
    # t = pitch @ t_gt + offset: the offset plus the pitch turning t_gt = (0, 0, -4)
    expect_t = 100 * ((pitch @ w2c[:, :, 3:])[:, :, 0] - w2c[:, :, 3] + torch.tensor([0.0, -0.01, 0.0], dtype=torch.float64))
    torch.testing.assert_close(dt, expect_t, atol=1e-9, rtol=0)
    assert abs(dt.mean(0)[1].item() - 100 * (-0.01 + 4 * math.sin(math.radians(0.02)))) < 1e-6
    # rotation errors are log(R_gt^T R) of the camera-to-world rotations: turning w2c by +0.02 degrees
    # about x turns c2w by -0.02
    torch.testing.assert_close(w, torch.tensor([-0.02, 0.0, 0.0], dtype=torch.float64).expand_as(w), atol=1e-9, rtol=0)
