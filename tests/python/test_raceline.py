"""The vehicle's own time-optimal line (train/control/raceline.py) and its use by the MPC table."""
from __future__ import annotations

import numpy as np
import pytest

from ddyn.control import raceline as R
from ddyn.control.mpc_setup import FOOTPRINT, MpcSettings, raceline_table
from ddyn.model.tracks import load_track
from ddyn.model.vehicle import load as load_vehicle


@pytest.fixture(scope="module")
def mobil():
    return load_track("ethzMobil")


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


def test_committed_line_is_the_vehicles_and_stays_inside(mobil, orca):
    path = R.default_path(orca.name, mobil.name)
    assert path.is_file(), "train/racelines/orca_1_43_ethzMobil.npz is committed (ddyn mpc raceline writes it)"
    meta = R.meta_of(path)
    assert meta["vehicle"] == orca.name and meta["track"] == mobil.name
    assert meta["vehicle_digest"] == orca.digest, "vehicle file changed: recompute with `ddyn mpc raceline`"
    assert meta["ipopt_status"] == "Solve_Succeeded"
    line = R.line_for(mobil, orca.name)
    assert line.path == str(path)
    # the footprint's centre keeps half the car's width + the margin from the bounds (curvilinear
    # corners are approximate on the tightest arcs: allow 5 mm)
    half = 0.5 * FOOTPRINT[orca.name][1]
    depth = mobil.boundary_distance(line.x, line.y)
    assert depth.min() >= half + meta["settings"]["margin"] - 0.005
    # one lap: the last point lies just before the start, progress covers the track
    s, _ = mobil.project(line.x, line.y)
    ds = (np.diff(s) + mobil.length / 2) % mobil.length - mobil.length / 2
    assert np.all(ds > 0) and abs(np.sum(ds) - mobil.length) < 0.1
    # the car can drive it: the speed never exceeds the drivetrain's top speed at full throttle
    c = orca.true_coefficients
    a, b, k = c["Cd"], c["Cm2"], c["Cm1"] - c["Cr0"]
    top = (-b + np.sqrt(b * b + 4 * a * k)) / (2 * a)
    assert line.speed.max() < top
    assert line.time[-1] < meta["lap_time_s"] < 1.2 * mobil.length / line.speed.mean()


def test_mpc_table_uses_the_computed_line(mobil, orca):
    table = raceline_table(mobil, orca.name, MpcSettings())
    line = R.line_for(mobil, orca.name)
    assert np.hypot(table["x"][0] - line.x[0], table["y"][0] - line.y[0]) < 1e-9
    assert table["speed"].max() <= line.speed.max() + 1e-9
    # a line without a committed computed one falls back to the data's line
    other = load_track("ethz")
    assert R.line_for(other, orca.name) is other.raceline


def test_solve_reproduces_the_committed_line(mobil, orca):
    """A fresh IPOPT solve at the committed settings gives the committed lap (about 45 s)."""
    path = R.default_path(orca.name, mobil.name)
    meta = R.meta_of(path)
    settings = R.RacelineSettings(**meta["settings"])
    result = R.solve(orca, mobil, settings)
    arrays = R.raceline_arrays(orca, mobil, result, settings)
    with np.load(path) as z:
        assert abs(result["T"] - meta["lap_time_s"]) < 1e-4 * meta["lap_time_s"]
        assert np.max(np.hypot(arrays["x"] - z["x"], arrays["y"] - z["y"])) < 1e-3
        assert np.max(np.abs(arrays["speed"] - z["speed"])) < 1e-2


def test_tighter_margin_gives_a_faster_lap(mobil, orca):
    """The optimum reacts to its constraints: less room to the bounds, shorter lap (coarse grid)."""
    coarse = dict(intervals=80)
    wide = R.solve(orca, mobil, R.RacelineSettings(margin=0.05, **coarse))["T"]
    tight = R.solve(orca, mobil, R.RacelineSettings(margin=0.01, **coarse))["T"]
    assert tight < wide - 0.02
