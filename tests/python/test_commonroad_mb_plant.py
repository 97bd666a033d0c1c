"""The multi-body plant and the plant effects added with it (issue 14): CommonRoad's PyPI vehicle_dynamics_mb
integrates it, a steady turn matches the physics, tyre relaxation, the stepped gearbox and a DBW period apart
from the log rate act as described, and the hold estimate and the gear_step candidate behave."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ddyn.errors import DdynError

vehiclemodels = pytest.importorskip("vehiclemodels", reason="COMMONROAD MISSING: pip install "
                                    "commonroad-vehicle-models (requirements.in); CI installs it")

from ddyn.gap import config as CFG, fit as F, heldout as HO, problem as P, report as R, selection as SEL  # noqa: E402
from ddyn.gap import hold_estimate
from ddyn.gap.benchmark import multibody as gap_mb  # noqa: E402
from ddyn.plants import commonroad_mb as MB  # noqa: E402
from ddyn.plants import commonroad_st as CP  # noqa: E402
from ddyn.model import backends, mathns  # noqa: E402
from ddyn.model import effects as E  # noqa: E402
from ddyn.model.single_track import COEFF_NAMES  # noqa: E402
from ddyn.model.vehicle import load as load_vehicle  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
NOMINAL = load_vehicle(MB.NOMINAL_VEHICLE)


def _settings(duration=2.0, **kw):
    return CP.LogSettings(duration=duration, noise_scale=0.0, **kw)


def test_the_pypi_multibody_model_integrates_the_plant(monkeypatch):
    """Every right-hand side is vehiclemodels' vehicle_dynamics_mb from the installed distribution, 4 per RK4
    step at 1 kHz; neither the single-track model nor ddyn.model's integrators run."""
    import vehiclemodels.vehicle_dynamics_mb as mb
    import vehiclemodels.vehicle_dynamics_std as std
    from importlib.metadata import distribution

    dist = distribution("commonroad-vehicle-models")
    installed = {Path(dist.locate_file(f)).resolve() for f in dist.files}
    assert Path(mb.__file__).resolve() in installed
    assert (REPO / "train") not in Path(mb.__file__).resolve().parents
    calls = {"n": 0}
    real = mb.vehicle_dynamics_mb

    def counting(x, u, p):
        assert len(x) == 29
        calls["n"] += 1
        return real(x, u, p)

    def forbidden(*a, **k):
        raise AssertionError("must not run")

    monkeypatch.setattr(mb, "vehicle_dynamics_mb", counting)
    monkeypatch.setattr(std, "vehicle_dynamics_std", forbidden)
    monkeypatch.setattr(backends, "step_numpy", forbidden)
    ds = MB.make_log("putnam", CP.PlantEffects(), 4, _settings(0.2, roll_channel=True))
    assert calls["n"] == 4 * (len(ds) - 1) * round(NOMINAL.sample_time * CP.PLANT_RATE)
    assert ds.vehicle == "commonroad_vehicle2_mb" and "vehicle_dynamics_mb" in ds.metadata["plant"]
    assert {"true_body_roll", "roll", "true_vx"} <= set(ds.extras)


def _steady(model, delta=0.04, v0=15.0, seconds=4.0):
    """Constant steering, speed held by a P loop on the throttle: the state after `seconds` and 0.5 s before."""
    p = CP.commonroad_parameters()
    env = CP._Env(p=p, m_true=NOMINAL.known.mass, m_nominal=NOMINAL.known.mass, downforce=0.0,
                  servo_tau=CP.SERVO_TAU, model=model)
    x = list(model.init(0.0, 0.0, delta, v0, 0.0, p))
    env.n_model = len(x)
    h, thr, hist = 1.0 / CP.PLANT_RATE, 0.0, []
    for i in range(int(seconds * CP.PLANT_RATE)):
        if i % 10 == 0:
            thr = 0.3 * (v0 - model.observe(x)[4]) + 0.05
        x = CP.rk4_step(x, h, delta, thr, env)
        hist.append(model.observe(x))
    return hist[-1], hist[-int(0.5 * CP.PLANT_RATE)]


def test_steady_turn_matches_the_bicycle_and_the_body_rolls_out():
    """In a steady 0.36 g turn the multi-body car's yaw rate is the linear bicycle's v delta / (L + K v^2), with
    the cornering stiffnesses B C D of the mapped vehicle file (its tyres are still linear there), and the body
    rolls out of the turn by a saloon's few degrees per g."""
    (_, _, _, _, vx, vy, r, roll), before = _steady(MB.MbModel())
    assert r == pytest.approx(before[6], rel=1e-3)                       # steady
    c = dict(zip(COEFF_NAMES, NOMINAL.true_vector()))
    k = NOMINAL.known
    L = k.lf + k.lr
    K = k.mass / L * (k.lr / (c["Bf"] * c["Cf"] * c["Df"]) - k.lf / (c["Br"] * c["Cr"] * c["Dr"]))
    assert r == pytest.approx(vx * 0.04 / (L + K * vx * vx), rel=0.05)
    ay_g = vx * r / CP.G
    assert 0.3 < ay_g < 0.4
    assert roll < 0 and 3.0 < math.degrees(-roll) / ay_g < 15.0          # deg per g, out of the (left) turn


def test_mb_log_is_kinematically_consistent():
    """The logged positions move with the logged body velocities and yaw (noise-free log)."""
    ds = MB.make_log("putnam", CP.PlantEffects(), 6, _settings(4.0))
    s = ds.states
    Ts = ds.sample_time
    vel = np.diff(s[:, :2], axis=0) / Ts
    c, si = np.cos(s[:, 2]), np.sin(s[:, 2])
    mid = 0.5 * (np.column_stack([s[:, 3] * c - s[:, 4] * si, s[:, 3] * si + s[:, 4] * c])[:-1]
                 + np.column_stack([s[:, 3] * c - s[:, 4] * si, s[:, 3] * si + s[:, 4] * c])[1:])
    assert np.max(np.abs(vel - mid)) < 0.05
    assert np.max(np.abs(np.diff(np.unwrap(s[:, 2])) / Ts - 0.5 * (s[1:, 5] + s[:-1, 5]))) < 0.01


@pytest.mark.parametrize("make", [CP.make_log, MB.make_log], ids=["std", "mb"])
def test_tyre_relaxation_acts_through_the_package_tyres(make):
    """A relaxation length changes the yaw response; a tiny one changes nearly nothing (the relaxed slip angles
    follow the kinematic ones); the package's tyre functions are its own again after the log."""
    from vehiclemodels.utils import tire_model

    orig = tire_model.formula_lateral
    base = make("putnam", CP.PlantEffects(), 8, _settings())
    tiny = make("putnam", CP.PlantEffects(tire_relaxation=0.05), 8, _settings())
    slow = make("putnam", CP.PlantEffects(tire_relaxation=4.0), 8, _settings())
    assert tire_model.formula_lateral is orig
    d_tiny = np.max(np.abs(tiny.states[:, 5] - base.states[:, 5]))
    d_slow = np.max(np.abs(slow.states[:, 5] - base.states[:, 5]))
    assert d_slow > 10 * d_tiny and d_slow > 1e-3
    with pytest.raises(Exception, match="relaxation"):
        make("putnam", CP.PlantEffects(tire_relaxation=0.01), 8, _settings(0.2))


def test_gearbox_shifts_and_the_candidate_matches_its_steps():
    """The plant shifts at GEAR_SHIFTS (downshifts lower), and the gear_step candidate's force factor is the
    plant's (1 + step)^(GEAR_REF - gear) between shifts."""
    assert CP.gear_for(7.0, 1) == 1 and CP.gear_for(15.0, 1) == 3 and CP.gear_for(19.5, 4) == 4
    assert CP.gear_for(18.5, 4) == 3
    ds = CP.make_log("putnam", CP.PlantEffects(gear_step=0.3), 9, _settings(8.0))
    gears = ds.extras["true_gear"]
    assert set(np.unique(gears)) <= {1, 2, 3, 4, 5} and len(np.unique(gears)) >= 1
    for v in (11.0, 17.0, 23.5):
        g = CP.gear_for(v, 1)
        assert float(E.gear_factor(mathns.NUMPY, np.array(v), 0.3)) == pytest.approx(1.3 ** (CP.GEAR_REF - g))
    assert CP.GEAR_SHIFTS == E.GEAR_SHIFTS and CP.GEAR_REF == E.GEAR_REF
    assert "gear_step" in E.DRIVETRAIN and "gear_step" not in E.EFFECT_NAMES    # opt-in (extended)


def test_dbw_period_apart_from_the_log_rate_and_its_detection():
    """A DBW unit at half the log rate logs each command twice (detected: 2 samples); one at twice the log rate
    logs every sample anew; the default is the log rate."""
    slow = CP.make_log("putnam", CP.PlantEffects(), 10, _settings(6.0, dbw_period=0.08))
    fast = CP.make_log("putnam", CP.PlantEffects(), 10, _settings(6.0, dbw_period=0.02))
    assert np.all(slow.states[0:-1:2, 7] == slow.states[1::2, 7])
    assert hold_estimate.detect_period(slow)["samples"] == 2
    assert hold_estimate.detect_period(fast)["samples"] == 1
    assert fast.metadata["dbw_period"] == repr(0.02)
    with pytest.raises(Exception):
        CP.make_log("putnam", CP.PlantEffects(), 10, _settings(1.0, dbw_period=0.0005))


def test_hold_estimate_is_bounded_and_recorded():
    """diagnose(hold="estimate") fits the hold delay on [0, Ts/2] and records the grid and the step structure."""
    ds = CP.make_log("putnam", CP.PlantEffects(), 11, CP.LogSettings(duration=12.0))
    nominal = P.nominal_from_vehicle(load_vehicle(CP.NOMINAL_VEHICLE), ds)
    d = SEL.diagnose(ds, nominal, candidates=("steer_delay",), max_effects=1, max_starts=30, gate=None, hold="estimate")
    info = d["nominal"]["hold_estimate"]
    assert 0.0 <= info["hold"] <= 0.5 * ds.sample_time + 1e-12 == info["bound"] + 1e-12
    assert d["nominal"]["command_hold_delay"] == pytest.approx(info["hold"])
    assert len(info["grid"]) == hold_estimate.GRID_STEPS + 1
    assert info["dbw_period_from_steps"]["samples"] == 1


def test_hold_from_steps_is_half_the_logged_command_period():
    """hold="steps": half a sample for a unit at the log rate or faster, m/2 samples for one holding each command
    for m samples; the delay a steering-delay candidate then reports is what comes on top of it."""
    slow = CP.make_log("putnam", CP.PlantEffects(), 10, _settings(6.0, dbw_period=0.08))
    fast = CP.make_log("putnam", CP.PlantEffects(), 10, _settings(6.0, dbw_period=0.02))
    assert hold_estimate.from_steps(slow)["hold"] == pytest.approx(slow.sample_time)
    assert hold_estimate.from_steps(fast)["hold"] == pytest.approx(0.5 * fast.sample_time)
    ds = CP.make_log("putnam", CP.PlantEffects(steer_delay=0.06), 11, CP.LogSettings(duration=30.0))
    nominal = P.nominal_from_vehicle(load_vehicle(CP.NOMINAL_VEHICLE), ds)
    d = SEL.diagnose(ds, nominal, candidates=("steer_delay",), max_effects=1, max_starts=30, gate=None, hold="steps")
    assert d["nominal"]["command_hold_delay"] == pytest.approx(0.5 * ds.sample_time)
    assert d["nominal"]["hold_estimate"]["rule"] == "half the logged command period"
    # the 60 ms delay of a unit at the log rate: closer with the step hold (0.082 on this 30 s log) than with none
    # (0.101, the half sample of staircase lag read as delay)
    steps = d["candidates"][0]["params"]["delay"]
    d0 = SEL.diagnose(ds, nominal, candidates=("steer_delay",), max_effects=1, max_starts=30, gate=None, hold=False)
    assert abs(steps - 0.06) < abs(d0["candidates"][0]["params"]["delay"] - 0.06) - 0.01
    assert steps == pytest.approx(0.06, abs=0.025)


def test_mb_case_plan_covers_the_new_effects():
    cases = gap_mb.plan(12, 3)
    effects = [c["effect"] for c in cases]
    assert effects[:2] == ["tire_relaxation", "gear_step"] and effects.count("none") == 3
    assert set(gap_mb.EFFECT_RANGES) - {"none"} <= set(effects)
    assert all(c["plant"] == "mb" and "gear_step" in c["candidates"] for c in cases)
    assert len({c["seed"] for c in cases}) == 12


def test_config_hold_takes_estimate(tmp_path):
    """hold: false (default), true, or "estimate" (the hold delay fitted); anything else is refused naming the key."""
    assert CFG.DiagnosisConfig().hold is False
    for text, want in (("true", True), ('"estimate"', "estimate"), ('"steps"', "steps")):
        f = tmp_path / "c.toml"
        f.write_text(f"hold = {text}\n")
        assert CFG.DiagnosisConfig.from_file(f).hold == want
    f.write_text("hold = 0.02\n")
    with pytest.raises(DdynError, match="hold"):
        CFG.DiagnosisConfig.from_file(f)


def test_identified_mb_nominal_is_fitted_on_an_effect_free_mb_log(monkeypatch):
    """--plant commonroad-mb --nominal identified: the 17 coefficients come from gap_independent's fit on one
    effect-free multi-body log (its own seed, driven as the cases are), stay inside the mapped file's ranges,
    differ from the mapped file and predict that log better than it (a short log here: 17 s, about the
    shortest whose 95 % fit part leaves the 20 held-out rows the fit needs)."""
    from ddyn.gap import calibration as CAL
    from ddyn.gap.benchmark import commonroad as G

    monkeypatch.setattr(G, "IDENT_DURATION", 17.0)
    logs, real = [], MB.make_log

    def recording(track, effects, seed, settings, *a, **k):
        ds = real(track, effects, seed, settings, *a, **k)
        logs.append((effects, seed, settings, ds))
        return ds

    monkeypatch.setattr(MB, "make_log", recording)
    c, info = gap_mb.identified_coefficients(hold=True)
    assert len(logs) == 1
    effects, seed, settings, log = logs[0]
    assert effects == CP.PlantEffects() and seed == gap_mb.IDENT_SEED == info["seed"]
    assert settings.driver_grip == gap_mb.DRIVER_GRIP and settings.duration == 17.0
    assert "vehicle_dynamics_mb" in info["plant"] and info["vehicle_file"] == MB.NOMINAL_VEHICLE.name
    mapped = NOMINAL.true_vector()
    lo, hi = NOMINAL.range_arrays()
    assert np.all((lo - 1e-9 <= c) & (c <= hi + 1e-9) | (mapped == 0))
    assert np.max(np.abs(c - mapped) / np.where(mapped != 0, np.abs(mapped), 1.0)) > 0.01

    def err(coeffs):
        p = P.Problem(log, P.nominal_from_vehicle(NOMINAL, log, coeffs), 0.95, refit=(), hold=True)
        return float(np.sum(p.residuals({}, np.zeros(0), p.rows_all) ** 2))

    assert err(c) < err(mapped)


def test_mb_parameter_sets_and_the_default_is_unchanged():
    """make_log(params=...): the AV-21 multi-body car (at the multi-body benchmark's driver grip) runs with its own
    nominal file and rolls less than the VW van (stiff race springs, a low centre of gravity); the default call is
    that with the explicit defaults, and rows recorded before the families were added."""
    ds = MB.make_log("putnam", CP.PlantEffects(), 4, CP.LogSettings(duration=1.0, roll_channel=True))
    assert ds.states[10].tolist() == [187.832282479552, -121.10565374070595, -3.0668413551373854, 24.93989101567745,
                                      -0.022191650559878595, 0.014637635454066274, 0.2502542937960925,
                                      0.0012318977223476969]
    assert float(ds.extras["roll"][25]) == -0.009682685365226132
    explicit = MB.make_log("putnam", CP.PlantEffects(), 4, CP.LogSettings(duration=1.0, roll_channel="imu"),
                           nominal=MB.NOMINAL_VEHICLE, params="vehicle2")
    assert np.array_equal(ds.states, explicit.states) and np.array_equal(ds.extras["roll"], explicit.extras["roll"])
    settings = CP.LogSettings(duration=8.0, noise_scale=0.0, start_s=1620.0, driver_grip=0.65)
    av = MB.make_log("putnam", CP.PlantEffects(), 4, settings, params="av21")
    van = MB.make_log("putnam", CP.PlantEffects(), 4, settings, params="vehicle3")
    assert av.vehicle == "commonroad_av21_mb" and van.vehicle == "commonroad_vehicle3_mb"
    assert "AV-21" in av.source and np.abs(av.states[:, 5]).max() > 0.3
    ay = {k: np.abs(d.states[:, 3] * d.states[:, 5]).max() for k, d in (("av", av), ("van", van))}
    roll = {k: np.abs(d.extras["true_body_roll"]).max() for k, d in (("av", av), ("van", van))}
    assert roll["av"] / ay["av"] < 0.5 * roll["van"] / ay["van"]
    with pytest.raises(DdynError, match="unknown CommonRoad parameter set"):
        MB.make_log(params="vehicle4")
