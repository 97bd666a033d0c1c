"""The reference every prediction figure is read against: nothing changes (constant velocity and yaw rate).

A one-step RMSE of vx, vy or omega means little alone: on a log sampled fast against the car's dynamics the next
state is close to the current one, and on a noisy log the noise sets a floor no model can pass. The reference is
what a user gets for free: the body velocities (vx, vy) and the yaw rate stay as they are, so the one-step
prediction is the current state, and the position rolls forward on the arc those constant values trace (the
exact solution, no step size). It is scored on exactly the windows and starts `ddyn evaluate` scores a model on
(same history length, same horizon), so the two read side by side. A model worse than it on a channel predicts
changes of that channel that do not happen.

Measured on the real Putnam log's held-out conditions (results/ddm_real_heldout.json, reference_* figures), this
reference beats the trained DDMs on vy and omega at their worst seed on lap 1 and above 20 m/s, and on lap 2 all but
the powertrain settings with five rows of history; every DDM wins vx and the positions (ADE, FDE).
"""
from __future__ import annotations

import numpy as np

from ddyn.data.dataset import Dataset
from ddyn.data.windows import TARGET_NAMES, rollout_starts, valid_end_rows

NAME = "nothing changes (constant vx, vy and yaw rate)"
# below this |omega * t| (rad) the arc's closed form loses digits to cancellation: its series is used instead
_SMALL_TURN = 1e-6


def arc_displacement(vx, vy, omega, yaw, t):
    """World-frame displacement (dx, dy) after time t of a body moving at constant body-frame velocity (vx, vy)
    and yaw rate omega from heading yaw: the integral of R(yaw + omega s) (vx, vy) over s in [0, t]."""
    vx, vy, omega, yaw = (np.asarray(a, dtype=float) for a in (vx, vy, omega, yaw))
    turn = omega * t
    small = np.abs(turn) < _SMALL_TURN
    safe = np.where(small, 1.0, omega)
    # integral of (cos(omega s), sin(omega s)) ds: (sin(turn) / omega, (1 - cos(turn)) / omega); the series
    # t (1, turn / 2) where the turn is tiny
    c = np.where(small, t, np.sin(turn) / safe)
    s = np.where(small, 0.5 * turn * t, (1.0 - np.cos(turn)) / safe)
    # body-frame displacement, then rotated by the start heading
    bx, by = c * vx - s * vy, s * vx + c * vy
    return np.cos(yaw) * bx - np.sin(yaw) * by, np.sin(yaw) * bx + np.cos(yaw) * by


def constant_motion_errors(ds: Dataset, tau: int, steps: int, max_starts: int = 20000) -> dict:
    """The reference's figures on ds, on the windows and starts ddyn.learn.evaluate scores a model of history tau
    and horizon `steps` on: one-step RMSE and max |error| of vx, vy, omega, and ADE / FDE (m) of the position."""
    k = valid_end_rows(ds, tau)
    out = {"name": NAME, "samples": int(len(k))}
    if len(k):
        err = ds.states[k + 1, 3:6] - ds.states[k, 3:6]
        out["rmse"] = dict(zip(TARGET_NAMES, np.sqrt((err ** 2).mean(axis=0)).tolist()))
        out["max_error"] = dict(zip(TARGET_NAMES, np.abs(err).max(axis=0).tolist()))
    k = rollout_starts(ds, tau, steps, max_starts)     # the starts ddyn.learn.evaluate.rollout_errors uses
    if len(k) == 0:
        return out | {"ade": float("nan"), "fde": float("nan"), "starts": 0}
    x0, y0, yaw0, vx, vy, omega = (ds.states[k, i] for i in range(6))
    errs = []
    for j in range(1, steps + 1):
        dx, dy = arc_displacement(vx, vy, omega, yaw0, j * ds.sample_time)
        errs.append(np.hypot(x0 + dx - ds.states[k + j, 0], y0 + dy - ds.states[k + j, 1]))
    e = np.array(errs)
    return out | {"ade": float(e.mean()), "fde": float(e[-1].mean()), "starts": int(len(k))}


def format_reference(r: dict) -> str:
    """One line for `ddyn evaluate`: the reference's figures in the summary's units."""
    if "rmse" not in r:
        return f"  reference, {r['name']}: no window"
    return (f"  reference, {r['name']}: vx {r['rmse']['vx']:.3e}  vy {r['rmse']['vy']:.3e}  "
            f"omega {r['rmse']['omega']:.3e}  ADE {r['ade']:.3e} m  FDE {r['fde']:.3e} m")
