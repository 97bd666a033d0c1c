"""ddyn diagnose: finds a hidden effect on short simulated logs, says "none" without one, reads the real log."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ddyn.cli import main
from ddyn.gap import config as CFG, fit as F, heldout as HO, problem as P, report as R, selection as SEL
from ddyn.data.dataset import write_canonical
from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicles

ORCA = vehicles.load("orca_1_43")


def _sim(effects, seed=21, laps=2.0, noise=1.0):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, "ethzMobil", laps=laps, seed=seed, noise_scale=noise, progress=False, effects=effects)


@pytest.fixture(scope="module")
def delay_log(shared_data):
    return _sim("steer_delay=0.03")


def _diagnose(ds, **kw):
    return SEL.diagnose(ds, P.nominal_from_vehicle(ORCA, ds), **kw)


def test_finds_a_hidden_steer_delay(delay_log):
    d = _diagnose(delay_log)
    assert d["selected"][0] == "steer_delay"
    best = d["candidates"][0]
    assert best["effect"] == "steer_delay" and best["significant"]
    assert best["params"]["delay"] == pytest.approx(0.03, rel=0.1)
    assert 0 < best["uncertainty"]["delay"] < 0.01
    h = best["heldout"]
    assert h["rmse_after"]["omega"] < 0.5 * h["rmse_before"]["omega"] and h["ade_after"] < h["ade_before"]
    assert best["gap_closed_pct"] > 80
    # where: the error concentrates where the steering moves fast
    rate = d["where"]["factors"]["steering_rate"]
    assert rate[-1]["error_share"] > rate[0]["error_share"]
    assert any("steering" in s for s in d["where"]["summary"])


def test_finds_a_hidden_bank_angle(shared_data):
    d = _diagnose(_sim("bank_angle=0.03", seed=22))
    assert d["selected"][0] == "bank_angle"
    assert d["model"]["effects"][0]["params"]["angle"] == pytest.approx(0.03, rel=0.15)


def test_says_none_on_an_effect_free_log(shared_data):
    d = _diagnose(_sim(None, seed=23))
    assert d["selected"] == []
    assert d["verdict"].startswith("none")
    assert not any(c["significant"] for c in d["candidates"])


def test_noise_free_fit_is_exact(shared_data):
    ds = _sim("tire_wear=0.01", seed=24, laps=1.0, noise=0.0)
    d = _diagnose(ds, candidates=("tire_wear", "downforce", "mass_offset"))
    assert d["selected"][0] == "tire_wear"
    assert d["model"]["effects"][0]["params"]["rate"] == pytest.approx(0.01, rel=1e-4)


def test_noise_floor_matches_the_true_models_error(shared_data):
    """The floor (what a perfect model leaves under white sensor noise, fed through the model's Jacobian) equals
    the true plant's one-step MSE, and a slowly varying model error (a constant bank) does not raise it."""
    ds = _sim("bank_angle=0.03", seed=22)
    prob = P.Problem(ds, P.nominal_from_vehicle(ORCA, ds), 0.6, refit=())
    rows = prob.rows_all
    res_true = prob.target[rows + 1] - prob.predict({"bank_angle": 0.03}, np.zeros(0), rows)
    res_nominal = prob.target[rows + 1] - prob.predict({}, np.zeros(0), rows)
    mse_true = np.mean(res_true ** 2, axis=0)
    assert HO._noise_floor(prob, res_true) == pytest.approx(mse_true, rel=0.05)
    assert np.mean(res_nominal[:, 1] ** 2) > 1.5 * mse_true[1]              # the bank shows in vy ...
    assert HO._noise_floor(prob, res_nominal) == pytest.approx(mse_true, rel=0.05)   # ... but not in the floor


SCHEMA_KEYS = {"selected", "candidates", "where", "model", "nominal", "split", "method", "schema", "verdict"}


def _check_schema(d: dict):
    assert SCHEMA_KEYS <= set(d)
    assert isinstance(d["selected"], list)
    for c in d["candidates"]:
        assert {"effect", "params", "uncertainty", "heldout", "gap_closed_pct", "delta_bic", "significant"} <= set(c)
        h = c["heldout"]
        assert set(h["rmse_before"]) == set(h["rmse_after"]) == {"vx", "vy", "omega"}
        assert {"ade_before", "ade_after"} <= set(h)
    bics = [c["delta_bic"] for c in d["candidates"]]
    assert bics == sorted(bics)                           # best first
    assert {"factors", "summary", "one_step_rmse", "multi_step_rmse", "multi_step_final_rmse"} <= set(d["where"])
    assert set(d["where"]["multi_step_rmse"]) == {"vx", "vy", "omega"}


def test_cli_writes_json_markdown_and_plots(delay_log, tmp_path):
    data = write_canonical(delay_log, tmp_path / "log.csv")
    out = tmp_path / "diag"
    cfg = tmp_path / "cands.toml"
    cfg.write_text('candidates = "steer_delay,steer_lag,bank_angle"\n')
    assert main(["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(data), "--out", str(out),
                 "--config", str(cfg)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["config"]["candidates"] == ["steer_delay", "steer_lag", "bank_angle"]
    assert d["calibration"]["name"] is None and d["calibration"]["why"].startswith("uncalibrated")
    assert "Uncalibrated" in (out / "diagnosis.md").read_text()
    _check_schema(d)
    assert d["selected"] == ["steer_delay"]
    assert "track_position" in d["where"]["factors"]         # the log names its track
    md = (out / "diagnosis.md").read_text()
    assert "steer_delay" in md and "where.png" in md
    assert all((out / f).stat().st_size > 1000 for f in ("where.png", "residuals.png", "which.png"))


def test_reads_the_racecar_csv(shared_data, tmp_path):
    src = shared_data / "real" / "Putnam_park2023_run4_2.csv"
    if not src.is_file():
        pytest.skip(f"SHARED DATA MISSING: {src}")
    lines = src.read_text().splitlines()
    piece = tmp_path / "putnam_piece.csv"
    piece.write_text("\n".join([lines[0]] + lines[3000:4500]) + "\n")
    out = tmp_path / "real"
    cfg = tmp_path / "cands.json"
    cfg.write_text('{"candidates": ["steer_delay", "yaw_rate_bias", "grade"]}')
    # `ddyn diagnose` is the alias of `ddyn gap diagnose`
    assert main(["diagnose", "--vehicle", "av21", "--data", str(piece), "--out", str(out), "--no-plots",
                 "--config", str(cfg)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    _check_schema(d)
    assert d["nominal"]["vehicle"] == "av21" and d["split"]["heldout_rows"] > 100
    assert all(np.isfinite(v) for v in d["where"]["one_step_rmse"].values())


def test_checkpoint_nominal(delay_log, tmp_path):
    import torch

    from ddyn.data.windows import features
    from ddyn.learn import checkpoint
    from ddyn.learn.training import TrainConfig, TrainResult, build_model

    torch.manual_seed(0)
    f = features(delay_log)
    cfg = TrainConfig(tau=3, hidden=8, layers=2)
    model = build_model(cfg, ORCA, f.mean(axis=0), np.maximum(f.std(axis=0), 1e-9))
    path = checkpoint.save(checkpoint.make(TrainResult(model, cfg, np.ones(3), [], 0.0, 0.0), ORCA, "x", "x", 0),
                           tmp_path / "ddm.ckpt")
    from ddyn.gap.benchmark import own as GB
    from ddyn.errors import DdynError

    with pytest.raises(DdynError, match="av21"):          # --real --model wants a model of the Putnam car
        GB.run_real(tmp_path / "real", model=str(path))
    nominal = P.nominal_from_checkpoint(path, delay_log)
    assert nominal.coeffs.shape == (len(delay_log), 17) and not nominal.valid[:2].any() and nominal.valid[2:-1].all()
    d = SEL.diagnose(delay_log, nominal, candidates=("steer_delay", "grade"), refit=())
    _check_schema(R.public(d))
    assert d["nominal"]["source"].startswith("DDM checkpoint")


# ---------------------------------------------------------------------------------------------- gap benchmark

def test_benchmark_plan_and_scoring():
    from ddyn.gap.benchmark import own as GB
    from ddyn.model import effects as E

    cases = GB.plan(390, seed=3)
    assert {c["effect"] for c in cases} == set(E.EFFECT_NAMES) | {"none"}
    assert sum(c["effect"] == "none" for c in cases) == 60 and {c["vehicle"] for c in cases} == {"orca_1_43", "av21"}
    # each fold holds every effect on every vehicle it visits
    for f in (0, 1):
        fold = [c for c in cases if c["fold"] == f]
        assert len(fold) == 195 and {(c["vehicle"], c["effect"]) for c in fold} == \
            {(c["vehicle"], c["effect"]) for c in cases}
    for c in cases:
        if c["effect"] != "none":
            m, t = abs(c["magnitude"]), GB.PRIOR_THRESHOLDS[c["vehicle"]][c["effect"]]
            assert GB.DRAW_RANGE[0] * t <= m <= min(GB.DRAW_RANGE[1] * t,
                                                     GB.MAX_MAGNITUDE[c["vehicle"]].get(c["effect"], np.inf))
    assert len({c["seed"] for c in cases}) == len(cases)
    assert not {c["seed"] for c in cases} & {c["seed"] for c in GB.plan(390, seed=GB.DEFAULT_SEED)}
    assert GB.DEFAULT_SEED not in GB.DEVELOPMENT_SEEDS

    rows = [{"magnitude": m, "correct": ok} for m, ok in [(1, False), (2, True), (3, False), (4, True), (5, True),
                                                          (6, True)]]
    from ddyn.gap import calibration as CAL    # the one threshold rule, shared by every benchmark

    assert CAL.reliable_threshold(rows) == 4
    assert CAL.reliable_threshold(rows[:5] + [{"magnitude": 6, "correct": False}]) is None   # the largest missed

    # detection depends on magnitude: found from 1.5 x the prior guess up, missed below; one false alarm
    def outcome(c):
        found = c["effect"] == "none" or abs(c["magnitude"]) >= 1.5 * GB.PRIOR_THRESHOLDS[c["vehicle"]][c["effect"]]
        top1 = c["effect"] if found else "none"
        return dict(c, status="ok", top1=top1, correct=found, selected=[] if top1 == "none" else [top1],
                    param_error=0.05 if found else None, gap_vs_oracle=0.97 if found else None, diagnose_seconds=1.0)
    fake = [outcome(c) for c in cases]
    alarm = next(r for r in fake if r["effect"] == "none")
    alarm["selected"], alarm["top1"], alarm["correct"] = ["grade"], "grade", False
    sc = GB.score(fake)
    s = sc["summary"]
    assert s["false_alarm_rate"] == pytest.approx(1 / 60)
    assert sc["confusion"]["all"]["none"]["grade"] == 1
    assert s["targets"]["false_alarm_rate <= 0.05"]
    # measured thresholds: the smallest found magnitude, never below 1.5 x the guess; cross-fitted accuracy 100 %
    for p in sc["per_effect"].values():
        if p["reliable_from"] is not None:
            assert p["reliable_from"] >= 1.5 * p["prior_threshold"] * (1 - 1e-12)
    assert s["top1_above_measured_threshold"] == 1.0 and "orca_1_43/grade" not in s["never_reliable"]
    assert s["extra_effects_rate"] == 0.0
    assert s["top1_above_prior_threshold"] < 1.0 and s["top1_all_effect_cases"] < 1.0
    md = GB.markdown(sc, {}, 60.0, {"seed": 3, "case_seeds": "x", "development_seed": False})
    assert "| none |" in md and "reliable from" in md
    # more alarms fail the target; a miss at the largest magnitude leaves the effect without a threshold
    for r in [r for r in fake if r["effect"] == "none"][1:4]:
        r["selected"], r["top1"], r["correct"] = ["bank_angle"], "bank_angle", False
    grade = [r for r in fake if r["effect"] == "grade" and r["vehicle"] == "orca_1_43"]
    max(grade, key=lambda r: abs(r["magnitude"]))["correct"] = False
    sc = GB.score(fake)
    assert sc["summary"]["false_alarm_rate"] == pytest.approx(4 / 60)
    assert not sc["summary"]["targets"]["false_alarm_rate <= 0.05"]
    assert set(sc["summary"]["never_reliable"]) == set(s["never_reliable"]) | {"orca_1_43/grade"}


def test_benchmark_cli_tiny_run(shared_data, tmp_path):
    """Two cases end to end on the 1:43 car: simulate, identify the nominal, diagnose blind, score, write."""
    from ddyn.gap.benchmark import own as GB

    out = tmp_path / "gb"
    cfg = tmp_path / "orca.toml"
    cfg.write_text('[benchmark]\nvehicles = ["orca_1_43"]\n')
    # the plan's first two slots: steer_delay and throttle_delay at random magnitudes (maybe below detection),
    # so the bookkeeping is checked, not the verdicts
    assert main(["gap", "benchmark", "--plant", "own", "--cases", "2", "--config", str(cfg), "--out", str(out),
                 "--no-progress", "--seed", "5"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert [r["effect"] for r in doc["results"]] == ["steer_delay", "throttle_delay"]
    assert all(r["status"] == "ok" and r["rows"] > 500 for r in doc["results"])
    assert doc["settings"]["seed"] == 5 and not doc["settings"]["development_seed"]
    assert doc["summary"]["effect_cases"] == 2 and doc["summary"]["none_cases"] == 0
    for r in doc["results"]:
        assert r["e_oracle"] <= r["e_nominal"] and (r["top1"] != r["effect"] or r["e_diagnosed"] < r["e_nominal"])
    assert "top-1" in (out / "results.md").read_text() and (out / "detection.png").stat().st_size > 1000
    # --rescore: the same cases scored again from results.json give the same summary
    (out / "results.md").unlink()
    assert main(["gap", "rescore", "--out", str(out)]) == 0
    again = json.loads((out / "results.json").read_text())
    assert again["summary"] == doc["summary"] and (out / "results.md").is_file()


def test_benchmark_case_runs(shared_data):
    from ddyn.gap.benchmark import own as GB

    case = {"case": 0, "vehicle": "orca_1_43", "track": "ethzMobil", "effect": "bank_angle", "magnitude": 0.03,
            "seed": 99}
    r = GB.run_case(case, ORCA, ORCA.true_vector())
    assert r["status"] == "ok" and r["correct"] and r["param_error"] < 0.15
    assert r["e_diagnosed"] < r["e_nominal"] and 0.8 < r["gap_vs_oracle"] < 1.2


def test_estimate_at_a_range_edge_is_flagged():
    ctx = {"dt": 0.02, "v_ref": 2.0, "v_max": 4.0, "duration": 30.0}
    assert P.at_bound("mass_offset", -0.5, ctx) and P.at_bound("combined_slip", 5.0, ctx)
    assert not P.at_bound("mass_offset", 0.1, ctx)
    assert not P.at_bound("steer_delay", 0.0, ctx)          # zero is "off", not an edge
    assert P.at_bound("steer_delay", 12 * 0.02, ctx)


def test_benchmark_real_log(shared_data, tmp_path):
    """--real: the nominal identified on the first half of the Putnam log, the rest diagnosed; honest caveats."""
    from ddyn.gap.benchmark import own as GB

    if not (shared_data / "real" / "Putnam_park2023_run4_2.csv").is_file():
        pytest.skip("SHARED DATA MISSING: the Putnam log")
    summary = GB.run_real(tmp_path)
    assert set(summary) == {"vehicle_file", "identified"}
    for r in summary.values():
        assert isinstance(r["selected"], list) and r["where"]
        at_edge = [e["effect"] for e in r["model"]["effects"] if e["at_bound"]]
        assert all(any(n in c for c in r["caveats"]) for n in at_edge)
        assert r["split"]["heldout_rows"] > 1000
    ident = summary["identified"]["nominal"]
    lo, hi = GB.load_vehicle("av21").range_arrays()
    c = np.array(list(ident["coefficients"].values()))
    assert np.all(c >= lo - 1e-9) and np.all(c <= hi + 1e-9)
    assert (tmp_path / "identified" / "diagnosis.json").is_file() and (tmp_path / "real.json").is_file()
    assert "Nominal: identified" in GB.real_markdown(summary)


def test_an_estimate_on_a_range_edge_is_never_the_verdict(delay_log, monkeypatch):
    """The 30 ms steering delay, with the delay's search range cut to 10 ms: the delay still pays for itself, but
    only from the range's edge, so the verdict is "not explained by the effect library", nothing is selected."""
    kw = dict(candidates=("steer_delay",), max_effects=1, max_starts=50)
    assert _diagnose(delay_log, **kw)["selected"] == ["steer_delay"]
    bounds = P._bounds
    cut = lambda n, ctx: (0.0, 0.01) if n == "steer_delay" else bounds(n, ctx)  # noqa: E731
    monkeypatch.setattr(P, "_bounds", cut)      # the edge test (at_bound) and the fit's range
    monkeypatch.setattr(F, "_bounds", cut)
    d = _diagnose(delay_log, **kw)
    assert d["selected"] == [] and d["model"]["effects"] == []
    assert d["verdict"].startswith("none: not explained by the effect library")
    assert d["unexplained"]["effect"] == "steer_delay" and d["unexplained"]["delta_bic"] < 0
    assert d["unexplained"]["params"]["delay"] == pytest.approx(0.01, abs=1e-4)
    assert d["greedy"][0]["at_bound"] and d["greedy"][0]["added"] is None


def test_a_find_below_its_detection_limit_is_reported_not_selected(delay_log, tmp_path):
    """Detection limits (diagnose --detection-limits): the 30 ms steering delay is selected under a limit of
    20 ms or with no limit for it; above its estimate (40 ms) or with a null limit it is reported as below the
    limit and nothing is selected; an effect without a limit is unaffected."""
    kw = dict(candidates=("steer_delay",), max_effects=1, max_starts=50)
    for limits in (None, {"steer_delay": 0.02}, {"steer_lag": 0.5}, {"steer_delay": 0.02, "*": None}):
        assert _diagnose(delay_log, detection_limits=limits, **kw)["selected"] == ["steer_delay"]
    # "*": every effect without an entry ({"*": None}: only the calibrated effects are ever claimed)
    for limits in ({"steer_delay": 0.04}, {"steer_delay": None}, {"steer_lag": 0.01, "*": None}):
        d = _diagnose(delay_log, detection_limits=limits, **kw)
        assert d["selected"] == [] and d["model"]["effects"] == [] and d["unexplained"] is None
        assert d["below_limit"]["effect"] == "steer_delay"
        assert d["below_limit"]["limit"] == limits.get("steer_delay", limits.get("*"))
        assert d["below_limit"]["params"]["delay"] == pytest.approx(0.03, rel=0.1)
        assert d["verdict"].startswith("none: steer_delay pays on the held-out data") and "not claimed" in d["verdict"]
        assert d["greedy"][0]["below_limit"] and d["greedy"][0]["added"] is None
        # the log's stated limit is never below what a claim needs: a 30 ms delay under a 40 ms limit would not
        # be claimed, so "a steering delay below X would not be found" states at least 40 ms (none: not claimable)
        stated = d["limits"]["steer_delay"]
        level = limits.get("steer_delay", limits.get("*"))
        if level is None:
            assert stated["limit"] is None and stated["bound_by"] == "not claimable"
        else:
            assert stated["limit"] >= level and stated["bound_by"] == "decision level"
    free = _diagnose(delay_log, detection_limits=None, **kw)["limits"]["steer_delay"]
    assert free["bound_by"] == "evidence" and free["limit"] < 0.04
    # limits in a config file: validated, unknown effects refused with the key named
    f = tmp_path / "limits.json"
    f.write_text('{"detection_limits": {"steer_delay": 0.04, "downforce": null, "*": null}}')
    assert CFG.DiagnosisConfig.from_file(f).detection_limits == {"steer_delay": 0.04, "downforce": None, "*": None}
    f.write_text('{"detection_limits": {"warp_drive": 1}}')
    with pytest.raises(DdynError, match="detection_limits: unknown effect 'warp_drive'"):
        CFG.DiagnosisConfig.from_file(f)


@pytest.mark.parametrize("mode", ["smoothed", "output-error"])
def test_every_fit_mode_finds_the_delay(delay_log, mode):
    """The errors-in-variables fits find the same hidden 30 ms delay; held-out scores stay one-step."""
    d = _diagnose(delay_log, candidates=("steer_delay", "mass_offset"), max_effects=1, max_starts=50, fit=mode)
    assert d["selected"] == ["steer_delay"] and d["method"]["fit_mode"] == mode
    assert d["model"]["effects"][0]["params"]["delay"] == pytest.approx(0.03, rel=0.15)
    with pytest.raises(Exception, match="unknown fit"):
        _diagnose(delay_log, fit="two-step")


def test_leave_out_smoother():
    """The smoother reproduces a quadratic exactly (edges included), leaves the predicted sample out, and cuts
    white noise's variance to sum(w^2) of it."""
    from ddyn.gap import eiv

    t = np.arange(60.0)
    states = np.zeros((60, 8))
    states[:, 3] = 1 + 0.1 * t - 0.002 * t ** 2
    seg = np.r_[np.zeros(30), np.ones(30)]
    sm, gain = eiv.smooth_states(states, seg)
    assert np.allclose(sm[:, 3], states[:, 3], atol=1e-9) and 0.1 < gain < 0.35
    w = eiv.loo_weights(np.array([-2, -1, 0, 2]))
    assert w @ np.array([4.0, 1, 0, 4]) == pytest.approx(0.0)       # y = t^2 at 0
    rng = np.random.default_rng(0)
    noise = np.zeros((4000, 8))
    noise[:, 3:6] = rng.normal(0, [0.05, 0.02, 0.005], (4000, 3))
    est = np.sqrt(eiv.noise_variance(noise, np.zeros(4000)))
    assert est == pytest.approx([0.05, 0.02, 0.005], rel=0.05)
    sm, gain = eiv.smooth_states(noise, np.zeros(4000))
    assert np.var(sm[10:-10, 3]) == pytest.approx(gain * 0.05 ** 2, rel=0.1)
    # the sample one ahead is left out: the smoothed state does not correlate with it
    assert abs(np.corrcoef(sm[10:-11, 3], noise[11:-10, 3])[0, 1]) < 0.05


def test_cli_dbw_config(delay_log, tmp_path):
    """--config dbw (shipped): the hold, output error and the calibrated margin, recorded in diagnosis.json; a
    file's own settings; mass_inertia and steer_servo are recorded."""
    data = write_canonical(delay_log, tmp_path / "log.csv")
    out = tmp_path / "diag"
    cfg = tmp_path / "dbw2.toml"
    cfg.write_text('[diagnosis]\nhold = true\nfit = "output-error"\nmin_evidence = 2\n'
                   'candidates = ["steer_delay", "mass_offset"]\n')
    assert main(["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(data), "--out", str(out), "--no-plots",
                 "--config", str(cfg)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["method"]["fit_mode"] == "output-error"
    assert d["nominal"]["command_hold_delay"] == pytest.approx(0.5 * delay_log.sample_time)
    assert d["gate"]["min_evidence"] == 2.0
    assert d["nominal"]["mass_offset_scales_iz"] is False and d["nominal"]["steer_servo_tau"] == 0.0
    shipped = CFG.DiagnosisConfig.from_file("dbw")
    assert shipped.hold is True and shipped.fit == "output-error" and shipped.min_evidence == pytest.approx(13.02)
    cfg.write_text('[diagnosis]\nhold = true\nfit = "output-error"\ncandidates = ["steer_lag"]\n'
                   'mass_inertia = true\nsteer_servo = 0.01\n')
    out2 = tmp_path / "diag2"
    assert main(["gap", "diagnose", "--vehicle", "orca_1_43", "--data", str(data), "--out", str(out2), "--no-plots",
                 "--config", str(cfg)]) == 0
    d = json.loads((out2 / "diagnosis.json").read_text())
    assert d["nominal"]["mass_offset_scales_iz"] is True and d["nominal"]["steer_servo_tau"] == 0.01


def test_multistep_evidence(shared_data):
    """--evidence multistep:N (opt-in): windows start after the fit/held-out cut and do not overlap; a hidden mass
    offset pays under it, an effect-free log selects nothing; the one-step figure is kept beside it; bad specs fail;
    the default stays one-step."""
    assert CFG.parse_evidence_spec(None) == (0, False) and CFG.parse_evidence_spec("one-step") == (0, False)
    assert CFG.parse_evidence_spec("multistep") == (CFG.MULTISTEP_DEFAULT_STEPS, False)
    assert CFG.parse_evidence_spec("multistep:7") == (7, False)
    for bad in ("multistep:1", "multistep:x", "rollout:5"):
        with pytest.raises(Exception, match="evidence"):
            CFG.parse_evidence_spec(bad)
    ds = _sim("mass_offset=0.15", seed=24)
    prob = P.Problem(ds, P.nominal_from_vehicle(ORCA, ds), CFG.DiagnosisConfig().fit_fraction)
    prob.set_evidence(10)
    s = prob.ev_starts
    assert len(s) >= 20 and s.min() >= prob.rows_held[0] and np.all(np.diff(s) >= 10)
    assert np.all(ds.segment[s + 10] == ds.segment[s]) and s.max() + 10 < len(ds)
    # the true effect shrinks the multi-step error, most at the end of the window (a slow effect accumulates)
    r0, r1 = prob.multistep_rss({}, np.zeros(2)), prob.multistep_rss({"mass_offset": 0.15}, np.zeros(2))
    assert r1.shape == (10, 3) and r1[-1, 0] < 0.5 * r0[-1, 0]
    kw = dict(candidates=("mass_offset", "steer_delay"), max_effects=1, max_starts=50)
    d = _diagnose(ds, evidence="multistep:10", **kw)
    c = next(c for c in d["candidates"] if c["effect"] == "mass_offset")
    assert d["selected"] == ["mass_offset"] and c["delta_bic"] < c["delta_bic_one_step"] < 0
    assert d["method"]["evidence"].startswith("multistep:10")
    d0 = _diagnose(_sim(None, seed=23), evidence="multistep:10", **kw)
    assert d0["selected"] == [] and all(c["delta_bic"] > 0 for c in d0["candidates"])
    d1 = _diagnose(ds, **kw)
    assert d1["method"]["evidence"] == "one-step" and "delta_bic_one_step" not in d1["candidates"][0]
    assert d1["candidates"][0]["delta_bic"] == pytest.approx(c["delta_bic_one_step"])


def test_endpoint_evidence(shared_data):
    """--evidence endpoint:N (opt-in): the multi-step windows, but only each window's N-th-step error is scored and
    the penalty counts windows (one roughly independent sample each, so the correlated errors within a window are
    not counted as independent evidence): the score is that formula; it is weaker than the all-steps score; a hidden
    mass offset still pays; an effect-free log selects nothing."""
    assert CFG.parse_evidence_spec("endpoint:7") == (7, True) and CFG.parse_evidence_spec("endpoint") == (25, True)
    assert CFG.parse_evidence_spec("multistep:7") == (7, False) and CFG.parse_evidence_spec(None) == (0, False)
    for bad in ("endpoint:1", "endpoint:x", "end:5"):
        with pytest.raises(Exception, match="evidence"):
            CFG.parse_evidence_spec(bad)
    ds = _sim("mass_offset=0.15", seed=24)
    kw = dict(candidates=("mass_offset", "steer_delay"), max_effects=1, max_starts=50)
    d = _diagnose(ds, evidence="endpoint:10", **kw)
    dm = _diagnose(ds, evidence="multistep:10", **kw)
    c = next(c for c in d["candidates"] if c["effect"] == "mass_offset")
    cm = next(c for c in dm["candidates"] if c["effect"] == "mass_offset")
    assert d["selected"] == ["mass_offset"] and c["delta_bic"] < 0 and d["method"]["evidence"].startswith("endpoint:10")
    # the same fit: the one-step figure is shared; the endpoint score is the last step's alone, so it is weaker
    assert c["delta_bic_one_step"] == pytest.approx(cm["delta_bic_one_step"])
    assert cm["delta_bic"] < c["delta_bic"]
    # the formula: dLL of the last step's (vx, vy, omega) errors over the windows, the penalty ln(windows)
    prob = P.Problem(ds, P.nominal_from_vehicle(ORCA, ds), CFG.DiagnosisConfig().fit_fraction)
    prob.set_evidence(10, endpoint=True)
    nw = len(prob.ev_starts)
    base = {"rss": np.ones(3), "ms_rss": np.full((10, 3), 4.0)}
    cand = {"rss": np.ones(3), "ms_rss": np.full((10, 3), 4.0)}
    cand["ms_rss"][-1] = 1.0
    s = SEL._score(prob, base, cand, 1, 1)
    f2 = prob.floor ** 2
    dll = -0.5 * nw * (np.sum(np.log(1.0 / nw + f2)) - np.sum(np.log(4.0 / nw + f2)))
    assert s["delta_loglik"] == pytest.approx(dll) and s["delta_bic"] == pytest.approx(-2 * dll + np.log(nw))
    d0 = _diagnose(_sim(None, seed=23), evidence="endpoint:10", **kw)
    assert d0["selected"] == [] and all(c["delta_bic"] > 0 for c in d0["candidates"])


def test_a_profile_limit_counts_only_the_held_out_rows_the_fit_part_covered():
    """A bank or grade that varies along the lap is learned only where the fit part drove: profile_coverage
    keeps the held-out rows next to a knot the fit rows inform (periodic: the last interval wraps to the first
    knot), and none when a plausible channel carries the family to every row or the family has no profile."""
    from types import SimpleNamespace

    from ddyn.gap import candidates as C, limits as L

    lay = C.Layout(position=np.array([10.0, 25.0, 125.0, 175.0, 260.0]), length=200.0,
                   knots=np.array([0.0, 50.0, 100.0, 150.0]), free=[0, 1], source="test", roll=None)
    prob = SimpleNamespace(layout=lay, rows_held=np.array([1, 2, 3, 4]))
    # 25: knots 0-1 (free); 125: knots 2-3 (neither free); 175: knots 3-0 (0 free); 260 = 60: knots 1-2 (1 free)
    assert L.profile_coverage(prob, "grade").tolist() == [True, False, True, True]
    assert L.profile_coverage(prob, "steer_delay") is None
    lay.free = []
    assert not L.profile_coverage(prob, "bank_angle").any()
    prob.layout = None
    assert L.profile_coverage(prob, "bank_angle") is None

