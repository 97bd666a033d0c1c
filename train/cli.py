"""The `ddyn` command line: one entry point, commands grouped by noun.

Each command lives in the module that does the work; the module exposes `register(subparsers)`,
which adds its parser(s) and sets `func` to a function taking the parsed arguments. A group
(`ddyn sil run`, `ddyn can export`, ...) is a parser of its own whose subcommands come from the
modules listed for it. Expected failures (DdynError) print one clear line and exit 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass

from ddyn.errors import DdynError


@dataclass(frozen=True)
class Command:
    """A top-level command: one module's own parser (help None), or a group of the modules' parsers."""
    name: str
    modules: tuple[str, ...]
    help: str | None = None


# in the order `ddyn --help` lists them: the main job's flow first, then the tools around it
COMMANDS: tuple[Command, ...] = (
    Command("simulate", ("ddyn.data.simulate",)),
    Command("import", ("ddyn.data.importers",)),
    Command("train", ("ddyn.learn.train_cmd",)),
    Command("evaluate", ("ddyn.learn.evaluate",)),
    Command("finetune", ("ddyn.learn.finetune",)),
    Command("denoise", ("ddyn.learn.denoise",)),
    Command("tune", ("ddyn.learn.tune",)),
    Command("export", ("ddyn.learn.export",)),
    Command("codegen", ("ddyn.codegen.generate", "ddyn.analysis.crosscheck"),
            "C code of the vehicle model, EKF Jacobians and MPC pieces (CasADi), and its check against Python"),
    Command("mpc", ("ddyn.control.raceline", "ddyn.control.mpc_lap", "ddyn.control.mpc_tracks"),
            "racing lines (CasADi + IPOPT) and closed-loop laps of the C MPC on the host"),
    Command("sil", ("ddyn.sil.run", "ddyn.sil.table", "ddyn.sil.tracks"),
            "software in the loop: plant and controller as processes over virtual CAN"),
    Command("gap", ("ddyn.gap.cli",),
            "the sim-to-real gap diagnosis: diagnose a log, calibrate, benchmark, rescore (docs/gap.md)"),
    Command("diagnose", ("ddyn.gap.cli:register_alias",)),
    Command("study", ("ddyn.studies.ddm", "ddyn.studies.fthd", "ddyn.studies.denoise", "ddyn.studies.drivetrain",
                      "ddyn.analysis.fidelity"),
            "the papers' tables and the project's studies (DDM/DPM, FTHD, denoising, fidelity)"),
    Command("results", ("ddyn.results.cli",),
            "the headline figures as data: re-run them and compare with their committed files, the README table"),
    Command("bench", ("ddyn.bench.runtime", "ddyn.bench.controller", "ddyn.bench.large_net", "ddyn.bench.qp"),
            "timing of the C runtime against Python (median, p99, max)"),
    Command("can", ("ddyn.codegen.can", "ddyn.data.can_log", "ddyn.bench.can"),
            "the drive-by-wire CAN protocol: C code from the DBC, candump logs, bus replay and record, timing"),
    Command("lcm", ("ddyn.data.lcm_replay",), "LCM telemetry: publish a dataset as the controller's messages"),
)


def commands_named(*names: str) -> tuple[Command, ...]:
    """The listed top-level commands only (tests use it so that a parser imports just their modules)."""
    unknown = set(names) - {c.name for c in COMMANDS}
    if unknown:
        raise KeyError(f"no such command: {sorted(unknown)}")
    return tuple(c for c in COMMANDS if c.name in names)


def build_parser(commands: tuple[Command, ...] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ddyn", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for cmd in COMMANDS if commands is None else commands:
        if cmd.help is None:
            (module,) = cmd.modules
            module, _, fn = module.partition(":")     # "module:function": another register function of it
            getattr(importlib.import_module(module), fn or "register")(sub)
            continue
        group = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        group_sub = group.add_subparsers(dest="subcommand", required=True, metavar="SUBCOMMAND")
        for module in cmd.modules:
            importlib.import_module(module).register(group_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    name = " ".join(filter(None, (args.command, getattr(args, "subcommand", None))))
    try:
        result = args.func(args)
    except DdynError as e:
        print(f"ddyn {name}: error: {e}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
