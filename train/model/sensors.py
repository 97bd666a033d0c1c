"""Measurement models of the car's sensors, written once against a math namespace (like ddyn.model.single_track).

Each model maps the 8-component state (and the coefficients, where the physics
enters) to what a sensor reads. `ddyn codegen model` turns them, with their Jacobians,
into C for the car's EKF; numpy evaluates them for simulated sensor data.

  gnss_position  (x, y) of the reference point, m
  heading        yaw, rad (innovations are wrapped to [-pi, pi) by the filter)
  yaw_rate       omega, rad/s (IMU gyro)
  acceleration   (ax, ay) body-frame acceleration, m/s^2 (IMU accelerometer):
                 ax = dvx - vy omega, ay = dvy + vx omega, from the model's own forces
  wheel_speed    (v_front, v_rear): longitudinal speed of the front wheel plane,
                 vx cos(delta) + (vy + lf omega) sin(delta), and of the rear axle, vx; m/s
  steering       delta, rad (steering angle sensor)
"""
from __future__ import annotations

from typing import Sequence

from ddyn.model.mathns import MathNamespace
from ddyn.model.single_track import KnownParams, derivatives

MEASUREMENTS = {
    "gnss_position": 2,
    "heading": 1,
    "yaw_rate": 1,
    "acceleration": 2,
    "wheel_speed": 2,
    "steering": 1,
}


def measure(ns: MathNamespace, name: str, state: Sequence, coeffs: Sequence, p: KnownParams) -> tuple:
    x, y, yaw, vx, vy, omega, _, delta = state
    if name == "gnss_position":
        return (x, y)
    if name == "heading":
        return (yaw,)
    if name == "yaw_rate":
        return (omega,)
    if name == "acceleration":
        d = derivatives(ns, state, (0.0, 0.0), coeffs, p)  # the input rates do not enter dvx, dvy
        return (d[3] - vy * omega, d[4] + vx * omega)
    if name == "wheel_speed":
        return (vx * ns.cos(delta) + (vy + p.lf * omega) * ns.sin(delta), vx)
    if name == "steering":
        return (delta,)
    raise ValueError(f"unknown measurement {name!r}; expected one of {', '.join(MEASUREMENTS)}")
