"""Shared fixtures: where the shared reference data lives; skips fail the run unless allow-listed."""
from __future__ import annotations

from pathlib import Path

import pytest

from ddyn.paths import shared_data_dir

# a skipped test fails the run unless tests/skip_allowlist.txt lists it (tests/python/skip_guard.py)
pytest_plugins = ["skip_guard"]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data folder; a test that needs it is skipped loudly when it is absent."""
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"SHARED DATA MISSING: {d} does not exist (set DDYN_SHARED_DATA)")
    return d

