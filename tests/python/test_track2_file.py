"""How the paper's Track-2 file (DYN-PP-ETHZMobil.npz) was produced: ddyn.analysis.track2_file."""
from __future__ import annotations

import numpy as np

from ddyn.analysis.track2_file import _chain_errors, drivetrain_r2, track2_provenance
from ddyn.data import simulate
from ddyn.model import tracks, vehicle


def test_which_arrays_are_consistent_with_the_model(shared_data):
    r = track2_provenance(shared_data / "reference" / "DYN-PP-ETHZMobil.npz", fit=False)
    assert r["inputs_integrate_to_states_6_7"] < 1e-12          # inputs: the rates of throttle and steering
    assert r["dstates_6_7_minus_cumsum_of_inputs"] < 1e-12      # dstates 6-7: the rates summed without Ts
    assert r["dstates_6_7_max"] > 10.0                          # ... so no throttle a car has
    assert r["dstates_3_5_minus_states_3_5_max"]["omega"] > 10.0
    # states 3-5 are no chain of the model with either coefficient set: per-step errors of about a
    # rad/s in yaw rate, where a chain of the model (below) agrees to rounding
    for name, e in r["chain"].items():
        assert e["median"]["omega"] > 0.5 and e["median"]["vx"] > 0.01, name
    assert r["drivetrain_r2"]["best"] < 0.8


def test_the_same_check_passes_on_a_log_of_the_model(shared_data):
    """The check can pass: a log simulated with the model, in the file's layout, is a chain of it."""
    v = vehicle.load("orca_1_43")
    ds = simulate.simulate(v, tracks.load_track("ethzMobil"), laps=1, seed=5, progress=False)
    states, rates = ds.states.T, ds.inputs[:-1].T
    err = _chain_errors(states, rates, v.true_vector(), v, "euler")
    assert err.max() < 1e-9
    assert drivetrain_r2(states, v.sample_time)[0] > 0.9
