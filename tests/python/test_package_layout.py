"""The Python package's shape (README, Architecture): one importable package `ddyn` whose
subpackages import each other without cycles, and a command line grouped by noun."""
from __future__ import annotations

import ast
import importlib
import tomllib
from pathlib import Path

import pytest

import ddyn
import ddyn.codegen
from ddyn.cli import build_parser
from ddyn.paths import BUILD

REPO = Path(__file__).resolve().parents[2]
PACKAGE_ROOTS = {"ddyn": Path(ddyn.__file__).parent, "ddyn.codegen": Path(ddyn.codegen.__file__).parent}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg, root in PACKAGE_ROOTS.items():
        for f in root.rglob("*.py"):
            rel = f.relative_to(root).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            mods[".".join([pkg, *parts])] = f
    return mods


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Every ddyn module `name` imports, at the top or inside a function (a lazy import is still a cycle)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            cands = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                mod = ".".join(base[: len(base) - node.level + 1] + ([mod] if mod else []))
            cands = [mod] + [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        out |= {c for c in cands if c in known and c != name}
    return out


def test_the_package_is_ddyn_only():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert all(p == "ddyn" or p.startswith("ddyn.") for p in cfg["packages"])
    assert cfg["package-dir"] == {"ddyn": "train", "ddyn.codegen": "codegen"}
    assert set(_modules()) >= {"ddyn.model.single_track", "ddyn.codegen.generate", "ddyn.sil.run"}


def test_no_import_cycles():
    mods = _modules()
    graph = {m: _imports(m, p, set(mods)) for m, p in mods.items()}
    # a package's __init__ is imported with any of its modules; the inits here import nothing,
    # so edges to a package are edges to an empty module and cannot close a cycle
    assert all(not graph[p] for p in mods if mods[p].name == "__init__.py"), "an __init__ imports a module"
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_every_module_imports():
    for m in sorted(_modules()):
        importlib.import_module(m)


def _commands(parser) -> dict:
    for action in parser._actions:
        if action.__class__.__name__ == "_SubParsersAction":
            return action.choices
    return {}


def test_commands_are_grouped_and_say_what_they_do():
    top = _commands(build_parser())
    # 18: the noun groups plus the `diagnose` alias of `gap diagnose` (kept for old scripts) and `results`
    assert len(top) <= 18, sorted(top)
    helps = {a.dest: a.help for p in [build_parser()] for act in p._actions
             if act.__class__.__name__ == "_SubParsersAction" for a in act._choices_actions}
    for name, parser in top.items():
        assert helps.get(name), f"ddyn {name} has no help"
        for sub, sub_parser in _commands(parser).items():
            sub_helps = {a.dest: a.help for act in parser._actions
                         if act.__class__.__name__ == "_SubParsersAction" for a in act._choices_actions}
            assert sub_helps.get(sub), f"ddyn {name} {sub} has no help"
    assert set(_commands(top["sil"])) == {"run", "table", "faults", "pid-sweep", "tracks"}
    assert set(_commands(top["can"])) == {"codegen", "export", "import", "replay", "record", "bench"}
    assert set(_commands(top["study"])) >= {"ddm", "fthd", "denoise"}
    assert set(_commands(top["gap"])) == {"diagnose", "calibrate", "lofo", "pool", "benchmark", "rescore"}


def test_default_tool_and_data_paths_point_into_the_repository():
    """Module-level default paths (build tools, racelines, vehicle files, generated code) must resolve
    from the repository root, not from a module's own folder, which moved in the restructure."""
    import pathlib

    checked = 0
    for m in sorted(_modules()):
        mod = importlib.import_module(m)
        for name, value in vars(mod).items():
            if name.isupper() and isinstance(value, pathlib.Path):
                checked += 1
                if value.is_relative_to(BUILD):
                    assert value == BUILD or value.parts[len(BUILD.parts)] == "c_src", f"{m}.{name} = {value}"
                elif "build" in value.parts:
                    assert value.is_relative_to(REPO / "build-net100k"), f"{m}.{name} = {value}"
                elif value.is_absolute() and value.is_relative_to(REPO / "out"):
                    continue  # outputs, made on demand
                elif value.is_absolute() and value.is_relative_to(REPO):
                    assert value.exists(), f"{m}.{name} = {value} does not exist"
    assert checked >= 5
