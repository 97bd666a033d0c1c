"""docs/commands.md is generated from the parsers (ddyn.commands_doc) and must be current: after changing a parser,
run `.venv/bin/python -m ddyn.commands_doc --write`."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

from ddyn import commands_doc
from ddyn.cli import build_parser
from ddyn.paths import REPO


def test_commands_md_is_current():
    assert commands_doc.DOC.read_text() == commands_doc.render(), (
        "docs/commands.md is not what the parsers give: run .venv/bin/python -m ddyn.commands_doc --write")


def _all_parsers(parser, prog="ddyn"):
    yield prog, parser
    for name, _, sub in commands_doc._subcommands(parser):
        yield from _all_parsers(sub, f"{prog} {name}")


def test_every_command_and_option_is_in_the_doc():
    text = commands_doc.render()
    sections = {}
    for block in text.split("\n#")[1:]:
        title, _, body = block.lstrip("#").strip().partition("\n")
        sections[title] = body
    n = 0
    for prog, parser in _all_parsers(build_parser()):
        if prog == "ddyn":
            continue
        assert prog in sections, f"{prog} has no section"
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            # a positional appears under its metavar where it has one (`[NAME ...]`), else under its name
            for flag in action.option_strings or [action.metavar if isinstance(action.metavar, str) else action.dest]:
                assert flag in sections[prog], f"{prog}: {flag} missing"
                n += 1
    assert n > 300


def test_the_doc_does_not_depend_on_this_machine(tmp_path):
    """Defaults that are machine paths (build folder, shared data, the repository) are written relative."""
    env = dict(os.environ, DDYN_BUILD_DIR=str(tmp_path / "elsewhere"), DDYN_SHARED_DATA=str(tmp_path / "data"))
    out = subprocess.run([sys.executable, "-m", "ddyn.commands_doc"], env=env, capture_output=True, text=True,
                         check=True).stdout
    assert out == commands_doc.render()
    assert str(REPO) not in out and str(tmp_path) not in out
