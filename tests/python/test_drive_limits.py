"""The drivetrain's full-pedal and full-brake forces the racing line's guess and the tracker's speed limit read
(ddyn.control.drive_limits): every drivetrain form through the model's own force, the papers' form unchanged."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ddyn.control.drive_limits import longitudinal_force, top_speed
from ddyn.errors import DdynError
from ddyn.model.vehicle import load


@pytest.mark.parametrize("name", ["av21", "orca_1_43"])
def test_the_papers_form_gives_the_hand_written_arithmetic_bit_for_bit(name):
    v = load(name)
    c = v.true_coefficients
    for speed in np.linspace(0.0, 40.0, 17):
        brake = (c["Cm1"] - c["Cm2"] * speed) + c["Cr0"] + c["Cd"] * speed * speed      # what mpc_setup wrote
        assert -longitudinal_force(v, float(speed), -1.0) == brake
    a, b, k = c["Cd"], c["Cm2"], c["Cm1"] - c["Cr0"]
    assert top_speed(v) == (-b + np.sqrt(b * b + 4 * a * k)) / (2 * a)
    assert longitudinal_force(v, 0.0, 1.0) == c["Cm1"] - c["Cr0"]


def test_the_power_limited_form_brakes_through_its_brake_gain_and_tops_out_where_power_meets_drag():
    v = load("av21_power")
    c = v.true_coefficients
    top = top_speed(v)
    # at the top speed the wheel power over speed balances the resistances (power-limited there)
    assert c["Cm2"] / top == pytest.approx(c["Cr0"] + c["Cd"] * top * top, rel=1e-9)
    assert abs(longitudinal_force(v, top, 1.0)) < 1e-6 and longitudinal_force(v, 0.9 * top, 1.0) > 0.0
    # full brake: the known brake gain plus the resistances, not the drive's (Cm1 - Cm2 v), which the hand-written
    # papers' formula read as a force of minus hundreds of kN for Cm2 in W
    assert -longitudinal_force(v, 20.0, -1.0) == pytest.approx(v.known.brake_gain + c["Cr0"] + c["Cd"] * 400.0)
    # from rest full pedal gives the traction cap less the resistance
    assert longitudinal_force(v, 0.0, 1.0) == pytest.approx(c["Cm1"] - c["Cr0"])


def test_a_drivetrain_that_cannot_move_the_car_is_one_line():
    v = load("av21_power")
    stuck = dataclasses.replace(v, true_coefficients={**v.true_coefficients, "Cr0": 1e6})
    with pytest.raises(DdynError, match="full pedal does not move the car"):
        top_speed(stuck)
