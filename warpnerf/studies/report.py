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
from warpnerf.studies.paper import barf_numbers, paper_numbers

RESULTS_MD = os.path.join("docs", "results.md")
README = "README.md"
BEGIN, END = "<!-- report:headline -->", "<!-- /report:headline -->"

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
_METRICS = {"pose": (("rot_err_deg", "rot. err (deg)", 3), ("trans_err_x100", "trans. err (x100)", 3),
                     ("psnr", "PSNR", 2)),
            "fewshot": (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("lpips", "LPIPS", 3))}


# --- flattening records ---------------------------------------------------------------------------

def recorded_runs(records: list[dict]) -> list[dict]:
    """One row per run across all records: the run's metrics and config plus the record's provenance."""
    rows = []
    for rec in records:
        for run in rec["runs"]:
            rows.append({"record": rec["name"], "kind": rec["kind"], "command": rec["command"],
                         "commit": rec.get("commit"), "dirty": rec.get("dirty"), "date": rec["date"],
                         "machine": rec["machine"], "cpu": rec["cpu"], "metrics": run["metrics"],
                         "config": run["config"], "run": run.get("run")})
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
    commit = (row["commit"] or "no git")[:7] + ("+dirty" if row["dirty"] else "")
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


def runs_table(rows: list[dict], link_prefix: str) -> str:
    lines = ["| record | scene | task | model | G2fR | iters | seed | PSNR | SSIM | LPIPS | rot. (deg) | trans. (x100) "
             "| training (s) | render (s/view) | peak RSS (MB) | threads | alone (other cores) | commit, date |",
             "|" + "---|" * 18]
    for r in rows:
        m, c = r["metrics"], r["config"]
        lines.append(" | ".join([
            f"| {_link(r['record'], link_prefix)}", str(m.get("scene", c.get("scene"))), str(m.get("task", c.get("task"))),
            str(m.get("model", c.get("model"))), "w/" if m.get("g2fr", c.get("g2fr")) else "w/o",
            str(m.get("iters", c.get("iters"))), str(m.get("seed", c.get("seed"))),
            _fmt(m.get("psnr"), 2), _fmt(m.get("ssim"), 3), _fmt(m.get("lpips"), 3),
            _fmt(m.get("rot_err_deg"), 3), _fmt(m.get("trans_err_x100"), 3),
            _fmt(m.get("train_seconds"), 0), _fmt(m.get("render_seconds_per_view"), 2), _fmt(m.get("peak_rss_mb"), 0),
            str(m.get("threads", "?")), _alone(r["cpu"]), _provenance(r)]) + " |")
    return "\n".join(lines)


def paper_table(task: str, rows: list[dict]) -> str:
    """Ours (mean ± std over the recorded seeds) beside the paper's, per dataset scene and model.
    Built-in scenes share names with the paper's but are other scenes: they never get paper numbers."""
    ours = [r for r in rows if r["metrics"].get("task") == task and r["metrics"].get("scene_source") != "builtin"]
    if not ours:
        return "No record yet."
    cols = _METRICS[task]
    head = ["scene", "model", "regime (ours)"]
    for _, label, _ in cols:
        head += [f"{label} w/ G2fR", f"{label} w/o"]
    if task == "pose":
        head.append("BARF (paper): rot / trans / PSNR")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    groups: dict = {}
    for r in ours:
        m = r["metrics"]
        key = (m.get("scene"), m.get("model", "ngp"), m.get("iters"))
        groups.setdefault(key, {"w/": [], "w/o": []})["w/" if m.get("g2fr") else "w/o"].append(r)
    for (scene, model, iters), arms in sorted(groups.items(), key=lambda kv: tuple(str(x) for x in kv[0])):
        paper = paper_numbers(scene or "", task, model)
        seeds = sorted({r["metrics"].get("seed") for arm in arms.values() for r in arm}, key=str)
        noise = next((r["config"].get("pose_noise") for arm in arms.values() for r in arm), None)
        views = next((r["metrics"].get("n_train_views") for arm in arms.values() for r in arm), None)
        regime = f"{iters} iters, {views} views, seed{'s' if len(seeds) > 1 else ''} {','.join(map(str, seeds))}"
        if task == "pose" and noise is not None:
            regime += f", noise {noise}"
        cells = [str(scene), str(model), regime]
        for key, _, digits in cols:
            for arm in ("w/", "w/o"):
                cell = _mean_std([r["metrics"].get(key) for r in arms[arm]], digits)
                if arm in paper and key in paper[arm]:
                    cell += f" ({paper[arm][key]:.{digits}f})"
                cells.append(cell)
        if task == "pose":
            barf = barf_numbers(scene or "", task)
            cells.append(" / ".join(_fmt(barf.get(k), d) for k, _, d in cols) if barf else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + ("\n\nOurs, then the paper's figure in brackets; mean ± std where several seeds "
                               f"were recorded. Regimes differ: {PAPER_REGIME[task]}.")


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
    return "\n".join(parts) + "\n"


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
    return 0

