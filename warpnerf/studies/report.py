"""``warpnerf report``: docs/results.md and the README's headline table, rendered from the records.

Every figure the project reports lives in a record (``docs/results/<name>.json``, written by
``--record NAME``; see :mod:`warpnerf.runs.record`). This module only reads records and formats
them: the headline runs, every recorded run's quality and speed, and the paper's Tab. 1 (pose) and
Tab. 3 (few-shot) with the paper's numbers beside ours and both regimes stated. ``--check`` renders
the same text and fails when a committed file differs, so a hand-edited or stale figure cannot land.
"""

from __future__ import annotations

import os
import statistics
from typing import Optional

from warpnerf.runs.record import ALONE_MAX_OTHER_CORES, DEFAULT_DIR, RecordError, load_records
from warpnerf.studies.paper import METRIC_COLUMNS, barf_numbers, paper_key, paper_numbers
from warpnerf.train import plots

RESULTS_MD = os.path.join("docs", "results.md")
README = "README.md"
BEGIN, END = "<!-- report:headline -->", "<!-- /report:headline -->"
CURVES_PNG = "fewshot_curves.png"  # in the records folder, beside the records it is drawn from

# The README's headline rows, in order: (record name, what it shows). A name without a record
# prints as "no record" rather than disappearing.
HEADLINE = (
    ("main_command", "the README's first command (built-in chair, few-shot, G2fR)"),
    ("lego_full", "NeRF-synthetic lego, all 100 views"),
    ("fern_full", "LLFF fern (forward-facing, NDC)"),
)

# The paper's regime, quoted from the paper (Sec. 5, Tab. 2), for the comparison tables.
PAPER_REGIME = {
    "pose": ("paper: Tab. 1 states no iteration count; Tab. 2 (lego) lists NGP + G2fR at 20k and Mtrf + G2fR at "
             "50k iterations on an RTX 4090; \"we perturb the se(3) camera poses with additive noise N(0, 0.15I) in "
             "the synthetic dataset\" (Sec. 5.1); BARF's evaluation"),
    "fewshot": ("paper: NGP, \"we use 10 images as inputs\" (synthetic), \"Training spans 200k iterations\" "
                "(Sec. 5.2); RTX 4090"),
}
TASK_TITLES = {"pose": "Camera-pose optimisation beside the paper's Tab. 1",
               "fewshot": "Few-shot reconstruction beside the paper's Tab. 3"}

# --- flattening records ---------------------------------------------------------------------------

def recorded_runs(records: list[dict]) -> list[dict]:
    """One row per run across all records: the run's metrics and config plus the record's provenance."""
    rows = []
    for rec in records:
        for run in rec["runs"]:
            # a run that measured its own code and CPU share (metrics.json "code", "cpu") speaks for itself;
            # older runs inherit the record's
            # (a run recorded after it trained, by 'warpnerf record', has only its own word: none if it predates it)
            inherited = {"commit": None, "dirty": None} if rec["kind"] == "runs" else \
                {"commit": rec.get("commit"), "dirty": rec.get("dirty")}
            code = run["metrics"].get("code") or inherited
            rows.append({"record": rec["name"], "pairs_with": rec.get("pairs_with"), "kind": rec["kind"],
                         "command": rec["command"],
                         "commit": code.get("commit"), "dirty": code.get("dirty"), "date": rec["date"],
                         "machine": rec["machine"], "cpu": run["metrics"].get("cpu") or rec["cpu"],
                         "metrics": run["metrics"], "config": run["config"], "run": run.get("run")})
    return rows


def _fmt(v, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def _mean_std(values: list, digits: int) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "n/a"
    if len(values) == 1:
        return _fmt(values[0], digits)
    return f"{statistics.fmean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def _provenance(row: dict) -> str:
    unknown = "commit not measured" if row["kind"] == "runs" else "no git"
    commit = (row["commit"] or unknown)[:7 if row["commit"] else None] + ("+dirty" if row["dirty"] else "")
    return f"{commit}, {row['date'][:10]}"


def _alone(cpu: dict) -> str:
    other = cpu.get("other_cores")
    if other is None:
        return "unknown"
    return f"{'yes' if other < ALONE_MAX_OTHER_CORES else 'no'} ({other:.2f})"


def _link(name: str, prefix: str) -> str:
    return f"[{name}]({prefix}{name}.json)"


# --- tables -------------------------------------------------------------------------------------------

def headline_table(records: list[dict], link_prefix: str) -> str:
    by_name = {r["name"]: r for r in records}
    lines = ["| record | what | PSNR (dB) | SSIM | training (s) | render (s/view) | alone (other cores) | commit, date |",
             "|---|---|---|---|---|---|---|---|"]
    for name, what in HEADLINE:
        rec = by_name.get(name)
        if rec is None or not rec["runs"]:
            lines.append(f"| {name} | {what} | no record | | | | | |")
            continue
        row = recorded_runs([rec])[0]
        m = row["metrics"]
        lines.append(f"| {_link(name, link_prefix)} | {what} | {_fmt(m.get('psnr'), 2)} | {_fmt(m.get('ssim'), 3)} | "
                     f"{_fmt(m.get('train_seconds'), 0)} | {_fmt(m.get('render_seconds_per_view'), 2)} | "
                     f"{_alone(row['cpu'])} | {_provenance(row)} |")
    machines = sorted({f"{r['machine'].get('cpu')}, {r['machine'].get('cores')} cores"
                       for n, _ in HEADLINE if (r := by_name.get(n))})
    note = f"Machine: {'; '.join(machines)}." if machines else "No headline record yet."
    return "\n".join(lines) + f"\n\n{note} Commands and configs are in each record."


def g2fr_cell(arm: str) -> str:
    return {"fixed": "w/", "none": "w/o"}.get(arm) or f"w/ ({arm})"


def runs_table(rows: list[dict], link_prefix: str) -> str:
    lines = ["| record | scene | task | model | G2fR | iters | seed | split | PSNR | SSIM | LPIPS | rot. (deg) "
             "| trans. (x100) | training (s) | render (s/view) | peak RSS (MB) | threads | alone (other cores) "
             "| commit, date |",
             "|" + "---|" * 19]
    for r in rows:
        m, c = r["metrics"], r["config"]
        lines.append(" | ".join([
            f"| {_link(r['record'], link_prefix)}", str(m.get("scene", c.get("scene"))), str(m.get("task", c.get("task"))),
            str(m.get("model", c.get("model"))), g2fr_cell(arm_of({"g2fr": c.get("g2fr"), **m}, c)),
            str(m.get("iters", c.get("iters"))), str(m.get("seed", c.get("seed"))), m.get("eval_split", "test"),
            _fmt(m.get("psnr"), 2), _fmt(m.get("ssim"), 3), _fmt(m.get("lpips"), 3),
            _fmt(m.get("rot_err_deg"), 3), _fmt(m.get("trans_err_x100"), 3),
            _fmt(m.get("train_seconds"), 0), _fmt(m.get("render_seconds_per_view"), 2), _fmt(m.get("peak_rss_mb"), 0),
            str(m.get("threads", "?")), _alone(r["cpu"]), _provenance(r)]) + " |")
    return "\n".join(lines)


def paper_table(task: str, rows: list[dict]) -> str:
    """Ours (mean ± std over the recorded seeds) beside the paper's, per dataset scene and model.
    Built-in scenes share names with the paper's but are other scenes: they never get paper numbers.
    Few-shot has its own table (:func:`fewshot_table`)."""
    if task == "fewshot":
        return fewshot_table(rows)
    ours = [r for r in rows if r["metrics"].get("task") == task and r["metrics"].get("scene_source") != "builtin"]
    if not ours:
        return "No record yet."
    cols = METRIC_COLUMNS[task]
    head = ["scene", "model", "regime (ours)"]
    for _, label, _ in cols:
        head += [f"{label} w/ G2fR", f"{label} w/o"]
    if task == "pose":
        head.append("BARF (paper): rot / trans / PSNR")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    groups: dict = {}
    for r in ours:
        m = r["metrics"]
        # a record is one set of settings; the pose start (noise or identity) is part of the regime
        key = (m.get("scene"), m.get("model", "ngp"), m.get("iters"), r["record"],
               m.get("pose_init") or r["config"].get("pose_init") or "noise")
        groups.setdefault(key, {"w/": [], "w/o": []})["w/" if m.get("g2fr") else "w/o"].append(r)
    for (scene, model, iters, record_name, start), arms in sorted(groups.items(),
                                                                   key=lambda kv: tuple(str(x) for x in kv[0])):
        paper = paper_numbers(scene or "", task, model)
        seeds = sorted({r["metrics"].get("seed") for arm in arms.values() for r in arm}, key=str)
        noise = next((r["metrics"].get("pose_noise_rot", r["config"].get("pose_noise")) for arm in arms.values()
                      for r in arm), None)  # the sigma applied (metrics), else the one asked for
        views = next((r["metrics"].get("n_train_views") for arm in arms.values() for r in arm), None)
        regime = f"{iters} iters, {views} views, seed{'s' if len(seeds) > 1 else ''} {','.join(map(str, seeds))}"
        if task == "pose" and start == "identity":
            regime += ", start identity (BARF's LLFF)"
        elif task == "pose" and noise is not None:
            regime += f", noise {noise}"
        regime += f", record {record_name}"
        cells = [str(scene), str(model), regime]
        for key, _, digits in cols:
            for arm in ("w/", "w/o"):
                cell = _mean_std([r["metrics"].get(key) for r in arms[arm]], digits)
                pkey = paper_key(key)
                if arm in paper and pkey in paper[arm]:
                    cell += f" ({paper[arm][pkey]:.{digits}f})"
                cells.append(cell)
        if task == "pose":
            barf = barf_numbers(scene or "", task)
            cells.append(" / ".join(_fmt(barf.get(k), d) for k, _, d in cols if k in barf) if barf else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + ("\n\nOurs, then the paper's figure in brackets; mean ± std where several seeds "
                               f"were recorded. Regimes differ: {PAPER_REGIME[task]}.")


ARM_LABELS = {"fixed": "w/ G2fR (fixed β)", "none": "w/o"}


def arm_of(metrics: dict, config: Optional[dict] = None) -> str:
    """The G²fR arm a run belongs to: fixed | none | "adaptive W/T" (its plateau window and tol) |
    "heldout W/A/G/D/K" (its check window, checks averaged, min gain, drop and val views)."""
    if not metrics.get("g2fr"):
        return "none"
    schedule = metrics.get("g2fr_schedule") or "fixed"
    if schedule == "fixed":
        return "fixed"
    c = config or {}
    if schedule == "heldout":
        keys = ("g2fr_heldout_window", "g2fr_heldout_average", "g2fr_heldout_min_gain", "g2fr_heldout_drop",
                "g2fr_heldout_views")
        return "heldout " + "/".join(str(c.get(k, "?")) for k in keys)
    return f"adaptive {c.get('g2fr_plateau_window', '?')}/{c.get('g2fr_plateau_tol', '?')}"


def arm_label(arm: str) -> str:
    if arm in ARM_LABELS:
        return ARM_LABELS[arm]
    kind, params = arm.split(" ", 1)
    if kind == "heldout":
        window, average, gain, drop, views = params.split("/")
        return f"w/ G2fR (held-out, window {window}, mean of {average}, gain {gain}, drop {drop}, {views} val views)"
    window, tol = params.split("/")
    return f"w/ G2fR (adaptive, window {window}, tol {tol})"


def arm_order(arms) -> list[str]:
    """fixed, the adaptive variants, the held-out variants, then the baseline."""
    return sorted(set(arms), key=lambda a: (a == "none", a != "fixed", a.startswith("heldout"), a))


def regime_of(row: dict) -> str:
    """The settings that make a few-shot regime, from the run's config (what the records group on)."""
    c, m = row["config"], row["metrics"]
    table = c.get("log2_table_size")
    bg = "random bg" if c.get("random_background") else "fixed bg"
    size = f"/{c['downscale']}" if c.get("downscale", 1) != 1 else ""
    return f"{m.get('iters')} it, images{size or ' full size'}, 2^{table} table, {bg}, lr x{c.get('lr_final_ratio')}"


def fewshot_groups(rows: list[dict], split: Optional[str] = "test") -> dict:
    """(record, scene, view set, regime, scene source, split) -> {arm: {seed: row}} for the few-shot runs whose
    final metrics were measured on ``split`` (None: any split). A record made with ``--pairs-with BASE``
    (an arm added later to a finished table) joins BASE's groups, so its arm is paired with BASE's baseline
    where the regime is the same; the record cell then names both."""
    groups: dict = {}
    for r in rows:
        m = r["metrics"]
        if m.get("task") != "fewshot" or (split is not None and m.get("eval_split", "test") != split):
            continue
        key = (r.get("pairs_with") or r["record"], m.get("scene"), m.get("view_set") or "fps", regime_of(r), m.get("scene_source"),
               m.get("eval_split", "test"))
        groups.setdefault(key, {}).setdefault(arm_of(m, r["config"]), {})[m.get("seed")] = r
    return groups


def paired_gap(arm: dict, base: dict, key: str = "psnr") -> str:
    """Mean ± std over seeds of arm - w/o, and on how many seeds the arm is at least the baseline."""
    gaps = [arm[s]["metrics"][key] - base[s]["metrics"][key] for s in sorted(arm, key=str) if s in base]
    if not gaps:
        return "n/a"
    spread = f"{statistics.fmean(gaps):+.2f}" + (f" ± {statistics.stdev(gaps):.2f}" if len(gaps) > 1 else "")
    return f"{spread} ({sum(g >= 0 for g in gaps)}/{len(gaps)} ≥ 0)"


def fewshot_table(rows: list[dict]) -> str:
    """Tab. 3 beside ours: per record (one regime), scene and view set, each arm's test PSNR / SSIM as
    mean ± std over seeds, the paired PSNR gap of each masked arm to w/o (same views, seed, noise), and
    the paper's figure in brackets for the dataset scenes."""
    groups = fewshot_groups(rows)
    if not groups:
        return "No record yet."
    arms = arm_order(a for g in groups.values() for a in g)
    head = ["record", "scene", "views", "regime (ours)", "seeds", "epochs (w/o)"]
    head += [f"PSNR {arm_label(a)}" for a in arms] + [f"SSIM {arm_label(a)}" for a in arms]
    head += [f"PSNR gap {arm_label(a).split(' ', 1)[1]} − w/o" for a in arms if a != "none"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (record, scene, view_set, regime, source, _), by_arm in sorted(groups.items(), key=lambda kv: tuple(map(str, kv[0]))):
        builtin = source == "builtin"
        paper = {} if builtin else paper_numbers(scene or "", "fewshot", "ngp")
        seeds = sorted({s for arm in by_arm.values() for s in arm}, key=str)
        base = by_arm.get("none", {})
        epochs = _mean_std([r["metrics"].get("epochs") for r in base.values()], 1)
        name = f"{scene} (built-in procedural, not NeRF-synthetic {scene})" if builtin else str(scene)
        names = sorted({r["record"] for arm in by_arm.values() for r in arm.values()}, key=lambda n: (n != record, n))
        cells = [" + ".join(names), name, view_set, regime, ",".join(map(str, seeds)), epochs]
        for key, digits in (("psnr", 2), ("ssim", 3)):
            for a in arms:
                cell = _mean_std([r["metrics"].get(key) for r in by_arm.get(a, {}).values()], digits)
                paper_arm = "w/o" if a == "none" else ("w/" if a == "fixed" else None)
                if paper_arm in paper and key in paper[paper_arm]:
                    cell += f" ({paper[paper_arm][key]:.{digits}f})"
                cells.append(cell)
        cells += [paired_gap(by_arm.get(a, {}), base) for a in arms if a != "none"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + ("\n\nOurs (test split), then the paper's figure in brackets for the NeRF-synthetic "
                               "scenes; mean ± std over seeds. The arms of a seed are paired: the same views (fps: "
                               "farthest-point from view 0, the same for every seed; random: drawn with the seed), seed "
                               "and ray noise. Epochs are passes over the training pixels. Regimes differ: "
                               f"{PAPER_REGIME['fewshot']}.")


def fewshot_curves(rows: list[dict]) -> dict:
    """{panel: {arm label: (epochs, mean PSNR, std PSNR)}} of the recorded held-out curves, averaged over
    seeds at each measured step, one panel per (record, scene, view set): what :func:`write_figures` plots.
    Runs measured on val (settings being chosen) are drawn too; each label names its curve's split."""
    panels: dict = {}
    for (record, scene, view_set, _, _, split), by_arm in fewshot_groups(rows, split=None).items():
        curves = {}
        for a in arm_order(by_arm):
            runs = by_arm[a]
            hists = [(r["metrics"].get("heldout_history") or [], r["metrics"].get("heldout_epochs") or [])
                     for r in runs.values()]
            n = min(min(len(h), len(e)) for h, e in hists) if hists else 0
            if n < 2:
                continue
            ep = [statistics.fmean(e[i] for _, e in hists) for i in range(n)]
            vals = [[h[i][1] for h, _ in hists] for i in range(n)]
            std = [statistics.stdev(v) if len(v) > 1 else 0.0 for v in vals]
            curve_split = next(iter(runs.values()))["metrics"].get("heldout_split", "test")
            curves[f"{arm_label(a)} ({curve_split}, {len(hists)} seed{'s' if len(hists) > 1 else ''})"] = (
                ep, [statistics.fmean(v) for v in vals], std)
        if curves:
            panels[f"{record}: {scene}, {view_set}" + ("" if split == "test" else f" (final metrics on {split})")] = curves
    return panels


EXPORTS_TITLE = "Meshes exported from recorded runs"


def export_table(records: list[dict], link_prefix: str) -> str:
    """One row per mesh ``export --record`` record: the run it read (from the record's ``source_run``), the
    settings, the counts before and after the floaters were removed, the export's time and peak memory.
    "" when there is none."""
    recs = [r for r in records if r["kind"] == "export" and r["export"].get("what") == "mesh"]
    if not recs:
        return ""
    lines = ["| record | run | resolution | iso-level | pieces dropped under (faces) | vertices (before → after) "
             "| faces (before → after) | pieces (before → after) | export (s) | peak RSS (MB): run loaded, export "
             "| alone (other cores) | commit, date |",
             "|" + "---|" * 12]
    for rec in recs:
        e, m, c = rec["export"], rec["source_run"]["metrics"], rec["source_run"]["config"]
        run = (f"{m.get('scene', c.get('scene'))} {m.get('task', c.get('task'))}, {m.get('iters', c.get('iters'))} iters, "
               f"test PSNR {_fmt(m.get('psnr'), 2)}")
        dropped = "none (--keep-floaters)" if e["min_component_faces"] <= 1 else str(e["min_component_faces"])
        counts = [f"{e[k + '_before']:,} → {e[k]:,}" for k in ("vertices", "faces", "pieces")]
        row = {"kind": rec["kind"], "commit": rec.get("commit"), "dirty": rec.get("dirty"), "date": rec["date"]}
        lines.append(" | ".join([f"| {_link(rec['name'], link_prefix)}", run, str(e["resolution"]), f"{e['threshold']:g}",
                                 dropped, *counts, _fmt(e.get("export_seconds"), 0),
                                 f"{_fmt(e.get('peak_rss_mb_load'), 0)}, {_fmt(e.get('peak_rss_mb'), 0)}",
                                 _alone(rec["cpu"]), _provenance(row)]) + " |")
    return "\n".join(lines) + (
        "\n\n`warpnerf export --what mesh --record NAME` (docs/outputs.md). Before: marching cubes' output; after: the "
        "PLY written, once the connected pieces (faces sharing a vertex) under the given face count are dropped "
        "(the largest always stays). Peak RSS: of the process once the run is loaded (scene and field), then "
        "during the export alone (the loaded run stays resident). The commit is the export's; the run's own "
        "metrics and config are in the record.")


VIEWER_TITLE = "Viewer start-up"


def viewer_table(records: list[dict], link_prefix: str) -> str:
    """One row per ``bench viewer --record`` record: the run it loaded, how (cameras only, or its images
    decoded), the first and median ``load_for_viewing`` seconds, the process's median wall-clock and peak
    RSS, and whether the CPU was free. "" when there is none."""
    recs = [r for r in records if r["kind"] == "bench" and r["bench"].get("what") == "viewer"]
    if not recs:
        return ""
    lines = ["| record | run | views (train + test), size | load | load_for_viewing (s): first, median | "
             "process (s), median | peak RSS (MB) | repeats | alone (other cores) | commit, date |",
             "|" + "---|" * 10]
    for rec in recs:
        b, m, c = rec["bench"], rec["source_run"]["metrics"], rec["source_run"]["config"]
        run = f"{m.get('scene', c.get('scene'))} {m.get('task', c.get('task'))}, {m.get('iters', c.get('iters'))} iters"
        w, h = b["image_size"]
        how = "cameras only" if b["cameras_only"] else "images decoded"
        row = {"kind": rec["kind"], "commit": rec.get("commit"), "dirty": rec.get("dirty"), "date": rec["date"]}
        lines.append(" | ".join([f"| {_link(rec['name'], link_prefix)}", run,
                                 f"{b['train_views']} + {b['test_views']}, {w}x{h}", how,
                                 f"{_fmt(b['load_seconds_first'], 2)}, {_fmt(b['load_seconds_median'], 2)}",
                                 _fmt(b["process_seconds_median"], 2), _fmt(b["peak_rss_mb_max"], 0),
                                 str(b["repeats"]), _alone(rec["cpu"]), _provenance(row)]) + " |")
    return "\n".join(lines) + (
        "\n\n`warpnerf bench viewer --run RUN --record NAME` (docs/outputs.md): each repeat a fresh process that "
        "imports the viewer and runs `load_for_viewing` as `warpnerf view` does; the first repeat is the one a user "
        "waits for, the median is over the others. A run whose checkpoint records the background it trained with "
        "is loaded cameras only; an older run has its images decoded (what every viewer start-up did before).")


# --- documents ------------------------------------------------------------------------------------

def render_results(records: list[dict], records_dir: str = DEFAULT_DIR) -> str:
    prefix = os.path.relpath(records_dir, os.path.dirname(RESULTS_MD)).replace(os.sep, "/") + "/"
    rows = recorded_runs(records)
    parts = [
        "# Results",
        "",
        "<!-- Generated by `warpnerf report` from docs/results/*.json. Do not edit: re-record and re-render. -->",
        "",
        "Every figure here is a record in [docs/results/](results/): the command, commit, date, machine, the run's "
        "metrics.json and config.toml, and whether the run had the CPU to itself (*alone*: other processes used "
        f"fewer than {ALONE_MAX_OTHER_CORES} cores on average, measured from /proc/stat during the run). Timings "
        "are only comparable between alone runs on the same machine. Test metrics use the scene's test views "
        "as the run's config says; the older lab notebook is [results_history.md](results_history.md).",
        "",
        "## Headline",
        "",
        headline_table(records, prefix),
        "",
        "## Every recorded run",
        "",
        runs_table(rows, prefix) if rows else "No record yet.",
    ]
    for task in ("pose", "fewshot"):
        parts += ["", f"## {TASK_TITLES[task]}", "", paper_table(task, rows)]
    if fewshot_curves(rows):
        parts += ["", "## Few-shot held-out PSNR against epochs", "",
                  f"![few-shot curves]({prefix}{CURVES_PNG})", "",
                  "Mean over the recorded seeds at each measured step, ±1 std shaded; the split each curve was "
                  "measured on is in its label. Drawn by `warpnerf report` from the records' held-out histories."]
    exports = export_table(records, prefix)
    if exports:
        parts += ["", f"## {EXPORTS_TITLE}", "", exports]
    viewer = viewer_table(records, prefix)
    if viewer:
        parts += ["", f"## {VIEWER_TITLE}", "", viewer]
    return "\n".join(parts) + "\n"


def write_figures(root: str = ".", records_dir: Optional[str] = None) -> list[str]:
    """The figures the report links, drawn from the records (not compared by ``--check``: image bytes
    depend on the matplotlib version)."""
    rel_dir = records_dir or DEFAULT_DIR
    panels = fewshot_curves(recorded_runs(load_records(os.path.join(root, rel_dir))))
    if not panels:
        return []
    path = os.path.join(root, rel_dir, CURVES_PNG)
    plots.plot_band_curves(path, panels, "epochs (passes over the training pixels)", "held-out PSNR (dB)")
    return [path]


def render_readme(readme_text: str, records: list[dict], records_dir: str = DEFAULT_DIR) -> str:
    """The README with the text between its headline markers replaced by the headline table."""
    start, end = readme_text.find(BEGIN), readme_text.find(END)
    if start < 0 or end < start:
        raise RecordError(f"{README}: the markers {BEGIN} ... {END} are missing")
    prefix = records_dir.replace(os.sep, "/").rstrip("/") + "/"
    return readme_text[:start + len(BEGIN)] + "\n" + headline_table(records, prefix) + "\n" + readme_text[end:]


def rendered_files(root: str = ".", records_dir: Optional[str] = None) -> dict[str, str]:
    """{path: text} of every file the report writes, rendered from the records under ``root``."""
    rel_dir = records_dir or DEFAULT_DIR
    records = load_records(os.path.join(root, rel_dir))
    out = {os.path.join(root, RESULTS_MD): render_results(records, rel_dir)}
    readme = os.path.join(root, README)
    if os.path.isfile(readme):
        with open(readme) as fh:
            out[readme] = render_readme(fh.read(), records, rel_dir)
    return out


def stale_files(root: str = ".", records_dir: Optional[str] = None) -> list[str]:
    stale = []
    for path, text in rendered_files(root, records_dir).items():
        try:
            with open(path) as fh:
                current = fh.read()
        except OSError:
            current = None
        if current != text:
            stale.append(path)
    return stale


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("report", help="render docs/results.md and the README's headline table from the records",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--root", default=".", help="the project checkout (default: the current folder)")
    p.add_argument("--records", default=None, help=f"records folder relative to --root (default {DEFAULT_DIR})")
    p.add_argument("--check", action="store_true",
                   help="write nothing; exit 1 when a rendered file differs from what the records give")


def run_cli(args) -> int:
    if args.check:
        stale = stale_files(args.root, args.records)
        if stale:
            print(f"stale: {', '.join(stale)} (run 'warpnerf report' and commit the result)")
            return 1
        print("report: rendered files match the records")
        return 0
    for path, text in rendered_files(args.root, args.records).items():
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
        print(f"wrote {path}")
    for path in write_figures(args.root, args.records):
        print(f"wrote {path}")
    return 0

