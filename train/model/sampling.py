"""Random points of a vehicle's operating envelope, for cross-checks between implementations.

Covers the awkward corners on purpose: vx exactly 0, |vx| below the model's v_min,
reversing, large slip, inputs and coefficients anywhere in their limits and ranges.
"""
from __future__ import annotations

import numpy as np

from ddyn.model.single_track import N_COEFF
from ddyn.model.vehicle import Vehicle


def random_cases(vehicle: Vehicle, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(states (n, 8), inputs (n, 2), coeffs (n, 17)) spread over the vehicle's envelope."""
    vmax, vmin = vehicle.max_speed, vehicle.known.v_min
    lim = vehicle.input_limits
    vx = rng.uniform(-0.1 * vmax, vmax, n)
    # a fifth of the cases at or near standstill, where the slip angles are delicate
    slow = rng.random(n) < 0.2
    vx[slow] = rng.uniform(-2 * vmin, 2 * vmin, slow.sum())
    vx[: max(1, n // 50)] = 0.0
    states = np.column_stack([
        rng.uniform(-100, 100, n) * vmax / 40,      # x
        rng.uniform(-100, 100, n) * vmax / 40,      # y
        rng.uniform(-np.pi, np.pi, n),              # yaw
        vx,
        rng.uniform(-0.3, 0.3, n) * np.maximum(np.abs(vx), vmin),   # vy: up to ~17 deg body slip
        rng.uniform(-3, 3, n) * vmax / vehicle.known.lf / 40,       # omega
        rng.uniform(*lim["throttle"], n),
        rng.uniform(*lim["steering"], n),
    ])
    inputs = np.column_stack([rng.uniform(*lim["dthrottle"], n), rng.uniform(*lim["dsteering"], n)])
    lo, hi = vehicle.range_arrays()
    coeffs = lo + (hi - lo) * rng.random((n, N_COEFF))
    return states, inputs, coeffs
