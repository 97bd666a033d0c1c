"""`hold = "estimate"`: the drive-by-wire command hold estimated from the log, not assumed.

Why: `--hold` gives every hypothesis half a log sample of delay on throttle and steering, the average lag of
commands held for one log sample behind the ramp the model integrates between samples. A DBW unit that runs
faster than the log (a 50 or 100 Hz unit logged at 25 Hz) holds each command for less than a log sample: its
staircase lags the smooth command by half ITS period, so the assumed half sample is too much and the excess
is taken from the delay estimates (or read as a lead the delay candidates cannot fit). So:

  step structure   when the logged commands repeat in runs of m equal samples while they change (a DBW unit
                   slower than the log), the unit's period is m log samples (reported; detect_period);
  hold delay       the effective hold delay, one value for both commands, fitted as a parameter of the
                   nominal: the nominal's fit-part cost (Df, Dr refitted, as under every hypothesis) on a grid
                   over [0, Ts/2], refined by a parabola through the best three points. The upper bound is the
                   log-rate hold: a unit at the log's rate or faster cannot lag by more, and a real actuator delay
                   on top (which the grid would otherwise absorb, a hold and a delay look alike) is left to the
                   delay candidates, which then estimate it on top of the bound, as with `--hold`.

`hold = "steps"`: half the command period the step structure shows (a unit at the log's rate: half a sample; one
holding each command for m samples: m/2). What the family calibration uses: on its plants the fitted hold read
either 0 or its bound (the nominal's cost hardly moves over [0, Ts/2], and a real delay in the log does not move it
to the bound), and a delay's estimate took the difference (+0.02-0.03 s on 40 ms delays at 25 Hz). Its limit: a unit
faster than the log, fed smooth commands, lags by less than half a sample, which the log cannot show; its delays
then read up to half a sample long.

The estimate also takes up what acts like a short delay in the plant (a fast steering servo's lag); it is the
delay the log's commands show, reported in diagnosis.json (`nominal.hold_estimate`).
"""
from __future__ import annotations

import numpy as np

GRID_STEPS = 8          # grid points above zero over [0, Ts/2]


def detect_period(ds, min_change: float = 1e-9) -> dict:
    """Run lengths of equal consecutive logged commands (throttle, steering) while they change: the DBW
    period in log samples when the unit is slower than the log (1: one new command per sample)."""
    runs = []
    for col in (6, 7):
        u = np.asarray(ds.states[:, col], float)
        change = np.abs(np.diff(u)) > min_change
        idx = np.flatnonzero(change)
        if len(idx) > 10:
            runs.append(np.diff(idx))
    if not runs:
        return {"samples": None, "period_s": None, "note": "the commands hardly change: no step structure"}
    r = np.concatenate(runs)
    m = int(np.median(r))
    return {"samples": m, "period_s": m * float(ds.sample_time),
            "share_of_runs_at_median": float(np.mean(r == m))}


def from_steps(ds) -> dict:
    """The hold of `hold = "steps"`: {hold (s), rule, dbw_period_from_steps}."""
    period = detect_period(ds)
    m = period["samples"] or 1
    return {"hold": 0.5 * m * float(ds.sample_time), "rule": "half the logged command period",
            "dbw_period_from_steps": period}


def estimate(make_problem, fit, sample_time: float, steps: int = GRID_STEPS) -> dict:
    """make_problem(hold seconds) -> a diagnosis Problem; fit(problem) -> a Fit (its .cost: the fit part's).
    Returns {hold (s), grid [[hold, cost]], at_bound}."""
    grid = np.linspace(0.0, 0.5 * sample_time, steps + 1)
    costs = np.array([fit(make_problem(float(h))).cost for h in grid])
    i = int(np.argmin(costs))
    best = float(grid[i])
    if 0 < i < len(grid) - 1:       # parabola through the best three points
        c0, c1, c2 = costs[i - 1:i + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best = float(grid[i] + 0.5 * (grid[1] - grid[0]) * (c0 - c2) / den)
    return {"hold": best, "grid": [[float(h), float(c)] for h, c in zip(grid, costs)],
            "at_bound": i == len(grid) - 1, "bound": float(grid[-1])}
