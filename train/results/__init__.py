"""Results as data: the headline figures as small committed files, the README's table made from them, and a
checker that re-runs their commands.

- `ddyn.results.files`: a result file (`results/<name>.json`), loaded and validated (`load`, `load_all`);
- `ddyn.results.table`: the README's results table between its two marker comments (`render_table`, `readme_with_table`);
- `ddyn.results.check`: re-run a file's commands in a temporary folder and compare each figure within the
  tolerance the file states (`check_result`);
- `ddyn.results.cli`: `ddyn results check [--fast] [NAME ...]` and `ddyn results table [--write]`.

The format is described in results/README.md.
"""
from __future__ import annotations

import importlib

__all__ = ["RESULTS_DIR", "Figure", "ResultFile", "load", "load_all"]


def __getattr__(name: str):
    """The names above load ddyn.results.files on first use (package inits import nothing: test_package_layout)."""
    if name not in __all__:
        raise AttributeError(f"module 'ddyn.results' has no attribute {name!r}")
    return getattr(importlib.import_module("ddyn.results.files"), name)
