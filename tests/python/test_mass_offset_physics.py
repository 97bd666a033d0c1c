"""The mass offset as the independent plant has it (issue 14, docs/gap_independent.md "What a mass offset is"):
mass and yaw inertia scaled together, tyre forces proportional to the load. With --mass-inertia the diagnosis's
candidate (Df, Dr refitted) is exactly that: a change of the longitudinal response only. Without it the
candidate also changes the yaw response, and on the plant it came out with the wrong sign.
Also the known steering servo of --steer-servo."""
from __future__ import annotations

import numpy as np
import pytest

vehiclemodels = pytest.importorskip("vehiclemodels", reason="COMMONROAD MISSING: pip install "
                                    "commonroad-vehicle-models (requirements.in); CI installs it")

from ddyn.gap import config as CFG, fit as F, heldout as HO, problem as P, report as R, selection as SEL  # noqa: E402
from ddyn.plants import commonroad_st as CP  # noqa: E402
from ddyn.model import effects as E  # noqa: E402
from ddyn.model import mathns  # noqa: E402
from ddyn.model.single_track import COEFF_NAMES  # noqa: E402
from ddyn.model.vehicle import load as load_vehicle  # noqa: E402

NOMINAL = load_vehicle(CP.NOMINAL_VEHICLE)


def _log(effects=CP.PlantEffects(), seed=4, duration=6.0):
    return CP.make_log("putnam", effects, seed, CP.LogSettings(duration=duration))


@pytest.fixture(scope="module")
def short():
    return _log()


def _derivatives(ds, mass_inertia, f):
    """State derivatives at the log's rows, nominal and under "the car is (1 + f) heavier" with the tyre peak
    forces Df, Dr refitted by the load, 1 + f."""
    c = NOMINAL.true_vector().copy()
    heavy_c = c.copy()
    for name in ("Df", "Dr"):
        heavy_c[COEFF_NAMES.index(name)] *= 1.0 + f
    fx0 = E.EffectSet()
    fx1 = E.EffectSet(mass_offset=f, mass_inertia=mass_inertia)
    out = []
    for row in ds.states[::10]:
        z = tuple(float(v) for v in row)
        out.append((E.derivatives(mathns.NUMPY, z, (0.0, 0.0), tuple(c), NOMINAL.known, fx0, E.Aux()),
                    E.derivatives(mathns.NUMPY, z, (0.0, 0.0), tuple(heavy_c), NOMINAL.known, fx1, E.Aux())))
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def test_a_scaled_car_changes_only_the_longitudinal_response(short):
    """The derivation in the docs: m, Iz and the tyre forces all (1 + f) leave dvy/dt and domega/dt unchanged and
    scale the longitudinal forces' part of dvx/dt by 1 / (1 + f); without Iz the yaw response changes too."""
    f = 0.2
    base, heavy = _derivatives(short, True, f)
    np.testing.assert_allclose(heavy[:, 4:6], base[:, 4:6], rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(heavy[:, 3] - base[:, 3])) > 1e-3
    base, heavy_old = _derivatives(short, False, f)
    np.testing.assert_allclose(heavy_old[:, 5], (1.0 + f) * base[:, 5], rtol=1e-9, atol=1e-12)


def test_a_heavier_plant_is_estimated_heavier():
    """A +25 % mass offset on the plant: the candidate with the inertia scaled finds it with the right sign and
    within a few hundredths of it on a 30 s log; the old candidate (Iz unchanged) found a negative offset."""
    ds = _log(CP.PlantEffects(mass_offset=0.25), seed=7, duration=30.0)

    def estimate(mass_inertia):
        prob = P.Problem(ds, P.nominal_from_vehicle(NOMINAL, ds), CFG.DiagnosisConfig().fit_fraction, hold=True,
                         mass_inertia=mass_inertia)
        return F.fit(prob, ("mass_offset",)).values["mass_offset"]

    assert estimate(True) == pytest.approx(0.25, abs=0.1)
    assert estimate(False) < 0.1


def test_the_known_servo_and_nominal_effects_a_hypothesis_replaces_them(short):
    prob = P.Problem(short, P.nominal_from_vehicle(NOMINAL, short), 0.6, hold=True, steer_servo=0.01)
    assert prob.effects({}).steer_lag == pytest.approx(0.01)
    assert prob.effects({"steer_lag": 0.05}).steer_lag == pytest.approx(0.05)
    fx = prob.effects({"steer_delay": 0.03})
    assert fx.steer_lag == pytest.approx(0.01) and fx.steer_delay == pytest.approx(0.03 + 0.5 * short.sample_time)
    assert P.Problem(short, P.nominal_from_vehicle(NOMINAL, short), 0.6).effects({}).steer_lag == 0.0
    # any effect the nominal carries (a data sheet's power limit), replaced by a hypothesis of the same effect
    prob = P.Problem(short, P.nominal_from_vehicle(NOMINAL, short), 0.6,
                     nominal_effects=CFG.DiagnosisConfig.from_dict({"nominal_effects": "power_limit=92000"}).nominal_effects)
    assert prob.effects({}).power_limit == 92000.0 and prob.effects({"power_limit": 5e4}).power_limit == 5e4
