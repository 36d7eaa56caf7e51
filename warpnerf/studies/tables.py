"""The paper's comparison as Markdown tables and plots, from sweep results (``RunResult``s).

``<out>/table.md`` is shaped like the paper's Tab. 1 (pose: rotation error, translation error x100,
PSNR, with BARF's published row) and Tab. 3 (few-shot: PSNR, SSIM, LPIPS), with the paper's own
numbers (:mod:`warpnerf.studies.paper`) in brackets where the paper reports the scene; a built-in
scene is named as warpnerf's procedural scene and gets none. The few-shot table has a row per
(scene, view set), cells ``mean ± std`` over seeds, and per masked arm the paired PSNR gap to the
arm without G²fR. Rendering only: the sweep (:mod:`warpnerf.studies.sweep`) writes these after its
runs, and ``warpnerf table`` (:mod:`warpnerf.studies.table`) is a sweep.
"""

from __future__ import annotations

import os
import statistics
from typing import Optional

from warpnerf.geometry.cameras import describe_unconverged
from warpnerf.studies.paper import METRIC_COLUMNS, MIPNERF360, NERF_SYNTHETIC, barf_numbers, paper_key, paper_numbers
from warpnerf.train import plots

TRANS_NOTE = ("translation error x100 is BARF's quantity: mean over views of 100 x |t_w2c(aligned) - t_w2c(gt)| "
              "after the Sim(3) alignment of camera centres (`trans_err_x100`), as in the paper")

# (metrics key, label, format) of each task's columns: the one definition in paper.py, as format strings
COLUMNS = {task: [(key, label, f"{{:.{digits}f}}") for key, label, digits in cols]
           for task, cols in METRIC_COLUMNS.items()}
TITLES = {"pose": "Camera-pose optimisation (cf. paper Tab. 1)", "fewshot": "Few-shot reconstruction (cf. paper Tab. 3)",
          "full": "Full reconstruction"}
MODEL_NAMES = {"ngp": "NGP (hash grid)", "mtrf": "Mtrf (multi-resolution CP)"}

# sweep arms in table order: column label, label in a gap column, key of the paper's numbers
ARM_ORDER = ("g2fr", "adaptive", "heldout", "nog2fr")
ARM_LABELS = {"g2fr": "w/ G2fR (fixed β)", "adaptive": "w/ G2fR (adaptive)", "heldout": "w/ G2fR (held-out)",
              "nog2fr": "w/o"}
GAP_LABELS = {"g2fr": "fixed β", "adaptive": "adaptive", "heldout": "held-out"}
# the arms of the schedules that need no budget: a row key and a label in the per-scene tables and seed notes
BUDGETLESS = (("adaptive", "w/ adaptive"), ("heldout", "w/ held-out"))
PAPER_ARMS = {"g2fr": "w/", "nog2fr": "w/o"}
BASELINE = "nog2fr"
VIEW_SET_NOTES = {"fps": "fps (farthest-point over camera centres: the same views for every seed)",
                  "random": "random (views drawn with each seed)"}


def scene_label(scene: str, builtin: bool) -> str:
    """The scene cell: a built-in scene is warpnerf's procedural scene, not the dataset scene of its name."""
    if not builtin:
        return scene
    dataset = ("NeRF-synthetic" if scene.lower() in NERF_SYNTHETIC else
               "Mip-NeRF 360" if scene.lower() in MIPNERF360 else None)
    return f"{scene} (built-in procedural, not {dataset} {scene})" if dataset else f"{scene} (built-in procedural)"


def _row_arms(rows: dict) -> list[tuple[str, str]]:
    """(row key, column label) of the arms of a per-scene table: w/ and w/o always, adaptive and held-out when
    present."""
    extra = [(arm, ARM_LABELS[arm]) for arm, _ in BUDGETLESS if any(arm in arms for arms in rows.values())]
    if not extra:
        return [("w/", "w/ G2fR"), ("w/o", "w/o")]
    return [("w/", ARM_LABELS["g2fr"]), *extra, ("w/o", "w/o")]


def format_table(task: str, rows: dict, model: str = "ngp") -> str:
    """rows: scene -> {"w/": metrics, "w/o": metrics} (and "adaptive", "heldout": metrics of those arms). Paper
    numbers sit in brackets where known (only for dataset scenes: a built-in scene of the same name
    is a different scene, and its cell says so). The pose table ends with the paper's BARF row for
    the scene (rot / trans / PSNR)."""
    cols = COLUMNS[task]
    arm_cols = _row_arms(rows)
    head = ["scene"] + [f"{label} {arm_label}" for _, label, _ in cols for _, arm_label in arm_cols]
    if task == "pose":
        head.append("BARF (paper): rot / trans / PSNR")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, arms in rows.items():
        builtin = any(m.get("scene_source") == "builtin" for m in arms.values())
        paper = {} if builtin else paper_numbers(scene, task, model)
        cells = [scene_label(scene, builtin)]
        for key, _, fmt in cols:
            for arm, _ in arm_cols:
                ours = arms.get(arm, {}).get(key)
                cell = "n/a" if ours is None else fmt.format(ours)
                pkey = paper_key(key)
                if arm in paper and pkey in paper[arm]:
                    cell += f" ({fmt.format(paper[arm][pkey])})"
                cells.append(cell)
        if task == "pose":
            barf = {} if builtin else barf_numbers(scene, task)
            cells.append(" / ".join(fmt.format(barf[k]) for k, _, fmt in cols if k in barf) if barf else "")
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


# ----------------------------------------------------------------------------- few-shot: rows per view set

def _by_seed(runs: list, arm: str, key: str) -> dict[int, float]:
    """seed -> ``key`` of the finished runs of ``arm`` among ``runs`` (one table row)."""
    return {r.run.seed: r.metrics[key] for r in runs
            if r.run.arm == arm and r.metrics and isinstance(r.metrics.get(key), (int, float))}


def mean_std(values: list[float], fmt: str) -> str:
    """One value as is; several as ``mean ± sample std``; none as n/a."""
    if not values:
        return "n/a"
    if len(values) == 1:
        return fmt.format(values[0])
    return f"{fmt.format(statistics.mean(values))} ± {fmt.format(statistics.stdev(values))}"


def paired_gaps(runs: list, arm: str, key: str = "psnr") -> list[float]:
    """``arm - w/o`` of ``key`` for each seed (in seed order) where both finished."""
    masked, base = _by_seed(runs, arm, key), _by_seed(runs, BASELINE, key)
    return [masked[s] - base[s] for s in sorted(masked) if s in base]


def format_gap(gaps: list[float]) -> str:
    """``mean ± std (k/n)``: the paired gaps' mean and sample std, and in k of n seeds arm >= w/o."""
    if not gaps:
        return "n/a"
    spread = f" ± {statistics.stdev(gaps):.2f}" if len(gaps) > 1 else ""
    return f"{statistics.mean(gaps):+.2f}{spread} ({sum(g >= 0 for g in gaps)}/{len(gaps)})"


def fewshot_table(group: list, model: str = "ngp") -> str:
    """Tab. 3 from few-shot ``RunResult``s: a row per (scene, view set), a column per metric and arm
    present, then per masked arm the paired PSNR gap to w/o. Paper numbers in brackets for dataset scenes."""
    arms = [a for a in ARM_ORDER if any(r.run.arm == a for r in group)]
    masked = [a for a in arms if a != BASELINE] if BASELINE in arms else []
    cols = COLUMNS["fewshot"]
    head = (["scene", "view set"] + [f"{label} {ARM_LABELS[a]}" for _, label, _ in cols for a in arms]
            + [f"PSNR gap {GAP_LABELS[a]} - w/o (seeds >= w/o)" for a in masked])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, view_set in dict.fromkeys((r.run.scene, r.run.view_set) for r in group):
        runs = [r for r in group if (r.run.scene, r.run.view_set) == (scene, view_set)]
        builtin = any((r.metrics or {}).get("scene_source") == "builtin" for r in runs)
        paper = {} if builtin else paper_numbers(scene, "fewshot", model)
        cells = [scene_label(scene, builtin), view_set or "-"]
        for key, _, fmt in cols:
            for arm in arms:
                cell = mean_std(list(_by_seed(runs, arm, key).values()), fmt)
                published = paper.get(PAPER_ARMS.get(arm), {}).get(key)
                cells.append(cell if published is None else f"{cell} ({fmt.format(published)})")
        cells += [format_gap(paired_gaps(runs, arm)) for arm in masked]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _heldout_sentence(runs: list, scene: str, view_set: Optional[str]) -> str:
    """Where w/ G2fR (fixed β) leads w/o most in held-out PSNR, for the first seed with both histories."""
    for seed in sorted({r.run.seed for r in runs}):
        pair = {label: next((r.metrics for r in runs if r.metrics and r.run.seed == seed and r.run.arm == arm), {})
                for arm, label in (("g2fr", "w/"), (BASELINE, "w/o"))}
        gap = heldout_gap(pair)
        if gap:
            return (f" {scene} {view_set} (seed {seed}): the held-out PSNR gap w/ (fixed β) - w/o is largest at "
                    f"step {gap[0] + 1}: {gap[1]:+.2f} dB ({gap[2]:.2f} vs {gap[3]:.2f}).")
    return ""


def fewshot_note(group: list, model: str) -> str:
    """What the few-shot table shows: model, view sets, seeds, that the arms are paired, where it ran."""
    finished = [r for r in group if r.metrics]
    seeds = sorted({r.run.seed for r in finished})
    view_sets = list(dict.fromkeys(r.run.view_set for r in group))
    note = (f"Ours (paper in brackets), model {MODEL_NAMES.get(model, model)}; view sets "
            f"{', '.join(VIEW_SET_NOTES.get(v, str(v)) for v in view_sets)}; seed{'s' if len(seeds) > 1 else ''} "
            f"{', '.join(map(str, seeds)) or 'none'}")
    if len(seeds) > 1:
        note += (" (cells: mean ± sample std over the seeds that finished; gaps: mean ± std of the per-seed "
                 "PSNR differences, and in how many seeds the masked arm was >= w/o)")
    note += (f"; iterations {_iters(finished)}; ran on {_ran_on(finished)}. The arms are paired: in a row, the "
             "arms of a seed train on the same views with the same seed and differ only in G2fR.")
    if any(r.metrics.get("scene_source") == "builtin" for r in finished):
        note += " Built-in scenes are warpnerf's procedural renders, not the paper's datasets: no paper numbers."
    for scene, view_set in dict.fromkeys((r.run.scene, r.run.view_set) for r in group):
        note += _heldout_sentence([r for r in group if (r.run.scene, r.run.view_set) == (scene, view_set)],
                                  scene, view_set)
    return note


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


def seed_gaps(group: list, scene: str, key: str = "psnr", arm: str = "g2fr") -> list[tuple[int, float]]:
    """``(seed, arm - w/o)`` of ``key`` for every seed where both arms of ``scene`` finished, in seed
    order: the paired differences, which a mean over seeds hides (is the gap bigger than the
    seed-to-seed spread?)."""
    runs = [r for r in group if r.run.scene == scene]
    masked, base = _by_seed(runs, arm, key), _by_seed(runs, BASELINE, key)
    return [(seed, masked[seed] - base[seed]) for seed in sorted(masked) if seed in base]


def format_seed_gaps(scene: str, gaps: list[tuple[int, float]], key: str = "psnr", arm_label: str = "w/") -> str:
    """One sentence: the per-seed gaps, their mean and sample standard deviation."""
    values = [g for _, g in gaps]
    per_seed = ", ".join(f"{g:+.2f} (seed {s})" for s, g in gaps)
    return (f"{scene}: {key.upper()} {arm_label} - w/o per seed {per_seed}; mean {statistics.mean(values):+.2f}, "
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


def _iters(finished: list) -> str:
    iters = sorted({r.metrics.get("iters") for r in finished if r.metrics.get("iters") is not None})
    return ", ".join(map(str, iters)) or "n/a"


def _scene_rows(group: list) -> dict:
    """scene -> {"w/" | "adaptive" | "heldout" | "w/o": metrics averaged over seeds} (pose and full tables)."""
    rows: dict = {}
    for scene in dict.fromkeys(r.run.scene for r in group):
        rows[scene] = {}
        for arm, label in (("g2fr", "w/"), *((a, a) for a, _ in BUDGETLESS), ("nog2fr", "w/o")):
            ms = [r.metrics for r in group if r.run.scene == scene and r.run.arm == arm and r.metrics]
            if ms:
                rows[scene][label] = _mean_over_seeds(ms)
    return rows


def scene_section(task: str, model: str, group: list) -> tuple[str, str]:
    """(note, table) of a pose or full table: a row per scene, cells averaged over seeds."""
    rows = _scene_rows(group)
    finished = [r for r in group if r.metrics]
    seeds = sorted({r.run.seed for r in finished})
    note = (f"Ours (paper in brackets), model {MODEL_NAMES.get(model, model)}, seed{'s' if len(seeds) > 1 else ''} "
            f"{', '.join(map(str, seeds)) or 'none'}{' (mean)' if len(seeds) > 1 else ''}, iterations "
            f"{_iters(finished)}; ran on {_ran_on(finished)}.")
    if task == "pose":
        note += f" The {TRANS_NOTE}."
    if len(seeds) > 1:
        for scene in rows:
            for arm, label in (("g2fr", "w/"), *BUDGETLESS):
                gaps = seed_gaps(group, scene, arm=arm)
                if len(gaps) > 1:
                    note += " " + format_seed_gaps(scene, gaps, arm_label=label)
    return note, format_table(task, rows, model)


def tables_markdown(results: list) -> str:
    """Markdown sections, one per (task, model), from sweep ``RunResult``s (done or skipped)."""
    sections = []
    for task, model in dict.fromkeys((r.run.task, r.run.model) for r in results):
        group = [r for r in results if (r.run.task, r.run.model) == (task, model)]
        if task == "fewshot":
            note, table = fewshot_note(group, model), fewshot_table(group, model)
        else:
            note, table = scene_section(task, model, group)
        failed = [r.run.name for r in group if r.status == "failed"]
        if failed:
            note += f" Failed runs (n/a): {', '.join(failed)}."
        sections.append(f"### {TITLES.get(task, task)}, {model}\n\n{note}\n\n{table}\n")
    return "\n".join(sections)


def _paired_metrics(results: list, run) -> dict:
    """{"w/": metrics, "w/o": metrics} of the fixed-β and baseline runs paired with ``run``, {} where missing."""
    same = (run.task, run.scene, run.model, run.seed, run.view_set)
    return {label: next((o.metrics for o in results if o.metrics and o.run.arm == arm
                         and (o.run.task, o.run.scene, o.run.model, o.run.seed, o.run.view_set) == same), {})
            for arm, label in (("g2fr", "w/"), (BASELINE, "w/o"))}


def write_tables(spec, results: list) -> str:
    """``<out>/table.md``, for pose runs ``<out>/<scene>_<model>_pose_error.png`` and for few-shot runs
    ``<out>/<scene>_<model>_fewshot_heldout[_<view set>].png`` (first seed); returns the Markdown."""
    text = tables_markdown(results)
    for r in results:
        if r.run.arm != "g2fr" or r.run.seed != min(spec.seeds):
            continue
        if r.run.task == "fewshot":
            suffix = f"_{r.run.view_set}" if r.run.view_set not in (None, "fps") else ""
            plot_heldout_comparison(os.path.join(spec.out, f"{r.run.scene}_{r.run.model}_fewshot_heldout{suffix}.png"),
                                    r.run.scene, _paired_metrics(results, r.run))
        if r.run.task == "pose":
            plot_pose_comparison(os.path.join(spec.out, f"{r.run.scene}_{r.run.model}_pose_error.png"), r.run.scene,
                                 _paired_metrics(results, r.run))
    tmp = os.path.join(spec.out, "table.md.tmp")
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, os.path.join(spec.out, "table.md"))
    return text
