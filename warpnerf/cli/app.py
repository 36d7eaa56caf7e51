"""The ``warpnerf`` command line: train, eval, scenes, table, sweep, bench, render, export, view, doctor, process.

Heavy imports (torch, warp) happen inside the subcommands so ``warpnerf --help`` is instant: the
imports inside functions here are those (``# lazy``). User errors (bad data, bad config) print one
line and exit 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from collections.abc import Callable

# torch's OpenMP wait settings, before anything imports torch (the config registry below does): a
# short spin instead of libgomp's default busy wait or passive wake-ups (warpnerf/openmp.py)
from warpnerf.openmp import set_wait_defaults

set_wait_defaults()

from warpnerf import device
from warpnerf.runs import record
from warpnerf.studies import report
from warpnerf.cli import doctor
from warpnerf.cli.errors import UserError
from warpnerf.cli.flags import add_config_flags, config_overrides, preset_values, task_for_help
from warpnerf.cli.outputs import add_output_commands
from warpnerf.cli.recording import Recorder, add_record_flags
from warpnerf.train.config import MODELS, VIEW_SETS, ConfigError, build_config, load_toml, resolve_config_file


def _add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto (cuda if Warp sees one, else cpu), cpu, cuda, cuda:N")
    p.add_argument("--threads", type=int, default=None, help="CPU threads for Warp launches and torch ops (default: min(2, cores))")


def _setup_device(args) -> str:
    try:
        if args.threads is not None:
            device.limit_cpu_threads(args.threads)
        return device.resolve_device(args.device)
    except ValueError as e:
        raise UserError(str(e)) from e


def _table_record_dirs(results: list) -> tuple[list[str], dict]:
    """Run folders of a table or sweep's finished runs, and which of them this invocation only read."""
    dirs = [r.run.cfg.run_dir() for r in results if r.metrics]
    reused = [r.run.name for r in results if r.status == "skipped"]
    return dirs, ({"reused_runs": reused} if reused else {})


def cmd_record(args) -> int:
    """``warpnerf record NAME RUN_DIR...``: a record of run folders that finished without ``--record``."""
    path = record.check_new_record(args.record, args.records_dir, replace=args.record_replace)
    extra = {}
    if args.pairs_with:  # an arm run after the table it joins: its runs pair with that record's baseline
        base = record.record_path(args.pairs_with, args.records_dir)
        if not os.path.isfile(base):
            raise record.RecordError(f"--pairs-with {args.pairs_with}: no record {base}")
        extra["pairs_with"] = args.pairs_with
    runs = [record.read_run_files(d) for d in args.runs]
    rec = record.build_record(args.record, "runs", args.argv, runs, record.cpu_of_runs(runs),
                              extra={"run_code": [r["metrics"].get("code") for r in runs], **extra})
    record.write_record(path, rec)
    print(f"record: {path} ({len(runs)} run{'s' if len(runs) != 1 else ''}; commit and CPU share as each run measured)")
    return 0


def cmd_sweep(args) -> int:
    from warpnerf.studies import sweep  # lazy: keeps --help fast (torch)

    recorder = Recorder(args, "table")
    return sweep.run_cli(args, on_done=lambda res: recorder.write(*_table_record_dirs(res["results"])))


def cmd_bench(args) -> int:
    from warpnerf.studies import bench  # lazy: keeps --help fast (torch, Warp)

    dev = _setup_device(args)
    if args.record and args.what != "viewer":
        raise UserError(f"--record: warpnerf bench {args.what} prints its numbers only; bench viewer records them")
    if args.what == "viewer":
        from warpnerf.outputs import viewer_bench  # lazy: keeps --help fast

        if not args.run:
            raise UserError("warpnerf bench viewer needs --run RUN (a run folder with a checkpoint)")
        if args.repeats < 1:
            raise UserError(f"--repeats {args.repeats}: need at least 1")
        recorder = Recorder(args, "bench")  # a record that could not be written fails before any work (one line)
        try:
            res = viewer_bench.bench_viewer(args.run, repeats=args.repeats, device=dev, threads=args.threads)
        except RuntimeError as e:
            raise UserError(str(e)) from None
        print(json.dumps(res) if args.json else viewer_bench.format_viewer(res))
        if recorder.path:  # the benchmark's numbers and the run it loaded (its metrics and config)
            recorder.write([], extra={"bench": {"what": "viewer", **res}, "source_run": record.read_run_files(args.run)})
        return 0
    if args.what == "encoding":
        res = bench.bench_encoding(n=args.n, levels=args.levels, log2_table_size=args.log2_table_size,
                                   repeats=args.repeats, device=args.device, model=args.model,
                                   roofline=not args.no_roofline)
        print(json.dumps(res) if args.json else bench.format_encoding(res))
        return 0
    if args.what == "render":
        if not args.run:
            raise UserError("warpnerf bench render needs --run RUN (a finished run folder)")
        res = bench.bench_render(args.run, views=args.views, device=args.device, every_sample=args.every_sample)
        print(json.dumps(res) if args.json else bench.format_render(res))
        return 0
    if args.what == "step":
        res = bench.bench_step(repeats=args.repeats, device=args.device, data_root=args.data_root,
                               roofline=not args.no_roofline)
        print(json.dumps(res) if args.json else bench.format_step(res))
        return 0
    raise UserError(f"unknown benchmark '{args.what}'")


def cmd_train(args) -> int:
    from warpnerf.runs.folder import read_run_config  # lazy: keeps --help fast (torch)
    from warpnerf.runs.run import run_training  # lazy: keeps --help fast (torch)

    overrides = config_overrides(args)  # None = not given: the preset or --config file keeps its value
    task = args.task
    if args.resume:
        # the run's own config, with whatever the command line changes on top (checked against it)
        saved = read_run_config(args.resume)
        task, overrides["out"] = saved.task, args.resume
        file_values = load_toml(resolve_config_file(args.config)) if args.config else {}
        base = {k: v for k, v in saved.to_dict().items() if k != "task"}
        overrides = {**base, **file_values, **{k: v for k, v in overrides.items() if v is not None}}
        cfg = build_config(task, None, overrides)
    else:
        cfg = build_config(task, args.config, overrides)
    recorder = Recorder(args, "run")
    metrics = run_training(cfg, progress=not args.quiet, overwrite=args.overwrite, resume=bool(args.resume),
                           force=args.force)
    if metrics.get("already_finished"):
        return 0
    print(_summary(metrics))
    print(f"run folder: {cfg.run_dir()}")
    recorder.write([cfg.run_dir()])
    return 0


def _summary(m: dict) -> str:
    parts = [f"PSNR {m['psnr']:.2f} dB", f"SSIM {m['ssim']:.3f}", f"{m['iters']} iters",
             f"train {m['train_seconds']:.0f} s", f"render {m['render_seconds_per_view']:.2f} s/view"]
    return "; ".join(parts + _pose_summary(m))


def _pose_summary(m: dict) -> list[str]:
    """The pose task's figures in a run's (or an evaluation's) metrics; [] for other tasks."""
    parts = []
    if "rot_err_deg" in m:
        aligned = " (orientations aligned)" if m.get("pose_alignment") == "orientations" else ""
        parts += [f"rot err {m['rot_err_deg']:.3f} deg{aligned}", f"trans err (BARF) x100 {m['trans_err_x100']:.3f}"]
        if "rot_err_deg_barf" in m:  # BARF's evaluation code: centres aligned, float32 arccos clamp
            parts.append(f"BARF's metric: rot {m['rot_err_deg_barf']:.3f} deg, trans x100 {m['trans_err_x100_barf']:.3f}")
        from warpnerf.geometry.cameras import describe_unconverged  # lazy: keeps --help fast (torch)

        stuck = describe_unconverged(m, max_ids=8)  # one view far off dominates the means: say so
        if stuck:
            parts.append(stuck)
        found = m.get("reregistered") or []
        if found:
            steps = sorted({r["step"] for r in found})
            parts.append("re-registered view(s) " + "; ".join(
                f"{', '.join(str(r['view']) for r in found if r['step'] == s)} at step {s}" for s in steps))
    return parts


def cmd_eval(args) -> int:
    from warpnerf.runs.run import evaluate_run  # lazy: keeps --help fast (torch)

    _setup_device(args)
    res = evaluate_run(args.run, progress=not args.quiet, device=args.device)
    print("; ".join([f"PSNR {res['psnr']:.2f} dB", f"SSIM {res['ssim']:.3f}", *_pose_summary(res)])
          + f"; written to {args.run}/eval/metrics.json")
    return 0


def cmd_scenes(args) -> int:
    from warpnerf.data.resolve import describe_scenes  # lazy: keeps --help fast (torch)

    print(describe_scenes(args.data_root))
    return 0


def _seed_list(text: str) -> list[int]:
    """``--seed 0`` or ``--seed 0,1,2`` -> distinct ints in the given order."""
    try:
        seeds = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a seed or comma-separated seeds, got '{text}'") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"expected distinct seeds, got '{text}'")
    return seeds


def _name_list(what: str, allowed) -> Callable[[str], list[str]]:
    """An argparse type: ``a`` or ``a,b`` -> distinct names of ``allowed``, in the given order."""

    def parse(text: str) -> list[str]:
        names = [t.strip() for t in text.split(",") if t.strip()]
        for name in names:
            if name not in allowed:
                raise argparse.ArgumentTypeError(f"unknown {what} '{name}': expected one or more of "
                                                 f"{', '.join(allowed)}, comma-separated")
        if not names or len(set(names)) != len(names):
            raise argparse.ArgumentTypeError(f"expected distinct {what}s, got '{text}'")
        return names

    return parse


def cmd_table(args) -> int:
    from warpnerf.studies.sweep import report_failures  # lazy: keeps --help fast (torch)
    from warpnerf.studies.table import run_table  # lazy: keeps --help fast (torch)

    _setup_device(args)
    recorder = Recorder(args, "table")
    res = run_table(scenes=args.scenes.split(","), tasks=args.tasks.split(","), models=args.models.split(","),
                    data_root=args.data_root, iters=args.iters, out=args.out, seed=args.seed, device=args.device,
                    config_file=args.config, threads=args.threads, progress=not args.quiet, overwrite=args.overwrite,
                    view_sets=args.view_sets, arms=args.arms)
    print(res["table"])
    recorder.write(*_table_record_dirs(res["results"]))
    return report_failures(res["failed"])


class _Parser(argparse.ArgumentParser):
    """Usage mistakes as one line (the full usage of 'train' runs to 30 lines); --help shows the rest."""

    def error(self, message: str):
        self.exit(2, f"warpnerf: error: {message} (see '{self.prog} --help')\n")


def build_parser(help_task: str | None = None) -> argparse.ArgumentParser:
    """The ``warpnerf`` parser; ``help_task``: ``train --help`` shows that task's preset values (``--task X --help``)."""
    parser = _Parser(prog="warpnerf", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show full tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    preset = preset_values(help_task) if help_task else None
    if preset:
        epilog = (f"Defaults shown are task {help_task}'s: {preset[0]} over TrainConfig's defaults (a scene in the "
                  "LLFF layout adds configs/<task>_forward_facing.toml where one is shipped). Config flags not given "
                  "keep the value of --config FILE, else of that preset.")
    else:
        epilog = ("Defaults shown are TrainConfig's; each task's preset (configs/<task>.toml) changes some: "
                  "'warpnerf train --task X --help' shows the values task X runs with. Config flags not given keep "
                  "the value of --config FILE, else of the task preset, else the default shown.")
    t = sub.add_parser("train", help="train a NeRF on a scene and evaluate it", epilog=epilog)
    t.add_argument("--config", default=None, help="TOML file overriding the task preset, or the name of one shipped in configs/ (e.g. fewshot_paper)")
    add_config_flags(t, preset=preset)  # one flag per TrainConfig field (warpnerf/cli/flags.py)
    t.set_defaults(task=None)  # not given: the --config file's task, else full (build_config)
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--resume", metavar="RUN", default=None,
                   help="continue the unfinished run folder RUN from its last checkpoint")
    t.add_argument("--force", action="store_true", help="with --resume: accept a changed configuration")
    t.add_argument("--overwrite", action="store_true", help="clear an existing run folder at --out first")
    add_record_flags(t)
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="re-evaluate a finished run folder")
    e.add_argument("--run", required=True, help="run folder written by 'warpnerf train'")
    e.add_argument("--quiet", action="store_true")
    _add_device(e)
    e.set_defaults(func=cmd_eval)

    rc = sub.add_parser("record", help="record run folders that finished without --record (docs/results/NAME.json)")
    rc.add_argument("record", metavar="NAME", help="the record's name")
    rc.add_argument("runs", nargs="+", metavar="RUN_DIR", help="finished run folders (metrics.json and config.toml)")
    rc.add_argument("--records-dir", default=None, help="folder of the records (default docs/results)")
    rc.add_argument("--record-replace", action="store_true", help="replace an existing record of that name")
    rc.add_argument("--pairs-with", metavar="BASE", default=None,
                    help="an arm run after record BASE's table: pair its runs with BASE's baseline (same regime)")
    rc.set_defaults(func=cmd_record)

    sc = sub.add_parser("scenes", help="list built-in scenes and dataset scenes found under --data-root")
    sc.add_argument("--data-root", default=None)
    sc.set_defaults(func=cmd_scenes)

    from warpnerf.studies import sweep  # lazy (torch): 'warpnerf sweep SPEC.toml' (local or Ray backend)

    tb = sub.add_parser("table", help="reproduce the paper's tables: runs with and without G2fR")
    tb.add_argument("--scenes", default="lego")
    tb.add_argument("--tasks", default="fewshot,pose")
    tb.add_argument("--models", default="ngp", help="comma-separated encodings: ngp, mtrf")
    tb.add_argument("--data-root", default=None)
    tb.add_argument("--iters", type=int, default=None, help="override the presets' iterations")
    tb.add_argument("--out", default="runs/table")
    tb.add_argument("--seed", type=_seed_list, default=[0],
                    help="a seed, or comma-separated seeds (e.g. 0,1,2): each arm runs once per seed; the table "
                         "shows means over seeds (few-shot: mean ± std) and the paired PSNR gap of each masked arm to w/o")
    tb.add_argument("--view-sets", type=_name_list("view set", VIEW_SETS), default=["fps"],
                    help="few-shot view sets, comma-separated: fps (farthest-point, the same views for every seed), "
                         "random (drawn with each seed); a table row each (default fps)")
    tb.add_argument("--arms", type=_name_list("arm", tuple(sweep.ARMS)), default=["g2fr", "nog2fr"],
                    help="comma-separated: g2fr (G2fR, fixed schedule of eq. 15), adaptive (G2fR, a level opens when "
                         "the training loss plateaus), heldout (G2fR, levels open while the PSNR of val views stops "
                         "rising and close when it falls), nog2fr (no masking); paired per seed and view set "
                         "(default g2fr,nog2fr)")
    tb.add_argument("--config", default=None, help="TOML file overriding the task presets (every arm)")
    tb.add_argument("--reuse", action="store_true",
                    help="(always on now: a run folder holding a finished run of the same configuration is read)")
    tb.add_argument("--quiet", action="store_true", help="no progress bar")
    tb.add_argument("--overwrite", action="store_true",
                    help="replace finished runs whose configuration differs (e.g. other --iters); never others' folders")
    _add_device(tb)
    add_record_flags(tb)
    tb.set_defaults(func=cmd_table)
    sweep.add_parser(sub)
    add_record_flags(sub.choices["sweep"])
    sub.choices["sweep"].set_defaults(func=cmd_sweep)
    report.add_parser(sub)  # renders docs/results.md from docs/results/ (stdlib only: no torch)
    sub.choices["report"].set_defaults(func=report.run_cli)

    b = sub.add_parser("bench", help="benchmarks that print measured numbers")
    b.add_argument("what", choices=["encoding", "step", "render", "viewer"],
                   help="what to benchmark (viewer: warpnerf view's start-up, load_for_viewing, in fresh processes)")
    b.add_argument("--n", type=int, default=262144, help="points per call")
    b.add_argument("--levels", type=int, default=16)
    b.add_argument("--log2-table-size", type=int, default=19)
    b.add_argument("--model", default="ngp", choices=list(MODELS), help="encoding: hash grid or Mtrf CP lines")
    b.add_argument("--repeats", type=int, default=5, help="timed repeats (viewer: fresh processes, the first "
                                                            "reported apart)")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.add_argument("--no-roofline", action="store_true",
                   help="skip measuring the machine's gather and GEMM rates next to the benchmark")
    b.add_argument("--data-root", default=None, help="step: use this dataset's lego instead of the built-in chair")
    b.add_argument("--run", default=None, help="render: the finished run folder whose test views are rendered; "
                                                "viewer: the run folder (with a checkpoint) the viewer loads")
    b.add_argument("--views", type=int, default=5, help="render: test views timed (spread over the test set)")
    b.add_argument("--every-sample", action="store_true",
                   help="render: early ray termination off (every marched sample evaluated), the reference")
    _add_device(b)
    add_record_flags(b, "viewer only: the benchmark's numbers and the run's metrics and config")
    b.set_defaults(func=cmd_bench)
    add_output_commands(sub)  # render, export, view (commands on a finished run)
    doctor.add_parser(sub)  # machine report; imports torch/warp only when it runs
    # photos -> COLMAP -> dataset (issue 12)
    from warpnerf.data.process import add_parser as add_process_parser  # lazy: warpnerf.data loads torch

    add_process_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(help_task=task_for_help(argv))
    args = parser.parse_args(argv)
    args.argv = argv  # what --record writes as the command
    user_errors: tuple = (UserError, ConfigError, record.RecordError)
    interrupted: tuple = ()
    try:
        # after parsing, so that --help never loads torch and the trainer for these error types
        from warpnerf.data.errors import DatasetError  # lazy: see above
        from warpnerf.runs.run import TrainingInterrupted  # lazy: see above
        from warpnerf.studies.sweep import SweepInterrupted  # lazy: see above
        from warpnerf.train.checkpoint import CheckpointError, WriteError  # lazy: see above
        from warpnerf.train.trainer import TrainingError  # lazy: see above

        user_errors += (DatasetError, TrainingError, CheckpointError, WriteError)
        interrupted = (TrainingInterrupted, SweepInterrupted)
    except ImportError:  # pragma: no cover - partial installs
        pass
    try:
        return int(args.func(args) or 0)
    except interrupted as e:
        if getattr(e, "command", "") is None:  # a sweep or table: the same command continues it
            e.command = "warpnerf " + shlex.join(argv)
        print(f"warpnerf: {e}", file=sys.stderr)
        return 130
    except user_errors as e:
        if args.debug:
            raise
        print(f"warpnerf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpnerf: interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # the file system refused (read-only, full, vanished folder): one line naming the file
        if args.debug:
            raise
        where = f": {e.filename}" if e.filename else ""
        print(f"warpnerf: error: {e.strerror or e}{where} (--debug shows where)", file=sys.stderr)
        return 2
