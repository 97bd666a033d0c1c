"""The `ddyn` command line: one entry point, commands grouped by noun.

Each command lives in the module that does the work; the module exposes `register(subparsers)`,
which adds its parser(s) and sets `func` to a function taking the parsed arguments. A group
(`ddyn sil run`, `ddyn can export`, ...) is a parser of its own whose subcommands come from the
modules listed for it. Expected failures (DdynError) print one clear line and exit 2; so do usage errors and
an OSError naming a file that a command's own checks did not catch first. main() imports only the module(s)
of the command it runs, so that one missing optional dependency breaks only the commands that need it.
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
                      "ddyn.analysis.fidelity", "ddyn.studies.sil_loop", "ddyn.studies.sil_oracle",
                      "ddyn.studies.transfer"),
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


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line usage error (`ddyn train: error: ...`, exit 2), like every other expected failure;
    the usage is one `--help` away. Subparsers are of this class too (argparse passes the parser's class on)."""

    unavailable = ""   # a group's modules that could not be imported, named in its errors

    def error(self, message: str):
        note = f"; {self.unavailable}" if self.unavailable else ""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help{note})\n")


class _MissingDependency:
    """The stand-in of a command whose module cannot be imported (a missing optional dependency): the other
    commands still run, and this one fails with one line naming the module and what it lacks."""

    def __init__(self, command: str, module: str, error: ImportError):
        self.command, self.module, self.error = command, module, error

    def __call__(self, args):
        raise DdynError(f"this command needs {self.error.name or 'a module'} that {self.module} imports, "
                        f"which is not installed ({self.error})")


def _register(sub, cmd: Command, module: str) -> str | None:
    """Add the module's parser(s) to sub; when the module cannot be imported, a stand-in (a top-level command)
    or, for a group's module, whose subcommand names are in the module, the reason returned."""
    module, _, fn = module.partition(":")     # "module:function": another register function of it
    try:
        register = getattr(importlib.import_module(module), fn or "register")
    except ImportError as e:
        if cmd.help is not None:
            return f"{module} ({e})"
        stub = sub.add_parser(cmd.name, help=f"(unavailable: {e})", add_help=False)
        stub.set_defaults(func=_MissingDependency(cmd.name, module, e))
        return None
    register(sub)
    return None


def build_parser(commands: tuple[Command, ...] | None = None) -> argparse.ArgumentParser:
    """The parser of the given top-level commands (default all). Each command's module is imported here, so
    main() builds the parser of the one command it runs: a command's dependencies are loaded only when it runs,
    and one that is missing breaks that command alone."""
    parser = _Parser(prog="ddyn", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for cmd in COMMANDS if commands is None else commands:
        if cmd.help is None:
            (module,) = cmd.modules
            _register(sub, cmd, module)
            continue
        group = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        group_sub = group.add_subparsers(dest="subcommand", required=True, metavar="SUBCOMMAND")
        missing = [m for m in (_register(group_sub, cmd, module) for module in cmd.modules) if m]
        if missing:
            group.unavailable = "unavailable here (a missing dependency): " + "; ".join(missing)
            group.epilog = group.unavailable
    return parser


def _command_of(argv: list[str]) -> tuple[Command, ...] | None:
    """The top-level command argv names (its first word; the top-level parser has no options but --help),
    or None (no command, --help, an unknown name): then the parser of every command, for its listing."""
    first = next((a for a in argv if not a.startswith("-")), None)
    if first is None or argv.index(first) > 0:
        return None
    return commands_named(first) if first in {c.name for c in COMMANDS} else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command_of(argv))
    args, rest = parser.parse_known_args(argv)
    if rest and not isinstance(args.func, _MissingDependency):   # the stand-in takes any arguments
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    name = " ".join(filter(None, (args.command, getattr(args, "subcommand", None))))
    try:
        result = args.func(args)
    except DdynError as e:
        print(f"ddyn {name}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        # a file the command could not read or write (a folder where a file belongs, a full disk, no
        # permission) that its own checks did not catch first: still one line naming the file
        if e.filename is None:
            raise
        print(f"ddyn {name}: error: {e.filename}: {e.strerror or e}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
