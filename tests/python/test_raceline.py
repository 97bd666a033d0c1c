"""The vehicle's own time-optimal line (train/control/raceline.py) and its use by the MPC table."""
from __future__ import annotations

import numpy as np
import pytest

from ddyn.control import raceline as R
from ddyn.control.mpc_setup import MpcSettings, raceline_table
from ddyn.errors import DdynError
from ddyn.model.track_files import open_track, track_digest
from ddyn.model.tracks import load_track
from ddyn.model.vehicle import FOOTPRINT
from ddyn.model.vehicle import load as load_vehicle

COMMITTED = ("ethzMobil", "ethz")


@pytest.fixture(scope="module")
def mobil():
    return load_track("ethzMobil")


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


@pytest.mark.parametrize("name", COMMITTED)
def test_committed_line_is_the_vehicles_and_stays_inside(name, orca):
    track = load_track(name)
    path = R.default_path(orca.name, name)
    assert path.is_file(), f"train/racelines/orca_1_43_{name}.npz is committed (ddyn mpc raceline writes it)"
    meta = R.meta_of(path)
    assert meta["vehicle"] == orca.name and meta["track"] == name
    assert meta["vehicle_digest"] == orca.digest, "vehicle file changed: recompute with `ddyn mpc raceline`"
    assert meta["track_digest"] == track_digest(track)
    assert meta["ipopt_status"] == "Solve_Succeeded"
    line = R.line_for(track, orca.name)
    assert line.path == str(path)
    # the footprint's centre keeps half the car's width + the margin from the bounds (the frame's
    # straight normals against the polygonal bounds: allow 5 mm)
    half = 0.5 * FOOTPRINT[orca.name][1]
    depth = track.boundary_distance(line.x, line.y)
    assert depth.min() >= half + meta["settings"]["margin"] - 0.005
    # one lap: the last point lies just before the start, progress covers the track
    s, _ = track.project(line.x, line.y)
    ds = (np.diff(s) + track.length / 2) % track.length - track.length / 2
    assert np.all(ds > 0) and abs(np.sum(ds) - track.length) < 0.1
    # the car can drive it: the speed never exceeds the drivetrain's top speed at full throttle
    c = orca.true_coefficients
    a, b, k = c["Cd"], c["Cm2"], c["Cm1"] - c["Cr0"]
    top = (-b + np.sqrt(b * b + 4 * a * k)) / (2 * a)
    assert line.speed.max() < top
    assert line.time[-1] < meta["lap_time_s"] < 1.2 * track.length / line.speed.mean()


def test_mpc_table_uses_the_computed_line(mobil, orca, monkeypatch, tmp_path):
    table = raceline_table(mobil, orca.name, MpcSettings())
    line = R.line_for(mobil, orca.name)
    assert np.hypot(table["x"][0] - line.x[0], table["y"][0] - line.y[0]) < 1e-9
    assert table["speed"].max() <= line.speed.max() + 1e-9
    # a track without a computed line falls back to the data's line
    monkeypatch.setattr(R, "RACELINE_DIR", tmp_path)
    assert R.line_for(mobil, orca.name) is mobil.raceline


def test_a_line_of_another_track_with_the_same_name_is_not_used(orca, tmp_path, monkeypatch):
    """A user's track named like a committed line's track gets no line from it (geometry digest)."""
    from ddyn.model.track_files import write_track

    src = load_track("ethzMobil")
    write_track(src, tmp_path / "ethzMobil")
    user = open_track(str(tmp_path / "ethzMobil"), orca.name)
    monkeypatch.setattr(R, "USER_RACELINE_DIR", tmp_path / "lines")
    arrays = {"x": np.zeros(3), "y": np.zeros(3), "time": np.zeros(3), "speed": np.zeros(3),
              "inputs": np.zeros((2, 2)), "meta": np.array('{"track_digest": "0000"}')}
    R.save(R.default_path(orca.name, user), arrays)
    with pytest.raises(DdynError, match="no raceline"):
        R.line_for(user, orca.name)


@pytest.mark.parametrize("name", COMMITTED)
def test_solve_reproduces_the_committed_line(name, orca):
    """A fresh IPOPT solve at the committed settings lands on the committed line (ETHZ ~20 s, ETHZMobil ~35 s).
    The line is a nonconvex NLP: with another CPU's floating point IPOPT can stop at a neighbouring local optimum.
    Measured: on the machine that made the lines both reproduce exactly; on another, ETHZMobil stops after 120
    iterations (142 there) at a lap 0.21 % slower, 1.1 cm and 0.041 m/s off the committed line. So: the committed
    lap no slower than the fresh one (a line from other settings or an older model would be), and the fresh one
    within 0.5 % of it, 2 cm and 0.1 m/s."""
    track = load_track(name)
    path = R.default_path(orca.name, name)
    meta = R.meta_of(path)
    settings = R.RacelineSettings(**meta["settings"])
    result = R.solve(orca, track, settings)
    arrays = R.raceline_arrays(orca, track, result, settings)
    with np.load(path) as z:
        assert meta["lap_time_s"] <= result["T"] * (1 + 1e-4)
        assert result["T"] - meta["lap_time_s"] < 5e-3 * meta["lap_time_s"]
        assert np.max(np.hypot(arrays["x"] - z["x"], arrays["y"] - z["y"])) < 2e-2
        assert np.max(np.abs(arrays["speed"] - z["speed"])) < 1e-1


def test_tighter_margin_gives_a_faster_lap(mobil, orca):
    """The optimum reacts to its constraints: less room to the bounds, shorter lap (coarse grid)."""
    coarse = dict(intervals=80)
    wide = R.solve(orca, mobil, R.RacelineSettings(margin=0.05, **coarse))["T"]
    tight = R.solve(orca, mobil, R.RacelineSettings(margin=0.01, **coarse))["T"]
    assert tight < wide - 0.02
