"""docs/analysis/pose_offset.py: the camera-frame errors it reports."""

import importlib.util
import math
import os

import torch

from warpnerf import cameras as C

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load():
    spec = importlib.util.spec_from_file_location("pose_offset", os.path.join(ROOT, "docs", "analysis", "pose_offset.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _hemisphere(n=16):
    g = torch.Generator().manual_seed(0)
    az = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    el = torch.rand(n, generator=g, dtype=torch.float64) * 1.2 + 0.1
    return C.look_at(4.0 * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1))


def test_camera_frame_errors_recover_a_shared_offset():
    po = _load()
    gt = _hemisphere()
    # every camera moved by -0.01 along its own y axis in w2c terms, and pitched by 0.02 degrees
    w2c = C.invert(gt)
    pitch = C.rotation_about_axis((1.0, 0.0, 0.0), math.radians(0.02), dtype=torch.float64)
    shifted = torch.cat([pitch @ w2c[:, :, :3], pitch @ w2c[:, :, 3:] + torch.tensor([0.0, -0.01, 0.0],
                                                                                   dtype=torch.float64)[:, None]], -1)
    dt, w = po.camera_frame_errors(C.invert(shifted), gt)
    # t = pitch @ t_gt + offset: the offset plus the pitch turning t_gt = (0, 0, -4)
    expect_t = 100 * ((pitch @ w2c[:, :, 3:])[:, :, 0] - w2c[:, :, 3] + torch.tensor([0.0, -0.01, 0.0], dtype=torch.float64))
    torch.testing.assert_close(dt, expect_t, atol=1e-9, rtol=0)
    assert abs(dt.mean(0)[1].item() - 100 * (-0.01 + 4 * math.sin(math.radians(0.02)))) < 1e-6
    # rotation errors are log(R_gt^T R) of the camera-to-world rotations: turning w2c by +0.02 degrees
    # about x turns c2w by -0.02
    torch.testing.assert_close(w, torch.tensor([-0.02, 0.0, 0.0], dtype=torch.float64).expand_as(w), atol=1e-9, rtol=0)
