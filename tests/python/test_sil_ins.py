"""ddyn.sil.ins: the ground velocity from GNSS positions and an accelerometer, without a vehicle model (the SIL loop's
user's log takes its vy from it). A car on a weaving path with known velocity: what is asserted is that the smoother
recovers vy within the sensors' noise, without a time shift, through an accelerometer offset (a banked road's
gravity) and through missing GNSS rows, and that it reads the noise levels from the log."""
from __future__ import annotations

import numpy as np
import pytest

from ddyn.sil import ins

DT = 0.02


def weave(n=3000, seed=0, gnss=0.002, acc=0.05, offset=(0.0, 0.0), w=15.0):
    """A car at 2 m/s along a sinusoidal path with a sideslip that oscillates: true positions, body velocity and the
    body-frame specific force; noisy GNSS (m) and accelerometer (m/s^2) readings, the accelerometer offset by
    `offset` (body frame)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    psi = 0.6 * np.sin(0.5 * t)                           # heading
    beta = 0.03 * np.sin(w * t + 0.4)                     # sideslip (vy = V sin(beta)), weaving at w rad/s
    v = 2.0
    course = psi + beta
    vxw, vyw = v * np.cos(course), v * np.sin(course)
    # positions: integrate the velocity finely (trapezoid on a 10x grid) so that they are the true integral
    tf = np.arange(10 * n) * DT / 10
    cf = 0.6 * np.sin(0.5 * tf) + 0.03 * np.sin(w * tf + 0.4)
    xf = np.r_[0.0, np.cumsum(0.5 * (np.cos(cf[1:]) + np.cos(cf[:-1])) * v * DT / 10)]
    yf = np.r_[0.0, np.cumsum(0.5 * (np.sin(cf[1:]) + np.sin(cf[:-1])) * v * DT / 10)]
    x, y = xf[::10], yf[::10]
    dcourse = 0.3 * np.cos(0.5 * t) + 0.03 * w * np.cos(w * t + 0.4)
    aw = np.column_stack([-v * np.sin(course) * dcourse, v * np.cos(course) * dcourse])   # world acceleration
    c, s = np.cos(psi), np.sin(psi)
    ab = np.column_stack([c * aw[:, 0] + s * aw[:, 1], -s * aw[:, 0] + c * aw[:, 1]])     # into the body
    vy_body = -s * vxw + c * vyw
    meas = {"px": x + gnss * rng.standard_normal(n), "py": y + gnss * rng.standard_normal(n),
            "ax": ab[:, 0] + offset[0] + acc * rng.standard_normal(n),
            "ay": ab[:, 1] + offset[1] + acc * rng.standard_normal(n)}
    return t, psi, vy_body, meas


def smoothed(psi, meas, segment=None):
    seg = np.zeros(len(psi), int) if segment is None else segment
    return ins.body_lateral_velocity(meas["px"], meas["py"], meas["ax"], meas["ay"], psi, seg, DT)


def test_the_smoother_recovers_vy_within_the_noise_and_on_time():
    t, psi, vy, meas = weave()
    got = smoothed(psi, meas)
    inner = slice(50, -50)
    rms = np.sqrt(np.mean((got - vy)[inner] ** 2))
    # differenced positions over two periods: 2 mm noise gives ~0.07 m/s; the smoother with the accelerometer far less
    diff = np.gradient(meas["px"], DT) * -np.sin(psi) + np.gradient(meas["py"], DT) * np.cos(psi)
    assert rms < 0.01 and rms < 0.2 * np.sqrt(np.mean((diff - vy)[inner] ** 2))
    # no time shift: the error is smallest unshifted (a shift of 2 ms would show)
    shifted = [np.sqrt(np.mean((got[inner] - np.interp(t[inner] + h, t, vy)) ** 2)) for h in (-0.004, 0.0, 0.004)]
    assert shifted[1] < min(shifted[0], shifted[2])


def test_a_constant_accelerometer_offset_is_taken_up():
    """A banked road: the flat accelerometer misses gravity's lateral part (here 1.5 m/s^2 in the body's y)."""
    _, psi, vy, meas = weave(offset=(0.0, -1.5))
    got = smoothed(psi, meas)
    assert np.sqrt(np.mean((got - vy)[100:-100] ** 2)) < 0.02


def test_missing_gnss_rows_are_predicted_through_and_segments_are_apart():
    _, psi, vy, meas = weave(n=1000)
    meas["px"][300:320] = np.nan
    meas["py"][300:320] = np.nan
    seg = np.r_[np.zeros(500, int), np.ones(498, int), np.full(2, 2)]
    got = smoothed(psi, meas, seg)
    assert np.isfinite(got[:998]).all() and np.isnan(got[998:]).all()   # a 2-row segment: too short, NaN
    assert np.sqrt(np.mean((got[300:320] - vy[300:320]) ** 2)) < 0.02


def test_the_noise_levels_are_read_from_the_log():
    _, psi, _, meas = weave(gnss=0.005, acc=0.2, seed=3, w=2.3)   # a slow weave: little jerk
    c, s = np.cos(psi), np.sin(psi)
    aw_x, aw_y = c * meas["ax"] - s * meas["ay"], s * meas["ax"] + c * meas["ay"]
    g, a = ins.noise_levels(meas["px"], meas["py"], aw_x, aw_y, meas["ax"], meas["ay"], DT)
    assert g == pytest.approx(0.005, rel=0.1)
    assert a == pytest.approx(0.2, rel=0.1)
