"""``warpnerf table``: the paper's comparison, with and without G²fR, as Markdown tables.

A thin layer over ``warpnerf sweep`` (:mod:`warpnerf.studies.sweep`): the flags make a sweep spec
(scenes x models x tasks x both arms x seeds), the sweep trains or skips each run and writes
``<out>/table.md`` with :mod:`warpnerf.studies.tables` (Tab. 1 / Tab. 3 shaped, the paper's own
numbers in brackets).
"""

from __future__ import annotations

from typing import Optional

from warpnerf.studies.sweep import SweepSpec, run_sweep


def table_spec(scenes: list[str], tasks: list[str], models: Optional[list[str]] = None, data_root: Optional[str] = None,
               iters: Optional[int] = None, out: str = "runs/table", seed: int | list[int] = 0, device: str = "auto",
               config_file: Optional[str] = None, threads: Optional[int] = None) -> SweepSpec:
    """The sweep spec behind ``warpnerf table``: both arms of every scene x model x task, for one
    seed or each of a list of seeds (the table then shows means and the per-seed gaps).
    No turntable: the table needs metrics only, and a 400x400 video costs minutes on a CPU."""
    overrides = {"video_frames": 0}
    if iters is not None:
        overrides["iters"] = iters
    return SweepSpec(scenes=scenes, models=models or ["ngp"], tasks=tasks,
                     seeds=[seed] if isinstance(seed, int) else list(seed), out=out,
                     data_root=data_root, config=config_file, device=device, num_cpus=threads, overrides=overrides,
                     retries=0)


def run_table(scenes: list[str], tasks: list[str], models: Optional[list[str]] = None, data_root: Optional[str] = None,
              iters: Optional[int] = None, out: str = "runs/table", seed: int | list[int] = 0, device: str = "auto",
              config_file: Optional[str] = None, threads: Optional[int] = None, progress: bool = True,
              overwrite: bool = False) -> dict:
    """Train (or skip, when finished with the identical configuration) both arms of every run and
    write ``<out>/table.md``. Returns ``run_sweep``'s result (``table``, ``results``, ``failed``).
    A finished run of another configuration (e.g. other ``iters``) is replaced only with ``overwrite``."""
    spec = table_spec(scenes, tasks, models, data_root, iters, out, seed, device, config_file, threads)
    return run_sweep(spec, progress=progress, overwrite=overwrite)
