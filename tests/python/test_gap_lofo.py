"""This log's own detection limits, the margin that grows with the log, the search past unclaimed effects, the
leave-one-family-out rules and the travelling calibration (ddyn.gap.limits, ddyn.gap.benchmark.lofo)."""
from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from ddyn.errors import CarLostError, DdynError
from ddyn.gap import calibration as CAL
from ddyn.gap import limits as L
from ddyn.gap.benchmark import lofo
from ddyn.gap.config import DiagnosisConfig


# ----------------------------------------------------------------------------------------------- limits

def test_limit_solves_the_expected_evidence_and_grows_with_the_margin():
    g = np.array([2e-4, 1e-4, 3e-4])
    n = 1500
    lo = L.limit(0.04, g, n, margin=10.0)
    hi = L.limit(0.04, g, n, margin=60.0)
    assert lo is not None and hi is not None and hi > lo
    # at the limit the expected gain equals the margin plus the criterion's own penalty
    t = lo / 0.04
    gain = n * np.sum(np.log1p(t * t * g))
    assert gain == pytest.approx(10.0 + math.log(n), rel=1e-6)


def test_a_log_without_information_on_an_effect_has_no_limit():
    assert L.limit(0.04, np.zeros(3), 1000, 5.0) is None


def test_sizes_that_matter_follow_the_log():
    ctx = {"duration": 300.0, "v_max": 30.0}
    assert L.size_that_matters("steer_delay", ctx) == 0.04
    assert math.exp(-L.size_that_matters("tire_wear", ctx) * 300.0) == pytest.approx(0.9)
    assert L.size_that_matters("downforce", ctx) * 30.0 ** 2 == pytest.approx(0.1)
    assert L.size_that_matters("bank_angle", ctx) == pytest.approx(math.radians(3.0))
    assert L.size_that_matters("throttle_map", ctx) is None


def test_margin_grows_with_the_heldout_rows():
    cfg = DiagnosisConfig(min_evidence=5.0, min_evidence_per_row=0.02)
    assert L.margin_of(cfg, 600) == pytest.approx(17.0)
    assert L.margin_of(cfg, 3000) == pytest.approx(65.0)
    with pytest.raises(DdynError, match="min_evidence_per_row"):
        DiagnosisConfig(min_evidence_per_row=-1.0)
    with pytest.raises(DdynError, match="decision_levels: unknown effect"):
        DiagnosisConfig(decision_levels={"warp_drive": 1.0})


@pytest.fixture(scope="module")
def delay_log():
    from ddyn.plants import commonroad_st as CP

    return CP.make_log("putnam", CP.PlantEffects(steer_delay=0.08), seed=5, settings=CP.LogSettings(duration=40.0))


def _nominal(ds):
    from ddyn.gap.problem import nominal_from_vehicle
    from ddyn.model.vehicle import load
    from ddyn.plants import commonroad_st as CP

    return nominal_from_vehicle(load(CP.NOMINAL_VEHICLE), ds)


def test_every_report_states_its_limits_and_a_delay_above_its_limit_is_found(delay_log):
    from ddyn.gap.selection import diagnose

    d = diagnose(delay_log, _nominal(delay_log), DiagnosisConfig(hold=True, min_evidence_per_row=0.02))
    lim = d["limits"]["steer_delay"]
    assert lim["limit"] is not None and lim["limit"] < 0.08
    assert "steering delay below" in lim["sentence"] and "would not be found on this log" in lim["sentence"]
    assert d["selected"][:1] == ["steer_delay"]
    assert set(d["limits"]) >= {"steer_delay", "throttle_delay", "steer_lag", "mass_offset", "yaw_rate_bias"}


def test_an_effect_that_pays_but_is_not_claimed_does_not_stop_the_search(delay_log):
    """steer_delay pays most but may never be claimed: it is kept as a nuisance and the search goes on."""
    from ddyn.gap.selection import diagnose

    cfg = DiagnosisConfig(hold=True, decision_levels={"steer_delay": None, "*": 0.0})
    d = diagnose(delay_log, _nominal(delay_log), cfg)
    assert d["greedy"][0]["best_candidate"] == "steer_delay"
    assert d["greedy"][0]["nuisance"] == "steer_delay" and d["greedy"][0]["added"] is None
    assert len(d["greedy"]) >= 2, "the search stopped at the unclaimed effect"
    assert "steer_delay" not in d["selected"]
    assert [e["effect"] for e in d["model"]["unclaimed"]][:1] == ["steer_delay"]
    # the same with no more rounds allowed past it: the search stops there
    d1 = diagnose(delay_log, _nominal(delay_log), cfg.with_(max_effects=1, max_unclaimed=0))
    assert len(d1["greedy"]) == 1


# ----------------------------------------------------------------------------------------------- lofo rules

def _rec(family, effect, truth, est, dbic, rows=1000, size=0.04, duration=120.0, limit=0.02, top=None, gap=10.0):
    top = top or (effect if effect != "none" else "steer_lag")
    fams = {effect: {"size": est, "at_bound": False, "delta_bic": dbic}} if effect != "none" else {}
    fams.setdefault(top, {"size": est, "at_bound": False, "delta_bic": dbic})
    return {"status": "ok", "family": family, "effect": effect, "true_magnitude": truth, "families": fams,
            "top": top, "delta_bic_top": dbic, "heldout_rows": rows, "runner_up_gap": gap, "duration": duration,
            "limits": {f: {"size": size, "limit": limit, "gain": [0, 0, 0]} for f in lofo.EFFECTS}, "claimed": []}


def test_decision_levels_need_enough_logs_and_weigh_hits_against_false_claims():
    # 20 logs holding a steering delay at its size (0.04), estimated 0.75-1.2 times it, and 10 effect-free logs
    # where a steering delay of 0.55 times the size pays: a level of 0.6 or 0.7 keeps every hit and no false claim
    # (the higher is taken), 0.5 adds the ten false ones, 0.8 and above lose hits; the low tail alone said 0.77
    hits = [_rec("a", "steer_delay", 0.04, 0.04 * r, -50) for r in np.linspace(0.75, 1.2, 20)]
    alarms = [_rec("a", "none", 0.0, 0.04 * 0.55, -50, top="steer_delay") for _ in range(10)]
    levels = lofo.decision_levels(hits + alarms)
    assert levels["steer_delay"] == pytest.approx(0.7)
    assert levels["steer_lag"] is None      # no logs of it: never claimed
    # false claims that outnumber the hits at every level, with more evidence than the hits (no margin parts
    # them): the family is not claimed at all
    many = [_rec("a", "none", 0.0, 0.04 * 1.5, -80 - k, top="steer_delay") for k in range(30)]
    assert lofo.decision_levels(hits + many)["steer_delay"] is None


def test_family_margins_leave_at_most_five_percent_of_alarm_logs_claimed():
    levels = {e: 0.5 for e in lofo.EFFECTS}
    # forty effect-free logs whose top candidate is a mass offset paying 1..40 dBIC per 1000 rows
    recs = [_rec("a", "none", 0.0, 0.15, -float(d), rows=1000, top="mass_offset", size=0.1) for d in range(1, 41)]
    # and a below-size steering delay that is the true effect: its decision level's to stop, not a margin's
    recs.append(_rec("a", "steer_delay", 0.03, 0.05, -900.0, rows=1000))
    m = lofo.family_margins(recs, levels)
    claimed = [r for r in recs if r["effect"] == "none" and -r["delta_bic_top"] > m["mass_offset"] * 1000]
    assert len(claimed) <= 0.05 * 41 and 0.035 < m["mass_offset"] <= 0.0400001
    # one family's spurious gains do not raise another's margin
    assert m["steer_delay"] == 0.0 and m["downforce"] == 0.0
    # a first candidate below its decision level, at a range edge or tied is not an alarm at any margin
    small = [_rec("a", "none", 0.0, 0.001, -500.0, top="mass_offset", size=0.1)]
    assert lofo.family_margins(small, levels)["mass_offset"] == 0.0


def test_a_family_below_its_margin_is_kept_as_a_nuisance(delay_log):
    from ddyn.gap.selection import diagnose

    n = None
    cfg = DiagnosisConfig(hold=True, family_margins_per_row={"steer_delay": 50.0, "*": 0.0})
    d = diagnose(delay_log, _nominal(delay_log), cfg)
    n = d["split"]["heldout_rows"]
    assert d["greedy"][0]["nuisance"] == "steer_delay" and "steer_delay" not in d["selected"]
    # its stated limit follows its own margin: no steering delay in range pays 50 dBIC per row
    assert d["limits"]["steer_delay"]["limit"] is None and n > 0


def test_score_reads_the_issue_rules():
    rows = [_rec("x", "steer_delay", 0.05, 0.05, -90, duration=300.0) | {"claimed": ["steer_delay"]},
            _rec("x", "steer_lag", 0.06, 0.06, -90, duration=300.0) | {"claimed": ["steer_delay"]},
            _rec("x", "mass_offset", 0.03, 0.03, -5, size=0.1) | {"claimed": ["mass_offset"]},   # below its size
            _rec("x", "none", 0.0, 0.0, -1) | {"claimed": []}]
    s = lofo.score(rows)
    assert (s["scored"], s["first_right"]) == (2, 1)
    assert s["below_size"] == 1 and s["below_size_claimed"] == 1
    assert s["effect_free"] == 1 and s["effect_free_claimed"] == 0
    assert s["delay_vs_lag"] == {"told": 2, "right": 1}


def test_a_profile_effect_is_as_large_as_the_road_the_log_drove(monkeypatch):
    """A bank or grade's size is the largest the car drove over in the log (the plant's true_bank / true_grade),
    not the track's drawn peak: a log that never reached the steep part holds a smaller effect; other effects,
    and a plant without the column, keep the drawn magnitude."""
    monkeypatch.setattr(lofo, "_oval_bank_peak", lambda: 0.35)
    bank = np.array([0.0, -0.01, 0.02, -0.015])
    ds = SimpleNamespace(extras={"true_bank": bank, "true_grade": np.array([0.0, 0.04, -0.05])})
    case = {"effect": "bank_angle", "magnitude": -0.12, "track": "putnam"}
    assert lofo.log_truth(case, ds) == pytest.approx(-0.02)          # the drawn sign, the driven peak
    assert lofo.log_truth(case | {"effect": "grade", "magnitude": 0.09}, ds) == pytest.approx(0.05)
    assert lofo.log_truth(case | {"effect": "steer_delay", "magnitude": 0.05}, ds) == 0.05
    assert lofo.log_truth(case | {"effect": "none", "magnitude": 0.0}, ds) == 0.0
    assert lofo.log_truth({"effect": "bank_angle", "magnitude": 0.0, "track": "oval"}, ds) == pytest.approx(0.02)
    bare = SimpleNamespace(extras={})
    assert lofo.log_truth(case, bare) == -0.12
    assert lofo.log_truth({"effect": "bank_angle", "magnitude": 0.0, "track": "oval"}, bare) == 0.35
    # the rule below the size that matters: a 0.12 rad drawn bank driven at 0.02 is a below-size log
    rec = _rec("x", "bank_angle", lofo.log_truth(case, ds), 0.0, 5.0, size=math.radians(3.0)) | {"claimed": []}
    s = lofo.score([rec])
    assert (s["scored"], s["below_size"]) == (0, 1)


def test_the_headline_is_the_worst_family_and_says_how_few_logs_a_family_scored():
    from ddyn.gap.benchmark import lofo_summary

    cal = {"decision_levels": {e: 1.0 for e in lofo.EFFECTS}, "family_margins_per_row": {e: 0.0 for e in lofo.EFFECTS}}
    right = _rec("x", "steer_delay", 0.05, 0.05, -90, duration=300.0) | {"claimed": ["steer_delay"]}
    wrong = _rec("x", "steer_lag", 0.06, 0.06, -90, duration=300.0) | {"claimed": ["steer_delay"]}
    doc = {"folds": {"a": {"calibration": cal, "score": lofo.score([right, right, right])},
                     "b": {"calibration": cal, "score": lofo.score([right, wrong])}}}
    sm = lofo_summary.summary(doc)
    assert sm["worst"]["first_right"] == {"value": 0.5, "family": "b", "target": 0.95, "met": False}
    assert (sm["scored_logs"], sm["scored_min"], sm["min_scored"]) == (5, 2, lofo_summary.MIN_SCORED)
    assert "Fewest scored logs of a family: 2 (at least 60 asked)." in lofo_summary.markdown(sm)


def test_the_misses_listed_are_the_logs_behind_the_rates():
    rows = [_rec("x", "steer_delay", 0.05, 0.05, -90, duration=300.0) | {"claimed": ["steer_delay"]},
            _rec("x", "steer_lag", 0.06, 0.06, -90, duration=300.0) | {"claimed": ["steer_delay"], "case": 7},
            _rec("x", "throttle_delay", 0.05, 0.05, -90, duration=300.0) | {"claimed": []},
            _rec("x", "grade", 0.06, 0.0, -1, limit=0.1) | {"claimed": []},          # 120 s, below its stated limit
            _rec("x", "mass_offset", 0.03, 0.03, -5, size=0.1) | {"claimed": ["mass_offset"]},
            _rec("x", "none", 0.0, 0.0, -1) | {"claimed": ["downforce"]},
            _rec("x", "none", 0.0, 0.0, -1) | {"claimed": []}]
    s, m = lofo.score(rows), lofo.misses(rows)
    assert [r["effect"] for r in m["scored_not_right"]] == ["steer_lag", "throttle_delay"]
    assert len(m["scored_not_right"]) == s["scored"] - s["first_right"]
    assert sorted(r["effect"] for r in m["claimed_no_claim"]) == ["mass_offset", "none"]
    assert len(m["claimed_no_claim"]) == s["effect_free_claimed"] + s["below_size_claimed"]
    md = "\n".join(lofo.misses_markdown(rows))
    assert "first claim is not their effect (2)" in md and "with a claim (2)" in md
    assert "| x | 7 | steer_lag | 0.06 | 0.02 | 300 | - | - | steer_delay | steer_lag (-90.0) |" in md
    assert "| throttle_delay | 0.05 | 0.02 | 300 | - | - | none |" in md


def test_plan_varies_the_campaign_and_is_reproducible():
    a = lofo.plan("commonroad-std", 24, 3)
    assert a == lofo.plan("commonroad-std", 24, 3)
    assert sum(c["effect"] == "none" for c in a) == 6
    assert len({c["duration"] for c in a}) > 1 and len({c["dbw_period"] for c in a}) > 1
    assert all(c["magnitude"] != 0 for c in a if c["effect"] != "none" and c["track"] != "oval")


def _log(seen: list, what):
    """A stand-in for a plant's log that records what make_case_log drove it with."""
    seen.append(what)
    return SimpleNamespace(metadata={})


def test_a_lost_car_is_driven_again_more_gently_and_the_log_says_so():
    """A case whose driver loses the car is driven again at REDRIVE_GRIPS (a real plant: the CommonRoad std car,
    driven at 1.3 of its grip, leaves Putnam within 30 s; at 0.7 it goes round); a loss at every grip is raised
    with each attempt named, and an error that is not a lost car is never retried."""
    from ddyn.gap.benchmark import families as F

    case = lofo.plan("commonroad-std", 8, 5)[0] | {"effect": "none", "track": "putnam", "duration": 30.0,
                                                    "target_speed": 40.0}
    grips = []

    def brave(fam, track, fx, seed, settings, params):   # the first attempt drives at 1.3 of the grip
        grips.append(settings.driver_grip)
        return F.make_log(fam, track, fx, seed, replace(settings, driver_grip=settings.driver_grip or 1.3), params)

    ds = lofo.make_case_log(case, brave)
    assert grips == [None, lofo.REDRIVE_GRIPS[0]] and float(ds.metadata["driver_grip"]) == lofo.REDRIVE_GRIPS[0]
    assert len(json.loads(ds.metadata["redriven"])) == 1 and "lost the CommonRoad car" in ds.metadata["redriven"]

    def lost(fam, track, fx, seed, settings, params):
        grips.append(settings.driver_grip)
        raise CarLostError(f"spun at grip {settings.driver_grip}")

    grips.clear()
    with pytest.raises(CarLostError, match="grip default: spun at grip None; driven again at grip 0.7, 0.6: spun"):
        lofo.make_case_log(case, lost)
    assert grips == [None, *lofo.REDRIVE_GRIPS]

    def broken(fam, track, fx, seed, settings, params):
        grips.append(settings.driver_grip)
        raise DdynError("unknown CommonRoad parameter set")

    grips.clear()
    with pytest.raises(DdynError, match="unknown CommonRoad parameter set"):
        lofo.make_case_log(case, broken)
    assert grips == [None]


def test_road_tracks_change_the_track_and_nothing_else(monkeypatch):
    """`--tracks road`: every log not on the oval drives its own full-size random road course (road:SEED, the log's
    seed); every other draw of the campaign is the Putnam campaign's, so the two differ in the track alone."""
    putnam, road = lofo.plan("commonroad-mb", 24, 3), lofo.plan("commonroad-mb", 24, 3, tracks="road")
    for p, r in zip(putnam, road):
        assert {k: v for k, v in p.items() if k != "track"} == {k: v for k, v in r.items() if k != "track"}
        assert r["track"] == ("oval" if p["track"] == "oval" else f"road:{p['seed']}")
    assert len({r["track"] for r in road if r["track"] != "oval"}) == sum(r["track"] != "oval" for r in road)
    seen = []
    monkeypatch.setattr(lofo.F, "make_log", lambda fam, track, fx, seed, settings, params: _log(seen, track))
    lofo.make_case_log(road[0] if road[0]["track"] != "oval" else road[1])
    assert seen[0].name.startswith("random") and seen[0].name.endswith("x200") and 1000 < seen[0].length < 5000
    assert lofo.cache_name(road[0]) != lofo.cache_name(putnam[0])
    with pytest.raises(DdynError, match="unknown track set 'moon'"):
        lofo.plan("commonroad-mb", 4, 3, tracks="moon")


def test_every_log_carries_roll_and_pitch_of_one_kind(monkeypatch):
    """Until 2026-11-30 no campaign log carried a pitch channel (a grade could only be found as a profile along
    laps, which 60 and 120 s logs of Putnam never drive). One attitude source per log gives both channels, and
    every kind of the issue (none, an IMU, a map, a broken one) is drawn."""
    cases = [c for fam in lofo.F.FAMILIES for c in lofo.plan(fam, 40, 8101)]
    assert all(c["pitch_channel"] == c["roll_channel"] for c in cases)
    assert {c["roll_channel"] for c in cases} == set(lofo.CHANNEL_KINDS)
    assert {c["roll_channel"] for c in cases if c["effect"] == "grade"} >= {"imu", "map"}
    seen = []
    monkeypatch.setattr(lofo.F, "make_log", lambda fam, track, fx, seed, settings, params: _log(seen, settings))
    for kind in lofo.CHANNEL_KINDS:
        lofo.make_case_log(cases[0] | {"roll_channel": kind, "pitch_channel": kind})
    assert [(st.roll_channel, st.pitch_channel) for st in seen] == [(k, k) for k in lofo.CHANNEL_KINDS]
    # the log's cache name follows its pitch channel: a log made without one is never read for a case with one
    assert lofo.cache_name(cases[0] | {"pitch_channel": "none"}) != lofo.cache_name(cases[0] | {"pitch_channel": "map"})


# ----------------------------------------------------------------------------------------------- calibration

def _study_doc():
    recs = [_rec("a", "steer_delay", 0.05, 0.05, -80.0) | {"sample_time": 0.04} for _ in range(4)]
    recs += [_rec("b", "none", 0.0, 0.0, -3.0) | {"sample_time": 0.04} for _ in range(4)]
    cal = lofo.calibrate(recs)
    return {"all_families_calibration": cal, "pass1": recs, "settings": {"seed": 1, "logs_per_family": 4},
            "folds": {}, "worst": None}


def test_a_travelling_calibration_covers_any_length_and_goes_stale_with_the_code(tmp_path):
    doc = _study_doc()
    cal = CAL.travelling_from_study("t", doc, lofo.applied_config(doc["all_families_calibration"]).to_dict(),
                                    "ddyn gap lofo --logs 4")
    path = CAL.write(cal, tmp_path / "t.json")
    back = CAL.load(path)
    assert back.applied().family_margins_per_row == cal.applied().family_margins_per_row
    assert back.applied().decision_levels["steer_delay"] == pytest.approx(1.0)
    for length in (30.0, 120.0, 900.0):
        assert back.covers(length, 0.04)[0]
    assert "outside" in back.covers(900.0, 0.04)[1]
    assert not back.covers(120.0, 0.01)[0]
    assert back.stale() is None
    raw = json.loads(path.read_text())
    raw["code_version"]["fitting"] = "0" * 16
    path.write_text(json.dumps(raw))
    assert "other fitting code" in CAL.load(path).stale()
    raw.pop("durations")
    path.write_text(json.dumps(raw))
    with pytest.raises(DdynError, match="durations"):
        CAL.load(path)


def test_a_cached_log_is_named_by_what_makes_it():
    """Two campaign sizes shuffle the same seeds onto other cases: a cache named by the seed alone handed one case
    the other's log. Named by every field that makes the log, the same case finds its file and another does not."""
    a = lofo.plan("commonroad-std", 24, 3)
    b = lofo.plan("commonroad-std", 30, 3)
    names_a = {lofo.cache_name(c) for c in a}
    assert len(names_a) == len(a)
    assert [lofo.cache_name(c) for c in a] == [lofo.cache_name(c) for c in lofo.plan("commonroad-std", 24, 3)]
    same_seed_other_case = [(x, y) for x in a for y in b if x["seed"] == y["seed"] and
                            any(x[k] != y[k] for k in lofo.LOG_FIELDS)]
    assert same_seed_other_case, "the two sizes should differ somewhere (else the test shows nothing)"
    assert all(lofo.cache_name(x) != lofo.cache_name(y) for x, y in same_seed_other_case)


# ----------------------------------------------------------------------------------------------- a new campaign

def _recorded_study(tmp_path, levels):
    """A recorded study's results.json with fold calibrations for commonroad-st and commonroad-std."""
    cal = {"decision_levels": {e: levels for e in lofo.EFFECTS},
           "family_margins_per_row": {e: 0.0 for e in lofo.EFFECTS}, "families": [], "logs": 0}
    doc = {"settings": {"seed": 1, "logs_per_family": 4}, "all_families_calibration": cal,
           "folds": {"commonroad-st": {"calibration": cal}, "commonroad-std": {"calibration": cal}}}
    path = tmp_path / "recorded.json"
    path.write_text(json.dumps(doc))
    return path, doc


def test_recorded_folds_refuse_the_same_seed_a_missing_family_and_a_non_study(tmp_path):
    path, doc = _recorded_study(tmp_path, 1.0)
    assert lofo.recorded_folds(doc, path, ["commonroad-st"], 2)["commonroad-st"] == doc["folds"]["commonroad-st"][
        "calibration"]
    with pytest.raises(DdynError, match="seed 1: the recorded study's own campaign"):
        lofo.recorded_folds(doc, path, ["commonroad-st"], 1)
    with pytest.raises(DdynError, match="no fold for mujoco"):
        lofo.recorded_folds(doc, path, ["commonroad-st", "mujoco"], 2)
    with pytest.raises(DdynError, match="recorded.json: not a leave-one-family-out study"):
        lofo.recorded_folds({"folds": {}}, path, ["commonroad-st"], 2)


def test_a_new_campaign_is_scored_under_the_recorded_folds_without_a_pass_one(tmp_path, capsys):
    """`ddyn gap lofo --folds-from`: no pass 1, each family's new logs diagnosed under the recorded fold (here one
    that never claims: no log gets a claim), the recorded calibrations in the results; --calibration-out refused."""
    from ddyn.cli import main

    path, doc = _recorded_study(tmp_path, None)
    args = ["gap", "lofo", "--families", "commonroad-st,commonroad-std", "--logs", "4", "--seed", "2",
            "--durations", "20", "--folds-from", str(path), "--out", str(tmp_path / "s"), "--no-progress"]
    assert main(args + ["--calibration-out", str(tmp_path / "c.json")]) != 0
    assert "makes none" in capsys.readouterr().err
    assert main(args) == 0
    res = json.loads((tmp_path / "s" / "results.json").read_text())
    assert res["pass1"] == [] and res["settings"]["folds_from"]["seed"] == 1
    assert res["settings"]["tracks"] == "putnam"
    assert {f: v["calibration"] for f, v in res["folds"].items()} == {f: v["calibration"]
                                                                      for f, v in doc["folds"].items()}
    ok = [r for r in res["pass2"] if r["status"] == "ok"]
    assert len(ok) >= 6 and all(r["claimed"] == [] for r in ok)
    md = (tmp_path / "s" / "results.md").read_text()
    assert "no log of this campaign chose anything" in md
    for fam in res["folds"]:      # each family's row says how many of its logs the plant could drive
        rows = [r for r in res["pass2"] if r["family"] == fam]
        assert f"| {fam} | {sum(r['status'] == 'ok' for r in rows)}/{len(rows)} | " in md


def _campaign(tmp_path, seed, rows, recorded="recorded.json"):
    """A --folds-from campaign's results.json holding these pass-2 rows (family "commonroad-st")."""
    cal = {"decision_levels": {e: 1.0 for e in lofo.EFFECTS},
           "family_margins_per_row": {e: 0.0 for e in lofo.EFFECTS}, "families": [], "logs": 0}
    doc = {"settings": {"seed": seed, "logs_per_family": len(rows), "base_config": {"x": 1},
                        "folds_from": {"results": recorded, "seed": 1, "logs_per_family": 40}},
           "folds": {"commonroad-st": {"calibration": cal, "score": lofo.score(rows)}},
           "all_families_calibration": cal, "pass1": [], "pass2": rows, "seconds": 10.0}
    path = tmp_path / f"c{seed}.json"
    path.write_text(json.dumps(doc))
    return path


def test_blind_campaigns_under_the_same_folds_are_scored_together(tmp_path, capsys):
    """`ddyn gap pool`: the union of the campaigns' pass-2 logs scored again per family (one campaign's one
    right of two and another's two wrong of two give one of four, not the mean of the rates); refused for a seed
    twice, a campaign under another recorded study, and one that calibrated on its own logs unless it is the study
    the campaigns were scored under."""
    from ddyn.cli import main

    right = _rec("commonroad-st", "steer_delay", 0.05, 0.05, -90, duration=300.0) | {"claimed": ["steer_delay"]}
    wrong = _rec("commonroad-st", "steer_lag", 0.06, 0.06, -90, duration=300.0) | {"claimed": ["steer_delay"]}
    free = _rec("commonroad-st", "none", 0.0, 0.0, -1) | {"claimed": ["mass_offset"]}
    a = _campaign(tmp_path, 2, [right, wrong])
    b = _campaign(tmp_path, 3, [wrong, wrong, free])
    road = json.loads(b.read_text())        # one campaign on road courses: the pool says it holds both
    road["settings"]["tracks"] = "road"
    b.write_text(json.dumps(road))
    assert main(["gap", "pool", str(a), str(b), "--out", str(tmp_path / "p")]) == 0
    res = json.loads((tmp_path / "p" / "results.json").read_text())
    assert res["settings"]["tracks"] == "putnam+road"
    s = res["folds"]["commonroad-st"]["score"]
    assert (s["scored"], s["first_right"], s["effect_free_claimed"]) == (4, 1, 1)
    assert res["settings"]["seed"] == [2, 3] and res["summary"]["worst"]["first_right"]["value"] == 0.25
    assert "seeds 2, 3, pooled" in (tmp_path / "p" / "results.md").read_text()
    c = _campaign(tmp_path, 4, [right], recorded="other.json")
    for args, msg in (([a, a], "seed 2 is pooled twice"), ([a, c], "scored under other.json"),
                      ([a, tmp_path / "recorded.json"], "not a leave-one-family-out study")):
        if "recorded" in str(args[1]):
            _recorded_study(tmp_path, 1.0)
        assert main(["gap", "pool", *map(str, args), "--out", str(tmp_path / "q")]) != 0
        assert msg in capsys.readouterr().err
    own = json.loads(a.read_text())
    del own["settings"]["folds_from"]
    (tmp_path / "own.json").write_text(json.dumps(own))
    assert main(["gap", "pool", str(tmp_path / "own.json"), str(b), "--out", str(tmp_path / "q")]) != 0
    assert "cannot be pooled as blind" in capsys.readouterr().err
    # the recorded study itself (seed 1, the folds the campaigns were scored under) joins: its pass 2 scored each
    # family under the fold of the others; with other fold calibrations (or another seed) it is refused
    study = json.loads(a.read_text())
    del study["settings"]["folds_from"]
    study["settings"]["seed"] = 1
    study["pass1"] = [right]
    (tmp_path / "study.json").write_text(json.dumps(study))
    assert main(["gap", "pool", str(tmp_path / "study.json"), str(b), "--out", str(tmp_path / "r")]) == 0
    res = json.loads((tmp_path / "r" / "results.json").read_text())
    s = res["folds"]["commonroad-st"]["score"]
    assert (s["scored"], s["first_right"]) == (4, 1) and res["settings"]["seed"] == [1, 3]
    assert res["settings"]["folds_from"]["seed"] == 1
    assert "that study's own logs are pooled too" in (tmp_path / "r" / "results.md").read_text()
    study["folds"]["commonroad-st"]["calibration"] = {**study["folds"]["commonroad-st"]["calibration"], "logs": 9}
    (tmp_path / "study.json").write_text(json.dumps(study))
    assert main(["gap", "pool", str(tmp_path / "study.json"), str(b), "--out", str(tmp_path / "q")]) != 0
    assert "cannot be pooled as blind" in capsys.readouterr().err
