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


def putnam_log() -> Path:
    """The real AV-21 log of the shared data (Putnam Park, RACECAR format) the studies train and score on."""
    return shared_data_dir() / "real" / "Putnam_park2023_run4_2.csv"


def check_writable(path: str | os.PathLike, what: str = "output", directory: bool = False) -> Path:
    """Refuse, before any work, an output path that cannot be written: an existing directory where a file is
    meant, a parent that is a file, or a place this process may not create a file in. Creates nothing and
    changes nothing (an existing file is opened for appending, a missing one tried as a temporary file in its
    nearest existing folder). directory: the path is an output folder (existing or to be made) instead of a
    file. DdynError names the option (`what`) and the path."""
    import tempfile

    from ddyn.errors import DdynError

    p = Path(path)
    if str(path) == "":
        raise DdynError(f"{what}: empty path")
    if p.is_dir() and not directory:
        raise DdynError(f"{what} {p}: is a directory, expected a file path")
    try:
        if directory and p.is_dir():
            with tempfile.TemporaryFile(dir=p):
                pass
            return p
        if directory and p.exists():
            raise DdynError(f"{what} {p}: is a file, expected a directory")
        if p.exists():
            with open(p, "ab"):
                pass
            return p
        parent = p.parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise DdynError(f"{what} {p}: {parent} is not a directory")
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise DdynError(f"{what} {p}: cannot be written ({e.strerror or e})") from None
    return p
