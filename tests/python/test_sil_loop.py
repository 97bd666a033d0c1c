"""`ddyn study sil-loop` (issue 34 item 3; ddyn.sil.loop): the controller's own log as a user's log, diagnosed, the
controller rebuilt from the diagnosis, against the oracle. In process (ddyn_sil_inprocess, emulated time) on
ETHZMobil; a short log drive (20 s, not the study's 60 s) so that it runs in well under two minutes. What is
asserted is the loop's plumbing and what the study's figures rest on, not the diagnosis's quality."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.sil import ins, loop
from ddyn.sil import run as sil


@pytest.fixture(scope="module")
def case(orca, mobil, tmp_path_factory):
    sil.build_binaries(None)
    out = tmp_path_factory.mktemp("loop")
    m = loop._drive(orca, mobil, out / "reference", effects={})
    ref = loop._row(m, out / "reference")
    return loop.run_case(orca, mobil, "steer_delay", 0.04, out / "case", ref, speeds=(0.6,), seconds=20.0), out


def test_the_loop_drives_diagnoses_rebuilds_and_scores(case, orca, mobil):
    c, out = case
    assert c["reference"]["lap_completed"] and c["reference"]["violations"] == 0
    # scored on the median of the flying laps, the lap from rest kept beside it; the start from rest is the slower
    for k in ("reference", "rebuilt", "oracle"):
        r = c[k]
        assert len(r["lap_times"]) == loop.SCORED_LAPS == 4
        assert (r["lap_s"], r["standing_lap_s"]) == (sorted(r["lap_times"][1:])[1], r["lap_times"][0])
    assert c["reference"]["lap_s"] < c["reference"]["standing_lap_s"]
    # every run drives the car's flying-lap line (the 1:43 car's own line is a standing start, 0.5 m/s at the line)
    assert loop.LINE == "flying"
    for k in ("reference", "case/before", "case/log_speed0.6", "case/rebuilt", "case/oracle"):
        table = np.loadtxt(out / k / "raceline.csv", delimiter=",", skiprows=1)
        want = sil.raceline_table(mobil, orca, speed_scale=0.6 if k.endswith("0.6") else None, line="flying")
        assert np.allclose(table[:, :3], want[:, :3], rtol=0, atol=1e-6), k
    assert sil.raceline_table(mobil, orca)[0, 2] < 0.5 * table[0, 2]     # not the car's own line, from 0.5 m/s
    # the nominal controller does not lap cleanly at full speed with the plant's 40 ms steering delay (it left the
    # track until the MPC's cost points were bounded by the car's reach, 09151bb: now a lap with 1 violation); the
    # oracle laps
    assert not (c["before"]["lap_completed"] and c["before"]["violations"] == 0)
    assert c["oracle"]["lap_completed"] and c["oracle"]["violations"] == 0
    assert c["oracle"]["vs_reference_pct"] < 2.0
    # the log drive: slower, no violation, at least the asked driving time
    ld = c["log_drive"]["chosen"]
    assert ld["speed_scale"] == 0.6 and ld["violations"] == 0 and ld["driven_s"] >= 20.0 and ld["usable_s"] >= 20.0
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
    assert set(c["rebuilt"]["targets"]) == {"clean_within_2pct_of_reference", "clean_within_2pct_of_reference_standing",
                                            "diagnosis_first_within_15pct", "diagnosis_first_within_15pct_alone",
                                            "within_1pct_of_oracle"}
    # the effect's own candidate fitted alone, against the truth
    assert dg["alone_error_pct"] == pytest.approx(100.0 * (dg["alone_estimate"] - 0.04) / 0.04)
    assert dg["alone_estimate"] == dg["steer_delay_candidate_s"]
    # the delay written is the diagnosis's steering delay fitted alone, to whole periods (or nothing, named)
    written = fx["controller_delays"].get("steer")
    if written is not None:
        assert written == pytest.approx(round(dg["steer_delay_candidate_s"] / 0.02) * 0.02)
    else:
        assert "steer_delay" not in fx["applied"]
    # every claim is either applied or named (a claimed bank_angle is applied since the bank reached the runtime)
    assert set(fx["selected"]) == set(fx["applied"]) | {line.split(":")[0] for line in fx["not_applied"]}
    assert "| ethzMobil | steer_delay 0.04 |" in loop.markdown([c])


def test_the_user_log_is_the_controller_estimate_and_the_set_points_sampled_centred(case, orca):
    c, out = case
    clog = out / "case" / "log_speed0.6" / "controller_log.csv"
    ds = loop.user_log(clog, orca.name, orca.sample_time)
    raw = sil.read_csv(clog)
    k = int(np.flatnonzero(raw["step"] == ds.time[10] / orca.sample_time)[0])
    assert ds.column("vx")[10] == raw["vx"][k]
    # vy from the GNSS/IMU smoother (the GNSS positions and the accelerometer, no vehicle model), not the filter's,
    # turned by the inertial heading (the GNSS heading read every period here); against the plant's own (its
    # trajectory.csv, the truth the loop never reads) within the noise: a wrong rotation or sign would be off by the
    # car's speed; and closer than the track of the filter's positions (which carry the filter's nominal model)
    assert "the GNSS/IMU smoother (ddyn.sil.ins) in" in ds.metadata["vy"]
    assert "the inertial heading (GNSS heading_meas and the yaw rate) in" in ds.metadata["vy"]
    keep = np.searchsorted(raw["step"], np.round(ds.time / orca.sample_time).astype(int))
    heading = loop.inertial_heading(raw["heading_meas"][keep], ds.column("omega"), ds.segment, orca.sample_time)
    assert ds.column("vy") == pytest.approx(ins.body_lateral_velocity(
        raw["gnss_x_meas"][keep], raw["gnss_y_meas"][keep], ds.extras["ax"], ds.extras["ay"], heading, ds.segment,
        orca.sample_time))
    truth, _ = loop.plant_states_log(out / "case" / "user_log.csv", out / "case" / "log_speed0.6" / "trajectory.csv",
                                     out / "plant_states.csv")
    got = loop.vy_against_plant(out / "case" / "user_log.csv", truth, clog, orca.sample_time)
    assert got["user_log"]["rms"] < 0.01 and abs(got["user_log"]["mean"]) < 0.002
    track = loop.track_lateral_velocity(ds.column("x"), ds.column("y"), heading, ds.segment, orca.sample_time)
    from ddyn.data.importers import read_canonical
    plant_vy = read_canonical(truth).column("vy")
    assert np.sqrt(np.mean((ds.column("vy") - plant_vy) ** 2)) < 0.5 * np.sqrt(np.mean((track - plant_vy) ** 2))
    # the accelerometer's readings ride along as the log's ax, ay
    assert np.isfinite(raw["ay_meas"]).all() and ds.extras["ay"][10] == raw["ay_meas"][k]
    u = raw["steering_cmd"]
    assert u[k - 1] != u[k] != u[k + 1]       # the set-point moves either side of row 10 (else the test is blind)
    # the held set-point sampled at its step: the mean of the one before and row k's own
    assert ds.column("steering")[10] == pytest.approx(0.5 * (u[k - 1] + u[k]))
    assert ds.column("dsteering")[10] == pytest.approx(0.5 * (u[k + 1] - u[k - 1]) / orca.sample_time)
    assert np.all(ds.column("vx") >= loop.MIN_VX)
    # the yaw rate is the IMU's reading of the period (every period gets one: the IMU runs at 100 Hz)
    assert np.isfinite(raw["yaw_rate_meas"]).all()
    assert ds.column("omega")[10] == raw["yaw_rate_meas"][k] != raw["omega"][k]


def test_the_user_log_takes_the_measured_yaw_rate_where_a_reading_came(tmp_path, orca):
    """A period without an IMU reading (NaN in yaw_rate_meas) keeps the filter's estimate; a log without the
    column (an older SIL, a car logging only its estimate) keeps the estimate throughout and says so."""
    head = "step,safe,throttle_cmd,steering_cmd,x,y,yaw,vx,vy,omega"
    rows = [f"{k},0,0.1,0.01,{k * 0.02},0,0,1,0,0.5" for k in range(6)]
    (tmp_path / "old.csv").write_text("\n".join([head] + rows) + "\n")
    meas = ["0.40", "nan", "0.60", "0.55", "nan", "0.52"]
    (tmp_path / "new.csv").write_text("\n".join([head + ",yaw_rate_meas,steering_meas"] +
                                                [f"{r},{m},nan" for r, m in zip(rows, meas)]) + "\n")
    old = loop.user_log(tmp_path / "old.csv", orca.name, orca.sample_time)
    assert np.all(old.column("omega") == 0.5) and "no yaw_rate_meas" in old.metadata["omega"]
    # no GNSS or accelerometer readings: vy from the track of the filter's positions, and it says so
    assert old.metadata["vy"].startswith("from the track of the filter's positions (the log has no GNSS")
    new = loop.user_log(tmp_path / "new.csv", orca.name, orca.sample_time)
    assert new.column("omega").tolist() == [0.40, 0.5, 0.60, 0.55, 0.5, 0.52]
    assert new.metadata["omega"].startswith("the IMU's yaw rate (yaw_rate_meas) in 4 of 6 rows")


def test_the_lateral_velocity_comes_from_the_track_of_the_positions():
    """A car on a circle (radius 20 m, 5 m/s over the ground) with a 0.1 rad sideslip: vy = 5 sin(0.1) in the
    body; within 0.1 % from 50 Hz samples inside a segment, 3 % at its ends (one-sided differences). Each segment
    differenced on its own (a jump between segments is not a speed)."""
    dt, r, v, beta = 0.02, 20.0, 5.0, 0.1
    t = np.arange(200) * dt
    course = v * t / r                     # the direction of travel on the circle
    x, y = r * np.sin(course), r * (1 - np.cos(course))
    yaw = course - beta                    # the body points 0.1 rad inside the direction of travel
    seg = np.r_[np.zeros(100, int), np.ones(100, int)]
    x[100:] += 50.0                        # the second segment elsewhere: no 2500 m/s jump may appear
    vy = loop.track_lateral_velocity(x, y, yaw, seg, dt)
    ends = np.isin(np.arange(200), [0, 99, 100, 199])
    assert vy[~ends] == pytest.approx(np.full(196, v * np.sin(beta)), rel=1e-3)
    assert vy[ends] == pytest.approx(np.full(4, v * np.sin(beta)), rel=0.03)


def test_the_inertial_heading_averages_the_gnss_noise_and_ignores_a_gyro_bias():
    """A car turning at 0.4 rad/s through the +-pi wrap: the gyro reads 0.02 rad/s high, the GNSS heading has
    0.01 rad of noise, wrapped into (-pi, pi], and misses every other period. The inertial heading is within a
    tenth of the noise of the truth inside the segment (a constant bias drifts linearly, and a centred mean keeps a
    line) and still well inside it within half a window of the ends; the raw readings are not."""
    dt, n = 0.02, 1000
    rng = np.random.default_rng(3)
    truth = 2.5 + 0.4 * np.arange(n) * dt
    gyro = np.full(n, 0.4 + 0.02)
    meas = np.angle(np.exp(1j * (truth + rng.normal(0.0, 0.01, n))))
    meas[1::2] = np.nan
    got = loop.inertial_heading(meas, gyro, np.zeros(n, int), dt)
    err = np.angle(np.exp(1j * (got - truth)))
    inside = slice(50, n - 50)
    assert np.sqrt(np.mean(err[inside] ** 2)) < 0.002 and np.max(np.abs(err)) < 0.01
    raw = np.angle(np.exp(1j * (meas - truth)))
    assert np.sqrt(np.nanmean(raw ** 2)) > 0.005                 # the readings themselves: the noise, 0.01
    assert np.max(np.abs(np.diff(got))) < 0.01      # unwrapped: no 2 pi step where the readings wrap
    # each segment integrates on its own; a segment without a reading is NaN (heading_channel falls back)
    seg = np.r_[np.zeros(500, int), np.ones(500, int)]
    meas2 = meas.copy()
    meas2[500:] = np.nan
    got2 = loop.inertial_heading(meas2, gyro, seg, dt)
    assert np.isnan(got2[500:]).all() and np.isfinite(got2[:500]).all()


def test_the_heading_falls_back_to_the_filter_without_readings():
    c = {"yaw": np.array([0.1, 0.2, 0.3, 0.4]), "heading_meas": np.full(4, np.nan)}
    keep, seg, omega = np.arange(4), np.zeros(4, int), np.zeros(4)
    got, why = loop.heading_channel(c, omega, keep, seg, 0.02)
    assert got.tolist() == [0.1, 0.2, 0.3, 0.4] and "no heading_meas" in why
    c["heading_meas"] = np.array([0.5, 0.5, np.nan, 0.5])
    got, why = loop.heading_channel(c, omega, keep, seg, 0.02)
    assert got == pytest.approx(np.full(4, 0.5)) and why.startswith("the inertial heading")


def test_the_accelerometer_is_the_latest_reading():
    c = {"ax_meas": np.array([np.nan, 1.0, np.nan, 3.0]), "ay_meas": np.array([np.nan, -2.0, np.nan, np.nan])}
    got = loop.accelerometer_channels(c)
    assert got["ax"].tolist() == [1.0, 1.0, 1.0, 3.0] and got["ay"].tolist() == [-2.0, -2.0, -2.0, -2.0]
    assert loop.accelerometer_channels({"ax_meas": np.full(3, np.nan), "ay_meas": np.full(3, np.nan)}) == {}
    assert loop.accelerometer_channels({"yaw_rate_meas": np.zeros(3)}) == {}


def test_a_bad_controller_log_is_one_line(tmp_path, orca):
    with pytest.raises(DdynError, match="no such file"):
        loop.user_log(tmp_path / "nope.csv", orca.name, orca.sample_time)
    (tmp_path / "c.csv").write_text("step,x\n0,1\n")
    with pytest.raises(DdynError, match="not a controller log: no column"):
        loop.user_log(tmp_path / "c.csv", orca.name, orca.sample_time)
    with pytest.raises(DdynError, match="unknown effect 'warp'"):
        loop.parse_cases("warp=1")


def test_the_log_drive_needs_the_asked_seconds_of_usable_log(tmp_path, monkeypatch, orca, mobil):
    """A drive that completes its laps crawling or on the safe command leaves the diagnosis too few rows: it is not
    chosen, a slower drive with a violation is (random:301, an 80 ms steering delay, noise seed 2: 37 usable rows)."""
    dt = orca.sample_time
    # per speed scale: violations, rows at vx >= MIN_VX without the safe command, rows crawling, rows safe
    plan = {0.6: (0, 40, 3000, 0), 0.5: (0, 1000, 100, 2000), 0.4: (1, 3200, 0, 10), 0.3: (0, 3300, 0, 0)}

    def drive(vehicle, track, d, effects, speed_scale, laps, seed, road_bank, line):
        viol, good, slow, safe = plan[speed_scale]
        n = good + slow + safe
        vx = np.r_[np.full(good, 1.0), np.full(slow, 0.1), np.full(safe, 1.0)]
        d.mkdir(parents=True)
        np.savetxt(d / "controller_log.csv", np.column_stack([np.arange(n), np.r_[np.zeros(good + slow), np.ones(safe)], vx]),
                   delimiter=",", header="step,safe,vx", comments="")
        return {"lap_times": [n * dt], "lap_completed": True, "violations": viol, "end_reason": "laps_completed",
                "tracking_error": {"mean": 0.02}}

    monkeypatch.setattr(loop, "_drive", drive)
    got, d = loop.log_drive(orca, mobil, tmp_path, {"steer_delay": 0.08}, ref_lap=4.0, speeds=(0.6, 0.5, 0.4),
                            seconds=60.0)
    assert [t["usable_s"] for t in got["tried"]] == pytest.approx([40 * dt, 1000 * dt, 3200 * dt])
    assert got["chosen"]["speed_scale"] == 0.4 and d == tmp_path / "log_speed0.4"
    # a clean drive with enough usable log ends the search at once
    got, d = loop.log_drive(orca, mobil, tmp_path / "b", {}, ref_lap=4.0, speeds=(0.3, 0.4), seconds=60.0)
    assert got["chosen"]["speed_scale"] == 0.3 and len(got["tried"]) == 1
    # none usable: one line that says how much each gave
    with pytest.raises(DdynError, match=r"0.6: laps_completed, 0 violations, 1 s usable"):
        loop.log_drive(orca, mobil, tmp_path / "c", {}, ref_lap=4.0, speeds=(0.6,), seconds=60.0)


def test_the_summary_counts_targets_per_effect_and_takes_the_worst_lap():
    def case(effect, first, completed, violations, vs_ref, vs_oracle):
        r = {"lap_completed": completed, "violations": violations}
        r |= {"vs_reference_pct": vs_ref} if vs_ref is not None else {}
        r |= {"vs_oracle_pct": vs_oracle} if vs_oracle is not None else {}
        r["targets"] = dict.fromkeys(loop.TARGETS, False)
        r["targets"] |= {"clean_within_2pct_of_reference": completed and violations == 0 and (vs_ref or 9) <= 2,
                         "within_1pct_of_oracle": vs_oracle is not None and abs(vs_oracle) <= 1}
        before = {"lap_completed": True, "violations": 0 if effect == "none" else 2}
        return {"effect": effect, "diagnosis": {"first_is_the_effect": first}, "rebuilt": r, "before": before}

    failed = {"track": "ethzMobil", "effect": "steer_delay", "size": 0.08, "reference": {}, "error": "no log drive"}
    s = loop.summarise([case("steer_delay", True, True, 0, 0.8, 0.0), case("steer_delay", False, True, 3, 140.0, -2.5),
                        case("steer_lag", True, True, 0, 2.9, 1.0), case("none", False, True, 0, 0.1, None),
                        case("throttle_delay", True, False, 1, None, None), failed])
    assert s["steer_delay"] == {"cases": 3, "not_scored": 1, "first_is_the_effect": 1, "before_clean": 0, "clean": 1,
                                **dict.fromkeys(loop.TARGETS, 0), "clean_within_2pct_of_reference": 1,
                                "within_1pct_of_oracle": 1, "worst_vs_reference_pct": 140.0,
                                "worst_vs_oracle_pct": -2.5}
    assert s["effects"]["cases"] == 5 and s["effects"]["clean"] == 2 and s["effects"]["first_is_the_effect"] == 3
    assert s["throttle_delay"]["worst_vs_reference_pct"] is None and s["none"]["cases"] == 1
    assert s["none"]["before_clean"] == 1


def test_a_rebuilt_lap_with_violations_meets_no_lap_target():
    """Within 1 % of the oracle's time but off the track (the downforce loop's rebuilt laps) is not a lap within 1 %
    of the oracle; clean, the same times meet it; the diagnosis's targets follow its own numbers."""
    dg = {"first_is_the_effect": True, "error_pct": 12.0, "alone_error_pct": -16.0}
    clean = {"lap_completed": True, "violations": 0, "vs_reference_pct": 1.5, "standing_vs_reference_pct": 2.5,
             "vs_oracle_pct": -0.6}
    t = loop.rebuilt_targets(dg, clean)
    assert tuple(t) == loop.TARGETS
    assert t == {"clean_within_2pct_of_reference": True, "clean_within_2pct_of_reference_standing": False,
                 "diagnosis_first_within_15pct": True, "diagnosis_first_within_15pct_alone": False,
                 "within_1pct_of_oracle": True}
    off = loop.rebuilt_targets(dg, dict(clean, violations=3))
    assert not off["within_1pct_of_oracle"] and not off["clean_within_2pct_of_reference"]
    assert off["diagnosis_first_within_15pct"]
    assert not loop.rebuilt_targets(dict(dg, first_is_the_effect=False), clean)["diagnosis_first_within_15pct"]


def test_a_run_is_scored_on_the_median_of_its_flying_laps(tmp_path):
    """One slow flying lap (the closed loop's chaos: a lap 9 % slow among laps within 0.1 %) does not move the
    score; the standing lap is kept apart; an unfinished run has no score; a one-lap run scores its one lap."""
    m = {"lap_times": [4.03, 3.72, 4.05, 3.70], "lap_completed": True, "violations": 0, "end_reason": "laps_completed",
         "tracking_error": {"mean": 0.02}, "worst_clearance": 0.1}
    r = loop._row(m, tmp_path)
    assert (r["lap_s"], r["standing_lap_s"]) == (3.72, 4.03)
    assert loop._row(dict(m, lap_completed=False), tmp_path)["lap_s"] is None
    assert loop._row(dict(m, lap_times=[5.1]), tmp_path)["lap_s"] == 5.1


def test_a_case_that_cannot_be_scored_is_recorded_and_the_study_goes_on(tmp_path, monkeypatch, capsys):
    """One case without a log drive (the nominal controller cannot drive 60 s at any speed) is kept as a case with
    its error, the other cases are scored, and loop.json is written with both."""
    fake_run = {"lap_completed": True, "lap_s": 5.2, "standing_lap_s": 5.4, "lap_times": [5.4, 5.2], "violations": 0,
                "end": "laps_completed", "tracking_error_mean_m": 0.02, "worst_clearance_m": 0.1, "plot": "x"}
    monkeypatch.setattr(loop, "_drive", lambda *a, **k: None)
    monkeypatch.setattr(loop, "_row", lambda m, out: dict(fake_run))

    def run_case(vehicle, track, effect, size, out, ref, *a):
        if size == 0.08:
            raise DdynError(f"{track.name}, plant effects {{'steer_delay': 0.08}}: no speed drives 60 s")
        r = dict(fake_run, targets=dict.fromkeys(loop.TARGETS, True), vs_reference_pct=0.5, vs_oracle_pct=0.0)
        return {"track": track.name, "effect": effect, "size": size, "reference": ref, "seconds": 1.0,
                "log_drive": {"chosen": {"speed_scale": 0.6, "driven_s": 61.0, "violations": 0}},
                "diagnosis": {"selected": [effect], "first": effect, "first_estimate": size, "first_is_the_effect": True},
                "rebuilt_effects": {"controller_delays": {"steer": size}, "not_applied": []},
                "before": dict(fake_run), "rebuilt": r, "oracle": dict(fake_run)}

    monkeypatch.setattr(loop, "run_case", run_case)
    parser = argparse.ArgumentParser()
    loop.register(parser.add_subparsers())
    args = parser.parse_args(["sil-loop", "--cases", "steer_delay=0.04,steer_delay=0.08", "--out", str(tmp_path)])
    assert loop._run(args) == 0
    doc = json.loads((tmp_path / "loop.json").read_text())
    assert doc["line"] == loop.LINE == "flying"     # every run's line, recorded
    assert [c.get("error") for c in doc["cases"]][0] is None and "no speed drives 60 s" in doc["cases"][1]["error"]
    assert (doc["summary"]["steer_delay"]["cases"], doc["summary"]["steer_delay"]["not_scored"],
            doc["summary"]["steer_delay"]["within_1pct_of_oracle"]) == (2, 1, 1)
    md = (tmp_path / "loop.md").read_text().splitlines()
    row = next(line for line in md if line.startswith("| ethzMobil | steer_delay 0.08 | not scored: "))
    assert row.count("|") == md[0].count("|")       # as many cells as the header
    assert "steer_delay=0.08: not scored" in capsys.readouterr().out


def test_centred_set_points_put_the_ramp_on_the_held_command():
    # a set-point held 1 for two periods between zeros: sampled at its steps, the ramp between the samples has
    # the held command's area and centre (no lead, no lag), which the set-point of the period before lacks
    u = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    c = loop.centred_set_points(u)
    assert c.tolist() == [0.0, 0.0, 0.5, 1.0, 0.5, 0.0, 0.0]
    t = np.arange(len(u))
    held_centre = np.sum(u * (t + 0.5)) / np.sum(u)              # the command held over [k, k + 1)
    ramp_area = np.trapezoid(c, t)
    ramp_centre = np.trapezoid(c * t, t) / ramp_area
    assert ramp_area == pytest.approx(np.sum(u)) and ramp_centre == pytest.approx(held_centre)
    before = np.r_[u[:1], u[:-1]]
    assert np.trapezoid(before * t, t) / np.trapezoid(before, t) == pytest.approx(held_centre + 0.5)


def test_a_diagnosis_that_fails_says_why_in_one_line(tmp_path):
    """The case's error is a cell of loop.md's table: the diagnosis's own one-line reason, not an empty tail of its
    stdout (a 60 s log drive that crawled left 36 usable rows: "exited 2:" and nothing after it, until this)."""
    bad = tmp_path / "user_log.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(DdynError) as e:
        loop.diagnose(bad, "orca_1_43", tmp_path / "d")
    msg = str(e.value)
    assert "\n" not in msg and "exited 2: " in msg and f"{bad}: unrecognised format" in msg
