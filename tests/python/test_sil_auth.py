"""Frame authentication in the SIL (docs/can.md "Authenticated frames", docs/sil.md "Frame authentication").

An attacker on the bus sends, after every genuine command, a forged DBW_Command (full steering left,
full throttle, the next counter, a valid CRC) with an authenticator made without the key
(`ddyn sil run --inject-forged-steering T0:T1`, played by ddyn_sil_inprocess). ethzMobil, orca_1_43,
true coefficients, the full-speed line (racing speed), attack from 1 s to 4 s of simulated time.
Everything asserted is counted (laps, violations, frames, simulated seconds); no wall-clock bound.
"""
from __future__ import annotations

import json
import os
import subprocess

import pytest

from ddyn.errors import DdynError
from ddyn.sil import run as sil

ATTACK = (1.0, 4.0)


@pytest.fixture(scope="module")
def clean_lap(orca, mobil, sil_bins, tmp_path_factory):
    """The authenticated lap without an attack: the reference the attacked lap must equal."""
    out = tmp_path_factory.mktemp("auth_clean")
    return sil.run_sil(sil.SilSpec.true_car(orca, mobil, auth=True), out, None, where="inprocess")


def test_with_the_key_forged_steering_is_refused_and_the_lap_is_clean(orca, mobil, tmp_path, sil_bins, clean_lap):
    m = sil.run_sil(sil.SilSpec.true_car(orca, mobil, auth=True, forged_steering=ATTACK), tmp_path, None, where="inprocess")
    assert m["lap_completed"], (m["end_reason"], m["violations"])
    assert m["violations"] == 0
    attack, plant, ctl = m["attack"], m["auth"]["plant"], m["auth"]["controller"]
    # one forged command after each genuine one in the window: 3 s of 50 Hz periods (measured 151)
    assert 140 <= attack["forged_commands_sent"] <= 160
    # the DBW unit refused every forged command and applied every genuine one
    assert plant["enabled"] and attack["refused_by_the_dbw_unit"] == plant["forged"] == attack["forged_commands_sent"]
    assert plant["replayed"] == 0
    assert plant["accepted"] == m["controller"]["periods"]
    # the controller verified every frame it used; nothing forged came its way
    assert ctl["enabled"] and ctl["accepted"] == m["controller"]["frames"]["ok"] > 0
    assert ctl["forged"] == ctl["replayed"] == ctl["stale"] == 0
    # the attack changed nothing: the same lap to the microsecond as without it
    assert clean_lap["lap_completed"] and clean_lap["violations"] == 0
    assert m["lap_times"] == clean_lap["lap_times"]
    assert clean_lap["auth"]["plant"]["forged"] == 0 and "attack" not in clean_lap


def test_without_authentication_the_same_attack_takes_the_car_off_the_track(orca, mobil, tmp_path, sil_bins):
    """The check above could fail: without a key the DBW unit applies the forged commands (valid
    counter and CRC), and the car leaves the track (measured: 4 violations, ended left_the_track)."""
    m = sil.run_sil(sil.SilSpec.true_car(orca, mobil, auth=False, forged_steering=ATTACK), tmp_path, None, where="inprocess")
    assert not m["auth"]["plant"]["enabled"] and m["attack"]["refused_by_the_dbw_unit"] == 0
    assert m["attack"]["forged_commands_sent"] > 0
    assert m["violations"] > 0
    assert not m["lap_completed"]


def test_the_configs_name_the_test_key_on_both_sides(orca, mobil, tmp_path, sil_bins):
    key = sil.dbw_test_key(sil_bins)
    assert oct(key.stat().st_mode & 0o777) in ("0o600", "0o400")
    spec = sil.SilSpec.true_car(orca, mobil, auth=True)
    pc = sil.plant_config(spec, "/tracks", "/out", key_file=str(key))
    cc = sil.controller_config(spec, "/out", key_file=str(key))
    assert pc["auth"]["key_file"] == cc["can"]["key_file"] == str(key)
    # without --auth neither names a key (the default stays unauthenticated)
    assert "auth" not in sil.plant_config(sil.SilSpec.true_car(orca, mobil), "/tracks", "/out")
    assert "key_file" not in sil.controller_config(sil.SilSpec.true_car(orca, mobil), "/out")["can"]


def test_the_controller_refuses_a_key_others_can_read(orca, mobil, tmp_path, sil_bins):
    """A key file readable by group or others is refused by name before any CAN (exit 2), never a
    silent fall back to unauthenticated frames."""
    key = tmp_path / "open.key"
    key.write_text(sil.dbw_test_key(sil_bins).read_text())
    key.chmod(0o644)
    path = sil.write_controller_files(sil.SilSpec.true_car(orca, mobil), sil.raceline_table(mobil, orca), tmp_path, str(tmp_path),
                                      key_file=str(key))
    env = {k: v for k, v in os.environ.items() if k != "DDYN_DBW_KEY_FILE"}
    r = subprocess.run([str(sil_bins / "ddyn_controller"), str(path)], capture_output=True, text=True, timeout=60,
                       env=env)
    assert r.returncode == 2 and "can.key_file" in r.stderr and str(key) in r.stderr, r.stderr
    # the key as the configuration names it is printed back by --check
    r = subprocess.run([str(sil_bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True,
                       timeout=60, env=env)
    assert r.returncode == 0 and json.loads(r.stdout)["can"]["key_file"] == str(key)


def test_the_attacker_is_played_in_process_only(orca, mobil, tmp_path):
    with pytest.raises(DdynError, match="inprocess"):
        sil.run_sil(sil.SilSpec.true_car(orca, mobil, forged_steering=ATTACK), tmp_path, None, where="guest")
    assert sil.parse_window("1:4") == (1.0, 4.0)
    with pytest.raises(Exception, match="T0 < T1"):
        sil.parse_window("4:1")


def test_an_authenticated_lap_over_vcan_in_the_guest(orca, mobil, tmp_path, sil_bins):
    """The two-process SIL with --auth: plant and ddyn_controller over vcan in the qemu guest (or a host's
    vcan), both with the build's test key; every frame both sides use is verified. About 10 s wall in the
    guest; bounded by 8 s of simulated time, not by the wall clock."""
    m = sil.run_sil(sil.SilSpec.true_car(orca, mobil, auth=True, max_time=8.0), tmp_path, None)
    plant, ctl = m["auth"]["plant"], m["auth"]["controller"]
    assert plant["enabled"] and ctl["enabled"]
    assert plant["accepted"] == m["controller"]["periods"] > 0, plant
    assert plant["forged"] == plant["replayed"] == plant["stale"] == 0
    assert ctl["accepted"] == m["controller"]["frames"]["ok"] > 0
    assert ctl["forged"] == ctl["replayed"] == ctl["stale"] == 0
    assert m["lap_completed"] and m["violations"] == 0


def test_an_authenticated_lap_survives_a_plant_restart_in_the_guest(orca, mobil, tmp_path, sil_bins):
    """--auth with the plant dying 2 s into the lap and restarted 0.5 s later from its snapshot, over vcan in
    the guest. The snapshot carries the plant's SecOC freshness values (transmit ones resumed 1024 ahead for
    the frames sent after the snapshot, PlantApp::restore), so the controller accepts the restarted plant's
    frames as new: no replays, and the lap completes as without --auth (measured 3 of 3: 6.037 s, 0 violations,
    the same lap to the microsecond as without --auth; about 10 s wall). Before, the restarted plant counted
    from 0 again: 604 frames refused as replays, safe state, 1 violation.
    On the receive side the restarted plant takes the controller's commands, whose freshness kept counting.
    Bounded by 8 s of simulated time, not by the wall clock."""
    m = sil.run_sil(sil.SilSpec.true_car(orca, mobil, auth=True, max_time=8.0, faults={"restart_plant": 2.0}), tmp_path, None)
    assert m["run"]["plant_exit"] == 0
    plant, ctl = m["auth"]["plant"], m["auth"]["controller"]
    assert plant["enabled"] and ctl["enabled"]
    # nothing refused as a replay on either side, nothing forged
    assert ctl["replayed"] == 0 and plant["replayed"] == 0, (ctl, plant)
    assert ctl["forged"] == 0 and plant["forged"] == 0
    assert plant["accepted"] > 0 and ctl["accepted"] > 0
    assert m["lap_completed"], (m["end_reason"], m["violations"], ctl)
    assert m["violations"] == 0
    assert m["lap_times"][0] < 6.5  # the 0.5 s outage is not lap time (the plant's clock stops)
    assert m["controller"]["status_counts"]["DDYN_CTRL_RECOVERED"] >= 1  # back on the MPC after the outage
