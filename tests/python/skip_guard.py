"""pytest plugin: a skipped test fails the run unless tests/skip_allowlist.txt lists it.

A skip here nearly always means a dependency or data set was missing; on CI that must be a failure,
not a quiet pass. DDYN_ALLOW_SKIPS=1 reports the skips without failing (local runs only).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from check_skips import ALLOWLIST, unexpected  # noqa: E402

_SKIPPED: dict[str, str] = {}


def _record_skip(report) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        _SKIPPED[report.nodeid] = reason


def pytest_runtest_logreport(report):
    _record_skip(report)


def pytest_collectreport(report):
    _record_skip(report)


def pytest_sessionfinish(session, exitstatus):
    bad = unexpected("pytest", sorted(_SKIPPED))
    if bad and os.environ.get("DDYN_ALLOW_SKIPS") != "1" and session.exitstatus == 0:
        lines = "\n".join(f"  {n}: {_SKIPPED[n]}" for n in bad)
        session.config.get_terminal_writer().line(
            f"\nSKIPPED TESTS FAIL THE RUN ({len(bad)} not on {ALLOWLIST}; DDYN_ALLOW_SKIPS=1 to allow locally):\n"
            f"{lines}", red=True)
        session.exitstatus = 1
