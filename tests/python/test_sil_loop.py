"""`ddyn study sil-loop` (issue 34 item 3; ddyn.sil.loop): the controller's own log as a user's log, diagnosed, the
controller rebuilt from the diagnosis, against the oracle. In process (ddyn_sil_inprocess, emulated time) on
ETHZMobil; a short log drive (20 s, not the study's 60 s) so that it runs in well under two minutes. What is
asserted is the loop's plumbing and what the study's figures rest on, not the diagnosis's quality."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.sil import loop
from ddyn.sil import run as sil


@pytest.fixture(scope="module")
def case(orca, mobil, tmp_path_factory):
    sil.build_binaries(None)
    out = tmp_path_factory.mktemp("loop")
    m = loop._drive(orca, mobil, out / "reference", effects={})
    ref = loop._row(m, out / "reference")
    return loop.run_case(orca, mobil, "steer_delay", 0.04, out / "case", ref, speeds=(0.6,), seconds=20.0), out


def test_the_loop_drives_diagnoses_rebuilds_and_scores(case):
    c, out = case
    assert c["reference"]["lap_completed"] and c["reference"]["violations"] == 0
    # the nominal controller does not lap cleanly at full speed with the plant's 40 ms steering delay (it left the
    # track until the MPC's cost points were bounded by the car's reach, 09151bb: now a lap with 1 violation); the
    # oracle laps
    assert not (c["before"]["lap_completed"] and c["before"]["violations"] == 0)
    assert c["oracle"]["lap_completed"] and c["oracle"]["violations"] == 0
    assert c["oracle"]["vs_reference_pct"] < 2.0
    # the log drive: slower, no violation, at least the asked driving time
    ld = c["log_drive"]["chosen"]
    assert ld["speed_scale"] == 0.6 and ld["violations"] == 0 and ld["driven_s"] >= 20.0
    # the diagnosis ran with its defaults on the user's log; the rebuilt controller's configuration records it
    dg = c["diagnosis"]
    assert (out / "case" / "diagnosis" / "diagnosis.json").is_file() and dg["truth"] == 0.04
    fx = c["rebuilt_effects"]
    cfg = json.loads((out / "case" / "rebuilt" / "controller.json").read_text())
    assert cfg["effects"]["diagnosis_sha256"] == fx["diagnosis_sha256"]
    assert cfg["control"]["delay"]["steering"] == fx["controller_delays"].get("steer", 0.0)
    metrics = json.loads((out / "case" / "rebuilt" / "sil_metrics.json").read_text())
    assert metrics["controller_effects"]["diagnosis_sha256"] == fx["diagnosis_sha256"]
    assert (out / "case" / "before" / "lap.png").is_file() and (out / "case" / "rebuilt" / "lap.png").is_file()
    assert set(c["rebuilt"]["targets"]) == {"clean_within_2pct_of_reference", "diagnosis_first_within_15pct",
                                            "diagnosis_first_within_15pct_alone", "within_1pct_of_oracle"}
    # the delay written is the diagnosis's steering delay fitted alone, to whole periods (or nothing, named)
    written = fx["controller_delays"].get("steer")
    if written is not None:
        assert written == pytest.approx(round(dg["steer_delay_candidate_s"] / 0.02) * 0.02)
    else:
        assert "steer_delay" not in fx["applied"]
    # every claim is either applied or named (a claimed bank_angle is applied since the bank reached the runtime)
    assert set(fx["selected"]) == set(fx["applied"]) | {line.split(":")[0] for line in fx["not_applied"]}
    assert "| ethzMobil | steer_delay 0.04 |" in loop.markdown([c])


def test_the_user_log_is_the_controller_estimate_and_the_set_points_sent_before(case, orca):
    c, out = case
    clog = out / "case" / "log_speed0.6" / "controller_log.csv"
    ds = loop.user_log(clog, orca.name, orca.sample_time)
    raw = sil.read_csv(clog)
    k = int(np.flatnonzero(raw["step"] == ds.time[10] / orca.sample_time)[0])
    assert ds.column("vx")[10] == raw["vx"][k]
    assert ds.column("steering")[10] == raw["steering_cmd"][k - 1]       # the set-point sent the period before
    assert ds.column("dsteering")[10] == pytest.approx((raw["steering_cmd"][k] - raw["steering_cmd"][k - 1])
                                                       / orca.sample_time)
    assert np.all(ds.column("vx") >= loop.MIN_VX)


def test_a_bad_controller_log_is_one_line(tmp_path, orca):
    with pytest.raises(DdynError, match="no such file"):
        loop.user_log(tmp_path / "nope.csv", orca.name, orca.sample_time)
    (tmp_path / "c.csv").write_text("step,x\n0,1\n")
    with pytest.raises(DdynError, match="not a controller log: no column"):
        loop.user_log(tmp_path / "c.csv", orca.name, orca.sample_time)
    with pytest.raises(DdynError, match="unknown effect 'warp'"):
        loop.parse_cases("warp=1")
