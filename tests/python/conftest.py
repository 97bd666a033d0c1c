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



@pytest.fixture(scope="session")
def multicast_route() -> str:
    """A route for LCM's multicast group (the tests that log over UDP multicast need one): set up here
    when the host has none (`ip route add GROUP/32 dev lo`, as scripts/test.sh does before pytest); a
    host where it cannot be added fails the test with the command, never a skip."""
    import subprocess

    from ddyn.sil.run import LCM_GROUP
    if subprocess.run(["ip", "route", "get", LCM_GROUP], capture_output=True).returncode != 0:
        r = subprocess.run(["ip", "route", "add", f"{LCM_GROUP}/32", "dev", "lo"], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.fail(f"no route for LCM's multicast group {LCM_GROUP} and none could be added "
                        f"({r.stderr.strip()}): run `ip route add {LCM_GROUP}/32 dev lo` as root")
    return LCM_GROUP


@pytest.fixture
def one_torch_thread():
    """Tiny trainings run faster on one thread, and do not fight other jobs on a small machine (a test module
    opts in with `pytestmark = pytest.mark.usefixtures("one_torch_thread")`)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# The SIL tests' car, track and executables (one set for the session: the binaries are built once)
@pytest.fixture(scope="session")
def orca():
    from ddyn.model.vehicle import load as load_vehicle

    return load_vehicle("orca_1_43")


@pytest.fixture(scope="session")
def mobil(shared_data):
    from ddyn.model.tracks import load_track

    return load_track("ethzMobil", shared_data)


@pytest.fixture(scope="session")
def sil_bins():
    """The SIL executables, built for the fixture network (with the build's test key)."""
    from ddyn.sil import run as sil

    return sil.build_binaries(None)
