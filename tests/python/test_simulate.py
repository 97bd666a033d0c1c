"""Tracks and closed-loop simulation (ddyn.model.tracks, ddyn.data.simulate)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import pytest

from ddyn.data.simulate import NOISY_CHANNELS, register, simulate
from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model import vehicle as vehicles
from ddyn.model.single_track import STATE_NAMES
from ddyn.model.tracks import Track, load_track

DATA = Path(os.environ.get("DDYN_SHARED_DATA") or Path(__file__).resolve().parents[2].parent / "shared" / "data")
if not (DATA / "tracks").is_dir():
    pytest.skip(f"SHARED DATA MISSING: {DATA / 'tracks'} does not exist; the track and simulation tests "
                f"need it (set DDYN_SHARED_DATA)", allow_module_level=True)

ORCA = vehicles.load("orca_1_43")
AV21 = vehicles.load("av21")


def _track(name: str) -> Track:
    return load_track(name, DATA)


def _margin_outside(track: Track, ds) -> np.ndarray:
    """Per row: how far the (true) position lies beyond the nearer bound (negative: inside)."""
    x = ds.extras.get("true_x", ds.column("x"))
    y = ds.extras.get("true_y", ds.column("y"))
    return -track.boundary_distance(x, y)


# ---------------------------------------------------------------------------------------------- tracks

@pytest.mark.parametrize("name, length, width, n", [("ethz", 17.8, 0.37, 666), ("ethzMobil", 12.8, 0.46, 377)])
def test_eth_tracks_load(name, length, width, n):
    t = _track(name)
    assert t.n == n
    assert t.length == pytest.approx(length, abs=0.1)
    assert t.width == pytest.approx(width, abs=0.01)
    assert np.all(t.half_width_left > 0.45 * width) and np.all(t.half_width_right > 0.45 * width)
    assert t.raceline is not None and len(t.raceline.x) == len(t.raceline.speed)
    # the racing line lies within the bounds
    assert np.all(t.inside(t.raceline.x, t.raceline.y, margin=0.01))


def _total_turn(t: Track) -> float:
    return float(np.sum(t.curvature_raw * 0.5 * (t._len + np.roll(t._len, 1))))


def test_putnam_centre_line_is_a_sensible_closed_loop():
    t = _track("putnam")
    assert 2000 < t.length < 5000                       # a road course of a few km (about 2.85 km)
    assert t.raceline is None
    assert 7.0 < t.width < 11.0                          # bounds about 9 m apart
    # evenly spaced, including the closing segment back to the start
    step = np.hypot(*(np.roll(t.center, -1, axis=0) - t.center).T)
    assert step.max() / step.min() < 1.05
    # a simple loop turns once in total (no figure-eights, folds or reversals)
    assert abs(abs(_total_turn(t)) - 2 * np.pi) < 0.05
    # between the bounds everywhere, roughly in the middle
    assert np.all(t.half_width_left > 0.35 * t.width) and np.all(t.half_width_right > 0.35 * t.width)
    # driven in the direction of the files' points (the real car's direction)
    i = np.argmin(np.hypot(t.inner[:, 0] - t.x[0], t.inner[:, 1] - t.y[0]))
    d_bound = t.inner[(i + 1) % len(t.inner)] - t.inner[i]
    assert np.dot(d_bound, [np.cos(t.heading[0]), np.sin(t.heading[0])]) > 0


def test_eth_centre_lines_turn_once():
    for name in ("ethz", "ethzMobil"):
        assert abs(abs(_total_turn(_track(name))) - 2 * np.pi) < 0.05


def test_missing_track_file_names_the_path(tmp_path):
    with pytest.raises(DdynError, match=str(tmp_path / "tracks" / "ethz_center.txt").replace("\\", "\\\\")):
        load_track("ethz", tmp_path)
    with pytest.raises(DdynError, match="putnam_inner_bound.csv"):
        load_track("putnam", tmp_path)
    with pytest.raises(DdynError, match="unknown track"):
        load_track("monza", tmp_path)


def _circle(r: float, n: int, w: float) -> Track:
    a = np.arange(n) * 2 * np.pi / n
    ring = lambda rad: np.c_[rad * np.cos(a), rad * np.sin(a)]  # noqa: E731
    return Track("circle", ring(r), ring(r - w / 2), ring(r + w / 2))


def test_projection_on_a_synthetic_circle():
    r, w = 10.0, 2.0
    t = _circle(r, 2000, w)                              # counter-clockwise: left is the inside
    assert t.length == pytest.approx(2 * np.pi * r, rel=1e-5)
    assert t.width == pytest.approx(w, rel=1e-4)
    assert t.left_name == "inner"
    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 2 * np.pi, 500)
    rad = rng.uniform(r - 3, r + 3, 500)
    s, lat = t.project(rad * np.cos(theta), rad * np.sin(theta))
    # the polygon's arc length is within its sagitta of the circle's
    expect_s = theta / (2 * np.pi) * t.length
    ds = (s - expect_s + t.length / 2) % t.length - t.length / 2
    assert np.max(np.abs(ds)) < 1e-3 * r
    assert np.allclose(lat, r - rad, atol=2e-4 * r)
    inside = t.inside(rad * np.cos(theta), rad * np.sin(theta))
    clear = np.abs(np.abs(rad - r) - w / 2) > 1e-3 * r   # not within the polygon's error of a bound
    assert np.array_equal(inside[clear], (np.abs(rad - r) < w / 2)[clear])
    # windowed search gives the same answer near the hint, and shapes are kept
    s2, lat2 = t.project(rad * np.cos(theta), rad * np.sin(theta), s_hint=expect_s, window=1.0)
    assert np.allclose(s2, s) and np.allclose(lat2, lat)
    s0, l0 = t.project(r + 0.5, 0.0)
    assert np.shape(s0) == () and s0 == pytest.approx(0.0, abs=1e-9) and l0 == pytest.approx(-0.5)


def test_projection_recovers_offsets_on_ethz():
    t = _track("ethz")
    rng = np.random.default_rng(2)
    s_true = rng.uniform(0, t.length, 300)
    off = rng.uniform(-0.15, 0.15, 300)
    x, y = t.position(s_true)
    h = t.heading_at(s_true)
    px, py = x - off * np.sin(h), y + off * np.cos(h)  # left normal
    s, lat = t.project(px, py)
    ds = (s - s_true + t.length / 2) % t.length - t.length / 2
    # exact on straights, approximate near the polygon's vertices in corners
    assert np.median(np.abs(ds)) < 1e-6 and np.median(np.abs(lat - off)) < 1e-9
    assert np.max(np.abs(lat - off)) < 0.02
    assert np.all(t.inside(px, py))
    # 0.3 m off the centre line, on the outside of any curve, is off this part of the track (it may lie on
    # a neighbouring part, hence the hint; towards the inside of a corner tighter than 0.3 m it comes back)
    side = np.where(t.curvature_at(s_true) > 0, -1.0, 1.0)
    ox, oy = x - side * 0.3 * np.sin(h), y + side * 0.3 * np.cos(h)
    assert not np.any(t.inside(ox, oy, s_hint=s_true, window=0.5))


# ---------------------------------------------------------------------------------------------- simulation

@pytest.fixture(scope="module")
def lap_ethz():
    return simulate(ORCA, _track("ethz"), laps=1, seed=0, progress=False)


@pytest.fixture(scope="module")
def lap_mobil():
    return simulate(ORCA, _track("ethzMobil"), laps=1, seed=0, progress=False)


@pytest.mark.parametrize("which, name", [("lap_ethz", "ethz"), ("lap_mobil", "ethzMobil")])
def test_one_lap_inside_bounds_at_a_sensible_speed(which, name, request):
    ds = request.getfixturevalue(which)
    track = _track(name)
    assert ds.metadata["laps"] == "1" and ds.metadata["track"] == name
    assert np.all(_margin_outside(track, ds) <= 0.0), "the car left the track"
    speed = np.hypot(ds.column("vx"), ds.column("vy"))
    assert 1.3 < speed.mean() < 2.5
    lap_time = ds.time[-1]
    assert track.length / lap_time == pytest.approx(speed.mean(), rel=0.15)
    # the excitation makes it slide somewhat, not only roll round steady corners
    beta = np.abs(np.arctan2(ds.column("vy"), ds.column("vx")))
    assert np.degrees(beta.max()) > 5.0
    assert len(ds) == len(ds.time) and ds.sample_time == ORCA.sample_time
    assert np.all(ds.segment == 0) and np.allclose(np.diff(ds.time), ORCA.sample_time)
    assert ds.vehicle == "orca_1_43" and "ethz" in ds.source


@pytest.mark.parametrize("which", ["lap_ethz", "lap_mobil"])
def test_inputs_respect_limits(which, request):
    ds = request.getfixturevalue(which)
    lim = ORCA.input_limits
    for col, key in (("throttle", "throttle"), ("steering", "steering"), ("dthrottle", "dthrottle"),
                     ("dsteering", "dsteering")):
        v = ds.column(col)
        assert v.min() >= lim[key][0] and v.max() <= lim[key][1], col
    # and they are used: the steering and its rate reach their limits in the hairpins
    assert np.abs(ds.column("steering")).max() > 0.9 * lim["steering"][1]


def test_rows_chain_with_euler(lap_ethz):
    ds = lap_ethz
    nxt = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], ORCA.true_vector(), ORCA.known, ds.sample_time,
                              "euler", 1)
    assert np.max(np.abs(nxt - ds.states[1:])) <= 1e-12
    assert ds.metadata["method"] == "euler"


def test_rows_chain_with_rk4():
    ds = simulate(ORCA, _track("ethzMobil"), duration=3.0, method="rk4", seed=3, progress=False)
    assert ds.metadata["method"] == "rk4" and ds.metadata["substeps"] == str(ORCA.rk4_substeps)
    nxt = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], ORCA.true_vector(), ORCA.known, ds.sample_time,
                              "rk4", ORCA.rk4_substeps)
    assert np.max(np.abs(nxt - ds.states[1:])) <= 1e-12
    assert len(ds) == 150


def test_determinism():
    track = _track("ethzMobil")
    a = simulate(ORCA, track, duration=2.0, seed=7, progress=False)
    b = simulate(ORCA, track, duration=2.0, seed=7, progress=False)
    c = simulate(ORCA, track, duration=2.0, seed=8, progress=False)
    assert np.array_equal(a.states, b.states) and np.array_equal(a.inputs, b.inputs)
    assert a.content_hash() == b.content_hash()
    assert not np.array_equal(a.states, c.states)


def test_noise_is_measurement_only():
    track = _track("ethz")
    clean = simulate(ORCA, track, duration=12.0, seed=4, progress=False)
    noisy = simulate(ORCA, track, duration=12.0, seed=4, noise_scale=2.0, progress=False)
    assert set(noisy.extras) == {f"true_{c}" for c in NOISY_CHANNELS}
    # the plant and the driver are untouched: same trajectory, throttle, steering and inputs
    for c in NOISY_CHANNELS:
        assert np.array_equal(noisy.extras[f"true_{c}"], clean.column(c))
    for c in ("throttle", "steering"):
        assert np.array_equal(noisy.column(c), clean.column(c))
    assert np.array_equal(noisy.inputs, clean.inputs)
    n = len(noisy)
    for c in NOISY_CHANNELS:
        err = noisy.column(c) - noisy.extras[f"true_{c}"]
        want = 2.0 * ORCA.sensor_noise_std[c]
        assert np.std(err) == pytest.approx(want, rel=4.0 / np.sqrt(n) + 0.02), c
        assert abs(np.mean(err)) < 4.0 * want / np.sqrt(n), c
    assert noisy.metadata["noise_scale"] == "2.0"


def test_av21_on_putnam_stays_on_track():
    track = _track("putnam")
    ds = simulate(AV21, track, duration=20.0, seed=0, progress=False)
    assert len(ds) == 500 and ds.sample_time == AV21.sample_time
    assert np.all(_margin_outside(track, ds) <= 0.0)
    speed = np.hypot(ds.column("vx"), ds.column("vy"))
    assert 15.0 < speed.mean() < 35.0
    lim = AV21.input_limits
    assert lim["steering"][0] <= ds.column("steering").min() and ds.column("steering").max() <= lim["steering"][1]
    assert lim["dsteering"][0] <= ds.column("dsteering").min() and ds.column("dsteering").max() <= lim["dsteering"][1]


def test_stops_at_laps_from_any_start():
    track = _track("ethzMobil")
    ds = simulate(ORCA, track, laps=0.5, start_s=9.0, seed=1, progress=False)
    prog = float(ds.metadata["progress_laps"])
    assert 0.5 <= prog < 0.5 + 3.0 * ds.states[:, 3].max() * ds.sample_time / track.length
    assert ds.metadata["laps"] == "0"


def test_bad_arguments_raise():
    track = _track("ethzMobil")
    with pytest.raises(DdynError, match="method"):
        simulate(ORCA, track, duration=1.0, method="midpoint", progress=False)
    with pytest.raises(DdynError, match="laps"):
        simulate(ORCA, track, laps=0, progress=False)
    with pytest.raises(DdynError, match="left the track"):
        simulate(ORCA, track, duration=10.0, target_speed=6.0, grip=2.5, excitation=0.0, progress=False)


def test_cli_writes_a_canonical_file(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DDYN_SHARED_DATA", str(DATA))
    parser = argparse.ArgumentParser(prog="ddyn")
    register(parser.add_subparsers(dest="command"))
    out = tmp_path / "sim.csv"
    args = parser.parse_args(["simulate", "--vehicle", "orca_1_43", "--track", "ethzMobil", "--duration", "2",
                              "--noise", "1", "--seed", "5", "-q", "-o", str(out)])
    assert args.func(args) == 0
    text = out.read_text().splitlines()
    assert text[0] == "# ddyn-dataset 1"
    assert "# method: euler" in text and "# seed: 5" in text
    header = next(line for line in text if not line.startswith("#"))
    cols = header.split(",")
    assert cols[:12] == ["time", "segment", *STATE_NAMES, "dthrottle", "dsteering"]
    assert "true_vx" in cols
    table = np.loadtxt(out, delimiter=",", comments="#", skiprows=1 + text.index(header))
    ref = simulate(ORCA, _track("ethzMobil"), duration=2.0, noise_scale=1.0, seed=5, progress=False)
    assert table.shape == (len(ref), len(cols))
    assert np.array_equal(table[:, 2:10], ref.states)    # repr round-trips float64 exactly
    printed = capsys.readouterr().out
    assert "rows" in printed and "max lateral offset" in printed
