"""Figures for the pose and training experiments (PNG files).

matplotlib is imported inside the functions, and figures are built with
``matplotlib.figure.Figure`` (rendered by the Agg canvas) rather than pyplot, so importing
warpnerf never imports matplotlib and no global backend or pyplot state is touched.
"""

from __future__ import annotations

import os
from typing import Mapping, Optional, Sequence

import numpy as np

# Colours shared by the camera and error plots (colour-blind-safe Okabe-Ito picks).
_GT = "#000000"
_NOISY = "#D55E00"
_EST = "#0072B2"
_RUN_COLOURS = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9"]


def _figure(figsize):
    from matplotlib.figure import Figure  # lazy: matplotlib costs ~0.5 s; tasks import this module for --help

    return Figure(figsize=figsize, dpi=110, layout="constrained")


def _save(fig, path: str) -> str:
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fig.savefig(path)
    return path


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _frustum_segments(c2w: np.ndarray, size: float) -> np.ndarray:
    """Line segments (N*8, 2, 3) of a small pyramid per camera: apex at the centre, base a
    rectangle at depth ``size`` along the viewing direction -z (OpenGL), with a 4:3 aspect."""
    R, c = c2w[:, :, :3], c2w[:, :, 3]
    hw, hh = 0.5 * size, 0.375 * size
    corners_cam = np.array([[-hw, -hh, -size], [hw, -hh, -size], [hw, hh, -size], [-hw, hh, -size]])
    corners = np.einsum("nij,kj->nki", R, corners_cam) + c[:, None]  # (N, 4, 3)
    segs = []
    for k in range(4):
        segs.append(np.stack([c, corners[:, k]], 1))
        segs.append(np.stack([corners[:, k], corners[:, (k + 1) % 4]], 1))
    return np.concatenate(segs, 0)


def plot_cameras(path: str, gt_c2w, noisy_c2w=None, est_c2w_aligned=None, title: str = "") -> str:
    """3-D view of camera poses: ground truth (black), noisy start (orange), optimised and
    Sim(3)-aligned estimate (blue), with a red line from each estimated centre to its ground truth.

    gt_c2w, noisy_c2w, est_c2w_aligned: (N, 3, 4) c2w (torch or numpy), OpenGL convention; the
    last two may be None. Each camera is drawn as its centre plus a small frustum pointing along
    its viewing direction. Writes a PNG to ``path`` and returns the path.
    """
    from matplotlib.lines import Line2D  # lazy: see _figure
    from mpl_toolkits.mplot3d.art3d import Line3DCollection  # lazy: see _figure

    sets = [("ground truth", _np(gt_c2w), _GT)]
    if noisy_c2w is not None:
        sets.append(("noisy initialisation", _np(noisy_c2w), _NOISY))
    if est_c2w_aligned is not None:
        sets.append(("optimised (aligned)", _np(est_c2w_aligned), _EST))

    gt = sets[0][1]
    centres = np.concatenate([s[1][:, :, 3] for s in sets], 0)
    lo, hi = centres.min(0), centres.max(0)
    extent = float(max((hi - lo).max(), 1e-6))
    size = 0.06 * extent  # frustum depth relative to the rig size, so any scene scale reads well

    fig = _figure((7.5, 7))
    ax = fig.add_subplot(projection="3d")
    handles = []
    for label, c2w, colour in sets:
        ax.add_collection3d(Line3DCollection(_frustum_segments(c2w, size), colors=colour, linewidths=0.8, alpha=0.8))
        ax.scatter(*c2w[:, :, 3].T, color=colour, s=10, depthshade=False)
        handles.append(Line2D([], [], color=colour, marker="o", markersize=4, label=label))
    if est_c2w_aligned is not None:
        est = _np(est_c2w_aligned)
        err = np.stack([est[:, :, 3], gt[:, :, 3]], 1)
        ax.add_collection3d(Line3DCollection(err, colors="#E41A1C", linewidths=1.2))
        handles.append(Line2D([], [], color="#E41A1C", label="estimate -> ground truth"))

    # Equal scale on all axes so that rotations look like rotations.
    mid = 0.5 * (lo + hi)
    half = 0.5 * extent + size
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (scene units)")
    ax.set_ylabel("y (scene units)")
    ax.set_zlabel("z (scene units)")
    ax.legend(handles=handles, loc="upper left")
    if title:
        ax.set_title(title)
    return _save(fig, path)


def plot_pose_error_curve(
    path: str,
    iters,
    rot_err_deg=None,
    trans_err_x100=None,
    label_suffix: str = "",
    title: str = "",
    log_y: bool = True,
    rot_label: str | None = None,
    events: Mapping[int, str] | None = None,
) -> str:
    """Pose error against training iteration: rotation (degrees) and translation (x100) panels.

    Either one run, ``plot_pose_error_curve(path, iters, rot_err_deg, trans_err_x100)``, labelled
    by ``label_suffix``, or several overlaid runs (e.g. G²fR on / off):
    ``plot_pose_error_curve(path, {"G²fR": (iters, rot, trans), "no mask": (...)})``.
    Sequences are 1-D (same length within a run). Log y axis by default, since the errors fall
    by orders of magnitude. ``rot_label``: the rotation panel's axis label (e.g. for the error
    without alignment). ``events``: iteration -> short text, drawn as a dotted vertical line in both
    panels (e.g. the views re-registered at that step). Returns the path.
    """
    if isinstance(iters, Mapping):
        runs = {k: v for k, v in iters.items()}
        if label_suffix:
            runs = {f"{k} {label_suffix}": v for k, v in runs.items()}
    else:
        if rot_err_deg is None or trans_err_x100 is None:
            raise ValueError("give iters, rot_err_deg and trans_err_x100, or a dict of runs")
        runs = {label_suffix or "run": (iters, rot_err_deg, trans_err_x100)}

    fig = _figure((10, 4))
    ax_r, ax_t = fig.subplots(1, 2)
    for i, (label, (it, rot, trans)) in enumerate(runs.items()):
        colour = _RUN_COLOURS[i % len(_RUN_COLOURS)]
        ax_r.plot(_np(it), _np(rot), color=colour, label=label)
        ax_t.plot(_np(it), _np(trans), color=colour, label=label)
    for ax in (ax_r, ax_t):
        for step, text in (events or {}).items():
            ax.axvline(step, color="0.4", linestyle=":", linewidth=1)
            ax.annotate(text, (step, 0.97), xycoords=("data", "axes fraction"), xytext=(2, 0),
                        textcoords="offset points", ha="left", va="top", rotation=90, fontsize=7, color="0.3")
    for ax, name in ((ax_r, rot_label or "rotation error (degrees)"), (ax_t, "translation error (BARF, w2c, x100)")):
        ax.set_xlabel("iteration")
        ax.set_ylabel(name)
        if log_y:
            ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_heldout_curves(path: str, runs: Mapping[str, tuple], title: str = "") -> str:
    """Held-out PSNR against training iteration for several runs (e.g. few-shot with and without
    G²fR): ``runs`` maps a label to ``(iterations, psnr_db)``. Returns the path."""
    fig = _figure((6.5, 4))
    ax = fig.subplots()
    for i, (label, (it, psnr)) in enumerate(runs.items()):
        ax.plot(_np(it), _np(psnr), marker="o", markersize=3, color=_RUN_COLOURS[i % len(_RUN_COLOURS)], label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    return _save(fig, path)


def plot_band_curves(path: str, panels: Mapping[str, Mapping[str, tuple]], xlabel: str, ylabel: str,
                     title: str = "") -> str:
    """One panel per entry of ``panels`` (panel title -> {label: (x, mean, std)}): each label's mean
    curve with a band of +-1 std (e.g. PSNR against epochs over seeds). Returns the path."""
    n = max(len(panels), 1)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = _figure((5.0 * cols, 4.0 * rows))
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax, (panel, curves) in zip(axes, panels.items()):
        for i, (label, (x, mean, std)) in enumerate(curves.items()):
            colour, style = _RUN_COLOURS[i % len(_RUN_COLOURS)], ("-", "--", ":")[i // len(_RUN_COLOURS) % 3]
            x, mean, std = _np(x), _np(mean), _np(std)
            ax.plot(x, mean, style, marker="o", markersize=2.5, color=colour, label=label)
            ax.fill_between(x, mean - std, mean + std, color=colour, alpha=0.2, linewidth=0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
        ax.set_title(panel, fontsize=9)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def _series(values, x_default: Optional[np.ndarray]):
    """(x, y) for one history entry: a list of numbers (x = the shared iteration axis when the
    lengths match, else 0..n-1) or a list of (iteration, value) pairs."""
    arr = _np(values) if len(values) else np.zeros(0)
    if arr.ndim == 2 and arr.shape[1] == 2:
        return arr[:, 0], arr[:, 1]
    if x_default is not None and len(x_default) == len(arr):
        return x_default, arr
    return np.arange(len(arr)), arr


def plot_training_curves(path: str, history: Mapping[str, Sequence], title: str = "") -> str:
    """One panel per metric of a training log, against iteration.

    history: name -> list of values. An entry named "iter", "iteration" or "step" is the shared
    x axis for entries of the same length; an entry may instead be a list of (iteration, value)
    pairs (e.g. a test PSNR measured every k steps). Names containing "loss" or "mse" get a log
    y axis. Units are read from the name, e.g. "psnr (dB)". Returns the path.
    """
    x_key = next((k for k in ("iter", "iteration", "step") if k in history), None)
    x_default = _np(history[x_key]) if x_key else None
    names = [k for k in history if k != x_key]
    if not names:
        raise ValueError("history has no metric to plot")
    ncol = min(3, len(names))
    nrow = (len(names) + ncol - 1) // ncol
    fig = _figure((4.2 * ncol, 3.2 * nrow))
    axes = np.atleast_1d(fig.subplots(nrow, ncol)).ravel()
    for ax, name in zip(axes, names):
        x, y = _series(history[name], x_default)
        ax.plot(x, y, color=_EST, marker="o" if len(y) < 30 else None, markersize=3)
        ax.set_xlabel("iteration")
        label = name
        if "psnr" in name.lower() and "db" not in name.lower():
            label = f"{name} (dB)"
        ax.set_ylabel(label)
        ax.set_title(name)
        if any(s in name.lower() for s in ("loss", "mse")) and len(y) and np.all(y > 0):
            ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[len(names):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


__all__ = ["plot_cameras", "plot_pose_error_curve", "plot_training_curves"]
