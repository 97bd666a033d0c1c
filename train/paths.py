"""Where things are: the repository and the shared reference data (override: DDYN_SHARED_DATA)."""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    return Path(os.environ.get("DDYN_SHARED_DATA", REPO.parent / "shared" / "data"))
