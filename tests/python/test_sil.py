"""ddyn sil: the configuration both processes read, and two-process runs over vcan (host or qemu guest).

The two-process runs boot the qemu guest of scripts/vcan_guest when the host has no vcan (about
15 s each in software emulation); a missing qemu, kernel or busybox is a failure, not a skip.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from train import sil
from train.errors import DdynError
from train.model import COEFF_NAMES
from train.tracks import load_track
from train.vehicle import load as load_vehicle


@pytest.fixture(scope="module")
def orca():
    return load_vehicle("orca_1_43")


@pytest.fixture(scope="module")
def mobil(shared_data):
    return load_track("ethzMobil", shared_data)


def spec_for(orca, mobil, **kw) -> sil.SilSpec:
    base = dict(vehicle=orca, track=mobil, coeffs_plant=orca.true_vector(), coeffs_controller=orca.true_vector(),
                nominal=orca.true_vector())
    base.update(kw)
    return sil.SilSpec(**base)


def test_effects_and_faults_parse_and_refuse():
    assert sil.parse_effects("steer_delay=0.04,mass_offset=0.1") == {"steer_delay": 0.04, "mass_offset": 0.1}
    with pytest.raises(DdynError, match="not_an_effect"):
        sil.parse_effects("not_an_effect=1")
    with pytest.raises(DdynError, match="bank_angle"):
        sil.parse_effects("bank_angle=0.1")  # an effect of train/effects.py the plant does not offer
    f = sil.parse_faults("drop=0.05 delay=0.04 silent=imu silent_at=2")
    assert f == {"drop": 0.05, "delay": 0.04, "silent": "imu", "silent_at": 2.0}
    with pytest.raises(DdynError, match="silent_at"):
        sil.parse_faults("silent=imu")
    with pytest.raises(DdynError, match="expected one of"):
        sil.parse_faults("silent=lidar silent_at=1")
    with pytest.raises(DdynError, match="fraction"):
        sil.parse_faults("drop=1.5")


def test_raceline_table_room_matches_the_track(orca, mobil):
    table = sil.raceline_table(mobil, orca)
    assert table.shape[1] == 5 and 100 < len(table) <= 1024
    assert np.all(table[:, 2] >= 0.5)  # the data's first point has speed 0: the reference is floored
    # room left + right + the car's width + both margins is the track's width at that point
    s, _ = mobil.project(table[:, 0], table[:, 1])
    wl, wr = mobil.half_widths(s)
    np.testing.assert_allclose(table[:, 3] + table[:, 4] + 0.05 + 2 * 0.02, wl + wr, atol=1e-9)
    # the time-optimal raceline runs closer to the bounds than half the car plus margin in places
    # (about 13 % of its points): the MPC's soft bounds handle that; elsewhere there is room
    assert np.mean((table[:, 3] > 0) & (table[:, 4] > 0)) > 0.8
    # one lap, closed: no long closing segment across the infield
    step = np.hypot(*np.diff(np.vstack([table[:, :2], table[:1, :2]]), axis=0).T)
    assert step.max() < 0.1
    wider = sil.raceline_table(mobil, orca, margin=0.0)
    np.testing.assert_allclose(wider[:, 3], table[:, 3] + 0.02)


def test_plant_config_and_controller_setup(orca, mobil, tmp_path):
    spec = spec_for(orca, mobil, effects={"steer_delay": 0.02},
                    faults={"drop": 0.05, "silent": "imu", "silent_at": 1.5, "kill_controller": 2.0})
    pc = sil.plant_config(spec, "/tracks", "/out")
    assert pc["coefficients"] == pytest.approx(list(orca.true_vector()))
    assert pc["effects"] == {"steer_delay": 0.02}
    assert pc["faults"]["drop"] == 0.05
    assert pc["sensors"]["yaw_rate"]["silent_from"] == 1.5 and pc["sensors"]["acceleration"]["silent_from"] == 1.5
    assert "silent_from" not in pc["sensors"]["gnss_position"]
    assert pc["sensors"]["gnss_position"]["noise"] == [orca.sensor_noise_std["x"], orca.sensor_noise_std["y"]]
    assert pc["start"][3] == 0.1 and pc["footprint"] == {"length": 0.1, "width": 0.05}
    table = sil.raceline_table(mobil, orca)
    text = sil.controller_setup(spec, table, "/out")
    words = text.split()
    assert words[words.index("die_at_step") + 1] == "100"  # 2 s at 50 Hz
    assert words[words.index("fixed") + 1] == "1"
    coeffs = [float(w) for w in words[words.index("coeffs") + 1: words.index("coeffs") + 1 + len(COEFF_NAMES)]]
    assert coeffs == pytest.approx(list(orca.true_vector()))
    assert int(words[words.index("track") + 1]) == len(table)


@pytest.fixture(scope="module")
def sil_bins():
    """The two SIL executables, built for the fixture network."""
    return sil.build_binaries(None)


def test_the_controller_refuses_a_malformed_setup(sil_bins, tmp_path):
    bad = tmp_path / "setup.txt"
    bad.write_text("vehicle orca_1_43\nperiod 0.02\nfixed 1\nnominal 1 2 3\n")
    r = subprocess.run([str(sil_bins / "ddyn_sil_controller"), str(bad)], capture_output=True, text=True)
    assert r.returncode == 2 and "malformed" in r.stderr
    r = subprocess.run([str(sil_bins / "ddyn_sil_plant"), str(tmp_path / "missing.json")], capture_output=True,
                       text=True)
    assert r.returncode == 2 and "cannot read config" in r.stderr


def test_controller_killed_mid_run_stops_the_car_within_the_deadline(orca, mobil, tmp_path, sil_bins):
    """Two processes over vcan: damaged command checksums are refused by the DBW unit; the controller
    dies at 1 s (SIGKILL, no last words); the plant's DBW watchdog brings the car to a controlled stop
    within its 80 ms deadline. (The controller side of checksum damage: test_fsim's SilLoop tests.)"""
    spec = spec_for(orca, mobil, faults={"corrupt": 0.1, "kill_controller": 1.0}, max_time=6.0)
    m = sil.run_sil(spec, tmp_path, None)
    dbw, bus = m["plant"]["dbw"], m["plant"]["bus"]
    assert m["end_reason"] == "safe_stop"
    assert dbw["trips"] == 1
    # the controller dies at its own period 50 (it counts periods from the first position frame it
    # receives); the trip follows its last valid command by the deadline: measured 1.1-1.21 s of
    # plant time
    assert 0.9 < dbw["first_trip_time"] < 1.5
    assert dbw["first_trip_latency"] <= 0.08 + 1e-3 + 1e-9
    assert m["safe_state"]["dbw_watchdog_latency"] == dbw["first_trip_latency"]
    # checksum damage: every damaged command was refused, and no good one
    assert bus["rx_corrupted"] > 0 and dbw["rejected"]["bad_checksum"] == bus["rx_corrupted"]
    assert m["controller"] is None  # killed: it wrote nothing
    assert (tmp_path / "lap.png").stat().st_size > 10_000
    traj = sil.read_csv(tmp_path / "trajectory.csv")
    assert abs(traj["vx"][-1]) < 1e-12  # held at standstill


def test_plant_restart_resumes_and_the_controller_goes_safe(orca, mobil, tmp_path, sil_bins):
    """The plant process dies at 1 s and comes back 0.5 s later from its last snapshot; meanwhile the
    controller sees no frames and commands the safe stop within 100 ms."""
    spec = spec_for(orca, mobil, faults={"restart_plant": 1.0}, max_time=2.0)
    m = sil.run_sil(spec, tmp_path, None)
    assert m["run"]["plant_exit"] == 0  # the restarted plant finished the run
    traj = sil.read_csv(tmp_path / "trajectory.csv")
    t = traj["t"]
    assert t[0] < 0.05 and t[-1] > 1.95  # both halves of the run are in the log
    lat = m["controller"]["first_stale_latency"]
    # an IMU frame may be missing for one period; without frames the controller's timer runs a
    # period after 1.5 periods (30 ms), then every period: the safe command follows at the second
    # one, 50 ms by design. This is wall time in an emulated guest on a shared machine: measured
    # 60-85 ms, 103 ms once under heavy load; the bound leaves room for that, the target is 100 ms
    assert 0.04 < lat < 0.15, lat
    assert m["safe_state"]["controller_stale_latency_wall"] == lat
    assert json.loads((tmp_path / "plant_resume.json").read_text())["resume"].endswith("snapshot.json")
    # the controller's LCM log goes straight into ddyn import
    from train.importers import load_any
    ds = load_any(tmp_path / "controller.lcm")
    assert len(ds) == m["controller"]["periods"]


def test_a_lap_with_the_true_coefficients_in_process(orca, mobil, tmp_path, sil_bins):
    """Plant and controller node in one process (frames through memory, host CPU): one lap of ETHZMobil
    from 0.1 m/s at 90 % of the raceline's speed completes inside the bounds."""
    spec = spec_for(orca, mobil, speed_scale=0.9, max_time=15.0)
    m = sil.run_sil(spec, tmp_path, None, where="inprocess")
    assert m["lap_completed"], m["end_reason"]
    assert m["violations"] == 0
    assert 4.5 < m["lap_times"][0] < 7.5
    assert m["tracking_error"]["mean"] < 0.1
    ctl = m["controller"]
    assert ctl["safe_periods"] == 0 and ctl["frames"]["checksum"] == 0
    assert abs(ctl["periods"] - m["plant"]["sim_time"] / orca.sample_time) <= 2
    assert (tmp_path / "controller.lcm").stat().st_size > 0
