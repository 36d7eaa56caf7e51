"""The paper's comparison as Markdown tables and plots, from sweep results (``RunResult``s).

``<out>/table.md`` is shaped like the paper's Tab. 1 (pose: rotation error, translation error x100,
PSNR, with BARF's published row) and Tab. 3 (few-shot: PSNR, SSIM, LPIPS), with the paper's own
numbers (:mod:`warpnerf.studies.paper`) in brackets where the paper reports the scene. Rendering
only: the sweep (:mod:`warpnerf.studies.sweep`) writes these after its runs, and ``warpnerf table``
(:mod:`warpnerf.studies.table`) is a sweep with both arms.
"""

from __future__ import annotations

import os
import statistics
from typing import Optional

from warpnerf.geometry.cameras import describe_unconverged
from warpnerf.studies.paper import barf_numbers, paper_numbers
from warpnerf.train import plots

TRANS_NOTE = ("translation error x100 is BARF's quantity: mean over views of 100 x |t_w2c(aligned) - t_w2c(gt)| "
              "after the Sim(3) alignment of camera centres (`trans_err_x100`), as in the paper")

COLUMNS = {
    "pose": [("rot_err_deg", "rot. err (deg)", "{:.3f}"), ("trans_err_x100", "trans. err (x100, BARF)", "{:.3f}"),
             ("psnr", "PSNR", "{:.2f}")],
    "fewshot": [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.3f}"), ("lpips", "LPIPS", "{:.3f}")],
    "full": [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.3f}"), ("lpips", "LPIPS", "{:.3f}")],
}
TITLES = {"pose": "Camera-pose optimisation (cf. paper Tab. 1)", "fewshot": "Few-shot reconstruction (cf. paper Tab. 3)",
          "full": "Full reconstruction"}
MODEL_NAMES = {"ngp": "NGP (hash grid)", "mtrf": "Mtrf (multi-resolution CP)"}


def format_table(task: str, rows: dict, model: str = "ngp") -> str:
    """rows: scene -> {"w/": metrics, "w/o": metrics}. Paper numbers sit in brackets where known
    (only for dataset scenes: a built-in scene of the same name is a different scene). The pose
    table ends with the paper's BARF row for the scene (rot / trans / PSNR)."""
    cols = COLUMNS[task]
    head = ["scene"] + [f"{label} {arm}" for _, label, _ in cols for arm in ("w/ G2fR", "w/o")]
    if task == "pose":
        head.append("BARF (paper): rot / trans / PSNR")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, arms in rows.items():
        builtin = any(m.get("scene_source") == "builtin" for m in arms.values())
        paper = {} if builtin else paper_numbers(scene, task, model)
        cells = [scene]
        for key, _, fmt in cols:
            for arm in ("w/", "w/o"):
                ours = arms.get(arm, {}).get(key)
                cell = "n/a" if ours is None else fmt.format(ours)
                if arm in paper and key in paper[arm]:
                    cell += f" ({fmt.format(paper[arm][key])})"
                cells.append(cell)
        if task == "pose":
            barf = {} if builtin else barf_numbers(scene, task)
            cells.append(" / ".join(fmt.format(barf[k]) for k, _, fmt in cols) if barf else "")
        lines.append("| " + " | ".join(cells) + " |")
    if task == "pose":  # a view stuck far off dominates a mean: name it, with the medians
        for scene, arms in rows.items():
            if any(m.get("pose_alignment") == "orientations" for m in arms.values()):
                lines.append(f"\n{scene}: forward-facing, so the alignment's rotation is fitted to the cameras' "
                             "orientations, not their centres (docs/studies/2026-12-07-pose-forward-facing.md): "
                             "not comparable with BARF's figures")
            for arm, m in arms.items():
                stuck = describe_unconverged(m)
                if stuck:
                    lines.append(f"\n{scene} {arm} G2fR: {stuck}")
    return "\n".join(lines)


def plot_pose_comparison(path: str, scene: str, arms: dict) -> None:
    """Rotation and translation error over iterations, with and without G²fR, in one figure."""
    curves = {}
    for arm, label in (("w/", "w/ G2fR"), ("w/o", "w/o G2fR")):
        hist = arms.get(arm, {}).get("pose_error_history")
        if hist:
            curves[label] = (hist["step"], hist["rot_err_deg"], hist["trans_err_x100"])
    if curves:
        plots.plot_pose_error_curve(path, curves, title=f"{scene}: pose error during training (translation: BARF's)")


def heldout_gap(arms: dict) -> Optional[tuple[int, float, float, float]]:
    """Where the held-out PSNR of the G²fR arm leads the baseline most: ``(step, gap_db, w_db, wo_db)``
    over the steps both arms measured (``heldout_history`` in metrics.json), or None."""
    w = {int(s): v for s, v in arms.get("w/", {}).get("heldout_history") or []}
    wo = {int(s): v for s, v in arms.get("w/o", {}).get("heldout_history") or []}
    common = sorted(set(w) & set(wo))
    if not common:
        return None
    step = max(common, key=lambda s: w[s] - wo[s])
    return step, w[step] - wo[step], w[step], wo[step]


def plot_heldout_comparison(path: str, scene: str, arms: dict) -> bool:
    """Held-out PSNR over iterations, with and without G²fR, in one figure; False if no history."""
    curves = {}
    for arm, label in (("w/", "w/ G2fR"), ("w/o", "w/o G2fR")):
        hist = arms.get(arm, {}).get("heldout_history")
        if hist:
            curves[label] = ([s for s, _ in hist], [v for _, v in hist])
    if not curves:
        return False
    plots.plot_heldout_curves(path, curves, title=f"{scene}: held-out PSNR during training")
    return True


def _mean_over_seeds(metrics: list[dict]) -> dict:
    """Numeric metrics averaged over seeds; everything else from the first seed."""
    out = dict(metrics[0])
    for key, value in metrics[0].items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            vals = [m.get(key) for m in metrics]
            if all(isinstance(v, (int, float)) for v in vals):
                out[key] = sum(vals) / len(vals)
    return out


def seed_gaps(group: list, scene: str, key: str = "psnr") -> list[tuple[int, float]]:
    """``(seed, w/ - w/o)`` of ``key`` for every seed where both arms of ``scene`` finished, in seed
    order: the paired differences, which a mean over seeds hides (is the gap bigger than the
    seed-to-seed spread?)."""
    by_seed: dict = {}
    for r in group:
        if r.run.scene == scene and r.metrics and isinstance(r.metrics.get(key), (int, float)):
            by_seed.setdefault(r.run.seed, {})[r.run.arm] = r.metrics[key]
    return [(seed, arms["g2fr"] - arms["nog2fr"]) for seed, arms in sorted(by_seed.items())
            if "g2fr" in arms and "nog2fr" in arms]


def format_seed_gaps(scene: str, gaps: list[tuple[int, float]], key: str = "psnr") -> str:
    """One sentence: the per-seed gaps, their mean and sample standard deviation."""
    values = [g for _, g in gaps]
    per_seed = ", ".join(f"{g:+.2f} (seed {s})" for s, g in gaps)
    return (f"{scene}: {key.upper()} w/ - w/o per seed {per_seed}; mean {statistics.mean(values):+.2f}, "
            f"std {statistics.stdev(values):.2f}.")


def _ran_on(results: list) -> str:
    """Where the runs ran, from the runs themselves (device, threads, machine), not assumed."""
    seen = []
    for r in results:
        m = r.metrics or {}
        if not m:
            continue
        dev = f"{m.get('device', '?')}" + (f", {m['threads']} Warp threads" if m.get("device") == "cpu" and
                                           m.get("threads") else "")
        text = f"{dev} on {r.machine}" if r.machine else dev
        if text not in seen:
            seen.append(text)
    return "; ".join(seen) if seen else "no finished run"


def tables_markdown(results: list) -> str:
    """Markdown sections, one per (task, model), from sweep ``RunResult``s (done or skipped)."""
    sections = []
    keys = []
    for r in results:
        k = (r.run.task, r.run.model)
        if k not in keys:
            keys.append(k)
    for task, model in keys:
        group = [r for r in results if (r.run.task, r.run.model) == (task, model)]
        rows: dict = {}
        for scene in dict.fromkeys(r.run.scene for r in group):
            rows[scene] = {}
            for arm, label in (("g2fr", "w/"), ("nog2fr", "w/o")):
                ms = [r.metrics for r in group if r.run.scene == scene and r.run.arm == arm and r.metrics]
                if ms:
                    rows[scene][label] = _mean_over_seeds(ms)
        finished = [r for r in group if r.metrics]
        seeds = sorted({r.run.seed for r in finished})
        iters = sorted({r.metrics.get("iters") for r in finished if r.metrics.get("iters") is not None})
        failed = [r.run.name for r in group if r.status == "failed"]
        note = (f"Ours (paper in brackets), model {MODEL_NAMES.get(model, model)}, seed{'s' if len(seeds) > 1 else ''} "
                f"{', '.join(map(str, seeds)) or 'none'}{' (mean)' if len(seeds) > 1 else ''}, iterations "
                f"{', '.join(map(str, iters)) or 'n/a'}; ran on {_ran_on(finished)}.")
        if task == "pose":
            note += f" The {TRANS_NOTE}."
        if task == "fewshot":
            for scene, arms in rows.items():
                gap = heldout_gap(arms)
                if gap:
                    first = f" (seed {seeds[0]})" if len(seeds) > 1 else ""  # the histories are the first seed's
                    note += (f" {scene}{first}: the held-out PSNR gap w/ - w/o is largest at step {gap[0] + 1}: "
                             f"{gap[1]:+.2f} dB ({gap[2]:.2f} vs {gap[3]:.2f}).")
        if len(seeds) > 1:
            for scene in rows:
                gaps = seed_gaps(group, scene)
                if len(gaps) > 1:
                    note += " " + format_seed_gaps(scene, gaps)
        if failed:
            note += f" Failed runs (n/a): {', '.join(failed)}."
        sections.append(f"### {TITLES.get(task, task)}, {model}\n\n{note}\n\n{format_table(task, rows, model)}\n")
    return "\n".join(sections)


def write_tables(spec, results: list) -> str:
    """``<out>/table.md``, for pose runs ``<out>/<scene>_<model>_pose_error.png`` and for few-shot runs
    ``<out>/<scene>_<model>_fewshot_heldout.png``; returns the Markdown."""
    text = tables_markdown(results)
    for r in results:
        if r.run.task == "fewshot" and r.run.arm == "g2fr" and r.run.seed == min(spec.seeds):
            arms = {label: next((o.metrics for o in results if o.metrics and o.run.task == "fewshot"
                                 and o.run.scene == r.run.scene and o.run.model == r.run.model
                                 and o.run.seed == r.run.seed and o.run.arm == arm), {})
                    for arm, label in (("g2fr", "w/"), ("nog2fr", "w/o"))}
            plot_heldout_comparison(os.path.join(spec.out, f"{r.run.scene}_{r.run.model}_fewshot_heldout.png"),
                                    r.run.scene, arms)
        if r.run.task == "pose" and r.run.arm == "g2fr" and r.run.seed == min(spec.seeds):
            arms = {label: next((o.metrics for o in results if o.metrics and o.run.task == "pose"
                                 and o.run.scene == r.run.scene and o.run.model == r.run.model
                                 and o.run.seed == r.run.seed and o.run.arm == arm), {})
                    for arm, label in (("g2fr", "w/"), ("nog2fr", "w/o"))}
            plot_pose_comparison(os.path.join(spec.out, f"{r.run.scene}_{r.run.model}_pose_error.png"), r.run.scene,
                                 arms)
    tmp = os.path.join(spec.out, "table.md.tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, os.path.join(spec.out, "table.md"))
    return text
