"""A vehicle file's own effects (Vehicle.effects): parsed and checked where they enter, carried into the gap
diagnosis's nominal, and a hypothesis of the same effect is what comes on top of them; the rule that decides
which effects are a car's own (ddyn.gap.baseline)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.gap import baseline, problem as P
from ddyn.model import vehicle as vehicles

ORCA = vehicles.load("orca_1_43")


def _with(tmp_path, **extra):
    raw = json.loads(ORCA.raw_json)
    raw.update(extra)
    path = tmp_path / "car.json"
    path.write_text(json.dumps(raw))
    return path


def test_effects_are_read_from_the_vehicle_file(tmp_path):
    v = vehicles.load(_with(tmp_path, effects={"downforce": 0.002, "steer_delay": 0.01}))
    assert v.effects == {"downforce": 0.002, "steer_delay": 0.01}
    assert ORCA.effects == {}


@pytest.mark.parametrize("effects, words", [
    ({"aero": 0.1}, "effects.aero is not an effect"),
    ({"downforce": "0.1"}, "effects.downforce must be a number"),
    ({"downforce": float("nan")}, "effects.downforce must be finite"),
    ([0.1], "effects must be a JSON object"),
])
def test_bad_effects_are_one_line_naming_the_key(tmp_path, effects, words):
    path = _with(tmp_path, effects=effects)
    with pytest.raises(DdynError) as e:
        vehicles.load(path)
    assert words in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)


@pytest.fixture(scope="module")
def log(shared_data):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, "ethzMobil", laps=0.5, seed=3, progress=False)


def test_a_hypothesis_adds_to_the_cars_own_effect(log, tmp_path):
    k0, dk = 2e-3, 1e-3
    own = vehicles.load(_with(tmp_path, effects={"downforce": k0}))
    with_own = P.Problem(log, P.nominal_from_vehicle(own, log), 0.8)
    plain = P.Problem(log, P.nominal_from_vehicle(ORCA, log), 0.8)
    rows = with_own.rows_held
    rho = np.zeros(0)
    # nothing hypothesised: the car's own downforce is in the nominal
    assert np.allclose(with_own.predict({}, rho, rows), plain.predict({"downforce": k0}, rho, rows))
    assert not np.allclose(with_own.predict({}, rho, rows), plain.predict({}, rho, rows))
    # a downforce hypothesis is the part on top of it
    assert np.allclose(with_own.predict({"downforce": dk}, rho, rows), plain.predict({"downforce": k0 + dk}, rho, rows))
    assert "downforce 0.002" in P.nominal_from_vehicle(own, log).label


def _claims(*pairs):
    return [{"effect": e, "value": v, "verdict": ""} for e, v in pairs]


def test_an_effect_first_on_most_logs_at_one_size_is_the_cars_own():
    claims = _claims(("downforce", 0.0017), ("downforce", 0.0019), ("steer_delay", 0.02))
    own, named = baseline.consistent_effect(claims)
    assert own == {"downforce": pytest.approx(0.0018)} and named == claims[:2]
    # the refit factors it was found with go with it
    claims[0]["refit"], claims[1]["refit"] = {"Df": 0.5, "Dr": 0.6}, {"Df": 0.7, "Dr": 0.8}
    assert baseline.refit_factors(named) == {"Df": pytest.approx(0.6), "Dr": pytest.approx(0.7)}


@pytest.mark.parametrize("claims", [
    _claims(("downforce", 0.0017), ("steer_delay", 0.02)),                          # no majority
    _claims(("downforce", 0.0017), (None, None), (None, None)),                     # one log of three
    _claims(("downforce", 0.001), ("downforce", 0.002)),                            # sizes a factor 2 apart
    _claims(("yaw_rate_bias", 0.01), ("yaw_rate_bias", -0.01)),                     # opposite signs
    _claims(("downforce", 0.0017), ("downforce", 0.0018), (None, None), (None, None)),   # half is not most
])
def test_anything_else_is_left_to_the_diagnosis(claims):
    assert baseline.consistent_effect(claims) == ({}, [])


def test_one_log_cannot_say_what_the_car_is():
    with pytest.raises(DdynError, match="at least 2 effect-free logs"):
        baseline.consistent_effect(_claims(("downforce", 0.0017)))
