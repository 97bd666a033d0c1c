"""ddyn.studies.holdout_verdict: issue 36's rule (worse beyond the seed spread rejects; the bound target) over
`ddyn study ddm real --holdout` outputs, on small results.json files written here."""
from __future__ import annotations

import json

import pytest

from ddyn.errors import DdynError
from ddyn.studies import holdout_verdict as hv

LAPS = "laps 1 test, laps 0, 2 train"
SPEED = "rows with vx >= 20 m/s test"


def _stat(xs):
    return {"mean": sum(xs) / len(xs), "min": min(xs), "max": max(xs), "spread": max(xs) - min(xs)}


def _write(folder, what, runs):
    """runs: {name: {"vx": [per seed], ..., "bound": [per-seed share of the worst coefficient], "Iz": [...]}}"""
    real, summary = [], []
    for name, f in runs.items():
        seeds = list(range(len(f["vx"])))
        for i in seeds:
            coeffs = {"Iz": {"mean": f["Iz"][i], "at_lower_bound": 0.0, "at_upper_bound": 0.0},
                      "Cd": {"mean": 0.5, "at_lower_bound": f["bound"][i], "at_upper_bound": 0.0}}
            real.append({"name": name, "seed": i, "split": {"what": what}, "coefficients": coeffs,
                         "in_sample": {}})
        test = {c: _stat(f[c]) for c in hv.CHANNELS}
        summary.append({"name": name, "label": name, "seeds": seeds, "test": test, "in_sample": test})
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps({"real": real, "holdout_summary": summary}))
    return folder


def _figures(vx, bound=(0.0, 0.0, 0.0), iz=(1500.0, 1500.0, 1500.0), **other):
    base = {c: [0.03, 0.031, 0.032] for c in hv.CHANNELS}
    return {**base, "vx": list(vx), **{k: list(v) for k, v in other.items()}, "bound": list(bound), "Iz": list(iz)}


def test_worse_beyond_the_spread_on_one_condition_rejects_whatever_else_it_wins(tmp_path):
    laps = _write(tmp_path / "laps", LAPS, {
        "ddm_putnam": _figures([0.043, 0.0432, 0.0434], bound=(1.0, 1.0, 1.0)),
        "good_laps_bad_speed": _figures([0.032, 0.0325, 0.033])})
    speed = _write(tmp_path / "speed", SPEED, {
        "ddm_putnam": _figures([0.034, 0.035, 0.036], omega=[0.003, 0.0034, 0.004]),
        "good_laps_bad_speed": _figures([0.029, 0.030, 0.031], omega=[0.013, 0.015, 0.017])})
    v = hv.judge(hv.collect([laps, speed]))
    s = v["good_laps_bad_speed"]
    assert s["rejected"] and not s["adoptable"]
    assert s["worse"] == [f"omega ({SPEED})"]
    assert sorted(s["better"]) == sorted([f"vx ({LAPS})", f"vx ({SPEED})"])
    assert s["conditions"][LAPS]["channels"]["vy"]["verdict"] == "within"
    lines = hv.report(v)
    assert any("REJECTED" in line and "omega" in line for line in lines)


def test_overlapping_ranges_are_within_and_the_bound_target_decides(tmp_path):
    laps = _write(tmp_path / "laps", LAPS, {
        "ddm_putnam": _figures([0.030, 0.031, 0.033]),
        # means outside each other's range would be a verdict; overlapping seeds are not
        "overlaps": _figures([0.029, 0.0305, 0.0315]),
        "pinned": _figures([0.029, 0.0305, 0.0315], bound=(0.02, 0.06, 0.01)),
        "iz_unphysical": _figures([0.029, 0.0305, 0.0315], iz=(1500.0, 5600.0, 1500.0))})
    v = hv.judge(hv.collect([laps]))
    assert v["overlaps"]["conditions"][LAPS]["channels"]["vx"]["verdict"] == "within"
    assert v["overlaps"]["adoptable"]
    assert not v["pinned"]["meets_bound_target"] and not v["pinned"]["adoptable"] and not v["pinned"]["rejected"]
    assert v["pinned"]["conditions"][LAPS]["bounds"]["worst_coefficient"] == "Cd"
    assert not v["iz_unphysical"]["meets_bound_target"]
    assert not v["ddm_putnam"]["adoptable"]      # the baseline is not a candidate against itself


def test_a_setting_not_measured_on_every_condition_is_not_adoptable(tmp_path):
    laps = _write(tmp_path / "laps", LAPS, {"ddm_putnam": _figures([0.04] * 3), "only_laps": _figures([0.03] * 3)})
    speed = _write(tmp_path / "speed", SPEED, {"ddm_putnam": _figures([0.04] * 3)})
    v = hv.judge(hv.collect([laps, speed]))
    assert not v["only_laps"]["complete"] and not v["only_laps"]["adoptable"]


def test_bad_input_is_one_line(tmp_path, capsys):
    with pytest.raises(DdynError, match="no such file"):
        hv.collect([tmp_path / "missing"])
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "results.json").write_text("{}")
    with pytest.raises(DdynError, match="no holdout_summary"):
        hv.collect([tmp_path / "junk"])
    laps = _write(tmp_path / "laps", LAPS, {"other": _figures([0.03] * 3)})
    assert hv.main([str(laps)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no baseline run 'ddm_putnam'" in err
    broken = json.loads((laps / "results.json").read_text())
    del broken["real"][0]["split"]
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "results.json").write_text(json.dumps(broken))
    with pytest.raises(DdynError, match=r"broken/results.json: run 'other' lacks 'split'"):
        hv.collect([tmp_path / "broken"])
    # a split the reference cannot remake: one line naming the run and the key
    with_base = _write(tmp_path / "with_base", LAPS, {"ddm_putnam": _figures([0.03] * 3)})
    assert hv.main([str(with_base)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run 'ddm_putnam' (seed 0) lacks 'tau'" in err
    twice = _write(tmp_path / "laps2", LAPS, {"other": _figures([0.03] * 3)})
    with pytest.raises(DdynError, match="also in an earlier DIR"):
        hv.collect([laps, twice])


def test_the_reference_is_reported_beside_each_setting_not_part_of_the_rule(tmp_path):
    """With references given, each condition says on which channels a setting's worst seed beats "nothing
    changes"; a setting beating it nowhere is still judged by the rule alone."""
    laps = _write(tmp_path / "laps", LAPS, {"ddm_putnam": _figures([0.043, 0.0432, 0.0434]),
                                            "other": _figures([0.043, 0.0433, 0.0434])})
    figs = {"vx": 0.05, "vy": 0.02, "omega": 0.031, "ade": 0.01, "fde": 0.02}
    ref = {(LAPS, "ddm_putnam"): figs, (LAPS, "other"): figs}
    v = hv.judge(hv.collect([laps]), references=ref)
    c = v["other"]["conditions"][LAPS]
    assert c["reference"] == figs
    # vx 0.0434 < 0.05 and omega 0.032 > 0.031 at the worst seed: vx beats it, omega does not
    assert c["beats_reference"] == {"vx": True, "vy": False, "omega": False, "ade": False, "fde": False}
    assert v["other"]["adoptable"]
    lines = hv.report(v)
    assert any("beats the reference on vx" in line for line in lines)
    assert any(line.startswith("  reference on " + LAPS) and "the baseline beats it on vx" in line for line in lines)


def test_each_setting_is_read_against_the_reference_on_its_own_windows():
    """A setting with five rows of history scores on fewer windows than one with one row: its reference is made on
    its own, once per condition, history length and vehicle, not the first run's of the condition."""
    def run(tau):
        return {"seeds": [{"tau": tau, "vehicle": "av21"}]}

    splits = {LAPS: {"ddm_putnam": run(1), "same_tau": run(1), "tau5": run(5)}, SPEED: {"ddm_putnam": run(1)}}
    calls = []
    refs = hv.references_of(splits, score=lambda r: calls.append(r["tau"]) or {"vx": 0.05 + r["tau"]})
    assert calls == [1, 5, 1]
    assert refs[(LAPS, "tau5")] == {"vx": 5.05} and refs[(LAPS, "same_tau")] == refs[(LAPS, "ddm_putnam")]
    assert refs[(SPEED, "ddm_putnam")] == {"vx": 1.05}


def test_the_reference_is_scored_on_the_runs_own_held_out_rows(shared_data):
    """reference_of remakes a run's split of the Putnam log: on the speed split its one-step omega error is the
    rms change of omega over the held-out fast rows."""
    import numpy as np

    from ddyn.data.importers import load_any
    from ddyn.studies.ddm import split_real

    run = {"split": {"holdout": "speed", "speed": 20.0}, "tau": 1, "vehicle": "av21"}
    r = hv.reference_of(run)
    test = split_real(load_any(shared_data / "real" / "Putnam_park2023_run4_2.csv", vehicle="av21"), "speed")[1]
    same = test.segment[1:] == test.segment[:-1]
    assert r["omega"] == pytest.approx(float(np.sqrt(np.mean(np.diff(test.states[:, 5])[same] ** 2))))
    assert set(r) == {"vx", "vy", "omega", "ade", "fde"}
