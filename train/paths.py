"""Where things are: the repository and the shared reference data (override: DDYN_SHARED_DATA)."""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# The C build whose tools the commands drive (ddyn_bench, ddyn_mpc_lap, ...): the main job's build/
# by default; scripts/test.sh sets DDYN_BUILD_DIR to its own build-test/, so that running the tests
# never replaces the main job's build (built for the trained network) with the fixture network's.
BUILD = Path(os.environ.get("DDYN_BUILD_DIR") or REPO / "build")


def shared_data_dir() -> Path:
    return Path(os.environ.get("DDYN_SHARED_DATA", REPO.parent / "shared" / "data"))
