"""Shared fixtures: where the shared reference data lives."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path:
    return Path(os.environ.get("DDYN_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder; a test that needs it is skipped loudly when it is absent."""
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"SHARED DATA MISSING: {d} does not exist (set DDYN_SHARED_DATA)")
    return d
