"""``--record NAME`` for the commands that produce figures (train, table, sweep, export): the flags, and
:class:`Recorder`, which checks the record can be written before any work, measures the CPU left to other
processes while the work runs, then writes the record (:mod:`warpnerf.runs.record`)."""

from __future__ import annotations

import argparse

from warpnerf import device
from warpnerf.runs import record

RUNS_HELD = "each run's metrics.json and config.toml"


def add_record_flags(p: argparse.ArgumentParser, holds: str = RUNS_HELD) -> None:
    """``--record``, ``--records-dir``, ``--record-replace``; ``holds``: what the record keeps besides the
    command, commit, machine and whether the CPU was free."""
    p.add_argument("--record", metavar="NAME", default=None,
                   help=f"also write a results record docs/results/NAME.json (command, commit, machine, whether the "
                        f"CPU was free, {holds}); 'warpnerf report' renders it")
    p.add_argument("--records-dir", default=None, help="folder for --record (default docs/results)")
    p.add_argument("--record-replace", action="store_true", help="with --record: replace an existing record")


class Recorder:
    """``--record NAME``: checks the record can be written before any work, measures the CPU left to
    other processes while the work runs, then writes the record from the run folders."""

    def __init__(self, args, kind: str):
        self.args, self.kind, self.path, self.meter = args, kind, None, None
        if args.record:
            self.path = record.check_new_record(args.record, args.records_dir, replace=args.record_replace)
            self.meter = record.CpuMeter().start()

    def write(self, run_dirs: list[str], extra: dict | None = None) -> None:
        if self.path is None:
            return
        cpu = self.meter.stop()
        runs = [record.read_run_files(d) for d in run_dirs]
        rec = record.build_record(self.args.record, self.kind, self.args.argv, runs, cpu,
                                  threads=device.num_threads(), extra=extra)
        record.write_record(self.path, rec)
        alone = {True: "alone", False: f"NOT alone: other processes used {cpu['other_cores']:.2f} cores",
                 None: "alone: unknown"}[cpu["alone"]]
        print(f"record: {self.path} ({alone})")
