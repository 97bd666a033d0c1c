"""The full-scale AV-21 on Putnam (issue 18 item 4): its committed flying-lap line, a segment of the C
MPC's closed loop with its own settings (train/vehicles/mpc/av21.json), and a segment of the SIL in
process (plant, sensors, EKF, MPC over frames in memory). The full SIL lap over vcan is a documented
command (docs/tracks.md), not a test: 108 s of simulated time."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from ddyn.control import mpc_lap
from ddyn.control import raceline as R
from ddyn.control.mpc_setup import MpcSettings, settings_for
from ddyn.model.track_files import open_track
from ddyn.model.vehicle import FOOTPRINT
from ddyn.model.vehicle import load as load_vehicle


@pytest.fixture(scope="module")
def putnam(shared_data):
    return open_track("putnam", "av21")


def test_av21_settings_leave_the_1_43_defaults_alone():
    assert settings_for("orca_1_43") == MpcSettings()
    assert R.settings_for("orca_1_43") == R.RacelineSettings()
    a = settings_for("av21")
    assert a.spacing == 3.0 and a.margin == 0.3 and a.lateral_grip > 0.0 and a.brake_limit > 0.0


def test_av21_reference_asks_no_more_than_its_caps(putnam):
    """The MPC's table (issue 34): the line's own speed at most, no more lateral acceleration than lateral_grip of
    the tyres' peak, no harder braking than brake_limit of the full brake plus drag."""
    from ddyn.control.mpc_setup import raceline_table

    s = settings_for("av21")
    t = raceline_table(putnam, "av21", s)
    line = R.load_for("av21", putnam)
    av21 = load_vehicle("av21")
    c, mass = av21.true_coefficients, float(av21.known.mass)
    v, xy = t["speed"], np.column_stack([t["x"], t["y"]])
    assert v.max() <= s.speed_scale * line.speed.max() + 1e-9
    ds = np.hypot(*(np.roll(xy, -1, axis=0) - xy).T)
    nxt = np.roll(v, -1)
    decel = (v ** 2 - nxt ** 2) / (2 * ds)
    cap = s.brake_limit * ((c["Cm1"] - c["Cm2"] * nxt) + c["Cr0"] + c["Cd"] * nxt ** 2) / mass
    assert np.all(decel <= cap + 1e-6)
    a, b = np.roll(xy, 2, axis=0), np.roll(xy, -2, axis=0)  # the curvature over two points either side, as capped
    cross = (xy - a)[:, 0] * (b - xy)[:, 1] - (xy - a)[:, 1] * (b - xy)[:, 0]
    kappa = 2 * np.abs(cross) / np.prod([np.linalg.norm(d, axis=1) for d in (xy - a, b - xy, a - b)], axis=0)
    assert np.all(v ** 2 * kappa <= s.lateral_grip * (c["Df"] + c["Dr"]) / mass + 1e-6)
    uncapped = raceline_table(putnam, "av21", replace(s, lateral_grip=0.0, brake_limit=0.0))
    assert np.all(v <= uncapped["speed"] + 1e-9) and np.mean(v < uncapped["speed"] - 1e-9) < 0.5


def test_committed_av21_line_is_a_flying_lap_inside_putnam(putnam):
    line = R.load_for("av21", putnam)
    assert line is not None, "train/racelines/av21_putnam.npz missing or for another track"
    meta = R.meta_of(R.default_path("av21", putnam))
    want = R.resolved(R.settings_for("av21"), putnam).as_dict()
    assert meta["settings"] == want and meta["ipopt_status"] == "Solve_Succeeded"
    assert R.is_flying(putnam, "av21")
    with np.load(R.default_path("av21", putnam)) as z:
        vx, vy = z["states"][3], z["states"][4]
    assert np.all(np.abs(vy) <= np.tan(want["max_sideslip"]) * vx + 1e-6)  # no drift in the line
    assert np.all(putnam.boundary_distance(line.x, line.y) >= 0.5 * FOOTPRINT["av21"][1])
    assert 80.0 < meta["lap_time_s"] < 95.0 and line.speed.min() > 15.0  # a flying lap: never slow


def test_c_mpc_drives_av21_on_putnam_without_leaving_it(putnam):
    """30 s from the rolling start: through the fast right-hander where the car spun with the line's
    full speed (speed_scale 1.0, s = 495 m) and with the drifting line."""
    if not mpc_lap.DEFAULT_TOOL.is_file():
        pytest.fail(f"{mpc_lap.DEFAULT_TOOL} missing: build the C side first (scripts/test.sh does)")
    run = mpc_lap.run_c("av21", putnam, settings_for("av21"), 750)
    m = mpc_lap.score(putnam, run["x"], run["dt"], "av21")
    assert run["x"][0, 3] > 25.0  # rolling start
    assert m["violation_steps"] == 0, m
    assert m["progress_m"] > 700.0 and np.all(run["status"] == 0)


def test_sil_av21_on_putnam_in_process(putnam, tmp_path):
    """The SIL's full-scale path: Putnam's CSV bounds written for the plant, GNSS once per 40 ms period,
    the filter started where the car is at its first period: no reading gated, no safe period."""
    from ddyn.sil import run as sil

    av21 = load_vehicle("av21")
    spec = sil.SilSpec(vehicle=av21, track=putnam, coeffs_plant=av21.true_vector(),
                       coeffs_controller=av21.true_vector(), nominal=av21.true_vector(), max_time=12.0)
    out = tmp_path / "run"
    m = sil.run_sil(spec, out, None, where="inprocess")
    plant = json.loads((out / "plant.json").read_text())
    assert plant["sensors"]["gnss_position"]["rate"] == pytest.approx(25.0)
    assert plant["dbw"]["deadline"] == pytest.approx(0.16)
    ctl = json.loads((out / "controller_metrics.json").read_text())
    assert m["violations"] == 0 and m["plant"]["progress"] > 250.0, m["end_reason"]
    assert ctl["safe_steps"] == 0 and sum(ctl["sensor_rejected"].values()) == 0, ctl


def test_sil_pid_sweep_takes_a_users_track_files(shared_data, tmp_path, monkeypatch):
    """`ddyn sil pid-sweep --track FILES` (as sil run, table and faults): the plant reads the user's track
    from the run's folder and the lap is driven on it."""
    import shutil

    from ddyn.cli import main
    from ddyn.model.track_files import write_track
    from ddyn.model.tracks import load_track

    write_track(load_track("ethzMobil"), tmp_path / "files" / "mine")
    user = open_track(str(tmp_path / "files" / "mine"), "orca_1_43")
    monkeypatch.setattr(R, "USER_RACELINE_DIR", tmp_path / "lines")
    (tmp_path / "lines").mkdir()
    shutil.copy(R.default_path("orca_1_43", "ethzMobil"), R.default_path("orca_1_43", user))
    out = tmp_path / "sweep"
    rc = main(["sil", "pid-sweep", "--track", str(tmp_path / "files" / "mine"), "--kp", "2", "--ki", "1",
               "--where", "inprocess", "--max-time", "8", "--out", str(out)])
    rows = json.loads((out / "sil_pid_sweep.json").read_text())["rows"]
    run = out / "kp2_ki1_kd0_preview0"
    plant = json.loads((run / "plant.json").read_text())
    assert plant["track"] == "mine" and plant["track_dir"] == str(run / "track")
    assert len(rows) == 1 and rows[0]["lap_completed"] and rows[0]["violations"] == 0 and rc == 0
