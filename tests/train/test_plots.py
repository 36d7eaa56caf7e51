"""Smoke tests for warpnerf.train.plots: each figure is written as a non-trivial PNG."""

import math
import subprocess
import sys

import pytest
import torch

pytest.importorskip("matplotlib")

from warpnerf.geometry import cameras as C  # noqa: E402
from warpnerf.train import plots  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path):
    with open(path, "rb") as f:
        data = f.read()
    return data[:8] == PNG_MAGIC and len(data) > 10_000  # an empty figure is ~5 kB


def test_import_warpnerf_does_not_import_matplotlib():
    code = "import sys, warpnerf, warpnerf.geometry.cameras, warpnerf.train.metrics, warpnerf.train.plots; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_plots_write_pngs(tmp_path):
    centres = torch.tensor([[4.0 * math.cos(a), 4.0 * math.sin(a), 1.5] for a in torch.linspace(0, 6, 8).tolist()])
    gt = C.look_at(centres)
    noisy = C.perturb_poses(gt, 0.15, 0.15, torch.Generator().manual_seed(0))
    est = C.evaluate_poses(noisy, gt)["c2w_aligned"]
    p1 = plots.plot_cameras(str(tmp_path / "cams.png"), gt, noisy, est, "toy")
    it = list(range(0, 100, 10))
    rot = [10.0 / (1 + i) for i in it]
    trans = [30.0 / (1 + i) for i in it]
    p2 = plots.plot_pose_error_curve(str(tmp_path / "err.png"), {"on": (it, rot, trans), "off": (it, trans, rot)})
    p3 = plots.plot_pose_error_curve(str(tmp_path / "err1.png"), it, rot, trans, label_suffix="G2fR")
    p4 = plots.plot_training_curves(str(tmp_path / "train.png"),
                                    {"iter": it, "loss": rot, "psnr": trans, "test psnr": [(50, 20.0), (90, 22.0)]})
    for p in (p1, p2, p3, p4):
        assert _is_png(p)


def test_pose_error_curve_draws_events(tmp_path):
    """``events`` (the re-registration passes) add a marked line to both panels: the image changes."""
    import imageio.v3 as iio

    it = list(range(0, 100, 10))
    rot = [10.0 / (1 + i) for i in it]
    trans = [30.0 / (1 + i) for i in it]
    plain = plots.plot_pose_error_curve(str(tmp_path / "plain.png"), it, rot, trans)
    marked = plots.plot_pose_error_curve(str(tmp_path / "marked.png"), it, rot, trans,
                                         events={50: "2 views re-registered"})
    a, b = iio.imread(plain), iio.imread(marked)
    assert a.shape == b.shape and _is_png(marked)
    changed = (a != b).any(-1)
    # the marker sits at iteration 50, mid-way along each panel's x axis: two separate columns of change
    cols = changed.any(0).nonzero()[0]
    assert changed.sum() > 100 and cols.min() < a.shape[1] // 2 < cols.max(), cols
