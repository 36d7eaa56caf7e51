"""The ``warpnerf`` command line: ``train``, ``eval``, ``bench``, ``scenes``, ``table``.

Heavy imports (torch, warp) happen inside the subcommands so ``warpnerf --help`` is instant.
User errors (bad data, bad config) print one line and exit 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys


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
                                   repeats=args.repeats, device=args.device)
        print(json.dumps(res, indent=None if args.json else 2) if args.json else bench.format_encoding(res))
        return 0
    raise UserError(f"unknown benchmark '{args.what}'")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpnerf", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show full tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    b = sub.add_parser("bench", help="benchmarks that print measured numbers")
    b.add_argument("what", choices=["encoding"], help="what to benchmark")
    b.add_argument("--n", type=int, default=262144, help="points per call")
    b.add_argument("--levels", type=int, default=16)
    b.add_argument("--log2-table-size", type=int, default=19)
    b.add_argument("--repeats", type=int, default=5)
    b.add_argument("--json", action="store_true", help="print one JSON object")
    _add_device(b)
    b.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        if args.debug:
            raise
        print(f"warpnerf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpnerf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
