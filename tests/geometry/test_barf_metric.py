"""barf_pose_errors: BARF's own pose metric (prealign_cameras + evaluate_camera_alignment), checked
against independent references: known similarities and rotations, a numpy re-derivation of BARF's
steps in its own row-vector, world-to-camera OpenCV form, and evaluate_poses where they must agree."""

import math

import numpy as np
import pytest
import torch

from warpnerf.geometry import cameras as C

# BARF's rotation_distance clamps (tr - 1) / 2 at 1 - 1e-7 in float32: the smallest angle it can read
FLOOR_DEG = float(np.degrees(np.float64(np.arccos(np.float32(1 - 1e-7)))))  # 0.02798 deg
F = np.diag([1.0, -1.0, -1.0])  # OpenGL <-> OpenCV camera axes


def _float32_resolution_deg(theta_deg):
    """Two steps of BARF's float32 reading at angle theta: its trace, in [2, 4], is spaced 2^-22, so
    cos theta = (tr - 1)/2 steps by 2^-23, i.e. theta by 2^-23 / sin(theta) radians."""
    return 2 * np.degrees(2.0 ** -23 / np.sin(np.radians(theta_deg)))


def _random_rig(n, seed):
    """n cameras at random centres (not coplanar) looking at the origin, float64."""
    g = torch.Generator().manual_seed(seed)
    return C.look_at(2.0 * torch.randn(n, 3, generator=g, dtype=torch.float64)), g


def _sphere_rig(n=20, radius=4.0):
    """n cameras on a Fibonacci sphere looking at the origin (never exactly at a pole)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return C.look_at(torch.from_numpy(radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)))


def _forward_facing_rig(seed, jitter=1e-3):
    """20 cameras on a 5 x 4 grid in the xy plane (1.0 x 0.6), depths jittered by ``jitter``, all
    looking along -z (R = I in OpenGL): centres that barely span 3-D, as in LLFF."""
    g = torch.Generator().manual_seed(seed)
    xs, ys = torch.meshgrid(torch.linspace(-0.5, 0.5, 5, dtype=torch.float64),
                            torch.linspace(-0.3, 0.3, 4, dtype=torch.float64), indexing="ij")
    c = torch.stack([xs.flatten(), ys.flatten(), jitter * torch.randn(20, generator=g, dtype=torch.float64)], -1)
    return torch.cat([torch.eye(3, dtype=torch.float64).expand(20, 3, 3), c[..., None]], -1), g


def _numpy_barf(c2w_est, c2w_gt, kabsch=False):
    """BARF's steps re-derived in numpy float64, in its own form: w2c OpenCV poses, row vectors.
    ``kabsch=True`` replaces BARF's third-row sign fix by the proper one (what procrustes_sim3 does).
    Returns per-view rotation errors (deg, unclamped float64), translation errors x100, and R."""
    est, gt = np.asarray(c2w_est, np.float64), np.asarray(c2w_gt, np.float64)

    def w2c_opencv(c2w):
        R = F @ c2w[:, :, :3].transpose(0, 2, 1)
        return R, -np.einsum("nij,nj->ni", R, c2w[:, :, 3])

    R_pred, _ = w2c_opencv(est)
    R_gt, t_gt = w2c_opencv(gt)
    X0, X1 = gt[:, :, 3], est[:, :, 3]  # centres: X0 ground truth, X1 prediction
    t0, t1 = X0.mean(0, keepdims=True), X1.mean(0, keepdims=True)
    s0 = np.sqrt(((X0 - t0) ** 2).sum(-1).mean())
    s1 = np.sqrt(((X1 - t1) ** 2).sum(-1).mean())
    U, _, Vt = np.linalg.svd(((X0 - t0) / s0).T @ ((X1 - t1) / s1))
    if kabsch:
        R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    else:
        R = U @ Vt
        if np.linalg.det(R) < 0:
            R[2] *= -1
    c_al = (X1 - t1) / s1 @ R.T * s0 + t0
    R_al = R_pred @ R.T
    t_al = -np.einsum("nij,nj->ni", R_al, c_al)
    cos = (np.trace(R_al @ R_gt.transpose(0, 2, 1), axis1=1, axis2=2) - 1) / 2
    rot = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return rot, 100 * np.linalg.norm(t_al - t_gt, axis=-1), R


def test_exact_similarity_reads_the_float32_floor():
    gt, g = _random_rig(15, seed=0)
    Q = C.so3_exp(torch.randn(3, generator=g, dtype=torch.float64)).numpy()
    off = np.array([1.0, -2.0, 0.5])
    gt_np = gt.numpy()
    est = np.concatenate([Q @ gt_np[:, :, :3], (2.3 * gt_np[:, :, 3] @ Q.T + off)[..., None]], -1)
    m = C.barf_pose_errors(torch.from_numpy(est), gt)
    # every view at exactly the clamp floor (to one float32 ulp of acos across libms)
    assert m["rot_err_deg_barf_per_view"] == pytest.approx([FLOOR_DEG] * 15, rel=1e-6, abs=0)
    assert m["rot_err_deg_barf"] == pytest.approx(FLOOR_DEG, rel=1e-6, abs=0)
    assert max(m["trans_err_x100_barf_per_view"]) < 1e-8 and m["trans_err_x100_barf"] < 1e-8
    # the similarity is the inverse of the one applied: gt = (1/2.3) Q^T (est - off)
    s, R, t = m["sim3_barf"]
    assert s == pytest.approx(1 / 2.3, rel=1e-12)
    np.testing.assert_allclose(R.numpy(), Q.T, atol=1e-12)
    np.testing.assert_allclose(t.numpy(), -Q.T @ off / 2.3, atol=1e-12)
    assert not m["barf_reflection_fixed"] and not m["barf_svd_failed"]


def test_one_rotated_view_on_a_sphere():
    gt = _sphere_rig()
    est = gt.clone()
    roll = C.rotation_about_axis([0.0, 0.0, 1.0], math.radians(2.0), torch.float64)
    est[0, :, :3] = gt[0, :, :3] @ roll  # 2 deg about view 0's own optical axis; centres unchanged
    m = C.barf_pose_errors(est, gt)
    s, R, t = m["sim3_barf"]  # identical centres: the alignment is the identity
    assert s == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R.numpy(), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t.numpy(), 0.0, atol=1e-12)
    per_view = m["rot_err_deg_barf_per_view"]
    assert per_view[0] == pytest.approx(2.0, abs=1e-3)
    assert per_view[1:] == pytest.approx([FLOOR_DEG] * 19, rel=1e-6, abs=0)
    assert m["rot_err_deg_barf"] == pytest.approx((2.0 + 19 * FLOOR_DEG) / 20, abs=1e-4)
    assert max(m["trans_err_x100_barf_per_view"]) < 1e-8


def test_moved_centre_matches_numpy_reference():
    gt, _ = _random_rig(20, seed=1)
    est = gt.clone()
    est[5, :, 3] += torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    m = C.barf_pose_errors(est, gt)
    rot_ref, trans_ref, R_ref = _numpy_barf(est.numpy(), gt.numpy())
    np.testing.assert_allclose(m["trans_err_x100_barf_per_view"], trans_ref, rtol=0, atol=1e-6)
    assert m["trans_err_x100_barf"] == pytest.approx(trans_ref.mean(), abs=1e-6)
    assert trans_ref.min() > 0.1  # the moved camera pulls the alignment: every view is off
    # the alignment's rotation turns every view by the same angle (0.31 deg), well above the floor;
    # BARF's float32 reading scatters it by its step there, 0.0013 deg
    assert rot_ref.min() > 0.1
    assert (np.abs(np.array(m["rot_err_deg_barf_per_view"]) - rot_ref) <= _float32_resolution_deg(rot_ref)).all()
    np.testing.assert_allclose(m["sim3_barf"][1].numpy(), R_ref, atol=1e-12)


def test_camera_axis_flip_changes_nothing():
    gt, g = _random_rig(12, seed=2)
    est = C.perturb_poses(gt, 0.05, 0.05, generator=g)
    Ft = torch.from_numpy(F)

    def flip(c2w):  # same centres, camera axes x, -y, -z (OpenGL <-> OpenCV)
        return torch.cat([c2w[:, :, :3] @ Ft, c2w[:, :, 3:]], -1)

    a = C.barf_pose_errors(est, gt)
    b = C.barf_pose_errors(flip(est), flip(gt))
    assert min(a["rot_err_deg_barf_per_view"]) > 0.5 and min(a["trans_err_x100_barf_per_view"]) > 1.0
    np.testing.assert_allclose(b["rot_err_deg_barf_per_view"], a["rot_err_deg_barf_per_view"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b["trans_err_x100_barf_per_view"], a["trans_err_x100_barf_per_view"], rtol=0, atol=1e-9)
    # flipping only one side is not a no-op (the flip really reaches the metric): 180 deg per view
    c = C.barf_pose_errors(flip(est), gt)
    assert min(c["rot_err_deg_barf_per_view"]) > 170


def test_forward_facing_rig_agrees_with_evaluate_poses_without_reflection():
    gt, g = _forward_facing_rig(seed=0)
    # ~1 deg rotation noise about each camera's centre, 1e-3 translation noise
    est = C.perturb_poses(gt, math.radians(1.0), 1e-3, generator=g, frame="camera")
    m = C.barf_pose_errors(est, gt)
    e = C.evaluate_poses(est, gt, align="centres")
    assert np.isfinite(m["rot_err_deg_barf_per_view"]).all() and np.isfinite(m["trans_err_x100_barf_per_view"]).all()
    # precondition: no reflection, so BARF's sign fix and procrustes_sim3's Kabsch fix are not involved
    # (see the next test for when they are)
    assert not m["barf_reflection_fixed"]
    assert min(m["rot_err_deg_barf_per_view"]) > 0.2  # well above the floor
    assert abs(m["rot_err_deg_barf"] - e["rot_err_deg"]) < 0.05
    np.testing.assert_allclose(m["rot_err_deg_barf_per_view"], e["rot_err_deg_per_view"], rtol=0, atol=0.05)
    np.testing.assert_allclose(m["trans_err_x100_barf_per_view"], e["trans_err_x100_per_view"], rtol=0, atol=1e-6)


def test_forward_facing_rig_with_reflection_keeps_barfs_sign_fix():
    """World-frame noise moves the centres' depths by more than their jitter, and the best orthogonal
    fit of the centres is a reflection. BARF negates R's third row (reflection across the world xy
    plane); procrustes_sim3 reflects across the plane normal to u3, the gt-side singular vector of
    the smallest singular value. The two rotations differ by twice the angle between u3 and world z."""
    gt, g = _forward_facing_rig(seed=35)
    est = C.perturb_poses(gt, math.radians(1.0), 1e-3, generator=g, frame="world")
    m = C.barf_pose_errors(est, gt)
    e = C.evaluate_poses(est, gt, align="centres")
    assert m["barf_reflection_fixed"]  # precondition for this seed
    rot_b, trans_b, R_b = _numpy_barf(est.numpy(), gt.numpy())
    rot_k, trans_k, R_k = _numpy_barf(est.numpy(), gt.numpy(), kabsch=True)
    assert (np.abs(np.array(m["rot_err_deg_barf_per_view"]) - rot_b) <= _float32_resolution_deg(rot_b)).all()
    np.testing.assert_allclose(m["trans_err_x100_barf_per_view"], trans_b, rtol=0, atol=1e-6)
    np.testing.assert_allclose(e["rot_err_deg_per_view"], rot_k, rtol=0, atol=1e-9)
    np.testing.assert_allclose(e["trans_err_x100_per_view"], trans_k, rtol=0, atol=1e-6)
    # the two alignments' rotations differ by 2 * angle(u3, +-z)
    X0 = gt[:, :, 3].numpy() - gt[:, :, 3].numpy().mean(0)
    X1 = est[:, :, 3].numpy() - est[:, :, 3].numpy().mean(0)
    u3 = np.linalg.svd(X0.T @ X1)[0][:, 2]
    tilt = np.degrees(np.arccos(min(1.0, abs(u3[2]))))
    diff = float(C.rotation_error_deg(m["sim3_barf"][1], e["sim3"][1]))
    assert diff == pytest.approx(2 * tilt, abs=1e-6)
    assert diff > 0.1  # large enough to move views by more than the 0.05 deg of the previous test
    assert np.abs(rot_b - rot_k).max() > 0.05


def test_degenerate_centres_fall_back_to_identity():
    gt, g = _random_rig(8, seed=3)
    est = C.perturb_poses(gt, 0.05, 0.0, generator=g, frame="camera")
    est[:, :, 3] = 0.5  # every estimated centre the same point: s1 = 0, no alignment exists
    m = C.barf_pose_errors(est, gt)
    assert m["barf_svd_failed"]
    s, R, t = m["sim3_barf"]
    assert s == 1.0 and torch.equal(R, torch.eye(3, dtype=R.dtype)) and not t.any()
    # the errors are then those of the unaligned poses
    R_gt, R_est = gt[:, :, :3].numpy(), est[:, :, :3].numpy()
    rot = np.degrees(np.arccos(np.clip((np.trace(R_est.transpose(0, 2, 1) @ R_gt, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    trans = 100 * np.linalg.norm(np.einsum("nji,nj->ni", R_est, est[:, :, 3].numpy())
                                 - np.einsum("nji,nj->ni", R_gt, gt[:, :, 3].numpy()), axis=-1)
    assert (np.abs(np.array(m["rot_err_deg_barf_per_view"]) - rot) <= _float32_resolution_deg(rot)).all()
    np.testing.assert_allclose(m["trans_err_x100_barf_per_view"], trans, rtol=0, atol=1e-6)
