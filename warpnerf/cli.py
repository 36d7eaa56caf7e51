"""The ``warpnerf`` command line: ``train``, ``eval``, ``bench``, ``scenes``, ``table``.

Heavy imports (torch, warp) happen inside the subcommands so ``warpnerf --help`` is instant.
User errors (bad data, bad config) print one line and exit 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys

from .config import MODELS


class UserError(Exception):
    """An error caused by the user's input; printed as one line without a traceback."""


def _add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto (cuda if Warp sees one, else cpu), cpu, cuda, cuda:N")
    p.add_argument("--threads", type=int, default=None, help="CPU threads for Warp launches (default: min(2, cores))")


def _setup_device(args) -> str:
    from . import device

    if args.threads is not None:
        device.set_num_threads(args.threads)
    try:
        return device.resolve_device(args.device)
    except ValueError as e:
        raise UserError(str(e)) from e


def cmd_bench(args) -> int:
    from . import bench

    _setup_device(args)
    if args.what == "encoding":
        res = bench.bench_encoding(n=args.n, levels=args.levels, log2_table_size=args.log2_table_size,
                                   repeats=args.repeats, device=args.device, model=args.model)
        print(json.dumps(res) if args.json else bench.format_encoding(res))
        return 0
    if args.what == "step":
        res = bench.bench_step(repeats=args.repeats, device=args.device, data_root=args.data_root)
        print(json.dumps(res) if args.json else bench.format_step(res))
        return 0
    raise UserError(f"unknown benchmark '{args.what}'")


# train flags mirrored from TrainConfig; None means "not given" so presets and files keep their values
_TRAIN_FLAGS = [
    ("--scene", str, "scene name: a built-in (see 'warpnerf scenes') or a dataset scene under --data-root"),
    ("--data-root", str, "dataset folder (default: $WARPNERF_DATA)"),
    ("--iters", int, "training steps"),
    ("--out", str, "run folder (default runs/<scene>_<task>[_g2fr])"),
    ("--seed", int, "random seed (views, noise, sampling)"),
    ("--model", str, "grid encoding: ngp (hash grid) or mtrf (multi-resolution CP, the paper's Mtrf)"),
    ("--downscale", int, "integer image downscale"),
    ("--builtin-resolution", int, "image size of built-in scenes"),
    ("--g2fr-beta", float, "fraction of training over which G2fR switches levels on"),
    ("--g2fr-mask", str, "G2fR mask shape: cosine or binary"),
    ("--n-views", int, "fewshot: number of training views"),
    ("--views", str, "fewshot: named view list (freenerf8) or comma-separated ids"),
    ("--pose-noise", float, "pose: se(3) noise sigma (default 0.15 synthetic, 0.01 real)"),
    ("--pose-noise-rot", float, "pose: rotation noise sigma (overrides --pose-noise)"),
    ("--pose-noise-trans", float, "pose: translation noise sigma (overrides --pose-noise)"),
    ("--lr", float, "learning rate of grid and MLPs"),
    ("--batch-rays", int, "initial rays per step"),
    ("--target-samples", int, "samples per step the ray count adapts to"),
    ("--log2-table-size", int, "hash table size T = 2^k"),
    ("--eval-every", int, "evaluate every k-th test view"),
    ("--eval-max-views", int, "cap on evaluated test views (0: no cap)"),
    ("--video-frames", int, "turntable frames (0: no video)"),
]


def cmd_train(args) -> int:
    from .config import build_config
    from .run import run_training

    overrides = {flag.lstrip("-").replace("-", "_"): getattr(args, flag.lstrip("-").replace("-", "_"))
                 for flag, _, _ in _TRAIN_FLAGS}
    overrides["g2fr"] = args.g2fr
    overrides["device"] = args.device
    overrides["threads"] = args.threads
    cfg = build_config(args.task, args.config, overrides)
    metrics = run_training(cfg, progress=not args.quiet)
    print(_summary(metrics))
    print(f"run folder: {cfg.run_dir()}")
    return 0


def _summary(m: dict) -> str:
    parts = [f"PSNR {m['psnr']:.2f} dB", f"SSIM {m['ssim']:.3f}", f"{m['iters']} iters",
             f"train {m['train_seconds']:.0f} s", f"render {m['render_seconds_per_view']:.2f} s/view"]
    if "rot_err_deg" in m:
        parts += [f"rot err {m['rot_err_deg']:.3f} deg", f"trans err x100 {m['trans_err_x100']:.3f}"]
    return "; ".join(parts)


def cmd_eval(args) -> int:
    from .run import evaluate_run

    _setup_device(args)
    res = evaluate_run(args.run, progress=not args.quiet)
    print(f"PSNR {res['psnr']:.2f} dB; SSIM {res['ssim']:.3f}; written to {args.run}/eval/metrics.json")
    return 0


def cmd_scenes(args) -> int:
    from .data.resolve import describe_scenes

    print(describe_scenes(args.data_root))
    return 0


def cmd_table(args) -> int:
    from .table import run_table

    _setup_device(args)
    text = run_table(scenes=args.scenes.split(","), tasks=args.tasks.split(","), data_root=args.data_root,
                     iters=args.iters, out=args.out, seed=args.seed, device=args.device, config_file=args.config,
                     reuse=args.reuse)
    print(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpnerf", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show full tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train a NeRF on a scene and evaluate it")
    t.add_argument("--task", default="full", choices=["full", "fewshot", "pose"])
    t.add_argument("--config", default=None, help="TOML file overriding the task preset")
    for flag, typ, help_text in _TRAIN_FLAGS:
        t.add_argument(flag, type=typ, default=None, help=help_text)
    t.add_argument("--g2fr", action=argparse.BooleanOptionalAction, default=None,
                   help="G2fR coarse-to-fine level mask (paper eq. 15)")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_device(t)
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="re-evaluate a finished run folder")
    e.add_argument("--run", required=True, help="run folder written by 'warpnerf train'")
    e.add_argument("--quiet", action="store_true")
    _add_device(e)
    e.set_defaults(func=cmd_eval)

    sc = sub.add_parser("scenes", help="list built-in scenes and dataset scenes found under --data-root")
    sc.add_argument("--data-root", default=None)
    sc.set_defaults(func=cmd_scenes)

    tb = sub.add_parser("table", help="reproduce the paper's tables: runs with and without G2fR")
    tb.add_argument("--scenes", default="lego")
    tb.add_argument("--tasks", default="fewshot,pose")
    tb.add_argument("--data-root", default=None)
    tb.add_argument("--iters", type=int, default=None, help="override the presets' iterations")
    tb.add_argument("--out", default="runs/table")
    tb.add_argument("--seed", type=int, default=0)
    tb.add_argument("--config", default=None, help="TOML file overriding the task presets (both arms)")
    tb.add_argument("--reuse", action="store_true",
                    help="read run folders that already hold a finished run of the same configuration")
    _add_device(tb)
    tb.set_defaults(func=cmd_table)

    b = sub.add_parser("bench", help="benchmarks that print measured numbers")
    b.add_argument("what", choices=["encoding", "step"], help="what to benchmark")
    b.add_argument("--n", type=int, default=262144, help="points per call")
    b.add_argument("--levels", type=int, default=16)
    b.add_argument("--log2-table-size", type=int, default=19)
    b.add_argument("--model", default="ngp", choices=list(MODELS), help="encoding: hash grid or Mtrf CP lines")
    b.add_argument("--repeats", type=int, default=5)
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.add_argument("--data-root", default=None, help="step: use this dataset's lego instead of the built-in chair")
    _add_device(b)
    b.set_defaults(func=cmd_bench)

    from .process import add_parser as add_process_parser  # photos -> COLMAP -> dataset (issue 12)

    add_process_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from .config import ConfigError

    user_errors: tuple = (UserError, ConfigError)
    try:
        from .data.errors import DatasetError
        from .trainer import TrainingError

        user_errors += (DatasetError, TrainingError)
    except ImportError:  # pragma: no cover - partial installs
        pass
    try:
        return int(args.func(args) or 0)
    except user_errors as e:
        if args.debug:
            raise
        print(f"warpnerf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpnerf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
