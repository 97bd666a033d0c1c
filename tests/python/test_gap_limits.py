"""ddyn.gap.limits: a bank in the turns reads as tyre grip, and the stated bank limit says so."""
from __future__ import annotations

import numpy as np
import pytest

from ddyn.gap import limits as L, problem as P, selection as SEL
from ddyn.model import vehicle as vehicles

ORCA = vehicles.load("orca_1_43")


def _drive(pieces, speed, dt=0.02):
    """time and states of a drive at one speed through (length m, curvature 1/m) pieces."""
    lengths = np.array([p[0] for p in pieces], float)
    ends = np.cumsum(lengths)
    t = np.arange(0.0, ends[-1] / speed, dt)
    s = speed * t
    kappa = np.array([pieces[min(int(np.searchsorted(ends, x, side="right")), len(pieces) - 1)][1] for x in s])
    states = np.zeros((len(t), 6))
    states[:, 3], states[:, 5] = speed, speed * kappa
    return t, states, s


def test_the_turn_shape_follows_the_turns_smoothed_over_ten_wheelbases():
    """Straights 0, a 100 m radius left turn half the peak, the 50 m right turn -1; the change spread over the
    averaging window (ten wheelbases) around each turn entry; the same shape for a 1:43 model of the drive."""
    pieces = [(300, 0.0), (300, 0.01), (300, 0.0), (200, -0.02), (300, 0.0)]
    t, st, s = _drive(pieces, 20.0)
    shape = L.turn_shape(t, st, 3.0)

    def at(x):
        return float(np.interp(x, s, shape))
    assert at(150) == pytest.approx(0.0, abs=1e-9) and at(750) == pytest.approx(0.0, abs=1e-9)
    assert at(450) == pytest.approx(0.5, abs=0.01) and at(1000) == pytest.approx(-1.0, abs=0.01)
    assert np.max(np.abs(shape)) == pytest.approx(1.0)
    # the turn entry at 300 m: half the turn's value there, none 20 m before, all of it 20 m after
    assert at(300) == pytest.approx(0.25, abs=0.03) and at(280) == pytest.approx(0.0, abs=1e-9)
    assert at(320) == pytest.approx(0.5, abs=0.01)
    # a scale model of the same drive (lengths, speed and wheelbase / 43): the same shape, to a point of the
    # 31-point average (rounding moves a turn entry by one point of the grid)
    small_t, small_st, _ = _drive([(a / 43, k * 43) for a, k in pieces], 20.0 / 43)
    assert np.allclose(L.turn_shape(small_t, small_st, 3.0 / 43), shape, atol=1.5 / 31)
    # shorter than the averaging, or standing still: no turns to follow
    assert not L.turn_shape(t[:50], st[:50], 3.0).any()
    assert not L.turn_shape(t, np.zeros_like(st), 3.0).any()


@pytest.fixture(scope="module")
def free_log(shared_data):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, "ethzMobil", laps=2.0, seed=21, noise_scale=1.0, progress=False, effects=None)


def test_the_tyre_refit_takes_up_a_bank_in_the_turns_not_a_constant_one(free_log):
    """The premise of the bank's turns form: of a bank's change to the one-step predictions, the refit of the
    tyre's grip (Df, Dr) takes up most when the bank follows the turns and little when it is constant."""
    prob = P.Problem(free_log, P.nominal_from_vehicle(ORCA, free_log), 0.6)
    rho, rows = np.zeros(len(prob.refit)), prob.rows_held
    r0 = prob.residuals({}, rho, rows)
    var = np.mean(r0 ** 2, axis=0)
    dr = r0 - prob.residuals({"bank_angle": 0.05}, rho, rows)
    shape = L.turn_shape(free_log.time, free_log.states, ORCA.known.lf + ORCA.known.lr)
    kept = {}
    for name, d in (("constant", dr), ("turns", dr * shape[rows][:, None])):
        kept[name] = (np.sum(L._projected_gain(prob, rho, d, False, var))
                      / np.sum(L._projected_gain(prob, rho, d, True, var)))
    assert kept["constant"] > 0.8 and kept["turns"] < 0.4


def test_the_stated_bank_limit_is_that_of_a_bank_in_the_turns(free_log, monkeypatch):
    """The diagnosis states the bank's limit of its turns form, with the reason in its sentence, well above what
    the same bank spread evenly over the log (a shape of ones, refit projected out) would give."""
    kw = dict(candidates=("bank_angle",), max_effects=1, max_starts=50)
    stated = SEL.diagnose(free_log, P.nominal_from_vehicle(ORCA, free_log), **kw)["limits"]["bank_angle"]
    assert stated["bound_by"] == "turns" and "tyre refit" in stated["sentence"]
    monkeypatch.setattr(L, "turn_shape", lambda time, states, wheelbase: np.ones(len(time)))
    even = SEL.diagnose(free_log, P.nominal_from_vehicle(ORCA, free_log), **kw)["limits"]["bank_angle"]
    assert stated["limit"] > 1.5 * even["limit"]
