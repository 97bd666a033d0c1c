"""The MuJoCo rigid-body car plant (ddyn.plants.mujoco_car): it drives, its nominal fits it, and its effects act
the way their physics says."""
import copy
import json

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.model.tracks import load_track
from ddyn.plants import commonroad_st as CP
from ddyn.plants import mujoco_car as M
from ddyn.plants.commonroad_st import LogSettings, PlantEffects

G = 9.81
TRACK = load_track("putnam")


def _log(effects=PlantEffects(), seed=11, duration=20.0, track=TRACK, **kw):
    kw = {"target_speed": 20.0, "noise_scale": 0.0, **kw}
    return M.make_log(track, effects, seed, LogSettings(duration=duration, **kw))


@pytest.fixture(scope="module")
def free():
    return _log(duration=25.0, roll_channel=True, pitch_channel=True)


def _lag(cmd, true, dt, max_lag=0.3):
    """The shift (s) of `true` behind `cmd` minimising the squared difference, to 1 ms by interpolation."""
    t = np.arange(len(cmd)) * dt
    best, best_err = 0.0, np.inf
    for lag in np.arange(0.0, max_lag, 0.001):
        shifted = np.interp(t + lag, t, true)
        rows = t + lag < t[-1]
        err = np.mean((shifted[rows] - cmd[rows]) ** 2)
        if err < best_err:
            best, best_err = lag, err
    return best


def _accel_per_throttle(ds):
    """Least squares dvx/dt = b T + c0 + c1 vx^2 + c2 vy omega on the true states: b (m/s^2 at full pedal)."""
    e = ds.extras
    vx, vy, om = e["true_vx"], e["true_vy"], e["true_omega"]
    a = np.gradient(vx, ds.sample_time)
    T = ds.states[:, 6]
    X = np.column_stack([T, np.ones_like(T), vx * vx, vy * om])
    return np.linalg.lstsq(X[5:-5], a[5:-5], rcond=None)[0][0]


def test_api_and_layout_match_commonroad(free):
    assert M.NOMINAL_VEHICLE.is_file() and M.NOMINAL_VEHICLE.name == "mujoco_car.json"
    assert set(M.SUPPORTED_EFFECTS) <= set(CP.PLANT_EFFECTS)
    assert "tire_relaxation" not in M.SUPPORTED_EFFECTS and "gear_step" not in M.SUPPORTED_EFFECTS
    cp = CP.make_log(TRACK, PlantEffects(), 1, LogSettings(duration=1.0, target_speed=20.0))
    assert free.states.shape[1] == cp.states.shape[1] and free.inputs.shape[1] == cp.inputs.shape[1]
    assert set(cp.extras) <= set(free.extras)
    assert set(cp.metadata) == set(free.metadata)
    assert json.loads(free.metadata["plant_effects"]) == {}
    assert "mujoco" in free.metadata["plant"]
    assert len(free) == int(round(25.0 / free.sample_time)) + 1


def test_effect_free_log_stays_on_track(free):
    e = free.extras
    _, lat = TRACK.project(e["true_x"], e["true_y"])
    assert np.max(np.abs(lat)) < 2.5, "the driver keeps the car near the centre line"
    vx = e["true_vx"]
    assert 15.0 < np.mean(vx) < 25.0 and np.min(vx) > 10.0
    # it went round corners near the grip the driver plans with, without spinning
    ay = vx * e["true_omega"]
    assert np.max(np.abs(ay)) > 0.4 * G
    assert np.max(np.abs(e["true_vy"])) < 1.5
    # the logged yaw is continuous (unwrapped) and consistent with the yaw rate
    yaw = e["true_yaw"]
    assert np.max(np.abs(np.diff(yaw))) < 0.1
    assert np.allclose(np.diff(yaw) / free.sample_time, 0.5 * (e["true_omega"][1:] + e["true_omega"][:-1]),
                       atol=0.03)


def test_identified_nominal_predicts_a_fresh_log():
    # on a log with the file's sensor noise: at the noise floor (a one-step residual carries the noise of two
    # samples), far below the spread of vx and omega (vy barely rises above its noise on this car)
    fit = M.one_step_fit(M.NOMINAL_VEHICLE, seed=9410, duration=30.0)
    for c, f in fit.items():
        assert f["rms_residual"] < 1.25 * np.sqrt(2.0) * f["noise_std"], (c, f)
    assert fit["vx"]["rms_residual"] < 0.05 * fit["vx"]["std"]
    assert fit["omega"]["rms_residual"] < 0.1 * fit["omega"]["std"]
    # with a tenth of the noise the model's own error shows: still small against each channel's spread, and
    # better than predicting no change for vx and omega
    quiet = M.make_log(TRACK, PlantEffects(), 9411, LogSettings(duration=30.0, noise_scale=0.1))
    fit = M.one_step_fit(M.NOMINAL_VEHICLE, log=quiet)
    for c, f in fit.items():
        assert f["rms_residual"] < 0.35 * f["std"], (c, f)
    for c in ("vx", "omega"):
        assert fit[c]["rms_residual"] < 0.8 * fit[c]["rms_change"], (c, fit[c])


def test_the_cars_own_downforce_is_in_its_nominal(tmp_path):
    # the contact tyres' grip grows with speed: on every effect-free log the identification diagnosed, downforce
    # came first at one size (ddyn.gap.baseline), so the nominal carries it; on a fresh effect-free log a
    # downforce on top of it then pays far less than it does against the coefficients alone
    from ddyn.gap import baseline
    from ddyn.gap.problem import nominal_from_vehicle
    from ddyn.gap.selection import diagnose
    from ddyn.model.vehicle import load as load_vehicle

    own = load_vehicle(M.NOMINAL_VEHICLE)
    assert set(own.effects) == {"downforce"} and own.effects["downforce"] > 0
    raw = json.loads(own.raw_json)
    raw.pop("effects")
    bare_file = tmp_path / "bare.json"
    bare_file.write_text(json.dumps(raw))
    ds = M.make_log(TRACK, PlantEffects(), 9412, LogSettings(duration=60.0, target_speed=24.0))

    def downforce_dbic(veh):
        d = diagnose(ds, nominal_from_vehicle(veh, ds), baseline.config().with_(candidates=("downforce",)))
        return next(c["delta_bic"] for c in d["candidates"] if c["effect"] == "downforce")

    with_own, bare = downforce_dbic(own), downforce_dbic(load_vehicle(bare_file))
    assert bare < -50.0 and with_own > 0.25 * bare, (with_own, bare)


def test_steer_delay_delays_the_wheels():
    base = _log(seed=12)
    late = _log(PlantEffects(steer_delay=0.1), seed=12)
    dt = base.sample_time
    lag0 = _lag(base.states[:, 7], base.extras["true_steering"], dt)
    lag1 = _lag(late.states[:, 7], late.extras["true_steering"], dt)
    # the effect-free lag: the hold (half a sample) and the servo (~10 ms filter plus the servo loop)
    assert 0.01 < lag0 < 0.06, lag0
    assert abs((lag1 - lag0) - 0.1) < 0.02, (lag0, lag1)
    assert json.loads(late.metadata["plant_effects"]) == {"steer_delay": 0.1}


def test_steer_lag_slows_the_servo():
    slow = _log(PlantEffects(steer_lag=0.08), seed=12, duration=12.0)
    lag = _lag(slow.states[:, 7], slow.extras["true_steering"], slow.sample_time)
    assert 0.07 < lag < 0.14, lag


def test_mass_offset_accelerates_less(free):
    heavy = _log(PlantEffects(mass_offset=0.3), duration=25.0)
    b0, b1 = _accel_per_throttle(free), _accel_per_throttle(heavy)
    # the same drive force on 1.3 times the mass
    assert 0.8 < b0 / M.DRIVE_ACCEL < 1.15, b0
    assert 1.15 < b0 / b1 < 1.45, (b0, b1)


def test_bank_pulls_the_car_downhill_and_shows_in_the_roll_channel(free):
    # from 150 m before the most banked corner (banked into the turn, 0.15 rad at its peak)
    prof = CP.bank_profile(TRACK, 0.15)
    start = (float(TRACK.s[int(np.argmax(np.abs(prof)))]) - 150.0) % TRACK.length
    banked = _log(PlantEffects(bank_angle=0.15), duration=20.0, roll_channel=True, start_s=start)
    for ds in (free, banked):
        e = ds.extras
        # the roll channel is the road's bank plus the body's roll on its springs, plus an EKF's noise
        resid = e["roll"] - (e["true_bank"] + e["true_body_roll"])
        assert abs(np.std(resid) - M.ROLL_NOISE) < 0.3 * M.ROLL_NOISE
    assert np.allclose(free.extras["true_bank"], 0.0)
    assert np.max(np.abs(banked.extras["true_bank"])) > 0.1
    # the body rolls out of the turn (left turn, ay > 0: left side up, roll < 0), a few degrees per g
    e = free.extras
    ay = e["true_vx"] * e["true_omega"] / G
    slope = np.polyfit(ay, e["true_body_roll"], 1)[0]
    assert -0.12 < slope < -0.03, slope
    # a road banked down to the left (the track's own banking, 0.1 rad everywhere) on Putnam's first straight:
    # gravity pulls the car to the left, so it drifts left (vy > 0), leans left on its springs (body roll > 0,
    # more than in the flat log's straight) and the driver holds the line with a little right steering
    tilted = copy.copy(TRACK)
    tilted.bank = np.full(len(TRACK.curvature), 0.1)
    side = _log(track=tilted, duration=5.0, roll_channel=True)
    e = side.extras
    rows = slice(10, None)
    assert np.mean(e["true_vy"][rows]) > 0.03
    assert np.mean(e["true_body_roll"][rows]) > 0.004
    assert np.mean(side.states[rows, 7]) < np.mean(free.states[10:126, 7]) + 1e-3
    assert np.allclose(e["true_bank"], 0.1)
    assert abs(np.mean(e["roll"][rows]) - 0.1 - np.mean(e["true_body_roll"][rows])) < 0.002


def test_pitch_channel_squats_under_acceleration(free):
    e = free.extras
    ax = np.gradient(e["true_vx"], free.sample_time)
    slope = np.polyfit(ax / G, e["pitch"], 1)[0]
    assert slope > 0.003, slope      # nose up when accelerating


def test_unsupported_effect_is_refused():
    for name in ("gear_step", "tire_relaxation"):
        with pytest.raises(DdynError, match=name) as err:
            M.make_log(TRACK, PlantEffects(**{name: 0.1}), 1, LogSettings(duration=2.0))
        assert "\n" not in str(err.value) and "cannot" in str(err.value)


def test_channel_kinds_are_those_of_commonroad():
    """Until issue 33's pitch channels the plant logged an IMU roll for any truthy kind, "none", "map" and "broken"
    included, so the campaign's MuJoCo logs all carried one. Each kind now logs what it says."""
    imu = _log(PlantEffects(grade=0.08), duration=8.0, roll_channel="imu", pitch_channel="imu")
    none = _log(PlantEffects(grade=0.08), duration=8.0, roll_channel="none", pitch_channel="none")
    assert "roll" not in none.extras and "pitch" not in none.extras
    # the drive itself does not depend on what is logged
    assert np.array_equal(none.states, imu.states)
    road = _log(PlantEffects(grade=0.08), duration=8.0, roll_channel="map", pitch_channel="map")
    e = road.extras
    s, _ = TRACK.project(road.states[:, 0], road.states[:, 1])
    grade = np.asarray(TRACK.interpolate(CP.grade_profile(TRACK, 0.08), s), float)
    # a map of the road: no body pitch, no noise, the grade at the car's position to the map's cell and rounding
    assert np.max(np.abs(e["pitch"] - grade)) < 0.01
    assert np.max(np.abs(e["roll"])) == 0.0                      # a flat road's bank on the map
    assert np.max(np.abs(imu.extras["pitch"] - grade)) > 2 * np.max(np.abs(e["pitch"] - grade))
    broken = _log(PlantEffects(grade=0.08), duration=8.0, roll_channel="broken", pitch_channel="broken")
    # an untrustworthy channel: off the truth by far more than an IMU's noise and body motion
    assert np.median(np.abs(broken.extras["pitch"] - grade)) > 0.05
    with pytest.raises(DdynError, match="roll_channel 'lidar'"):
        _log(duration=1.0, roll_channel="lidar")
