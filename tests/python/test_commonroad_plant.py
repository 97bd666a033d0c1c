"""The independent plant (issue 14): CommonRoad's PyPI code integrates it, the log is in the canonical format with
DBW-held commands and noise, the effects act physically, and the project's model maps onto it."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

vehiclemodels = pytest.importorskip("vehiclemodels", reason="COMMONROAD MISSING: pip install "
                                    "commonroad-vehicle-models (requirements.in); CI installs it")

from ddyn.gap import config as CFG, fit as F, heldout as HO, problem as P, report as R, selection as SEL  # noqa: E402
from ddyn.gap import calibration as CAL
from ddyn.gap.benchmark import commonroad as G  # noqa: E402
from ddyn.plants import commonroad_st as CP  # noqa: E402
from ddyn.data.dataset import COLUMNS  # noqa: E402
from ddyn.errors import DdynError  # noqa: E402
from ddyn.model import backends  # noqa: E402
from ddyn.model.vehicle import load as load_vehicle  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
NOMINAL = load_vehicle(CP.NOMINAL_VEHICLE)


def _claims(claims, right, on_no_claim_logs):
    """A calibration's claim counts of one effect (calibration.claim_precisions)."""
    return {"claims": claims, "right": right, "on_no_claim_logs": on_no_claim_logs}


def _log(effects=CP.PlantEffects(), seed=4, duration=12.0, noise=1.0, color=0.0, track="putnam"):
    return CP.make_log(track, effects, seed, CP.LogSettings(duration=duration, noise_scale=noise, noise_color=color))


@pytest.fixture(scope="module")
def clean():
    return _log(noise=0.0)


def test_the_pypi_package_integrates_the_plant(monkeypatch):
    """Every right-hand side evaluation goes through vehiclemodels' vehicle_dynamics_std, installed from PyPI,
    4 per RK4 step at 1 kHz; none of ddyn.model's integrators runs."""
    import vehiclemodels.vehicle_dynamics_std as std

    from importlib.metadata import distribution

    dist = distribution("commonroad-vehicle-models")
    assert dist.version == "3.0.2"
    installed = {Path(dist.locate_file(f)).resolve() for f in dist.files}
    assert Path(std.__file__).resolve() in installed        # the distribution's own file, not a copy
    assert (REPO / "train") not in Path(std.__file__).resolve().parents
    calls = {"n": 0}
    real = std.vehicle_dynamics_std

    def counting(x, u, p):
        calls["n"] += 1
        return real(x, u, p)

    def forbidden(*a, **k):
        raise AssertionError("the project's model must not integrate the independent plant")

    monkeypatch.setattr(std, "vehicle_dynamics_std", counting)
    monkeypatch.setattr(backends, "step_numpy", forbidden)
    ds = _log(duration=1.0)
    steps = (len(ds) - 1) * round(NOMINAL.sample_time * CP.PLANT_RATE)
    assert calls["n"] == 4 * steps


def test_log_format_hold_and_noise(clean):
    noisy = _log(noise=1.0)
    assert noisy.sample_time == NOMINAL.sample_time and noisy.vehicle == NOMINAL.name == "commonroad_vehicle2"
    # the nominal file is loaded by path, kept out of the vehicles every vehicle-wide tool iterates
    from ddyn.model.vehicle import available

    assert NOMINAL.name not in available()
    assert np.allclose(np.diff(noisy.time), NOMINAL.sample_time)
    # the logged commands are the same with and without noise (the driver sees the true state)
    assert np.array_equal(noisy.states[:, 6:], clean.states[:, 6:])
    # the rates are the commands' forward differences (what the project's model integrates)
    assert np.allclose(noisy.inputs[:-1, 1] * noisy.sample_time, np.diff(noisy.states[:, 7]))
    # the actual wheel angle (servo + CommonRoad's rate limit) differs from the logged, held command
    assert np.max(np.abs(noisy.extras["true_steering"] - noisy.states[:, 7])) > 1e-4
    # white noise of the vehicle's sensor_noise_std on every logged state
    for i, c in enumerate(CP.NOISY):
        err = noisy.states[:, i] - noisy.extras[f"true_{c}"]
        assert 0.8 < err.std() / NOMINAL.sensor_noise_std[c] < 1.2, c
        assert abs(np.corrcoef(err[1:], err[:-1])[0, 1]) < 0.15, c


def test_coloured_noise():
    ds = _log(noise=1.0, color=0.8, duration=20.0)
    err = ds.states[:, 3] - ds.extras["true_vx"]
    assert 0.65 < np.corrcoef(err[1:], err[:-1])[0, 1] < 0.92
    assert 0.6 < err.std() / NOMINAL.sensor_noise_std["vx"] < 1.4


def test_nominal_vehicle_file_maps_the_plant(clean):
    """The mapped coefficients predict the plant's next velocities well (a sign or unit error in the mapping
    would not): one-step errors a small fraction of how much the states move over a step."""
    ds = clean
    pred = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], NOMINAL.true_vector(), NOMINAL.known,
                               ds.sample_time, "rk4", NOMINAL.rk4_substeps)
    for i in (3, 4, 5):
        err = np.sqrt(np.mean((pred[:, i] - ds.states[1:, i]) ** 2))
        move = np.sqrt(np.mean(np.diff(ds.states[:, i]) ** 2))
        assert err < 0.5 * move, (i, err, move)
    # and an unmapped car (the AV-21's coefficients) is clearly worse on omega
    av = load_vehicle("av21")
    bad = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], av.true_vector(), av.known, ds.sample_time, "rk4", 2)
    assert np.mean((bad[:, 5] - ds.states[1:, 5]) ** 2) > 4 * np.mean((pred[:, 5] - ds.states[1:, 5]) ** 2)


def _lag(a, b, dt):
    """The delay (s) of b behind a by cross-correlation of their increments."""
    da, db = np.diff(a), np.diff(b)
    lags = np.arange(0, 12)
    c = [np.dot(da[: len(da) - k], db[k:]) for k in lags]
    return lags[int(np.argmax(c))] * dt


def test_effects_act_physically(clean):
    delayed = _log(CP.PlantEffects(steer_delay=0.12), noise=0.0)
    base = _lag(clean.states[:, 7], clean.extras["true_steering"], clean.sample_time)
    late = _lag(delayed.states[:, 7], delayed.extras["true_steering"], delayed.sample_time)
    assert late - base == pytest.approx(0.12, abs=0.045)

    # open loop, the same commands: a heavier car gains less speed for the same throttle (drive force fixed),
    # and downforce lets a saturated front axle turn the car faster (more load, more grip, no more inertia)
    def drive(mass_offset=0.0, downforce=0.0, steer=0.0, throttle=0.0, seconds=0.6):
        p = CP.commonroad_parameters()
        p.I_z *= 1 + mass_offset
        env = CP._Env(p=p, m_true=NOMINAL.known.mass * (1 + mass_offset), m_nominal=NOMINAL.known.mass,
                      downforce=downforce, servo_tau=CP.SERVO_TAU)
        x = CP.init_std([0.0, 0.0, 0.0, 25.0, 0.0, 0.0, 0.0], p)
        for _ in range(int(seconds * CP.PLANT_RATE)):
            x = CP.rk4_step(x, 1.0 / CP.PLANT_RATE, steer, throttle, env)
        return x

    gain = drive(throttle=0.5)[3] - drive()[3]
    gain_heavy = drive(mass_offset=0.3, throttle=0.5)[3] - drive(mass_offset=0.3)[3]
    assert gain_heavy / gain == pytest.approx(1 / 1.3, rel=0.05)
    yaw = drive(steer=0.2, seconds=0.3)[5]
    yaw_df = drive(steer=0.2, seconds=0.3, downforce=4e-4)[5]
    assert yaw_df > 1.05 * yaw > 0
    # bank: into the turns, both signs on a road course
    from ddyn.model.tracks import load_track

    t = load_track("putnam")
    b = CP.bank_profile(t, 0.05)
    assert b.max() == pytest.approx(0.05) and b.min() < -0.01
    g = CP.grade_profile(t, 0.03)
    assert abs(g.mean()) < 1e-3 and g.max() == pytest.approx(0.03, rel=1e-3)


def test_gate_rescoring_and_calibration():
    rows = [{"status": "ok", "effect": "none", "selected_without_gate": ["mass_offset"] if i < 8 else [],
             "gate_ratio": 1.0 + 0.01 * i, "correct_without_gate": i >= 8, "delta_bic_top": -1.0} for i in range(20)]
    thr = CAL.calibrate(rows)     # 8 alarms, at most 1 allowed (5 % of 20): the 7th largest alarm ratio
    assert thr == pytest.approx(1.06)
    gated = CAL.with_gate(rows, thr)
    assert sum(bool(r["selected"]) for r in gated) == 1
    assert sum(bool(r["selected"]) for r in CAL.with_gate(rows, None)) == 8
    # the evidence margin: the first effect needs dBIC < -margin
    for i, r in enumerate(rows):
        r["delta_bic_top"] = -2.0 * i if r["selected_without_gate"] else 3.0
    m = CAL.calibrate_margin(rows)           # alarms at dBIC 0, -2, ..., -14: all but the strongest refused
    assert m == pytest.approx(12.0)
    kept = CAL.with_gate(rows, None, m)
    assert [r["top1"] for r in kept if r["selected"]] == ["mass_offset"] and kept[7]["selected"]
    # several calibration runs pooled: 5 % of all their effect-free logs (2 of 40 allowed, 1 of 20 alone), and
    # never below a margin a run was recorded with (its weaker alarms were not recorded)
    import json
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        paths = []
        quiet = [r | {"selected_without_gate": []} for r in rows]     # 20 more effect-free logs, no alarm
        for i, rs in enumerate((rows, quiet)):
            p = Path(d) / f"{i}.json"
            p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": rs}))
            paths.append(str(p))
        assert CAL.margin_of(paths[0]) == pytest.approx(12.0)
        # 8 alarms in 40 logs, 2 allowed: the two strongest (-14, -12) stay
        assert CAL.margin_of(",".join(paths)) == pytest.approx(10.0) == CAL.margin_of(paths)
        p = Path(d) / "strict.json"
        p.write_text(json.dumps({"settings": {"min_evidence": 20.0}, "results": []}))
        assert CAL.margin_of(paths + [str(p)]) == pytest.approx(20.0)


def test_diagnose_gate_vetoes_a_selection_inside_the_noise():
    ds = _log(CP.PlantEffects(steer_delay=0.08), duration=24.0)
    nominal = P.nominal_from_vehicle(NOMINAL, ds)
    kw = dict(candidates=("steer_delay", "mass_offset"), max_effects=1, max_starts=50)
    open_ = SEL.diagnose(ds, nominal, gate=None, **kw)
    assert open_["selected"] == ["steer_delay"] and open_["gate"]["ratio"] > 1.0
    shut = SEL.diagnose(ds, nominal, gate=open_["gate"]["ratio"] * 1.01, **kw)
    assert shut["selected"] == [] and shut["gate"]["gated"] and shut["gate"]["selected_without_gate"] == ["steer_delay"]
    assert shut["verdict"].startswith("none: the nominal's held-out error is within the noise floor")
    # the gated verdict keeps only the refit: it claims less of the error than the open one
    assert shut["model"]["error_reduction_pct"] < open_["model"]["error_reduction_pct"]


def test_the_oracle_gap_compares_the_diagnosis_with_the_true_effect_at_its_true_value(monkeypatch):
    """diagnose(truth=...) scores the model given the hidden effect at its true value (the refit around it); on a
    log with a clear steering delay the oracle closes a real gap, a far-off value does worse, and the diagnosis
    that finds the delay closes most of the oracle's gap, a vetoed one none of it."""
    ds = _log(CP.PlantEffects(steer_delay=0.08), seed=5, duration=40.0)
    nominal = P.nominal_from_vehicle(NOMINAL, ds)
    kw = dict(candidates=("steer_delay", "mass_offset"), max_effects=1, max_starts=50, gate=None, hold=True,
              steer_servo=CP.SERVO_TAU)     # the servo in the nominal: the delay on top of it is the plant's own
    case = {"effect": "steer_delay", "magnitude": 0.08}
    d = SEL.diagnose(ds, nominal, truth={"steer_delay": 0.08}, **kw)
    assert d["selected"] == ["steer_delay"] and d["truth"]["delta_bic"] < 0
    o = G.oracle_figures(d, case)
    assert o["e_oracle"] < o["e_refit"] and 0.8 < o["gap_vs_oracle"] < 1.2 and 0.8 < o["own_fit_vs_oracle"] < 1.2
    # the runner-up is far behind: no rival; with an ambiguity band wider than their gap it is named in the verdict
    assert d["rival"] is None and "not told apart" not in d["verdict"]
    gap = d["candidates"][1]["delta_bic"] - d["candidates"][0]["delta_bic"]
    monkeypatch.setattr(SEL, "AMBIGUITY_DBIC", gap + 1.0)
    tie = SEL.diagnose(ds, nominal, **kw)
    assert tie["selected"] == ["steer_delay"] and tie["rival"]["effect"] == "mass_offset"
    assert tie["rival"]["evidence_difference"] == pytest.approx(gap) and "or mass_offset" in tie["verdict"]
    assert tie["not_told_apart"] is None        # without detection limits the choice is named, not withheld
    # with detection limits (the delay above its limit) the same tie is reported and nothing is claimed
    strict = SEL.diagnose(ds, nominal, detection_limits={"steer_delay": 0.01, "*": None}, **kw)
    assert strict["selected"] == [] and strict["below_limit"] is None and strict["rival"] is None
    t = strict["not_told_apart"]
    assert t["effect"] == "steer_delay" and t["rival"] == "mass_offset"
    assert t["evidence_difference"] == pytest.approx(gap) and t["params"]["delay"] == pytest.approx(0.08, rel=0.2)
    assert strict["verdict"].startswith("none: steer_delay") and "not told apart, not claimed" in strict["verdict"]
    assert strict["greedy"][0]["not_told_apart"] and strict["greedy"][0]["added"] is None
    monkeypatch.setattr(SEL, "AMBIGUITY_DBIC", 2.0)     # far apart again: the delay is claimed under the same limits
    assert SEL.diagnose(ds, nominal, detection_limits={"steer_delay": 0.01, "*": None}, **kw)["selected"] == ["steer_delay"]
    assert d["runner_up"]["effect"] == "mass_offset" and d["runner_up"]["evidence_difference"] == pytest.approx(gap)
    far = G.oracle_figures(SEL.diagnose(ds, nominal, truth={"steer_delay": 0.3}, **kw), case)
    assert far["e_oracle"] > o["e_oracle"]
    row = {"status": "ok", "effect": "steer_delay", "selected_without_gate": ["steer_delay"], "gate_ratio": 1.0,
           "delta_bic_top": -5.0, **o}
    vetoed = CAL.with_gate([row], None, margin=10.0)[0]
    assert vetoed["gap_vs_oracle"] == 0.0 and vetoed["e_diagnosed"] == o["e_refit"]
    s = G.oracle_summary([row | {"correct": True}, vetoed | {"correct": False}])
    assert s["oracle_cases"] == 2 and s["median_gap_vs_oracle_found"] == pytest.approx(min(o["gap_vs_oracle"], 1.0))
    assert s["median_gap_vs_oracle"] == pytest.approx(0.5 * min(o["gap_vs_oracle"], 1.0))   # a miss closes nothing
    wrong = row | {"correct": False, "top1": "mass_offset"}     # a wrong effect that lowers the error
    s = G.oracle_summary([wrong, wrong])
    assert s["median_gap_vs_oracle"] == pytest.approx(min(o["gap_vs_oracle"], 1.0))
    assert s["median_gap_vs_oracle_strict"] == 0.0


def _sweep_doc(results: list[dict], duration: float = 24.0, seed: int = 11, **diag) -> dict:
    """A recorded sweep run (what `ddyn gap benchmark --case-set sweep` writes) around these cases."""
    from ddyn.gap.config import DiagnosisConfig

    return {"settings": {"plant": "commonroad", "case_set": "sweep", "duration": duration, "seed": seed,
                         "track": "putnam", "car": "commonroad_vehicle2", "nominal": "mapped", "sample_time": 0.04,
                         "pitch_channel": False, "roll_channel": False, "min_evidence": 0.0, "gate": None,
                         "diagnosis": DiagnosisConfig(**diag).to_dict()}, "results": results}


def test_gap_benchmark_commonroad_cli(tmp_path, monkeypatch, capsys):
    """Two cases in two processes, then rescores: at a margin that vetoes every selection, and against a
    calibration (its thresholds, its claim record); the files agree with what was scored."""
    import json

    from ddyn.cli import main

    monkeypatch.setattr(G, "DURATION", 24.0)   # workers are forked: they see the shorter logs
    out = tmp_path / "gap"
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "2", "--jobs", "2", "--seed", "3",
                 "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert [r["effect"] for r in doc["results"]] == ["steer_delay", "throttle_delay"]
    assert all(r["status"] == "ok" and r["rows"] == 601 for r in doc["results"])
    assert doc["settings"]["gate"] is None and doc["settings"]["diagnosis"] == G.DiagnosisConfig().to_dict()
    # claim precision: a calibration that names steering delay on throttle-delay logs too gives it no threshold
    def row(e, mag, top1):
        return {"status": "ok", "effect": e, "magnitude": mag, "estimate": mag, "top1": top1, "correct": top1 == e,
                "selected_without_gate": [top1], "gate_ratio": 1.2, "delta_bic_top": -50.0}
    rows = [row("steer_delay", m, "steer_delay") for m in (0.02, 0.05, 0.1)]
    cal = CAL.from_runs("t", [_sweep_doc(rows + [row("throttle_delay", m, "steer_delay") for m in (0.1, 0.2)])])
    assert cal.measured_thresholds["steer_delay"] == 0.02 and cal.thresholds["steer_delay"] is None
    assert cal.claim_record == {"counts": {"steer_delay": _claims(5, 3, 2)}, "withdrawn": ["steer_delay"]}
    path = CAL.write(cal, tmp_path / "t.json")
    assert main(["gap", "rescore", "--calibration", str(path), "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["settings"]["thresholds"]["steer_delay"] is None and doc["settings"]["calibration"]["name"] == "t"
    assert "such claims/claims: steer_delay 2/5 (3 right); withdrawn: steer_delay" in (out / "results.md").read_text()
    huge = max(-r["delta_bic_top"] for r in doc["results"]) * 2
    assert main(["gap", "rescore", "--min-evidence", str(huge), "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert all(r["top1"] == "none" for r in doc["results"]) and doc["settings"]["min_evidence"] == huge
    assert main(["gap", "rescore", "--min-evidence", "0", "--out", str(out)]) == 2     # a margin only rises
    assert "can only raise the margin" in capsys.readouterr().err
    kept = CAL.from_runs("k", [_sweep_doc(rows)])
    assert kept.thresholds["steer_delay"] == 0.02 and kept.claim_record["withdrawn"] == []
    # a calibration reads sweeps recorded with margin 0 and no limits, of one plant, length and setting
    with pytest.raises(DdynError, match="not a sweep recorded with margin 0"):
        CAL.from_runs("x", [_sweep_doc(rows, min_evidence=3.0)])
    with pytest.raises(DdynError, match="differs from run 0 in duration"):
        CAL.from_runs("x", [_sweep_doc(rows), _sweep_doc(rows, duration=60.0)])


def test_gap_benchmark_duration_sets_the_log_length_and_a_calibration_must_match_it(tmp_path, capsys):
    """--duration: every case's log has that many seconds (recorded in the settings and the table); a calibration
    made on logs of another length is refused, and one applies to the case sets it was made for only."""
    import json

    from ddyn.cli import main

    out = tmp_path / "gap"
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "1", "--seed", "3",
                 "--duration", "20", "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["settings"]["duration"] == 20.0 and doc["results"][0]["rows"] == 501
    assert isinstance(doc["results"][0]["estimate_top"], float)     # the top candidate's size, whatever it is
    assert "20 s logs" in (out / "results.md").read_text()
    cal = CAL.write(CAL.from_runs("c20", [_sweep_doc(doc["results"], duration=20.0)]), tmp_path / "c20.json")
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "1", "--seed", "5", "--duration", "60",
                 "--calibration", str(cal), "--out", str(tmp_path / "other"), "--no-progress"]) == 2
    assert "calibration c20 was made on 20 s logs" in capsys.readouterr().err
    assert main(["gap", "benchmark", "--plant", "commonroad", "--case-set", "oval", "--calibration", str(cal),
                 "--out", str(out)]) == 2
    assert "--calibration: the CommonRoad plants' putnam, sweep and above case sets only" in capsys.readouterr().err
    with pytest.raises(DdynError, match="--duration"):
        G.run(1, 3, duration=0.0)


def test_a_lost_car_is_retried_on_other_seeds_then_slower(monkeypatch):
    """make_case_log: `tries` seeds at the drawn speed, then as many more each RETRY_SLOWER slower (not below
    SLOWEST_RETRY); the log that came through carries the speed it was driven at, and a case lost at every speed
    comes back as not simulated with the last error."""
    tried, fastest = [], [19.0]

    def make_log(track, effects, seed, settings):
        tried.append((seed, settings.target_speed))
        if settings.target_speed > fastest[0]:
            raise DdynError(f"the driver lost the CommonRoad car (seed {seed})")
        return "log"

    monkeypatch.setattr(CP, "make_log", make_log)
    case = G.plan(1, 5)[0] | {"target_speed": 22.5}
    log, seed, err = G.make_case_log(case)
    assert log == "log" and err is None
    assert [v for _, v in tried] == [22.5, 22.5, 22.5, 22.5 - G.RETRY_SLOWER, 22.5 - 2 * G.RETRY_SLOWER]
    assert len({s for s, _ in tried}) == len(tried) and seed == tried[-1][0]
    tried.clear()
    log, _, err = G.make_case_log(case | {"target_speed": 40.0})
    assert log is None and "lost the CommonRoad car" in err
    assert [v for _, v in tried][3:] == [38.0, 36.0, 34.0]
    tried.clear()
    fastest[0] = 10.0
    G.make_case_log(case | {"target_speed": 15.0}, tries=2)
    assert [v for _, v in tried] == [15.0, 15.0, G.SLOWEST_RETRY, G.SLOWEST_RETRY]


def test_gap_benchmark_effects_filter_and_multistep_evidence(tmp_path, monkeypatch):
    """[benchmark] effects keeps only those cases, with the whole plan's case numbers and seeds; [diagnosis]
    evidence reaches every case (the multi-step dBIC decides, the one-step one is recorded beside it); a bad effect
    or spec fails."""
    import json

    from ddyn.cli import main

    monkeypatch.setattr(G, "DURATION", 24.0)
    out = tmp_path / "gap"
    cfg = tmp_path / "c.toml"
    cfg.write_text('[diagnosis]\nevidence = "multistep:10"\n[benchmark]\neffects = ["mass_offset", "none"]\n')
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "8", "--seed", "3", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "results.json").read_text())
    whole = G.plan(8, 3)
    assert [(r["case"], r["seed"]) for r in doc["results"]] == [(c["case"], c["seed"]) for c in whole
                                                                 if c["effect"] in ("mass_offset", "none")]
    assert doc["settings"]["evidence"] == "multistep:10" and "multistep:10" in (out / "results.md").read_text()
    r = doc["results"][0]
    assert r["effect"] == "mass_offset" and r["status"] == "ok"
    assert r["delta_bic_true_one_step"] != r["delta_bic_true"]
    with pytest.raises(DdynError, match="effects"):
        G.run(8, 3, bench=G.BenchmarkConfig(effects=("mass",)))
    with pytest.raises(DdynError, match="evidence"):
        G.DiagnosisConfig(evidence="rollout")


def test_gap_benchmark_pitch_channel(tmp_path, monkeypatch, capsys):
    """[benchmark] pitch_channel: the grade case's log carries the plant's pitch channel and its diagnosis tries the
    grade read from it; recorded in the settings and the table; refused where it does not apply."""
    import json

    from ddyn.cli import main

    monkeypatch.setattr(G, "DURATION", 24.0)
    out = tmp_path / "gap"
    cfg = tmp_path / "c.toml"
    cfg.write_text('[diagnosis]\nhold = true\n[benchmark]\neffects = ["grade"]\npitch_channel = true\n')
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "8", "--seed", "3", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["settings"]["pitch_channel"] and "pitch channel" in (out / "results.md").read_text()
    (r,) = doc["results"]
    assert r["effect"] == "grade" and r["status"] == "ok" and r["config"]["candidates"][-1] == "grade_from_pitch"
    log, _, _ = G.make_case_log(r)
    assert "pitch" in log.extras and "pitch" not in G.make_case_log(r | {"pitch_channel": False})[0].extras
    assert main(["gap", "benchmark", "--plant", "commonroad-mb", "--config", str(cfg), "--out", str(out)]) == 2
    assert "pitch_channel, roll_channel: the single-track plant's" in capsys.readouterr().err
    # roll_channel: the same for the bank (the bank case of the plan)
    cfg.write_text('[diagnosis]\nhold = true\n[benchmark]\neffects = ["bank_angle"]\nroll_channel = true\n')
    assert main(["gap", "benchmark", "--plant", "commonroad", "--cases", "8", "--seed", "3", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "results.json").read_text())
    (r,) = doc["results"]
    assert doc["settings"]["roll_channel"] and r["status"] == "ok" and r["config"]["candidates"][-1] == "bank_from_roll"
    assert "roll" in G.make_case_log(r)[0].extras


def test_the_command_hold_explains_the_dbw_delay():
    """On an effect-free log of the plant, the ramped commands of the nominal lag the DBW's held ones by about
    half a sample plus the servo: without --hold a steering delay of about that size is selected; with the hold
    modelled, nothing is, and a real 60 ms delay is estimated on top of the hold."""
    kw = dict(candidates=("steer_delay", "throttle_delay", "mass_offset"), max_effects=1, max_starts=50, gate=None)
    clean = _log(seed=5, duration=60.0)
    nominal = P.nominal_from_vehicle(NOMINAL, clean)
    ramp = SEL.diagnose(clean, nominal, **kw)
    assert ramp["selected"] == ["steer_delay"]
    assert 0.02 < ramp["model"]["effects"][0]["params"]["delay"] < 0.06
    assert SEL.diagnose(clean, nominal, hold=True, **kw)["selected"] == []
    late = _log(CP.PlantEffects(steer_delay=0.06), seed=5, duration=60.0)
    d = SEL.diagnose(late, P.nominal_from_vehicle(NOMINAL, late), hold=True, **kw)
    assert d["selected"] == ["steer_delay"]
    assert d["model"]["effects"][0]["params"]["delay"] == pytest.approx(0.06 + CP.SERVO_TAU, abs=0.015)


def test_identified_nominal_fits_the_plant_better(monkeypatch):
    """Option (b): coefficients fitted on an effect-free plant log stay inside the vehicle file's ranges and
    predict that log at least as well as the mapped ones."""
    monkeypatch.setattr(G, "IDENT_DURATION", 20.0)
    c, info = G.identified_coefficients(hold=True)
    lo, hi = NOMINAL.range_arrays()
    assert np.all((lo - 1e-9 <= c) & (c <= hi + 1e-9) | (NOMINAL.true_vector() == 0))
    log = CP.make_log(G.TRACK, CP.PlantEffects(), G.IDENT_SEED, CP.LogSettings(duration=20.0))

    def err(coeffs):
        p = P.Problem(log, P.nominal_from_vehicle(NOMINAL, log, coeffs), 0.95, refit=(), hold=True)
        return float(np.sum(p.residuals({}, np.zeros(0), p.rows_all) ** 2))

    assert err(c) < err(NOMINAL.true_vector())


def test_the_spurious_mass_offset_is_not_errors_in_variables(monkeypatch):
    """On a short effect-free plant log (command hold modelled), the mass offset a candidate fit finds is not an
    errors-in-variables bias: one-step steps from the noise-free states find it too (it is the plant's own
    mismatch, weighed through the lateral channels); the output-error fit, which weighs the longitudinal drift
    over ten steps, finds a much smaller one."""
    monkeypatch.setattr(G, "DURATION", 30.0)
    case = G.plan(12, G.EIV_SEED)[4] | {"effect": G.NONE, "magnitude": 0.0, "hold": True}
    r = G.eiv_case(case)
    m = {k: v["mass_offset"] for k, v in r["fits"].items()}
    assert m["one-step (logged states)"] < -0.1 and m["one-step from the noise-free states"] < -0.1
    assert abs(m["output-error"]) < 0.5 * abs(m["one-step (logged states)"])


def test_scoring_thresholds_and_delay_vs_lag():
    """Measured thresholds, top-1 above thresholds given from another run, steering delay vs lag."""
    def row(e, mag, top1):
        return {"status": "ok", "effect": e, "magnitude": mag, "top1": top1, "correct": top1 == e,
                "selected": [] if top1 == G.NONE else [top1], "selected_without_gate": [] if top1 == G.NONE else [top1],
                "correct_without_gate": top1 == e, "param_error": 0.1, "gate_ratio": 1.2,
                "gap_closed_pct": 50.0, "error_reduction_pct": 5.0, "gap_closed_pct_top_candidate": 1.0,
                "error_reduction_pct_top_candidate": 1.0, "gate_threshold": None, "min_evidence": 0.0,
                "diagnose_seconds": 1.0}
    rows = [row("steer_delay", m, "steer_delay" if m >= 0.05 else "steer_lag") for m in (0.02, 0.04, 0.06, 0.1)]
    rows += [row("steer_lag", m, "steer_lag" if m >= 0.1 else G.NONE) for m in (0.05, 0.1, 0.15)]
    rows += [row(G.NONE, 0.0, G.NONE), row(G.NONE, 0.0, "mass_offset")]
    assert CAL.reliable_threshold([r for r in rows if r["effect"] == "steer_delay"]) == pytest.approx(0.06)
    sc = G.score(rows, {"steer_delay": 0.04, "steer_lag": 0.1})
    s = sc["summary"]
    assert sc["per_effect"]["steer_lag"]["measured_threshold"] == pytest.approx(0.1)
    assert s["above_threshold_cases"] == 5 and s["top1_above_thresholds"] == pytest.approx(4 / 5)
    assert s["below_threshold_cases"] == 2 and s["any_selected_below_thresholds"] == pytest.approx(0.5)
    assert s["any_selected_none_or_below"] == pytest.approx(2 / 4)   # below: one lag named, one none; none: 1 of 2
    lad = sc["per_effect"]["steer_delay"]["ladder"]
    assert [x[0] for x in lad] == [0.1, 0.06, 0.04, 0.02] and [x[1] for x in lad][-2:] == ["steer_lag", "steer_lag"]
    assert "| steer_delay | 0.06 | 0.1 -> OK" in G.ladder_markdown(sc["per_effect"])
    dl = s["delay_vs_lag"]
    assert dl["named_either"] == 6 and dl["told_apart"] == pytest.approx(4 / 6) and dl["delay_named_lag"] == 2
    assert dl["flagged_not_told_apart"] is None      # runs recorded before the rival was: no claim either way
    # the two delays named lag flagged with the other as rival: where the diagnosis claims a choice, it is right
    for r in rows:
        r["rival"] = "steer_delay" if r["effect"] == "steer_delay" and r["top1"] == "steer_lag" else None
    dl = G.delay_vs_lag(rows)
    assert dl["flagged_not_told_apart"] == 2 and dl["told_apart_where_claimed"] == pytest.approx(1.0)
    assert s["false_alarm_rate"] == pytest.approx(0.5)
    assert s["withheld_below_limit"] == 0 and s["withheld_not_told_apart"] == 0 and "Reported, not claimed" not in \
        G._threshold_line(s, sc["per_effect"])
    # under detection limits: the 0.05 s lag withheld below its limit, the 0.02 s delay as not told apart
    rows[4]["below_limit"] = "steer_lag"
    rows[0] |= {"not_told_apart": ["steer_delay", "steer_lag"], "top1": G.NONE, "selected": [], "correct": False}
    s2 = G.score(rows, {"steer_delay": 0.04, "steer_lag": 0.1})["summary"]
    assert s2["withheld_below_limit"] == 1 and s2["withheld_not_told_apart"] == 1
    assert "below a limit on 1 logs, not told apart from a rival on 1" in G._threshold_line(s2, {})
    # thresholds pooled over two calibration runs: the union's cases of an effect, its tail from the top still
    # >= 95 % found (one run's miss at 0.2 s left it no threshold; with the other's cases it stops at that miss)
    import json
    import tempfile

    one = [row("throttle_delay", m, "throttle_delay" if m != 0.2 else G.NONE) for m in (0.05, 0.1, 0.2, 0.3)]
    two = [row("throttle_delay", m, "throttle_delay") for m in (0.06, 0.12, 0.18, 0.25, 0.29, 0.3)]
    with tempfile.TemporaryDirectory() as d:
        paths = []
        for i, rs in enumerate((one, two)):
            p = Path(d) / f"{i}.json"
            p.write_text(json.dumps({"results": rs, **G.score(rs)}))
            paths.append(str(p))
        assert CAL.thresholds_of(paths[0]) == {"throttle_delay": None}
        assert CAL.thresholds_of(",".join(paths)) == {"throttle_delay": pytest.approx(0.25)}
        # at a margin the thresholds are measured on the cases rescored with it: the weak finds below it lost
        weak = [r | {"delta_bic_top": -3.0 if r["magnitude"] < 0.2 else -50.0} for r in two]
        p = Path(d) / "weak.json"
        p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": weak}))
        assert CAL.thresholds_of(str(p)) == {"throttle_delay": pytest.approx(0.06)}
        assert CAL.thresholds_of(str(p), margin=5.0) == {"throttle_delay": pytest.approx(0.25)}
        with pytest.raises(DdynError, match="can only raise"):
            CAL.thresholds_of(str(p), margin=-1.0)
    # tied magnitudes enter the tail together, whichever order they come in
    tie = [row("steer_lag", 0.25, "steer_lag"), row("steer_lag", 0.2, "steer_lag"), row("steer_lag", 0.2, "steer_lag"),
           row("steer_lag", 0.15, "steer_lag"), row("steer_lag", 0.15, G.NONE)]
    assert CAL.reliable_threshold(tie) == CAL.reliable_threshold(tie[::-1]) == pytest.approx(0.2)
    # a tail of one magnitude level (pooled sweeps' top, one case per seed) measures no threshold, however many
    # cases it holds: found 4/4 at the largest downforce drawn only, 3/10 above it on a blind seed
    top_only = [row("downforce", 4e-4, "downforce") for _ in range(4)]
    top_only += [row("downforce", 3e-4, "downforce" if k < 3 else G.NONE) for k in range(4)]
    assert CAL.reliable_threshold(top_only) is None
    assert CAL.reliable_threshold(top_only, min_levels=1) == pytest.approx(4e-4)
    # the tail is judged as a whole: one miss near the top among 20 cases (95 % found) does not lift the threshold
    # above it; two (18/20) do, above the upper one (every tail holding it has fewer than 20 cases)
    mags = np.linspace(0.05, 0.3, 20)
    one_miss = [row("steer_lag", m, G.NONE if k == 17 else "steer_lag") for k, m in enumerate(mags)]
    assert CAL.reliable_threshold(one_miss) == pytest.approx(0.05)
    two_miss = [row("steer_lag", m, G.NONE if k in (3, 17) else "steer_lag") for k, m in enumerate(mags)]
    assert CAL.reliable_threshold(two_miss) == pytest.approx(mags[18])
    assert CAL.reliable_threshold([row("steer_lag", m, G.NONE) for m in mags]) is None
    # a run with --cases 30 holds the first 30 cases of one with 50 (rescore --cases 30 compares like with like)
    assert G.plan(30, 4242) == G.plan(50, 4242)[:30]


def test_decision_limits_sit_below_the_thresholds_by_the_estimate_spread_there(tmp_path):
    """Currie's decision level: threshold + bias - 1.645 sd of (|estimate| - |magnitude|) over the calibration
    cases within a factor two of the threshold; a case far from it does not count; no threshold, no limit; the
    threshold itself when too few cases measure a spread; and never below zero."""
    import json

    def row(e, mag, est, top1=None):
        top1 = top1 or e
        return {"status": "ok", "effect": e, "magnitude": mag, "estimate": est, "top1": top1,
                "correct": top1 == e, "selected_without_gate": [top1], "gate_ratio": 1.2, "delta_bic_top": -50.0}
    # found from 0.1 s up: threshold 0.1; the estimates' errors in the band [0.05, 0.2]: +0.03, -0.01, +0.01, -0.03
    rs = [row("steer_lag", 0.02, 0.2, G.NONE), row("steer_lag", 0.04, 0.01, G.NONE)]
    rs += [row("steer_lag", m, m + e) for m, e in ((0.1, -0.01), (0.15, 0.01), (0.2, -0.03), (0.4, 0.03))]
    rs += [row("steer_lag", 0.05, 0.08, G.NONE), row("steer_lag", 0.6, 0.2)]     # 0.6: outside the band
    rs += [row("downforce", 4e-4, 1e-4, G.NONE) for _ in range(3)]
    p = tmp_path / "cal.json"
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": rs}))
    assert CAL.thresholds_of(str(p)) == {"steer_lag": pytest.approx(0.1), "downforce": None}
    lim = CAL.decision_limits_of(str(p))
    err = np.array([0.03, -0.01, 0.01, -0.03])       # at 0.05, 0.1, 0.15, 0.2: 0.4 and 0.6 are outside [0.05, 0.2]
    assert lim["downforce"] is None
    assert lim["steer_lag"] == pytest.approx(0.1 + err.mean() - CAL.DECISION_Z * err.std(ddof=1))
    assert lim["steer_lag"] < 0.1
    # a wide spread would put the limit below zero: zero, every find claimed
    wide = [r | {"estimate": r["magnitude"] + (0.2 if k % 2 else -0.2)} for k, r in enumerate(rs)]
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": wide}))
    assert CAL.decision_limits_of(str(p))["steer_lag"] == 0.0
    # one case in the band measures no spread: the threshold itself
    few = [row("throttle_delay", m, m, "throttle_delay" if m >= 0.1 else G.NONE) for m in (0.02, 0.1, 0.3, 0.5)]
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": few}))
    assert CAL.decision_limits_of(str(p)) == {"throttle_delay": pytest.approx(0.1)}


def test_claim_precision_withdraws_the_threshold_of_an_effect_named_where_it_is_not(tmp_path):
    """--claim-precision: an effect found at every magnitude but also claimed first on logs where nothing should be
    claimed (downforce on banked ones, which have no threshold) gets no threshold and no decision level when over
    5 % of its claims land there; an effect whose claims hold keeps its own; a margin, a limit or the tie veto that
    withholds the wrong claims restores it."""
    import json

    def row(e, mag, top1, dbic=-50.0):
        return {"status": "ok", "effect": e, "magnitude": mag, "estimate": mag, "top1": top1,
                "correct": top1 == e, "selected_without_gate": [] if top1 == G.NONE else [top1],
                "gate_ratio": 1.2, "delta_bic_top": dbic}
    rs = [row("downforce", m, "downforce") for m in (5e-5, 1e-4, 2e-4, 4e-4)]
    rs += [row("steer_lag", m, "steer_lag") for m in (0.03, 0.06, 0.1, 0.2)]
    rs += [row("bank_angle", b, "downforce", dbic=-12.0) for b in (0.05, 0.1)] + [row(G.NONE, 0.0, G.NONE)]
    p = tmp_path / "cal.json"
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": rs}))
    assert CAL.claim_precisions(str(p)) == {"downforce": _claims(6, 4, 2), "steer_lag": _claims(4, 4, 0)}
    assert CAL.thresholds_of(str(p))["downforce"] == pytest.approx(5e-5)
    got = CAL.thresholds_of(str(p), precision=True)
    assert got["downforce"] is None and got["steer_lag"] == pytest.approx(0.03) and got["bank_angle"] is None
    assert CAL.decision_limits_of(str(p), precision=True)["downforce"] is None
    # at a margin of 20 the banked logs' downforce (dBIC -12) is not selected: every claim of it is right again
    assert CAL.claim_precisions(str(p), 20.0)["downforce"] == _claims(4, 4, 0)
    assert CAL.thresholds_of(str(p), 20.0, precision=True)["downforce"] == pytest.approx(5e-5)
    # only the claims the diagnosis would make count: a lag named steering delay with an estimate under the
    # delay's limit, or with the lag within AMBIGUITY_DBIC behind (the tie veto), is not one; a clear one is
    delay = [row("steer_delay", m, "steer_delay") for m in (0.02, 0.05, 0.1)]
    vetoed = [row("steer_lag", 0.03, "steer_delay") | {"estimate_top": 0.005, "runner_up_gap": 10.0},
              row("steer_lag", 0.04, "steer_delay") | {"estimate_top": 0.03, "runner_up_gap": 1.0}]
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": delay + vetoed}))
    assert CAL.claim_precisions(str(p)) == {"steer_delay": _claims(5, 3, 2)}
    assert CAL.precision_record(str(p)) == {"counts": {"steer_delay": _claims(3, 3, 0)}, "withdrawn": []}
    assert CAL.thresholds_of(str(p), precision=True)["steer_delay"] == pytest.approx(0.02)
    clear = row("steer_lag", 0.05, "steer_delay") | {"estimate_top": 0.03, "runner_up_gap": 10.0}
    p.write_text(json.dumps({"settings": {"min_evidence": 0.0}, "results": delay + vetoed + [clear]}))
    assert CAL.precision_record(str(p)) == {"counts": {"steer_delay": _claims(4, 3, 1)}, "withdrawn": ["steer_delay"]}
    assert CAL.thresholds_of(str(p), precision=True)["steer_delay"] is None
    assert CAL.decision_limits_of(str(p), precision=True)["steer_delay"] is None
    # the same claim on a lag above the lag's threshold is a top-1 miss there (the top-1 and delay-vs-lag targets
    # score it), not a claim where nothing should be claimed
    assert CAL.claim_precisions(str(p), limits={"steer_delay": 0.02},
                              thresholds={"steer_delay": 0.02, "steer_lag": 0.04}) == {"steer_delay": _claims(4, 3, 0)}


def test_diagnose_under_a_calibration_takes_its_settings_margin_and_decision_levels(tmp_path, capsys, monkeypatch):
    """gap diagnose --calibration FILE: the sweeps' settings (hold, fit, mass inertia), the pooled margin and decision
    levels, every uncalibrated effect never claimed, recorded in diagnosis.json and the report; a log of another
    length and a config whose settings differ are refused; by default a shipped calibration that covers the log is
    used, and a log none covers is diagnosed uncalibrated, saying why; a stale one is refused."""
    import json

    from ddyn.cli import main
    from ddyn.data.dataset import write_canonical
    from ddyn.model.tracks import load_track

    def row(e, mag, est, top1, dbic=-50.0):
        return {"status": "ok", "effect": e, "magnitude": mag, "estimate": est, "top1": top1, "correct": top1 == e,
                "selected_without_gate": [] if top1 == G.NONE else [top1], "gate_ratio": 1.2,
                "delta_bic_top": dbic}
    rs = [row("steer_delay", m, m * 1.05, "steer_delay" if m >= 0.03 else G.NONE) for m in (0.02, 0.03, 0.05, 0.08)]
    rs += [row(G.NONE, 0.0, None, G.NONE), row(G.NONE, 0.0, None, "mass_offset", dbic=-7.5)]
    diag = {"hold": True, "fit": "mixed:steer_delay,steer_lag", "mass_inertia": True}
    cal = CAL.from_runs("cr24", [_sweep_doc(rs, **diag)], "test")
    assert cal.margin == pytest.approx(7.5) and cal.claim_record["counts"] == {"steer_delay": _claims(3, 3, 0)}
    path = CAL.write(cal, tmp_path / "cr24.json")
    log = write_canonical(CP.make_log(load_track("putnam"), CP.PlantEffects(steer_delay=0.06), 5,
                                      CP.LogSettings(duration=24.0, target_speed=22.0)), tmp_path / "log.csv")
    base = ["gap", "diagnose", "--vehicle", str(CP.NOMINAL_VEHICLE), "--data", str(log), "--no-plots"]
    assert main(base + ["--calibration", str(path), "--out", str(tmp_path / "d")]) == 0
    d = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert d["calibration"]["name"] == "cr24" and d["gate"]["min_evidence"] == pytest.approx(7.5)
    assert d["config"]["detection_limits"] == pytest.approx(cal.decision_levels | {"*": None})
    assert d["gate"]["threshold"] is None and d["method"]["fit_mode"] == "mixed:steer_delay,steer_lag"
    assert d["nominal"]["mass_offset_scales_iz"] is True and d["nominal"]["command_hold_delay"] > 0
    assert "evidence margin dBIC < -7.5" in (tmp_path / "d" / "diagnosis.md").read_text()
    # a config with the same calibrated settings is fine; another one is not
    cfg = tmp_path / "c.toml"
    cfg.write_text('hold = true\nfit = "mixed:steer_delay,steer_lag"\nmass_inertia = true\n')
    assert main(base + ["--calibration", str(path), "--config", str(cfg), "--out", str(tmp_path / "e")]) == 0
    cfg.write_text('hold = true\nfit = "one-step"\nmass_inertia = true\n')
    assert main(base + ["--calibration", str(path), "--config", str(cfg), "--out", str(tmp_path / "x")]) == 2
    assert "the config's fit differ from the calibration's settings" in capsys.readouterr().err
    cal60 = CAL.write(CAL.from_runs("cr60", [_sweep_doc(rs, duration=60.0, **diag)]), tmp_path / "cr60.json")
    assert main(base + ["--calibration", str(cal60), "--out", str(tmp_path / "x")]) == 2
    assert "cr60 covers 54-66 s logs (60 s +- 10 %), this log is 24 s" in capsys.readouterr().err
    # shipped calibrations: the one covering the log is taken by default; none covering: uncalibrated, and why
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    monkeypatch.setattr(CAL, "SHIPPED_DIR", shipped)
    assert main(base + ["--out", str(tmp_path / "u")]) == 0
    d = json.loads((tmp_path / "u" / "diagnosis.json").read_text())
    assert d["calibration"] == {"name": None, "why": "uncalibrated: no calibration ships with this version"}
    CAL.write(cal, shipped / "cr24.json")
    CAL.write(CAL.load(cal60), shipped / "cr60.json")
    assert main(base + ["--out", str(tmp_path / "s")]) == 0
    d = json.loads((tmp_path / "s" / "diagnosis.json").read_text())
    assert d["calibration"]["name"] == "cr24" and "covers 22-26 s logs" in d["calibration"]["why"]
    assert main(base + ["--calibration", "none", "--out", str(tmp_path / "n")]) == 0
    assert json.loads((tmp_path / "n" / "diagnosis.json").read_text())["gate"]["min_evidence"] == 0.0
    cfg.write_text('fit = "one-step"\n')     # a config whose settings differ: the shipped one does not apply
    assert main(base + ["--config", str(cfg), "--out", str(tmp_path / "o")]) == 0
    why = json.loads((tmp_path / "o" / "diagnosis.json").read_text())["calibration"]["why"]
    assert why.startswith("uncalibrated: cr24 would cover this log, but the config's hold, fit, mass_inertia differ")
    # a calibration made with a servo or effects in the nominal never puts them into a nominal on its own: only
    # a config that states them (the same car) takes it
    servo = CAL.write(CAL.from_runs("servo24", [_sweep_doc(rs, steer_servo=0.01, **diag)]), tmp_path / "servo24.json")
    assert main(base + ["--calibration", str(servo), "--out", str(tmp_path / "x")]) == 2
    assert "servo24 was made with steer_servo in the nominal" in capsys.readouterr().err
    cfg.write_text('hold = true\nfit = "mixed:steer_delay,steer_lag"\nmass_inertia = true\nsteer_servo = 0.01\n')
    assert main(base + ["--calibration", str(servo), "--config", str(cfg), "--out", str(tmp_path / "v")]) == 0
    assert json.loads((tmp_path / "v" / "diagnosis.json").read_text())["nominal"]["steer_servo_tau"] == 0.01
    (shipped / "cr24.json").unlink()
    CAL.write(CAL.load(servo), shipped / "servo24.json")
    assert main(base + ["--out", str(tmp_path / "w")]) == 0
    d = json.loads((tmp_path / "w" / "diagnosis.json").read_text())
    assert d["calibration"]["name"] is None and "which only a config describing this car can give" in \
        d["calibration"]["why"] and d["nominal"]["steer_servo_tau"] == 0.0
    (shipped / "servo24.json").unlink()
    # made by other fitting code: refused when asked for, and not taken by default
    stale = json.loads(path.read_text()) | {"code_version": {"fitting": "0" * 16, "plant": cal.code_version["plant"]}}
    (shipped / "cr24.json").write_text(json.dumps(stale))
    assert main(base + ["--calibration", "cr24", "--out", str(tmp_path / "x")]) == 2
    assert "was made by other fitting code" in capsys.readouterr().err


def test_calibration_files_are_checked_and_name_what_is_wrong(tmp_path):
    for text, msg in (("{bad", "not a calibration file"), ('{"schema": "x"}', "schema 'x'"),
                      ('{"schema": "ddyn-gap-calibration 1"}', "missing")):
        f = tmp_path / "c.json"
        f.write_text(text)
        with pytest.raises(DdynError, match=msg):
            CAL.load(f)
    with pytest.raises(DdynError, match="no such file, nor a shipped calibration"):
        CAL.load("no-such-calibration")


def test_the_threshold_sweep_draws_every_effect_over_its_range_largest_first():
    """plan_sweep: each effect at SWEEP_LEVELS log-spaced magnitudes spanning its whole drawn range, largest
    first (a run cut short keeps the top of every effect's range, where reliable_threshold starts), one effect
    per log, effect-free logs among them, and case seeds apart from the mixed plan's."""
    levels = 5
    cases = G.plan_sweep(8 * levels, 11, levels=levels)
    for eff, (lo, hi) in G.EFFECT_RANGES.items():
        mags = [abs(c["magnitude"]) for c in cases if c["effect"] == eff]
        assert len(mags) == levels
        assert mags[0] == pytest.approx(hi) and mags[-1] == pytest.approx(lo) and mags == sorted(mags, reverse=True)
        assert np.allclose(np.diff(np.log(mags)), math.log(lo / hi) / (levels - 1))
        if eff not in G.SIGNED:
            assert all(c["magnitude"] > 0 for c in cases if c["effect"] == eff)
    assert sum(c["effect"] == G.NONE for c in cases) == levels
    signs = {math.copysign(1, c["magnitude"]) for c in cases if c["effect"] in G.SIGNED}
    assert signs == {-1.0, 1.0}
    assert not {c["seed"] for c in cases} & {c["seed"] for c in G.plan(8 * levels, 11)}
    assert G.plan_sweep(16, 11) == G.plan_sweep(24, 11)[:16]


def test_the_above_threshold_plan_draws_only_between_the_thresholds_and_the_range_tops():
    thr = {"steer_delay": 0.0557, "throttle_delay": 0.232, "steer_lag": 0.2, "mass_offset": None, "downforce": 4e-4}
    cases = G.plan_above(40, 5, thr)
    assert {c["effect"] for c in cases} == {"steer_delay", "throttle_delay", "steer_lag", "downforce"}
    for c in cases:
        assert thr[c["effect"]] - 1e-12 <= abs(c["magnitude"]) <= G.EFFECT_RANGES[c["effect"]][1] + 1e-12
    assert len({c["seed"] for c in cases}) == 40 and not {c["seed"] for c in cases} & {c["seed"] for c in G.plan(40, 5)}
    assert G.plan_above(40, 5, thr) == cases
    with pytest.raises(DdynError, match="thresholds"):
        G.plan_above(4, 5, {"mass_offset": None})


def test_the_mixed_fit_takes_the_steering_delay_one_step_and_refits_the_rest_by_output_error():
    """--fit mixed: a steering delay's value is the one-step fit's; the refit factors are then fitted by output
    error with that value held (so they match an output-error fit given the delay), and nothing else changes."""
    log = _log(CP.PlantEffects(steer_delay=0.06), seed=5, duration=12.0)

    def prob(mode):
        return P.Problem(log, P.nominal_from_vehicle(NOMINAL, log), 0.7, hold=True, fit_mode=mode)

    one, mixed, oe = prob("one-step"), prob("mixed"), prob("output-error")
    f1 = F.fit(one, ("steer_delay",), scan="steer_delay")
    fm = F.fit(mixed, ("steer_delay",), scan="steer_delay")
    fo = F.fit(oe, (), fixed={"steer_delay": f1.values["steer_delay"]})
    assert fm.values["steer_delay"] == pytest.approx(f1.values["steer_delay"])
    assert np.allclose(fm.rho, fo.rho, atol=1e-6) and not np.allclose(fm.rho, f1.rho, atol=1e-4)
    assert not mixed.one_step_now
    # without a steering delay the mixed fit is the output-error fit
    assert np.allclose(F.fit(mixed, ("mass_offset",)).rho, F.fit(oe, ("mass_offset",)).rho)
    # mixed:downforce takes downforce one-step instead, and the steering delay by output error
    md = prob("mixed:downforce")
    assert md.fit_mode == "mixed" and md.one_step_in_mixed == ("downforce",)
    fd = F.fit(md, ("downforce",))
    assert fd.values["downforce"] == pytest.approx(F.fit(one, ("downforce",)).values["downforce"])
    assert np.allclose(F.fit(md, ("steer_delay",), scan="steer_delay").rho,
                       F.fit(oe, ("steer_delay",), scan="steer_delay").rho)
    assert CFG.parse_fit_spec("mixed") == ("mixed", ("steer_delay",))
    assert CFG.parse_fit_spec("mixed:downforce,steer_delay") == ("mixed", ("downforce", "steer_delay"))
    for bad in ("mixed:wings", "output-error:downforce", "rollout"):
        with pytest.raises(DdynError, match="fit"):
            CFG.parse_fit_spec(bad)


def test_both_steering_effects_fitted_one_step_tell_a_delay_from_a_lag():
    """--fit mixed:steer_delay,steer_lag (the setting the four calibration sweeps chose, docs/gap_independent.md):
    each steering effect's value is its one-step fit's, and on plant logs with a hidden delay or lag the
    diagnosis names the right one with its value close."""
    for effect, value in (("steer_delay", 0.08), ("steer_lag", 0.12)):
        log = _log(CP.PlantEffects(**{effect: value}), seed=5, duration=20.0)
        nominal = P.nominal_from_vehicle(NOMINAL, log)
        both = P.Problem(log, nominal, 0.7, hold=True, fit_mode="mixed:steer_delay,steer_lag")
        one = P.Problem(log, nominal, 0.7, hold=True, fit_mode="one-step")
        assert both.one_step_in_mixed == ("steer_delay", "steer_lag")
        assert F.fit(both, (effect,), scan=effect).values[effect] == pytest.approx(
            F.fit(one, (effect,), scan=effect).values[effect])
        d = SEL.diagnose(log, nominal, candidates=("steer_delay", "steer_lag", "mass_offset"), max_effects=1,
                       max_starts=80, gate=None, hold=True, fit="mixed:steer_delay,steer_lag", steer_servo=0.01)
        assert d["selected"] == [effect], d["verdict"]
        est = next(iter(d["model"]["effects"][0]["params"].values()))
        assert est == pytest.approx(value, rel=0.25)


def test_cost_minima_find_a_hidden_steering_delay_one_step(monkeypatch):
    """cost_minima: where the fit's cost and the held-out one-step evidence put an effect's value, on a case's
    log; with the one-step fit both sit at the hidden steering delay's grid point, not at the grid's ends."""
    monkeypatch.setattr(G, "DURATION", 20.0)
    case = G.plan_sweep(8, 11)[0] | {"magnitude": 0.08}
    m = G.cost_minima(case, "steer_delay", (0.0, 0.04, 0.08, 0.16), fit="one-step")
    assert m["fit_minimum"] == pytest.approx(0.08) and m["heldout_minimum"] == pytest.approx(0.08)
    assert len(m["profile"]) == 4 and m["profile"][0]["fit_cost"] > m["profile"][2]["fit_cost"]


# ---- plant families: parameter sets, the linear-tyre model, roll/pitch channel kinds

# rows 0, 1, 10, 50 of the default log (seed 4, 2 s, imu roll and pitch), recorded before the families were added
_DEFAULT_ROWS = {
    0: ([197.5908743729411, -120.37074784600779, -3.0730335104699615, 24.001928760551287, 0.008732203773412186,
         -0.006262124411283317, 0.2, -0.0037072713065619545], 0.0022948497401704604, 0.0007005096630555216),
    1: ([196.66723353989846, -120.41567408022993, -3.0690069896471206, 24.005700086829194, -0.0020691973424618627,
         -0.0020399614140861407, 0.4, -0.0021127224637619677], -0.0018289957255557387, 0.006705526743737641),
    10: ([187.82622618732046, -121.10608937847479, -3.066802147600769, 24.955118701852026, -0.02731030645492969,
          0.015627064935853172, 0.24169333850081448, 0.0011406887880532888], 0.0013058591251183785,
         -0.0020950582262589013),
    50: ([148.28157969787804, -124.11126886215139, -3.0655834170493663, 24.793127503645216, 0.005027002642496459,
          -0.011648396532192878, -0.15032767988689036, -0.001872194847801984], 0.003812164596161945,
         0.0001790006035416545),
}
FAMILY_START = 1620.0     # m: the log runs through Putnam's tightest corners (s 1690-1740)


def test_the_default_log_is_bit_identical_to_before_the_families():
    settings = CP.LogSettings(duration=2.0, roll_channel=True, pitch_channel=True)
    ds = CP.make_log("putnam", CP.PlantEffects(), 4, settings)
    for k, (row, roll, pitch) in _DEFAULT_ROWS.items():
        assert ds.states[k].tolist() == row, k
        assert float(ds.extras["roll"][k]) == roll and float(ds.extras["pitch"][k]) == pitch, k
    explicit = CP.make_log("putnam", CP.PlantEffects(), 4, CP.LogSettings(duration=2.0, roll_channel="imu",
                                                                          pitch_channel="imu"),
                           nominal=CP.NOMINAL_VEHICLE, model="std", params="vehicle2")
    assert np.array_equal(ds.states, explicit.states) and np.array_equal(ds.inputs, explicit.inputs)
    assert all(np.array_equal(ds.extras[k], explicit.extras[k]) for k in ds.extras)
    assert ds.metadata == explicit.metadata and ds.vehicle == "commonroad_vehicle2"
    assert "parameters_vehicle2" in ds.metadata["plant"] and "BMW 320i" in ds.source
    assert CP.nominal_vehicle("std", "vehicle2") == CP.NOMINAL_VEHICLE


def test_parameter_sets_and_models_are_validated():
    with pytest.raises(DdynError, match="unknown CommonRoad parameter set 'vehicle9'"):
        CP.make_log("putnam", params="vehicle9")
    with pytest.raises(DdynError, match="unknown CommonRoad parameter set"):
        CP.commonroad_parameters("bmw")
    with pytest.raises(DdynError, match="unknown CommonRoad plant model 'ks'"):
        CP.make_log("putnam", model="ks")
    for kind in ("roll_channel", "pitch_channel"):
        with pytest.raises(DdynError, match=f"{kind} 'gyro' is not one of"):
            CP.make_log("putnam", settings=CP.LogSettings(duration=1.0, **{kind: "gyro"}))
    with pytest.raises(DdynError, match="linear tyres"):
        CP.make_log("putnam", CP.PlantEffects(tire_relaxation=0.5), model="st")
    # the AV-21 set: the project's mass and geometry on vehicle2's object, slicks; vehicle2's object untouched
    av, v2 = CP.commonroad_parameters("av21"), CP.commonroad_parameters()
    assert (av.m, av.a, av.b) == (790.0, 1.248, 1.7328) and 1000.0 <= av.I_z <= 1200.0
    assert av.tire.p_dy1 > v2.tire.p_dy1 == 1.0489 and v2.m == NOMINAL.known.mass
    assert abs(av.m_s + av.m_uf + av.m_ur - av.m) < 1e-9
    assert CP.PARAMETER_SETS["vehicle2"] == CP.SetConstants("BMW 320i", CP.ACCEL_SCALE, CP.DRAG, CP.ROLLING,
                                                            CP.ROLL_GRADIENT, CP.PITCH_GRADIENT)


def test_the_nominal_files_are_what_the_generator_writes(tmp_path):
    """The generator reproduces the hand-made vehicle2 file's numbers, and the committed files are its output."""
    doc = CP.vehicle_document("std", "vehicle2")
    for k, v in NOMINAL.true_coefficients.items():
        assert doc["true_coefficients"][k] == pytest.approx(v, rel=1e-4), k
    assert doc["known"]["mass"] == NOMINAL.known.mass
    written = CP.write_vehicle_files(tmp_path)
    assert len(written) == 10
    for path in written:
        committed = CP.PLANTS_DIR / path.name
        assert committed.read_text() == path.read_text(), path.name
        veh = load_vehicle(committed)
        assert CP.WRITE_COMMAND in veh.description
    for model in CP.MODELS:
        for params in CP.PARAMETER_SETS:
            assert load_vehicle(CP.nominal_vehicle(model, params)).known.mass == \
                CP.commonroad_parameters(params).m
    # the linear-tyre fit: the project's curve follows C alpha within a few % up to the driver's slips
    fit = CP.linear_tyre_fit(CP.commonroad_parameters())
    assert fit["rms"] < 0.04 and fit["max"] < 0.1 and 0.04 < fit["a_max"] < 0.05


@pytest.fixture(scope="module")
def families():
    settings = CP.LogSettings(duration=16.0, noise_scale=0.0, start_s=FAMILY_START)
    logs = {p: CP.make_log("putnam", CP.PlantEffects(), 4, settings, params=p) for p in CP.PARAMETER_SETS}
    logs["st"] = CP.make_log("putnam", CP.PlantEffects(), 4, settings, model="st")
    return logs


def test_each_parameter_set_drives_putnam_in_its_own_way(families):
    for p, ds in families.items():
        vx = ds.states[:, 3]
        assert 12.0 < vx.min() and vx.max() < 28.0 and np.all(np.isfinite(ds.states)), p
        assert np.abs(ds.states[:, 5]).max() > 0.3, p          # the log turns
    v1, v2, v3, av = (families[p] for p in ("vehicle1", "vehicle2", "vehicle3", "av21"))
    mass = {p: load_vehicle(families[p].metadata["vehicle_file"]).known.mass for p in CP.PARAMETER_SETS}
    assert mass["av21"] == 790.0 < mass["vehicle2"] < mass["vehicle1"] < mass["vehicle3"]
    assert "AV-21" in av.source and "av21" in av.metadata["plant"] and av.vehicle == "commonroad_av21"
    # the van's drag and the Escort's weaker pedal need more pedal over the same corners; the race car's slicks
    # let the driver through the tightest corner faster than the saloon
    pedal = {p: families[p].states[:, 6].mean() for p in CP.PARAMETER_SETS}
    assert pedal["vehicle3"] > pedal["vehicle2"] and pedal["vehicle1"] > pedal["vehicle2"]
    assert av.states[:, 3].min() > 1.05 * v2.states[:, 3].min()


def test_the_linear_tyre_model_runs_and_differs_from_std(families, monkeypatch):
    import vehiclemodels.vehicle_dynamics_st as st
    import vehiclemodels.vehicle_dynamics_std as std

    ds, ref = families["st"], families["vehicle2"]
    assert ds.vehicle == "commonroad_vehicle2_st" and "vehicle_dynamics_st" in ds.metadata["plant"]
    # the same driver on the same corners, another car: the linear tyres never saturate
    assert np.max(np.abs(ds.states[:, 4] - ref.states[:, 4])) > 0.1
    # its nominal file predicts it well one step ahead (the least-squares Pacejka stand-in for C alpha)
    veh = load_vehicle(CP.nominal_vehicle("st", "vehicle2"))
    pred = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], veh.true_vector(), veh.known, ds.sample_time, "rk4",
                               veh.rk4_substeps)
    std_pred = backends.step_numpy(ds.states[:-1], ds.inputs[:-1], NOMINAL.true_vector(), NOMINAL.known,
                                   ds.sample_time, "rk4", NOMINAL.rk4_substeps)
    # (one step through Putnam's tightest corners: the speed well; the sideslip far better than with the Pacejka
    # (std) file, whose saturating tyres the linear plant does not have)
    err = np.sqrt(np.mean((pred[:, :6] - ds.states[1:, :6]) ** 2, axis=0))
    err_std = np.sqrt(np.mean((std_pred[:, :6] - ds.states[1:, :6]) ** 2, axis=0))
    assert err[3] < 0.5 * np.sqrt(np.mean(np.diff(ds.states[:, 3]) ** 2))
    assert err[4] < 0.5 * err_std[4]
    calls = {"st": 0}
    real = st.vehicle_dynamics_st

    def counting(x, u, p):
        calls["st"] += 1
        return real(x, u, p)

    monkeypatch.setattr(st, "vehicle_dynamics_st", counting)
    monkeypatch.setattr(std, "vehicle_dynamics_std", lambda *a: pytest.fail("std called"))
    CP.make_log("putnam", CP.PlantEffects(), 4, CP.LogSettings(duration=0.2), model=CP.StModel())
    assert calls["st"] == 4 * 200


def test_roll_and_pitch_channel_kinds():
    fx = CP.PlantEffects(bank_angle=0.08, grade=0.04)
    logs = {}
    for kind, seed in (("imu", 4), ("map", 4), ("broken", 4), ("map", 5)):
        logs[kind, seed] = CP.make_log("putnam", fx, seed, CP.LogSettings(
            duration=16.0, noise_scale=0.0, start_s=FAMILY_START, roll_channel=kind, pitch_channel=kind))
    track = CP.load_track("putnam")
    imu = logs["imu", 4]
    bank, lean, grade = imu.extras["true_bank"], imu.extras["true_body_roll"], imu.extras["true_grade"]
    assert np.abs(bank).max() > 0.04 and np.abs(grade).max() > 0.02 and np.abs(lean).max() > 0.01
    assert np.std(imu.extras["roll"] - bank - lean) == pytest.approx(CP.ROLL_NOISE, rel=0.25)
    # map: the bank at the car's 10 m cell, no body roll, no noise but the map's rounding; the same value
    # wherever the car is in that cell, whichever log
    slope = np.max(np.abs(np.diff(CP.bank_profile(track, 0.08)))) / (track.length / track.n)
    for seed in (4, 5):
        m = logs["map", seed]
        err = m.extras["roll"] - m.extras["true_bank"]
        assert np.abs(err).max() <= slope * 0.5 * CP.MAP_RESOLUTION + 0.6 * CP.MAP_ROUNDING + 1e-9
        assert np.abs(err).max() > 0 and np.allclose(m.extras["roll"] / CP.MAP_ROUNDING,
                                                     np.round(m.extras["roll"] / CP.MAP_ROUNDING))
    cells = {}
    for seed in (4, 5):
        m = logs["map", seed]
        s, _ = track.project(m.extras["true_x"], m.extras["true_y"])
        for c, r, p in zip(np.floor(np.asarray(s) / CP.MAP_RESOLUTION), m.extras["roll"], m.extras["pitch"]):
            cells.setdefault(c, set()).add((r, p))
    assert len(cells) > 20 and all(len(v) == 1 for v in cells.values())
    assert not np.array_equal(logs["map", 4].states, logs["map", 5].states)
    # broken: drifts by radians, unrelated to the road
    b = logs["broken", 4]
    for ch, truth in (("roll", "true_bank"), ("pitch", "true_grade")):
        x = b.extras[ch]
        assert np.ptp(x) > 0.5 and np.abs(x - b.extras[truth]).max() > 0.5, ch
        assert abs(np.corrcoef(x, b.extras[truth])[0, 1]) < 0.5, ch
    # the channel kind changes nothing else
    assert np.array_equal(b.states, imu.states)
