"""``warpnerf table``: the paper's comparison, with and without G²fR, as Markdown tables.

A thin layer over ``warpnerf sweep`` (:mod:`warpnerf.studies.sweep`): the flags make a sweep spec
(scenes x models x tasks x arms x seeds, and few-shot view sets), the sweep trains or skips each run
and writes ``<out>/table.md`` with :mod:`warpnerf.studies.tables` (Tab. 1 / Tab. 3 shaped, the paper's
own numbers in brackets).
"""

from __future__ import annotations

from typing import Optional

from warpnerf.studies.sweep import DEFAULT_VIEW_SET, SweepSpec, run_sweep

DEFAULT_ARMS = ("g2fr", "nog2fr")


def table_spec(scenes: list[str], tasks: list[str], models: Optional[list[str]] = None, data_root: Optional[str] = None,
               iters: Optional[int] = None, out: str = "runs/table", seed: int | list[int] = 0, device: str = "auto",
               config_file: Optional[str] = None, threads: Optional[int] = None,
               view_sets: Optional[list[str]] = None, arms: Optional[list[str]] = None) -> SweepSpec:
    """The sweep spec behind ``warpnerf table``: ``arms`` (default g2fr, nog2fr) of every scene x model x
    task, for one seed or each of a list of seeds, few-shot runs for each of ``view_sets`` (default fps).
    No turntable: the table needs metrics only, and a 400x400 video costs minutes on a CPU."""
    overrides = {"video_frames": 0}
    if iters is not None:
        overrides["iters"] = iters
    return SweepSpec(scenes=scenes, models=models or ["ngp"], tasks=tasks, arms=list(arms or DEFAULT_ARMS),
                     seeds=[seed] if isinstance(seed, int) else list(seed),
                     view_sets=list(view_sets or [DEFAULT_VIEW_SET]), out=out, data_root=data_root,
                     config=config_file, device=device, num_cpus=threads, overrides=overrides, retries=0)


def run_table(scenes: list[str], tasks: list[str], models: Optional[list[str]] = None, data_root: Optional[str] = None,
              iters: Optional[int] = None, out: str = "runs/table", seed: int | list[int] = 0, device: str = "auto",
              config_file: Optional[str] = None, threads: Optional[int] = None, progress: bool = True,
              overwrite: bool = False, view_sets: Optional[list[str]] = None,
              arms: Optional[list[str]] = None) -> dict:
    """Train (or skip, when finished with the identical configuration) every run of :func:`table_spec`
    and write ``<out>/table.md``. Returns ``run_sweep``'s result (``table``, ``results``, ``failed``).
    A finished run of another configuration (e.g. other ``iters``) is replaced only with ``overwrite``."""
    spec = table_spec(scenes, tasks, models, data_root, iters, out, seed, device, config_file, threads,
                      view_sets=view_sets, arms=arms)
    return run_sweep(spec, progress=progress, overwrite=overwrite)
