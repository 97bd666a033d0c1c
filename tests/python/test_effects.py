"""Unmodelled effects (ddyn.model.effects) and the simulator's --effects hook."""
from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from ddyn.data.importers import read_canonical
from ddyn.errors import DdynError
from ddyn.model import effects as E
from ddyn.model import mathns
from ddyn.model import vehicle as vehicles
from ddyn.model.single_track import derivatives as nominal_derivatives

ORCA = vehicles.load("orca_1_43")
P = ORCA.known
C = ORCA.true_vector()
# a cornering state: 2 m/s, sliding a little, throttle on, steering left
STATE = (0.0, 0.0, 0.0, 2.0, 0.05, 1.5, 0.4, 0.15)
INPUTS = (0.0, 0.0)
MAGNITUDE = {"steer_delay": 0.03, "throttle_delay": 0.05, "steer_lag": 0.03, "bank_angle": 0.05, "grade": 0.05,
             "downforce": 0.05, "combined_slip": 0.5, "tire_relaxation": 0.01, "tire_wear": 0.01,
             "yaw_rate_bias": 0.1, "mass_offset": 0.15, "throttle_map": 0.5, "brake_gain": 0.5,
             "power_limit": 0.05, "gear_step": 0.2}


def _d(effects=None, aux=None):
    return np.array(E.derivatives(mathns.NUMPY, STATE, INPUTS, C, P, E.EffectSet.of(effects), aux or E.Aux()))


# ---------------------------------------------------------------------------------------------- parsing

def test_parse_json_key_value_and_dict_agree():
    a = E.parse_effects("steer_delay=0.04, bank_angle=0.05")
    b = E.parse_effects('[{"effect": "steer_delay", "params": {"delay": 0.04}},'
                        ' {"effect": "bank_angle", "params": {"angle": 0.05}}]')
    c = E.parse_effects({"steer_delay": 0.04, "bank_angle": {"angle": 0.05}})
    assert a == b == c
    assert [e.value for e in a] == [0.04, 0.05]
    prof = E.parse_effects("bank_angle.profile=sinusoid bank_angle.amplitude=0.02 bank_angle.wavelength=10")[0]
    assert prof.params == {"profile": "sinusoid", "amplitude": 0.02, "wavelength": 10}
    assert E.parse_effects(None) == [] and E.parse_effects("") == []
    assert json.loads(E.effects_json(a)) == [e.to_dict() for e in a]


@pytest.mark.parametrize("bad", ["warp_drive=1", "steer_delay", "steer_delay.gain=2", "steer_delay=-0.1",
                                 "[{\"effect\": \"grade\"", "mass_offset=-1", "steer_delay=1 steer_delay=2",
                                 "bank_angle.profile=spiral bank_angle=0.1", "bank_angle.profile=piecewise"])
def test_parse_rejects_bad_specs(bad):
    with pytest.raises(DdynError):
        E.EffectSet.of(bad)


def test_profiles():
    sin = E.Profile.of({"angle": 0.01, "profile": "sinusoid", "amplitude": 0.02})
    assert sin.at(0.0, 8.0) == pytest.approx(0.01)
    assert sin.at(2.0, 8.0) == pytest.approx(0.03)
    pw = E.Profile.of({"profile": "piecewise", "breaks": [[0, 0.1], [5, -0.1]]})
    assert pw.at(np.array([1.0, 6.0, 11.0]), 10.0).tolist() == [0.1, -0.1, 0.1]
    assert not E.Profile.of({"angle": 0.0}).active()


# ---------------------------------------------------------------------------------------------- directions

def test_zero_effects_are_the_nominal_derivative():
    nominal = np.array(nominal_derivatives(mathns.NUMPY, STATE, INPUTS, C, P))
    assert np.array_equal(_d(), nominal)
    zero = {k: 0.0 for k in E.ALL_EFFECTS}
    assert not E.EffectSet.of(zero).active()
    assert np.array_equal(_d(zero), nominal)


def test_drivetrain_terms():
    """Each drivetrain effect changes only vx's derivative, by the drive-term change its docstring states."""
    Cm1, Cm2 = C[12], C[13]
    vx = STATE[3]
    d0 = _d()

    def at(T, spec):
        s = list(STATE)
        s[6] = T
        return (np.array(E.derivatives(mathns.NUMPY, s, INPUTS, C, P, E.EffectSet.of(spec), E.Aux()))
                - np.array(E.derivatives(mathns.NUMPY, s, INPUTS, C, P, E.EffectSet(), E.Aux())))

    gain = Cm1 - Cm2 * vx
    assert at(0.4, "throttle_map=0.5")[3] == pytest.approx(gain * 0.5 * 0.4 * 0.6 / P.mass)
    assert at(1.0, "throttle_map=0.5")[3] == pytest.approx(0.0, abs=1e-12)       # full throttle unchanged
    assert at(-0.3, "throttle_map=0.5")[3] == pytest.approx(0.0, abs=1e-12)      # braking unchanged
    assert at(-0.3, "brake_gain=0.5")[3] == pytest.approx(gain * 0.5 * -0.3 / P.mass)
    assert at(0.3, "brake_gain=0.5")[3] == pytest.approx(0.0, abs=1e-12)
    cap = 0.5 * gain * 0.6 * vx          # a power that caps the drive force at half its value at T = 0.6
    assert at(0.6, {"power_limit": cap})[3] == pytest.approx(-0.5 * gain * 0.6 / P.mass)
    assert at(0.2, {"power_limit": cap})[3] == pytest.approx(0.0, abs=1e-12)     # below the cap
    assert np.array_equal(np.delete(at(0.6, {"power_limit": cap}), 3), np.zeros(7))
    assert np.array_equal(_d({"power_limit": 0.0}), d0)


def test_gravity_terms():
    d0 = _d()
    bank, grade = _d("bank_angle=0.05", E.Aux(bank=0.05)), _d("grade=0.05", E.Aux(grade=0.05))
    assert bank[4] - d0[4] == pytest.approx(E.G * math.sin(0.05))    # positive bank pushes to +vy
    assert grade[3] - d0[3] == pytest.approx(-E.G * math.sin(0.05))  # uphill slows
    assert np.array_equal(np.delete(bank, 4), np.delete(d0, 4))


def test_lateral_capacity_effects():
    d0 = _d()
    lateral = lambda d: d[4] + STATE[3] * STATE[5]   # noqa: E731  (F_y total / m)
    assert abs(lateral(_d("downforce=0.05"))) > abs(lateral(d0))                      # more grip with speed
    assert abs(lateral(_d("tire_wear=0.01", E.Aux(time=20.0)))) < abs(lateral(d0))     # worn tyres
    assert lateral(_d("tire_wear=0.01", E.Aux(time=0.0))) == pytest.approx(lateral(d0))
    # friction ellipse: the rear lateral force shrinks under drive force, the front one does not
    cs = _d("combined_slip=0.8")
    assert cs[5] != d0[5] and abs(lateral(cs) - lateral(d0)) > 0
    f = __import__("ddyn.model.single_track", fromlist=["forces"]).forces(mathns.NUMPY, STATE, C, P)
    x = 0.8 * f.Frx / C[8]
    assert cs[5] - d0[5] == pytest.approx(-f.Fry * (math.sqrt(1 - x * x) - 1) * P.lr / C[16])


def test_mass_offset_scales_accelerations_not_yaw():
    d0, dm = _d(), _d("mass_offset=0.25")
    force_x = d0[3] - STATE[4] * STATE[5]
    assert dm[3] - STATE[4] * STATE[5] == pytest.approx(force_x / 1.25)
    assert dm[5] == d0[5]


def _ramp_log(n=40, rate=0.5):
    dt = ORCA.sample_time
    t = np.arange(n) * dt
    states = np.tile(np.array(STATE, float), (n, 1))
    states[:, 7] = 0.01 + rate * t
    states[:, 6] = 0.2 + 2.0 * t
    inputs = np.column_stack([np.full(n, 2.0), np.full(n, rate)])
    return E.LogModel(t, np.zeros(n, int), states, inputs, P, dt), t, states


def test_delays_and_lag_slow_the_input_channels():
    lm, t, states = _ramp_log()
    ch = lm.channels(E.EffectSet.of("steer_delay=0.03 throttle_delay=0.05"))
    assert ch.steering[10] == pytest.approx(np.interp(t[10] - 0.03, t, states[:, 7]))  # fractional: interpolated
    assert ch.throttle[10] == pytest.approx(0.2 + 2.0 * (t[10] - 0.05))
    assert ch.steering[0] == states[0, 7]                                  # held before the start
    assert np.all(ch.steering[5:] < states[5:, 7]) and ch.dsteering[10] == pytest.approx(0.5)
    lag = lm.channels(E.EffectSet.of("steer_lag=0.05")).steering
    # tau dz/dt = u - z on a ramp: z trails u by rate * tau once settled
    assert np.all(lag[1:] < states[1:, 7])
    assert states[-1, 7] - lag[-1] == pytest.approx(0.5 * 0.05, rel=1e-3)


def test_relaxation_delays_the_slip_angle():
    n, dt = 30, ORCA.sample_time
    states = np.tile(np.array(STATE, float), (n, 1))
    states[10:, 4] = 0.3                     # a sudden side slip
    lm = E.LogModel(np.arange(n) * dt, np.zeros(n, int), states, np.zeros((n, 2)), P, dt)
    fx = E.EffectSet.of("tire_relaxation=0.02")
    mem = lm.relaxation_memory(fx, states, None, C)
    alpha = lm._alpha(states, states[:, 7], C)
    assert np.allclose(mem[:10], alpha[:10])
    assert abs(mem[10, 1]) < abs(alpha[10, 1])                          # rear slip lags the jump
    assert abs(mem[-1] - alpha[-1]).max() < 1e-6                        # and catches up
    b = math.exp(-dt * 2.0 / 0.02)
    assert mem[10, 1] == pytest.approx(alpha[10, 1] + (alpha[9, 1] - alpha[10, 1]) * b)


# ---------------------------------------------------------------------------------------------- simulator

@pytest.fixture(scope="module")
def track(shared_data):
    from ddyn.model.tracks import load_track

    return load_track("ethzMobil", shared_data)


@pytest.fixture(scope="module")
def nominal_run(track):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, track, duration=1.5, seed=5, noise_scale=1.0, progress=False)


@pytest.mark.parametrize("name", E.ALL_EFFECTS)
def test_zero_effect_simulation_is_bit_identical(name, track, nominal_run):
    from ddyn.data.simulate import simulate

    ds = simulate(ORCA, track, duration=1.5, seed=5, noise_scale=1.0, progress=False, effects={name: 0.0})
    assert np.array_equal(ds.states, nominal_run.states) and np.array_equal(ds.inputs, nominal_run.inputs)
    assert ds.metadata == nominal_run.metadata and ds.extras.keys() == nominal_run.extras.keys()


@pytest.mark.parametrize("method", ["euler", "rk4"])
@pytest.mark.parametrize("name", E.ALL_EFFECTS)
def test_log_predictor_reproduces_the_simulator(name, method, track):
    """The same memory rules in the simulator's plant and in the predictor on the recorded log."""
    from ddyn.data.simulate import simulate

    eff = {name: MAGNITUDE[name]}
    # the first braking of this drive comes at 8.3 s: the brake gain needs a log that reaches it
    ds = simulate(ORCA, track, duration=9.0 if name == "brake_gain" else 1.5, seed=2, method=method, progress=False,
                  effects=eff)
    assert json.loads(ds.metadata["effects"]) == [{"effect": name, "params": {E.MAIN_PARAM[name]: MAGNITUDE[name]}}]
    sub = ORCA.rk4_substeps if method == "rk4" else 1
    lm = E.LogModel.of(ds, P, method, sub)
    rows = ds.transition_index()
    target = ds.states[rows + 1, 3:6]
    with_effect = lm.one_step(E.EffectSet.of(eff), rows, C)
    without = lm.one_step(E.EffectSet(), rows, C)
    assert np.abs(with_effect - target).max() < 1e-12
    assert np.abs(without - target).max() > 1e-4          # the effect changes the dynamics
    if name == "yaw_rate_bias":
        assert np.allclose(ds.states[:, 5] - ds.extras["true_omega"], 0.1)


def test_sinusoid_bank_runs_and_differs(track, nominal_run):
    from ddyn.data.simulate import simulate

    ds = simulate(ORCA, track, duration=1.5, seed=5, noise_scale=1.0, progress=False,
                  effects="bank_angle.profile=sinusoid bank_angle.amplitude=0.1")
    assert not np.array_equal(ds.states, nominal_run.states)


def test_simulate_cli_records_effects(tmp_path, shared_data):
    from ddyn.data.simulate import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    out = tmp_path / "d.csv"
    args = parser.parse_args(["simulate", "--vehicle", "orca_1_43", "--track", "ethzMobil", "--duration", "1",
                              "--effects", "steer_delay=0.04", "-o", str(out), "-q"])
    assert args.func(args) == 0
    ds = read_canonical(out)
    assert json.loads(ds.metadata["effects"]) == [{"effect": "steer_delay", "params": {"delay": 0.04}}]
    args = parser.parse_args(["simulate", "--vehicle", "orca_1_43", "--track", "ethzMobil", "--duration", "1",
                              "--effects", '[{"effect":"bank_angle","params":{"angle":0.05}}]', "-o", str(out), "-q"])
    args.func(args)
    assert json.loads(read_canonical(out).metadata["effects"])[0]["effect"] == "bank_angle"
