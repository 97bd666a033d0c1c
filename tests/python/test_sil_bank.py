"""The road's bank in the SIL and a bank-aware controller (issue 34 items 1 and 4: the banked oval; docs/sil.md
"Road bank").

The plant drives the banked oval of ddyn.model.track_oval with the track's own bank (plant.json road_bank: the
lateral gravity g sin(bank) at the car's track position); the controller is told of the bank
(`--controller-bank`, controller.json control.bank: the profile along the raceline) or not. AV-21 on its flying
line of the oval (computed here when missing: 6 s), true coefficients, noise seed 1, in process
(ddyn_sil_inprocess: emulated time, frames through memory). Everything asserted is counted in simulated time.
Measured (seed 1, results/sil_banked_oval.json): the line 31.993 s; bank-aware 32.814 s (1.026 of the line),
0 violations, mean distance to the line 0.026 m; nominal (bank unknown) off the track after 12.0 s with 2
violations (mean 0.295 m); the same controller on the oval driven flat 32.993 s.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ddyn.control import raceline as R
from ddyn.errors import DdynError
from ddyn.model.track_files import open_track
from ddyn.model.track_oval import bank_at
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil import run as sil


@pytest.fixture(scope="module")
def av21():
    return load_vehicle("av21")


@pytest.fixture(scope="module")
def oval(av21):
    track = open_track("oval", av21.name)
    if R.load_for(av21.name, track) is None:
        # `ddyn mpc raceline --vehicle av21 --track oval --max-sideslip 0`: with the AV-21's sideslip bound (0.05
        # rad) IPOPT finds the oval's lap infeasible; without it the line solves in 40 iterations
        settings = R.resolved(replace(R.settings_for(av21.name), max_sideslip=0.0), track)
        R.save(R.default_path(av21.name, track), R.raceline_arrays(av21, track, R.solve(av21, track, settings),
                                                                   settings))
    return track


@pytest.fixture(scope="module")
def laps(av21, oval, sil_bins, tmp_path_factory):
    out = {}
    for told in (False, True):
        spec = sil.SilSpec.true_car(av21, oval, controller_bank=told)
        out[told] = sil.run_sil(spec, tmp_path_factory.mktemp(f"bank_{told}"), None, where="inprocess")
    return out


def test_the_bank_aware_controller_laps_the_banked_oval_within_5_percent_of_its_line(av21, oval, laps):
    line = R.meta_of(R.default_path(av21.name, oval))["lap_time_s"]
    m = laps[True]
    assert m["road_bank"] and m["controller_bank"]
    assert m["lap_completed"], (m["end_reason"], m["violations"])
    assert m["violations"] == 0 and m["controller"]["safe_periods"] == 0
    assert m["lap_times"][0] <= 1.05 * line, (m["lap_times"], line)  # measured 1.026
    assert m["tracking_error"]["mean"] < 0.1                           # measured 0.026 m


def test_the_nominal_controller_does_worse_on_the_banked_road(laps):
    """bank unknown: off the track (measured: after 12.0 s, 2 violations, 0.295 m from the line on average)"""
    nominal, aware = laps[False], laps[True]
    assert nominal["road_bank"] and not nominal["controller_bank"]
    assert not (nominal["lap_completed"] and nominal["violations"] == 0), nominal["end_reason"]
    assert nominal["tracking_error"]["mean"] > 3.0 * aware["tracking_error"]["mean"]


def test_the_raceline_carries_the_bank_only_when_told(av21, oval):
    table = sil.raceline_table(oval, av21)
    plain = sil.controller_config(sil.SilSpec.true_car(av21, oval), "/out", table=table)
    assert "bank" not in plain["control"]  # the file of before
    cfg = sil.controller_config(sil.SilSpec.true_car(av21, oval, controller_bank=True), "/out", table=table)
    assert cfg["control"]["bank"] is True
    bank = sil.raceline_bank(oval, table)
    s, _ = oval.project(table[:, 0], table[:, 1])
    assert np.allclose(bank, bank_at(oval, s)) and 0.15 < np.max(bank) < 0.36  # 9 to 20 degrees
    rows = sil.raceline_csv(table, bank).splitlines()
    assert rows[0].endswith(",bank") and len(rows[1].split(",")) == 6
    plant = sil.plant_config(sil.SilSpec.true_car(av21, oval), "/tracks", "/out", table)
    assert len(plant["road_bank"]) == len(oval.center) and np.allclose(plant["road_bank"], oval.bank)
    flat = sil.plant_config(sil.SilSpec.true_car(av21, oval, road_bank=False), "/tracks", "/out", table)
    assert "road_bank" not in flat
    mobil = open_track("ethzMobil", "orca_1_43")
    with pytest.raises(DdynError, match="control.bank.*has no bank profile"):
        sil.raceline_bank(mobil, np.zeros((4, 5)))
