"""The drivetrain's longitudinal force at full pedal and full brake along the speed, for the racing line's first
guess (ddyn.control.raceline.speed_profile) and the tracker's braking limit (ddyn.control.mpc_setup).

Read from the model's own drivetrain_force, so every drivetrain form (ddyn.model.single_track.DRIVETRAINS) gets
its own physics: before, both places wrote the papers' (Cm1 - Cm2 v) by hand, which for the power_limited form
(Cm2 a power in W) is a large negative force, so a SIL run of such a vehicle built a line of zero speed. For the
papers' form the arithmetic is the same as the hand-written one, operation for operation.
"""
from __future__ import annotations

import math

from ddyn.errors import DdynError
from ddyn.model.mathns import NUMPY
from ddyn.model.single_track import drivetrain_force
from ddyn.model.vehicle import Vehicle

TOP_SPEED_CEILING = 1000.0      # m/s: a bracket for the bisection, far above any car
BISECTION_STEPS = 200           # halvings of the bracket: below float resolution long before


def longitudinal_force(vehicle: Vehicle, v: float, pedal: float) -> float:
    """The drivetrain's force (N) at speed v and pedal in [-1, 1] (1 full throttle, -1 full brake), with the
    vehicle file's true coefficients."""
    c = vehicle.true_coefficients
    if c is None:
        raise DdynError(f"vehicle {vehicle.name!r} has no true coefficients to drive with")
    return float(drivetrain_force(v, pedal, c["Cm1"], c["Cm2"], c["Cr0"], c["Cd"], NUMPY, vehicle.known))


def top_speed(vehicle: Vehicle) -> float:
    """The speed at which full pedal balances the resistances: the papers' form's closed solution of
    Cd v^2 + Cm2 v - (Cm1 - Cr0) = 0, otherwise a bisection of the force (bounded: BISECTION_STEPS)."""
    c = vehicle.true_coefficients
    if vehicle.known.drivetrain == "papers":
        a, b, k = c["Cd"], c["Cm2"], c["Cm1"] - c["Cr0"]
        return (-b + math.sqrt(b * b + 4 * a * k)) / (2 * a)
    lo, hi = 0.0, TOP_SPEED_CEILING
    if longitudinal_force(vehicle, lo, 1.0) <= 0.0:
        raise DdynError(f"vehicle {vehicle.name!r}: full pedal does not move the car from rest (its drivetrain's "
                        "true coefficients)")
    if longitudinal_force(vehicle, hi, 1.0) > 0.0:
        raise DdynError(f"vehicle {vehicle.name!r}: full pedal still accelerates at {hi:g} m/s (no drag?)")
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if longitudinal_force(vehicle, mid, 1.0) > 0.0 else (lo, mid)
    return lo
