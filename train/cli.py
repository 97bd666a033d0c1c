"""The `ddyn` command line: one entry point, one subcommand per job.

Each subcommand lives in the module that does the work; the module exposes
`register(subparsers)`, which adds its parser and sets `func` to a function taking
the parsed arguments. Expected failures (DdynError) print one clear line and exit 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from .errors import DdynError

# modules that contribute subcommands, in the order `ddyn --help` lists them
SUBCOMMAND_MODULES = (
    "train.simulate",
    "train.importers",
    "train.lcm_replay",
    "codegen.generate",
    "train.crosscheck",
    "train.fidelity",
    "train.train_cmd",
    "train.evaluate",
    "train.study",
    "train.export",
    "train.bench",
    "train.finetune",
    "train.fthd_study",
    "train.denoise",
    "train.denoise_study",
    "train.tune",
    "codegen.can",
    "train.sil",
    "train.sil_table",
    "train.mpc_lap",
    "train.raceline",
    "train.can_log",
    "train.can_bench",
    "train.diagnose",
    "train.gap_benchmark",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ddyn", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        result = args.func(args)
    except DdynError as e:
        print(f"ddyn {args.command}: error: {e}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
