"""``warpnerf bench viewer --run RUN``: the viewer's start-up, :func:`~warpnerf.outputs.viewer.load_for_viewing`,
timed wall-clock in a fresh process per repeat (a second load in one process would find the modules imported,
Warp initialised and the files in its own caches), with each process's peak resident memory.

Each repeat runs ``python -m warpnerf.outputs.viewer_bench RUN DEVICE THREADS``, which prints one JSON object:
the seconds to import the viewer module (torch, Warp's Python side), the seconds of ``load_for_viewing`` (run
folder, checkpoint, scene, trainer, field state) and the process's peak RSS. The parent adds the process's
wall-clock (Python's start-up included). The first repeat is reported apart: it is the one a user waits for
after the run's files left the page cache (the next ones find them there).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time

from warpnerf import device as devmod  # imports nothing heavy (torch only when asked)


def measure_once(run_dir: str, device: str = "auto", threads: int | None = None) -> dict:
    """In this (fresh) process: import the viewer, :func:`load_for_viewing` the run as ``warpnerf view`` does
    (``device`` resolved, and Warp initialised, inside it); seconds and peak RSS."""
    t0 = time.perf_counter()
    from warpnerf.outputs.viewer import load_for_viewing  # timed: what `warpnerf view` imports before loading
    from warpnerf.train.trainer import peak_rss_mb  # lazy: timed with the viewer's imports (torch)

    t1 = time.perf_counter()
    if threads:
        devmod.limit_cpu_threads(threads)
    t2 = time.perf_counter()
    trainer = load_for_viewing(run_dir, device)
    t3 = time.perf_counter()
    scene = trainer.scene
    return {"import_seconds": t1 - t0, "load_seconds": t3 - t2, "peak_rss_mb": peak_rss_mb(),
            "cameras_only": trainer.cameras_only, "scene": scene.name, "scene_source": scene.source,
            "train_views": len(scene.train), "test_views": len(scene.test),
            "image_size": [scene.train.width, scene.train.height], "step": trainer.step}


def bench_viewer(run_dir: str, repeats: int = 3, device: str = "cpu", threads: int | None = None) -> dict:
    """``repeats`` fresh processes each timing :func:`measure_once`; per-repeat lists, the first and the
    median of the rest (of all when there is one)."""
    threads = threads or devmod.num_threads()
    env = {**os.environ, "WARPNERF_THREADS": str(threads)}
    rows = []
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "warpnerf.outputs.viewer_bench", run_dir, device, str(threads)],
                              capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            lines = (proc.stderr or proc.stdout).strip().splitlines()
            raise RuntimeError(f"the viewer's load failed in a fresh process: {lines[-1] if lines else proc.returncode}")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        row["process_seconds"] = wall
        rows.append(row)
    first, rest = rows[0], rows[1:] or rows

    def med(key: str) -> float:
        return statistics.median(r[key] for r in rest)

    return {"run": run_dir, "device": device, "threads": threads, "repeats": len(rows),
            **{k: first[k] for k in ("cameras_only", "scene", "scene_source", "train_views", "test_views",
                                     "image_size", "step")},
            "load_seconds": [round(r["load_seconds"], 3) for r in rows],
            "import_seconds": [round(r["import_seconds"], 3) for r in rows],
            "process_seconds": [round(r["process_seconds"], 3) for r in rows],
            "peak_rss_mb": [round(r["peak_rss_mb"], 1) for r in rows],
            "load_seconds_first": round(first["load_seconds"], 3),
            "load_seconds_median": round(med("load_seconds"), 3),
            "process_seconds_median": round(med("process_seconds"), 3),
            "peak_rss_mb_max": round(max(r["peak_rss_mb"] for r in rows), 1)}


def format_viewer(res: dict) -> str:
    """One line for a person."""
    how = "cameras only" if res["cameras_only"] else "images decoded (run from before checkpoints recorded the background)"
    w, h = res["image_size"]
    return (f"viewer start-up of {res['scene']} ({res['train_views']} train + {res['test_views']} test views, {w}x{h}, "
            f"{how}) on {res['device']}, {res['threads']} threads: load_for_viewing {res['load_seconds_first']:.2f} s "
            f"first, {res['load_seconds_median']:.2f} s median; process {res['process_seconds_median']:.2f} s median "
            f"(Python, imports and load); peak RSS {res['peak_rss_mb_max']:.0f} MB; {res['repeats']} fresh processes")


if __name__ == "__main__":  # one repeat of bench_viewer: RUN DEVICE THREADS -> one JSON line
    from warpnerf.openmp import set_wait_defaults

    set_wait_defaults()  # as the command line does, before torch loads
    print(json.dumps(measure_once(sys.argv[1], sys.argv[2], int(sys.argv[3]))))
