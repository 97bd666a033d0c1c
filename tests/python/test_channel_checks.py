"""The roll (pitch) channel's plausibility check on the channels a log can carry, and the laps a log's own path
gives when there is no track file (ddyn.data.roll_check, ddyn.data.laps, ddyn.gap.candidates.layout).

A real bank channel repeats lap after lap at the same spot (a map-derived one exactly, an IMU's with its body
roll and noise on top), however closely the bank follows the turns; a broken one (a random walk with jumps,
the real Putnam log's roll column) does not. The channels are built here from the simulated log's truth, so
they do not depend on which channel kinds the plant offers."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ddyn.data import laps as LP
from ddyn.data import roll_check as RC
from ddyn.gap import candidates as C
from ddyn.model.track_oval import oval_track
from ddyn.model.tracks import load_track
from ddyn.plants import commonroad_st as CP

G = 9.81
BODY_ROLL = 0.05          # rad per g: a saloon's body roll (out of the turn)
# a 554 m oval: 60 s at about 22 m/s drive 2.4 laps (the 20-degree turns, 9 and 5 on the straights)
OVAL = dict(straight=120.0, radius=50.0)


@pytest.fixture(scope="module")
def oval():
    # a 4-degree grade: above the 3 degrees that matter, below which a channel says flat (roll_check.FLAT)
    t = oval_track(**OVAL)
    ds = CP.make_log(t, CP.PlantEffects(grade=0.07, grade_phase=1.0), 1,
                     CP.LogSettings(duration=60.0, roll_channel=True, pitch_channel=True))
    return t, ds


@pytest.fixture(scope="module")
def putnam():
    """40 s of the flat Putnam track (no bank, no grade): under a lap, so no laps."""
    t = load_track("putnam")
    return t, CP.make_log(t, CP.PlantEffects(), 2, CP.LogSettings(duration=40.0, roll_channel=True,
                                                                  pitch_channel=True))


def _channels(track, ds) -> dict:
    """The roll channels a log can carry, from its truth: map-derived (the true bank held every 10 m along the
    track), IMU (bank, body roll out of the turn and an EKF's noise), broken (a random walk with jumps spanning
    radians, wrapped like an angle), drifting (the IMU's plus a 0.15 rad drift over the log: within range)."""
    e = ds.extras
    s, _ = track.project(e["true_x"], e["true_y"])
    world = getattr(track, "bank", None)
    world = np.zeros(track.n) if world is None else np.asarray(world, float)
    held = np.interp(10.0 * np.floor(s / 10.0), track.s, world, period=track.length)
    rng = np.random.default_rng(7)
    n = len(ds)
    body = e.get("true_body_roll", -BODY_ROLL * e["true_vx"] * e["true_omega"] / G)
    imu = e["true_bank"] + body + 0.003 * rng.standard_normal(n)
    walk = np.cumsum(0.01 * rng.standard_normal(n) + np.where(rng.random(n) < 0.003, rng.uniform(-2, 2, n), 0.0))
    return {"map": held, "map_other_sign": -held, "imu": imu,
            "broken": np.mod(walk + math.pi, 2 * math.pi) - math.pi,
            "drifting": imu + 0.15 * np.linspace(0.0, 1.0, n)}


def _with(ds, **channels):
    extras = {k: v for k, v in ds.extras.items() if k not in ("roll", "pitch")}
    return replace(ds, extras={**extras, **{k: v for k, v in channels.items() if v is not None}})


def _layout(ds, track=None):
    return C.layout(ds, track, np.arange(int(0.6 * len(ds))))


# -------------------------------------------------------------------------------------------------- laps

def _lined_laps(n_laps=2.9, amplitude=5.0, ts=0.04, speed=20.0):
    """A path round the oval whose line moves across the track (+-amplitude m, a period of 1.3 laps), so that
    every lap is driven on another line: (x, y, station along the centre line)."""
    t = oval_track(**OVAL)
    d = np.arange(0.0, n_laps * t.length, speed * ts)
    st = np.mod(d, t.length)
    x, y = t.position(st)
    h = t.heading_at(st)
    off = amplitude * np.sin(2 * math.pi * d / (1.3 * t.length))
    rng = np.random.default_rng(3)
    x = x - off * np.sin(h) + 0.02 * rng.standard_normal(len(d))
    y = y + off * np.cos(h) + 0.02 * rng.standard_normal(len(d))
    return t, x, y, st, d


def _spread_at_same_station(position, period, station, lap):
    """The largest difference (m) between a row's position and the first lap's at the same station."""
    first = lap == lap.min()
    order = np.argsort(station[first])
    ref = np.interp(station, station[first][order], position[first][order], period=None)
    diff = np.mod(position - ref + period / 2, period) - period / 2
    inner = (station > 5.0) & (station < station[first].max() - 5.0)   # the first lap's ends interpolate badly
    return float(np.max(np.abs(diff[~first & inner])))


def test_positions_from_laps_line_up_where_the_distance_travelled_does_not():
    t, x, y, st, d = _lined_laps()
    lp = LP.from_xy(x, y)
    assert lp.circuit and lp.laps == pytest.approx(2.9, abs=0.15)
    assert lp.length == pytest.approx(t.length, rel=0.03)      # the first lap's line: a few metres off the centre's
    assert np.all((lp.position >= 0) & (lp.position < lp.length)) and set(np.unique(lp.lap)) == {0, 1, 2}
    spread = _spread_at_same_station(lp.position, lp.length, st, lp.lap)
    assert spread < 3.0, spread
    # the distance travelled, wrapped at the first lap's: the lines' different lengths add up lap after lap
    travelled = LP.distance(np.column_stack([x, y]))
    by_distance = _spread_at_same_station(np.mod(travelled, lp.length), lp.length, st, lp.lap)
    assert by_distance > 10.0, by_distance


def test_layout_without_a_track_follows_the_logs_laps(oval, putnam):
    t, ds = oval
    lay = _layout(ds)
    assert lay.source.startswith("laps from x, y") and lay.length == pytest.approx(t.length, rel=0.01)
    assert len(lay.knots) == math.ceil(lay.length / C.KNOT_SPACING) and len(lay.free) == len(lay.knots)
    lp = LP.from_dataset(ds)
    s, _ = t.project(ds.extras["true_x"], ds.extras["true_y"])
    assert _spread_at_same_station(lay.position, lay.length, s, lp.lap) < 3.0
    # under a lap: no circuit, the distance travelled, and why
    tp, short = putnam
    lay = _layout(short)
    assert lay.length is None and lay.source.startswith("distance travelled (")
    assert "no complete lap" in lay.source
    assert np.array_equal(lay.position, C._distance(short))


def test_the_real_putnam_log_drives_laps(shared_data):
    from ddyn.data.importers import read_racecar_csv

    src = shared_data / "real" / "Putnam_park2023_run4_2.csv"
    if not src.is_file():
        pytest.skip(f"SHARED DATA MISSING: {src}")
    ds = read_racecar_csv(src)
    lp = LP.from_dataset(ds)
    assert lp.circuit and 2.0 < lp.laps < 3.0
    assert lp.length == pytest.approx(load_track("putnam").length, rel=0.02)
    # its roll column is not the road's: out of range, too fast, and not the same at the same spot lap to lap
    v = RC.check_dataset(ds, "roll", lp)
    assert v["rule"] == "laps" and not v["plausible"] and v["verdict"] == "implausible"
    assert {"range", "rate", "repeat"} <= set(v["failed"]), v["reason"]
    assert v["repeat_rms_rad"] > 4 * RC.MAX_REPEAT_RMS


# -------------------------------------------------------------------------------------- the roll check

def test_bank_channels_on_the_banked_oval_are_accepted_and_broken_ones_rejected(oval):
    t, ds = oval
    ch = _channels(t, ds)
    lp = LP.from_dataset(ds)
    verdicts = {k: RC.check_dataset(_with(ds, roll=v), "roll", lp) for k, v in ch.items()}
    for k in ("map", "map_other_sign", "imu"):
        v = verdicts[k]
        assert v["rule"] == "laps" and v["plausible"] and v["verdict"] == "plausible", (k, v["reason"])
        assert v["repeat_rms_rad"] < 0.2 * RC.MAX_REPEAT_RMS
        assert v["profile_max_rad"] == pytest.approx(math.radians(20.0), abs=0.01)    # the turns' bank
        assert "follows the lap" in v["reason"]
    # the IMU's body roll comes out as the body roll, not as the bank's match with the turns
    assert verdicts["imu"]["body_roll_per_g_rad"] == pytest.approx(-BODY_ROLL, abs=0.01)
    assert abs(verdicts["map"]["body_roll_per_g_rad"]) < 0.01
    assert not verdicts["broken"]["plausible"] and {"range", "repeat"} <= set(verdicts["broken"]["failed"])
    # a drift within range: the same spot moves from lap to lap
    drift = verdicts["drifting"]
    assert not drift["plausible"] and "range" not in drift["failed"] and "drift" in drift["failed"], drift["reason"]
    # the diagnosis reads the bank from the accepted channels only, with or without a track file
    for k, v in ch.items():
        for track in (None, t):
            assert C.available("bank_from_roll", _layout(_with(ds, roll=v), track)) == (k in ("map", "map_other_sign",
                                                                                               "imu")), (k, track)
    assert not C.available("bank_from_roll", _layout(_with(ds)))                                 # no channel


def test_a_channel_that_says_the_road_is_flat_adds_no_bank(oval, putnam):
    t, ds = oval
    n = len(ds)
    rng = np.random.default_rng(2)
    body = -BODY_ROLL * ds.extras["true_vx"] * ds.extras["true_omega"] / G
    # on laps: a map of a flat road, and an IMU on it (body roll and noise only)
    for roll in (np.zeros(n), body + 0.003 * rng.standard_normal(n)):
        lay = _layout(_with(ds, roll=roll))
        v = lay.roll
        assert v["rule"] == "laps" and v["plausible"] and v["flat"] and v["verdict"] == "flat", v["reason"]
        assert v["reason"].startswith("flat:") and not C.available("bank_from_roll", lay)
    # without laps (40 s of Putnam, no bank): the map and the IMU channel say flat, the broken one is rejected
    tp, short = putnam
    ch = _channels(tp, short)
    for k in ("map", "imu"):
        lay = _layout(_with(short, roll=ch[k]), tp)
        assert lay.roll["rule"] == "no laps" and lay.roll["verdict"] == "flat", (k, lay.roll["reason"])
        assert not C.available("bank_from_roll", lay)
    v = RC.check_dataset(_with(short, roll=ch["broken"]))
    assert not v["plausible"] and "range" in v["failed"]


def test_the_pitch_channel_the_same_way(oval, putnam):
    """A graded oval's pitch channel (grade, squat, noise) follows the lap and gives the grade; on flat Putnam the
    pitch channel says flat and grade_from_pitch is not tried."""
    t, ds = oval
    lay = _layout(ds)
    v = lay.pitch
    assert v["rule"] == "laps" and v["verdict"] == "plausible", v["reason"]
    assert v["profile_max_rad"] == pytest.approx(0.07, abs=0.005)
    assert abs(v["body_pitch_per_g_rad"]) < RC.MAX_BODY_PER_G and C.available("grade_from_pitch", lay)
    tp, short = putnam
    lay = _layout(short, tp)
    assert lay.pitch["verdict"] == "flat" and not C.available("grade_from_pitch", lay), lay.pitch["reason"]


def test_under_two_laps_of_cover_the_check_falls_back_to_bounds(oval):
    """With less than half the lap seen twice a bank cannot be told from a drift: the rule without laps (range,
    rate, drift over the log, the lateral regression), and the verdict says so."""
    t, ds = oval
    lp = LP.from_dataset(ds)
    rows = np.flatnonzero(lp.lap <= 0) if np.any(lp.lap > 0) else np.arange(len(ds))
    rows = np.arange(rows[-1] + int(0.2 * len(rows)))              # 1.2 laps
    roll = _channels(t, ds)["imu"][rows]
    s, lap, L = lp.position[rows], lp.lap[rows], lp.length
    ay = ds.states[rows, 3] * ds.states[rows, 5]
    v = RC.check(roll, ds.time[rows], ay, position=s, lap=lap, lap_length=L)
    assert v["rule"] == "no laps" and "checked without laps" in v["reason"] and v["repeat_cover"] < RC.MIN_REPEAT
    assert "roll_per_lateral_g_rad" in v and "drift_rad" in v
    walk = roll + 0.4 * np.linspace(0.0, 1.0, len(rows))           # a drift is still caught
    assert "drift" in RC.check(walk, ds.time[rows], ay, position=s, lap=lap, lap_length=L)["failed"]


def test_flat_means_no_bank_that_matters():
    """A channel says flat when, body roll taken off, its bank stays below the bank's size that matters (the
    issue's 3 degrees, ddyn.gap.limits) nearly everywhere: not below a smaller figure of its own."""
    from ddyn.data import roll_check
    from ddyn.gap import limits

    assert roll_check.FLAT == limits.SIZES["bank_angle"] == limits.SIZES["grade"]
    t = np.arange(0.0, 60.0, 0.04)
    ay = 6.0 * np.sin(0.3 * t)
    body = -0.08 * ay / 9.81
    # 2 degrees of wander that is neither body roll nor noise: under the size, flat; 5 degrees: a bank to read
    for amplitude, flat in ((2.0, True), (5.0, False)):
        roll = body + math.radians(amplitude) * np.sign(np.sin(0.05 * t))
        v = roll_check.check(roll, t, ay)
        assert v["plausible"] and v["flat"] is flat, (amplitude, v["reason"])


@pytest.fixture(scope="module")
def steep():
    """60 s of Putnam (under a lap: no laps) with a 7-degree grade profile."""
    t = load_track("putnam")
    return t, CP.make_log(t, CP.PlantEffects(grade=0.12), 3, CP.LogSettings(duration=60.0))


def test_a_steep_grade_without_laps_is_accepted_when_it_shows_in_the_acceleration(steep):
    """Without laps a pitch channel mostly unrelated to the longitudinal acceleration is rejected, unless its grade
    shows in that acceleration (roll_check.gravity_fit): the map's grade and an IMU's (body pitch, noise) pass
    with a gravity coefficient near -1, a channel logged the other way round near +1; the same channel read from
    another part of the drive, a constant-free sinusoid of the same size and a broken channel do not."""
    t, ds = steep
    e = ds.extras
    rng = np.random.default_rng(3)
    n = len(ds)
    ax = np.gradient(ds.states[:, 3], ds.sample_time) - ds.states[:, 4] * ds.states[:, 5]
    grade = np.asarray(e["true_grade"], float)
    assert np.ptp(grade) > 0.15
    imu = grade + 0.01 * ax / G + 0.003 * rng.standard_normal(n)
    walk = np.cumsum(0.01 * rng.standard_normal(n) + np.where(rng.random(n) < 0.003, rng.uniform(-2, 2, n), 0.0))
    channels = {"map": (grade, -1), "imu": (imu, -1), "other_way_round": (-grade, 1),
                "elsewhere": (np.roll(grade, n // 2), None), "made_up": (0.12 * np.sin(0.2 * ds.time), None),
                "broken": (np.mod(walk + math.pi, 2 * math.pi) - math.pi, None)}
    for name, (pitch, sign) in channels.items():
        v = RC.check_dataset(_with(ds, pitch=pitch), "pitch")
        assert v["rule"] == "no laps", name
        gv = v["gravity"]
        if sign is None:
            assert not v["plausible"] and not gv.get("waived"), (name, v["reason"], gv)
            continue
        assert v["plausible"] and not v["flat"] and gv["waived"] == "longitudinal", (name, v["reason"])
        assert gv["gravity_coefficient"] == pytest.approx(sign, abs=0.2), name
        assert "its grade shows in it" in v["reason"]
        # without the gravity fit the same channel fails the share of its spread the acceleration explains
        bare = RC.check(pitch, ds.time, ax, "pitch", "longitudinal")
        assert bare["failed"] == ["longitudinal"], (name, bare["reason"])
