"""Tracks from a user's files and seeded random tracks (ddyn.model.track_files, track_random):
round trips, the checks' errors, determinism, and the SIL plant getting the same track."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.model import track_random
from ddyn.model.track_files import check_track, open_track, track_digest, write_track
from ddyn.model.tracks import load_track


def _circle(n=200, r=2.0, w=0.4):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = lambda rad: np.column_stack([rad * np.cos(a), rad * np.sin(a)])  # noqa: E731
    return ring(r), ring(r - w / 2), ring(r + w / 2)


def _write(prefix, center, inner, outer):
    for part, pts in (("center", center), ("inner", inner), ("outer", outer)):
        np.savetxt(f"{prefix}_{part}.txt", np.asarray(pts).T, delimiter=",", fmt="%.17g")


@pytest.mark.parametrize("name", ["ethz", "ethzMobil"])
def test_named_track_round_trip_through_files(name, tmp_path, shared_data):
    src = load_track(name)
    write_track(src, tmp_path / "mine")
    # as a prefix, as the directory, as one of the files: the same geometry, bit for bit
    for spec in (tmp_path / "mine", tmp_path, tmp_path / "mine_outer.txt"):
        back = open_track(str(spec), "orca_1_43")
        assert back.name == "mine" and back.files["center"].endswith("mine_center.txt")
        for a, b in ((src.center, back.center), (src.inner, back.inner), (src.outer, back.outer)):
            assert np.array_equal(a, b)
        assert back.length == src.length and back.width == src.width
        assert track_digest(back) == track_digest(src)


def test_csv_with_widths_gives_the_same_track(tmp_path, shared_data):
    src = load_track("ethzMobil")
    path = tmp_path / "loop.csv"
    rows = np.column_stack([src.center, src.half_width_left, src.half_width_right])
    np.savetxt(path, rows, delimiter=",", header="x,y,w_left,w_right", comments="", fmt="%.17g")
    back = open_track(str(path), "orca_1_43")
    assert back.name == "loop" and np.array_equal(back.center, src.center)
    assert abs(back.length - src.length) < 1e-12
    # bounds rebuilt along the normals: the widths come back to within a millimetre
    assert np.max(np.abs(back.half_width_left - src.half_width_left)) < 1e-3
    assert np.max(np.abs(back.half_width_right - src.half_width_right)) < 1e-3


def test_open_loop_is_named(tmp_path):
    c, i, o = _circle()
    _write(tmp_path / "t", c[:150], i, o)  # the centre stops a quarter lap short
    with pytest.raises(DdynError, match=r"t_center\.txt: the loop is open"):
        open_track(str(tmp_path / "t"))


def test_self_intersecting_bound_is_named(tmp_path):
    c, i, o = _circle()
    i[[20, 60]] = i[[60, 20]]  # two points swapped: the bound crosses itself
    _write(tmp_path / "t", c, i, o)
    with pytest.raises(DdynError, match=r"t_inner\.txt: the inner bound crosses itself"):
        open_track(str(tmp_path / "t"))


def test_crossing_bounds_are_named(tmp_path):
    c, i, o = _circle()
    o[40:60] *= 1.7 / 2.2  # the outer bound dips inside the inner one
    _write(tmp_path / "t", c, i, o)
    with pytest.raises(DdynError, match=r"t_center\.txt: the centre line and the outer bound cross"):
        open_track(str(tmp_path / "t"))


def test_track_narrower_than_the_car_is_named(tmp_path):
    _write(tmp_path / "t", *_circle(w=0.04))  # the ORCA footprint is 5 cm wide
    with pytest.raises(DdynError, match=r"t_center\.txt: the track is 0\.040 m wide .* narrower than the orca_1_43"):
        open_track(str(tmp_path / "t"), "orca_1_43")
    assert open_track(str(tmp_path / "t")).width == pytest.approx(0.04, abs=1e-3)  # no car, no width check


def test_csv_errors_are_named(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("x,y,w_left,w_right\n0,0,0.2\n1,0,0.2\n1,1,0.2\n0,1,0.2\n")
    with pytest.raises(DdynError, match=r"bad\.csv: expected at least 4 rows of 4 columns"):
        open_track(str(p))
    p.write_text("0,0,0.2,-0.1\n1,0,0.2,0.2\n1,1,0.2,0.2\n0,1,0.2,0.2\n")
    with pytest.raises(DdynError, match=r"bad\.csv: widths must be positive"):
        open_track(str(p))


def test_missing_files_and_unknown_names_are_named(tmp_path):
    with pytest.raises(DdynError, match=r"nowhere_center\.txt"):
        open_track(str(tmp_path / "nowhere"))
    with pytest.raises(DdynError, match="random:SEED"):
        open_track("random:x")


def test_command_line_reports_a_bad_track_in_one_line(tmp_path):
    c, i, o = _circle()
    _write(tmp_path / "t", c[:150], i, o)
    r = subprocess.run([sys.executable, "-m", "ddyn.cli", "mpc", "raceline", "--track", str(tmp_path / "t"),
                        "--out", str(tmp_path / "x.npz")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "t_center.txt: the loop is open" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("seed", range(10))
def test_random_tracks_are_valid_and_like_the_eth_tracks(seed):
    t = open_track(f"random:{seed}", "orca_1_43")  # open_track runs check_track
    p = t.properties
    assert 8.0 <= t.length <= 18.0 and 0.37 <= p["width"] <= 0.46
    assert abs(t.width - p["width"]) < 2e-3
    assert p["min_radius"] >= 0.3 - 1e-9 and p["concave_bends"] >= 1 and p["hairpins"] >= 1
    assert p["closest_approach"] >= p["width"] + track_random.CLEARANCE


def test_random_tracks_are_deterministic_per_seed():
    a, b, c = track_random.random_track(5), track_random.random_track(5), track_random.random_track(6)
    assert np.array_equal(a.center, b.center) and np.array_equal(a.inner, b.inner)
    assert track_digest(a) == track_digest(b) != track_digest(c)


def test_sil_plant_gets_a_users_track(tmp_path, shared_data):
    """The plant reads <dir>/<name>_center.txt etc.: a user's or random track is written there as loaded."""
    from ddyn.sil.run import plant_track_dir

    assert plant_track_dir(load_track("ethz"), tmp_path) == shared_data / "tracks"
    user = open_track("random:3")
    d = plant_track_dir(user, tmp_path / "run")
    back = open_track(str(d / user.name))
    assert np.array_equal(back.center, user.center) and np.array_equal(back.outer, user.outer)
    check_track(back, "orca_1_43")


def test_simulate_and_diagnose_take_a_users_track(tmp_path):
    """`ddyn simulate --track <files>` drives the user's track; `ddyn diagnose --track <files>` loads it."""
    from ddyn.gap.problem import track_for as _track
    from ddyn.data.simulate import simulate

    write_track(open_track("random:4"), tmp_path / "mine")
    ds = simulate("orca_1_43", str(tmp_path / "mine"), laps=1, progress=False)
    assert ds.metadata["track"] == "mine" and float(ds.metadata["laps"]) >= 1
    assert _track(str(tmp_path / "mine"), ds).name == "mine"
    with pytest.raises(DdynError, match="nowhere_center.txt"):
        _track(str(tmp_path / "nowhere"), ds)


def test_sil_plant_drives_a_users_track_in_process(tmp_path, monkeypatch, shared_data):
    """The C++ plant reads the user's track from the run's folder and the lap completes on it
    (ETHZMobil written as a user's files; its committed line serves it: same geometry, same digest)."""
    import json
    import shutil

    from ddyn.control import raceline as R
    from ddyn.model.vehicle import load as load_vehicle
    from ddyn.sil import run as sil

    write_track(load_track("ethzMobil"), tmp_path / "files" / "mine")
    user = open_track(str(tmp_path / "files" / "mine"), "orca_1_43")
    monkeypatch.setattr(R, "USER_RACELINE_DIR", tmp_path / "lines")
    (tmp_path / "lines").mkdir()
    shutil.copy(R.default_path("orca_1_43", "ethzMobil"), R.default_path("orca_1_43", user))
    orca = load_vehicle("orca_1_43")
    spec = sil.SilSpec(vehicle=orca, track=user, coeffs_plant=orca.true_vector(),
                       coeffs_controller=orca.true_vector(), nominal=orca.true_vector(), max_time=15.0)
    out = tmp_path / "run"
    m = sil.run_sil(spec, out, None, where="inprocess")
    plant = json.loads((out / "plant.json").read_text())
    assert plant["track"] == "mine" and plant["track_dir"] == str(out / "track")
    assert (out / "track" / "mine_outer.txt").is_file()
    assert m["lap_completed"] and m["violations"] == 0, m["end_reason"]
