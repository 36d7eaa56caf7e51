"""Results records: the file behind every figure the project reports.

A record is one JSON file, ``docs/results/<name>.json``, written by ``--record NAME`` on ``train``,
``table``, ``sweep``, ``export`` and ``bench viewer``. It holds what it takes to check the figure: the command line, the commit
(and whether the tree had uncommitted changes), the date, the machine, whether the run had the CPU
to itself (measured, not declared), and each run's ``metrics.json`` and ``config.toml``.
``warpnerf report`` renders docs/results.md and the README's headline table from these files.

Whether a run was *alone* is measured from ``/proc/stat``: the machine's busy CPU time over the run,
minus this process's own (and its children's), divided by the wall time, is the number of cores that
other processes used on average (``other_cores``). On two cores even a small helper skews a timing,
so a record counts as alone only when ``other_cores`` < :data:`ALONE_MAX_OTHER_CORES`.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

FORMAT = "warpnerf-record-1"
# run: `train --record`; table: `table`/`sweep --record`; runs: `warpnerf record`, finished run folders
# recorded after they trained (their commit and CPU share come from each run's metrics.json);
# export: `export --record`, geometry exported from a finished run: no "runs" (it trained nothing), its
# "export" holds the counts, time and peak memory (<out>.export.json) and "source_run" the run's files;
# bench: `bench viewer --record`, a timing of a run's use (no "runs"): "bench" holds the numbers (its "what"
# says which benchmark), "source_run" the run's files
KINDS = ("run", "table", "runs", "export", "bench")
DEFAULT_DIR = os.path.join("docs", "results")
ALONE_MAX_OTHER_CORES = 0.10  # a tenth of a core on average: daemons and the shell, not a second job
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")


class RecordError(ValueError):
    """A record name, folder or file that cannot be used (one line, for the CLI)."""


def record_path(name: str, records_dir: Optional[str] = None) -> str:
    """``<records_dir>/<name>.json`` after checking the name: letters, digits, ``_ . -`` only, so a
    name cannot leave the folder (``../x``) or hide (``.x``)."""
    if not _NAME.match(name) or name.endswith(".json"):
        raise RecordError(f"record name {name!r}: use letters, digits, '_', '.' and '-' "
                          "(no path, no .json suffix)")
    return os.path.join(records_dir or DEFAULT_DIR, f"{name}.json")


def check_new_record(name: str, records_dir: Optional[str] = None, replace: bool = False) -> str:
    """Fail before any work when the record could not be written: bad name, an existing record
    (unless ``replace``) or a folder that cannot be created. Returns the record's path."""
    path = record_path(name, records_dir)
    if os.path.exists(path) and not replace:
        raise RecordError(f"record {path} exists: choose another name or pass --record-replace")
    folder = os.path.dirname(path) or "."
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        raise RecordError(f"cannot create the records folder {folder}: {e.strerror}") from None
    if not os.access(folder, os.W_OK):
        raise RecordError(f"the records folder {folder} is not writable")
    return path


# --- where, when, what ------------------------------------------------------------------------

def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """CPU model, core count, OS and the versions that decide the numbers."""
    info = {"cpu": _cpu_model(), "cores": os.cpu_count(), "platform": f"{platform.system()} {platform.machine()}",
            "python": platform.python_version()}
    for mod in ("torch", "warp"):
        m = sys.modules.get(mod)  # only what the run already imported: a record never loads torch itself
        if m is not None:
            info[mod] = getattr(m, "__version__", None) or getattr(getattr(m, "config", None), "version", None)
    return info


def git_state(path: str = ".") -> dict:
    """{"commit": sha or None, "dirty": bool or None} of the checkout holding ``path``: the code a
    record's figures came from (None outside a git checkout, e.g. an installed package)."""
    pkg = os.path.dirname(os.path.abspath(__file__))
    for where in (pkg, path):
        try:
            sha = subprocess.run(["git", "-C", where, "rev-parse", "HEAD"], capture_output=True, text=True,
                                 timeout=10).stdout.strip()
            if not sha:
                continue
            status = subprocess.run(["git", "-C", where, "status", "--porcelain", "--untracked-files=no"],
                                    capture_output=True, text=True, timeout=10).stdout
            return {"commit": sha, "dirty": bool(status.strip())}
        except (OSError, subprocess.SubprocessError):
            continue
    return {"commit": None, "dirty": None}


# --- did the run have the machine to itself -------------------------------------------------------

def _machine_busy_seconds() -> Optional[float]:
    """Busy CPU seconds of the whole machine since boot (all cores), from /proc/stat; None elsewhere."""
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    user, nice, system, idle, iowait, irq, softirq, steal = (int(x) for x in fields[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def _own_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


@dataclass
class CpuMeter:
    """Measures how many cores *other* processes used while a run went on (see the module doc)."""

    wall0: float = 0.0
    busy0: Optional[float] = None
    own0: float = 0.0

    def start(self) -> "CpuMeter":
        self.wall0, self.busy0, self.own0 = time.perf_counter(), _machine_busy_seconds(), _own_seconds()
        return self

    def stop(self) -> dict:
        wall = time.perf_counter() - self.wall0
        busy1 = _machine_busy_seconds()
        own = _own_seconds() - self.own0
        if self.busy0 is None or busy1 is None or wall <= 0:
            return {"wall_seconds": wall, "own_cpu_seconds": own, "other_cores": None, "alone": None}
        other = max(0.0, (busy1 - self.busy0) - own) / wall
        return {"wall_seconds": wall, "own_cpu_seconds": own, "other_cores": round(other, 4),
                "alone": other < ALONE_MAX_OTHER_CORES}


# --- the record -------------------------------------------------------------------------------------

def read_run_files(run_dir: str) -> dict:
    """{"metrics": metrics.json, "config": config.toml as a dict} of a finished run folder."""
    try:
        with open(os.path.join(run_dir, "metrics.json")) as fh:
            metrics = json.load(fh)
        with open(os.path.join(run_dir, "config.toml"), "rb") as fh:
            config = tomllib.load(fh)
    except (OSError, ValueError) as e:
        raise RecordError(f"cannot record {run_dir}: {e}") from None
    # the held-out curve (tens of points) stays: the epoch plots are drawn from records
    return {"run": os.path.basename(os.path.normpath(run_dir)), "metrics": metrics, "config": config}


def build_record(name: str, kind: str, argv: list[str], runs: list[dict], cpu: dict, threads: Optional[int] = None,
                 extra: Optional[dict] = None, now: Optional[_dt.datetime] = None) -> dict:
    """The record as a dict. ``runs`` are :func:`read_run_files` results (one for ``train``)."""
    if kind not in KINDS:
        raise RecordError(f"record kind {kind!r}: one of {', '.join(KINDS)}")
    now = now or _dt.datetime.now(_dt.timezone.utc)
    rec = {"format": FORMAT, "name": name, "kind": kind,
           "command": "warpnerf " + shlex.join(argv),
           **git_state(),
           "date": now.strftime("%Y-%m-%dT%H:%M:%SZ"),
           "machine": {**machine_info(), "threads": threads},
           "cpu": cpu,
           "runs": runs}
    if extra:
        rec.update(extra)
    return rec


def cpu_of_runs(runs: list[dict]) -> dict:
    """The CPU share of runs recorded after they trained, from each run's own measurement
    (metrics.json "cpu"): the busiest run decides; unknown when any run did not measure."""
    cpus = [r["metrics"].get("cpu") for r in runs]
    if not runs or any(not c or c.get("other_cores") is None for c in cpus):
        return {"wall_seconds": None, "own_cpu_seconds": None, "other_cores": None, "alone": None}
    other = max(c["other_cores"] for c in cpus)
    return {"wall_seconds": sum(c["wall_seconds"] for c in cpus), "own_cpu_seconds": sum(c["own_cpu_seconds"] for c in cpus),
            "other_cores": other, "alone": other < ALONE_MAX_OTHER_CORES}


def write_record(path: str, record: dict) -> str:
    """Write atomically (temp file + rename) with sorted keys, so a re-record diffs cleanly."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as fh:
        json.dump(record, fh, indent=1, sort_keys=True)
        fh.write("\n")
    os.replace(tmp, path)
    return path


def load_record(path: str) -> dict:
    """A record file, checked for the keys the report reads (one-line RecordError otherwise)."""
    try:
        with open(path) as fh:
            rec = json.load(fh)
    except (OSError, ValueError) as e:
        raise RecordError(f"{path}: not a readable record ({e})") from None
    if not isinstance(rec, dict) or rec.get("format") != FORMAT:
        raise RecordError(f"{path}: not a warpnerf record (format {FORMAT!r} expected)")
    for key in ("name", "kind", "command", "date", "machine", "cpu", "runs"):
        if key not in rec:
            raise RecordError(f"{path}: missing key {key!r}")
    for run in rec["runs"]:
        if not isinstance(run, dict) or "metrics" not in run or "config" not in run:
            raise RecordError(f"{path}: a run without metrics or config")
    if rec["kind"] == "export" and not (isinstance(rec.get("export"), dict) and isinstance(rec.get("source_run"), dict)):
        raise RecordError(f"{path}: an export record without its 'export' figures or 'source_run'")
    if rec["kind"] == "bench" and not (isinstance(rec.get("bench"), dict) and isinstance(rec.get("source_run"), dict)):
        raise RecordError(f"{path}: a bench record without its 'bench' figures or 'source_run'")
    return rec


def load_records(records_dir: Optional[str] = None) -> list[dict]:
    """Every record in the folder, sorted by name (an empty list when the folder does not exist)."""
    folder = records_dir or DEFAULT_DIR
    if not os.path.isdir(folder):
        return []
    return [load_record(os.path.join(folder, f)) for f in sorted(os.listdir(folder)) if f.endswith(".json")]
