"""`ddyn study sil-loop --cases road_bank=1` (issue 34, "From diagnosis to the car"; ddyn.sil.loop): the pieces of
the bank's closed loop that need no drive. The loop itself (AV-21 on the oval, ~3.5 min) is results/sil_loop_bank.json.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from ddyn.data.dataset import Dataset
from ddyn.data.importers import read_canonical
from ddyn.errors import DdynError
from ddyn.gap.candidates import curvature_knots
from ddyn.model.track_files import open_track
from ddyn.model.track_oval import bank_at
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil import loop


@pytest.fixture(scope="module")
def oval():
    return open_track("oval", "av21")


def _profile(oval, scale=1.0):
    knots = curvature_knots(oval)
    return {"knots_m": knots.tolist(), "angle_rad": (scale * np.asarray(bank_at(oval, knots))).tolist(),
            "periodic_length_m": float(oval.length), "position_from": "track oval"}


def test_the_bank_is_scored_in_the_turns_and_on_each_straight(oval):
    """The oval's own bank at the diagnosis's knots scores its turns at 20 degrees and its straights at 9 and 5,
    within the linear interpolation between knots (measured: 1.2 degrees at worst, next to a ramp); half of it is
    half; a constant is the same everywhere; on the flat road (the no-effect case) the truth is zero."""
    own = loop.bank_against_truth(_profile(oval), oval)
    assert own["turns"]["true_deg"] == pytest.approx(20.0) and own["turns"]["mean_deg"] == pytest.approx(20.0, abs=0.3)
    assert own["turns"]["max_error_deg"] < 1.5 and own["peak_deg"] == pytest.approx(20.0)
    assert [p["true_deg"] for p in own["straights"]] == pytest.approx([9.0, 5.0])
    assert [p["mean_deg"] for p in own["straights"]] == pytest.approx([9.0, 5.0], abs=0.3)
    half = loop.bank_against_truth(_profile(oval, 0.5), oval)
    assert half["turns"]["mean_deg"] == pytest.approx(10.0, abs=0.2)
    const = loop.bank_against_truth(math.radians(3.0), oval)
    assert const["turns"]["mean_deg"] == pytest.approx(3.0) and const["straights"][1]["mean_deg"] == pytest.approx(3.0)
    flat = loop.bank_against_truth(math.radians(3.0), oval, banked=False)
    assert flat["turns"]["true_deg"] == 0.0 and flat["turns"]["max_error_deg"] == pytest.approx(3.0)


def test_bank_found_reads_the_claim_and_each_candidate(oval):
    d = {"selected": [], "model": {"effects": []},
         "below_limit": {"effect": "bank_profile", "params": {"peak": 0.03}, "delta_bic": -900.0, "limit": 0.05},
         "candidates": [{"effect": "bank_profile", "params": {"peak": 0.03}, "delta_bic": -900.0, "significant": True,
                         "profile": _profile(oval, 0.1)},
                        {"effect": "yaw_rate_bias", "params": {"bias": 0.003}, "delta_bic": -800.0},
                        {"effect": "bank_angle", "params": {"angle": 0.02}, "delta_bic": 290.0}]}
    b = loop.bank_found(d, oval)
    assert b["claimed"] is None and set(b["candidates"]) == {"bank_profile", "bank_angle"}
    assert b["candidates"]["bank_profile"]["vs_truth"]["turns"]["mean_deg"] == pytest.approx(2.0, abs=0.05)
    assert b["not_claimed_why"] == {"below_limit": d["below_limit"]}
    d["model"]["effects"] = [{"effect": "bank_profile", "params": {"peak": 0.35}, "profile": _profile(oval)}]
    assert loop.bank_found(d, oval)["vs_truth"]["turns"]["mean_deg"] == pytest.approx(20.0, abs=0.3)


def test_the_user_log_names_its_track(tmp_path):
    """The track reaches the diagnosis as a user's log of a known track carries it: its `track` metadata."""
    rows = ["step,safe,throttle_cmd,steering_cmd,x,y,yaw,vx,vy,omega"] + [
        f"{k},0,0.1,0.01,{k * 0.8},0,0,20,0,0" for k in range(10)]
    (tmp_path / "controller_log.csv").write_text("\n".join(rows) + "\n")
    path = loop.write_user_log(tmp_path / "controller_log.csv", tmp_path / "u.csv", "av21", 0.04, track_name="oval")
    assert read_canonical(path).metadata["track"] == "oval"
    assert "track" not in loop.user_log(tmp_path / "controller_log.csv", "av21", 0.04).metadata


def test_road_bank_cases_are_refused_where_they_cannot_be(oval, tmp_path):
    assert loop.parse_cases("road_bank=1,none=0") == [("road_bank", 1.0), ("none", 0.0)]
    av21 = load_vehicle("av21")
    flat = open_track("ethzMobil", "orca_1_43")
    ref = {"lap_s": 30.0}
    with pytest.raises(DdynError, match="track 'ethzMobil' has no bank of its own"):
        loop.run_case(av21, flat, "road_bank", 1.0, tmp_path, ref)
    with pytest.raises(DdynError, match="road_bank=0.5: the track's bank is driven as it is"):
        loop.run_case(av21, oval, "road_bank", 0.5, tmp_path, ref)


def test_the_plant_states_log_replaces_the_estimates_only(tmp_path):
    """The experiment's log: the plant's states at the user's rows (matched in time), the inputs unchanged."""
    from ddyn.data.dataset import write_canonical

    t = np.arange(0.0, 2.0, 0.01)
    traj = ["t,x,y,yaw,vx,vy,omega"] + [f"{ti},{20 * ti},0,{0.1 * ti},20,0.2,0.1" for ti in t]
    (tmp_path / "trajectory.csv").write_text("\n".join(traj) + "\n")
    tk = np.arange(0.0, 1.5, 0.04)
    est = np.column_stack([20 * (tk + 0.04), 0 * tk, 0.1 * (tk + 0.04), 20 + 0 * tk, 0 * tk, 0 * tk,
                           0.3 + 0 * tk, 0.02 + 0 * tk])
    ds = Dataset(time=tk, segment=np.zeros(len(tk), int), states=est, inputs=np.zeros((len(tk), 2)),
                 sample_time=0.04, vehicle="av21", source="test")
    write_canonical(ds, tmp_path / "u.csv")
    path, shift = loop.plant_states_log(tmp_path / "u.csv", tmp_path / "trajectory.csv", tmp_path / "p.csv")
    out = read_canonical(path)
    assert shift == pytest.approx(0.04)
    assert np.allclose(out.column("vy"), 0.2) and np.allclose(out.column("x"), 20 * (tk + 0.04))
    assert np.allclose(out.column("throttle"), 0.3) and np.allclose(out.inputs, 0.0)


def test_vy_against_the_plant_compares_both_estimates_at_the_users_rows(tmp_path):
    """The experiment's figure: the user's log's vy and the filter's (the controller log's row of the same step)
    against the plant's, as mean and RMS of the estimate minus the plant."""
    from ddyn.data.dataset import write_canonical

    tk = np.arange(2, 12) * 0.04                      # the user's rows: steps 2..11
    def log(vy):
        return Dataset(time=tk, segment=np.zeros(len(tk), int), states=np.column_stack(
            [tk, 0 * tk, 0 * tk, 20 + 0 * tk, vy, 0 * tk, 0 * tk, 0 * tk]), inputs=np.zeros((len(tk), 2)),
            sample_time=0.04, vehicle="av21", source="test")
    write_canonical(log(0.25 + 0 * tk), tmp_path / "u.csv")
    write_canonical(log(0.2 + 0 * tk), tmp_path / "p.csv")
    steps = np.arange(14)
    rows = ["step,vy"] + [f"{k},{-0.1 if 2 <= k <= 11 else 9.0}" for k in steps]
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    got = loop.vy_against_plant(tmp_path / "u.csv", tmp_path / "p.csv", tmp_path / "c.csv", 0.04)
    assert got["user_log"]["mean"] == pytest.approx(0.05) and got["user_log"]["rms"] == pytest.approx(0.05)
    assert got["filter"]["mean"] == pytest.approx(-0.3) and got["filter"]["rms"] == pytest.approx(0.3)
    (tmp_path / "other.csv").write_text("step,vy\n0,0\n1,0\n")
    with pytest.raises(DdynError, match="not the controller log of"):
        loop.vy_against_plant(tmp_path / "u.csv", tmp_path / "p.csv", tmp_path / "other.csv", 0.04)
