"""Is a logged roll (or pitch) channel plausible enough to read the road's bank (grade) from it?

Why: a roll channel (an EKF's roll, relative to gravity) is the road's bank plus the body's roll on its
springs, so on a banked track it gives the bank profile directly, with no fit along the track. The RACECAR
Putnam log has a `roll` column that is not trustworthy (shared/data/README.md: it spans -1.9 to 2.3 rad),
so a channel is used only when it passes three checks:

  range   the 99.9th percentile of |roll| is at most MAX_ABS: steeper than any paved bank
          (Talladega's 33 degrees, 0.58 rad) plus a saloon's body roll is not a road;
  rate    the 99th percentile of |d roll / dt| is at most MAX_RATE: banks change over tens of metres and
          body roll follows the lateral acceleration; a channel that jumps faster is noise or wraps;
  drift   the linear trend over the log changes roll by at most MAX_DRIFT: a road's bank returns to itself
          each lap, an integrating sensor's error does not;
  lateral when the lateral acceleration vx omega is known, roll regressed on a constant and it (bank into
          the turns, body roll out of them): the slope must be at most MAX_PER_G rad per g (a bank of
          0.6 rad taken at 0.6 g, the steepest pairing a banked turn gives), and the fit must leave at most
          MAX_UNEXPLAINED of roll's spread unless that spread is small (< MAX_ABS / 10): a channel
          unrelated to the car's motion, or scaled wrongly, is not the car's roll.
The thresholds are physical bounds, not fitted to any log.
"""
from __future__ import annotations

import numpy as np

MAX_ABS = 0.7            # rad
MAX_RATE = 1.0           # rad/s
MAX_DRIFT = 0.2          # rad over the log
MAX_UNEXPLAINED = 0.9    # share of roll's standard deviation left by const + k a_y
MAX_PER_G = 1.0          # rad/g


def check(roll, time, lateral_acceleration=None, label: str = "roll", motion: str = "lateral") -> dict:
    """The checks' figures and the verdict {plausible, failed: [names], reason: text}. label, motion: the
    channel's and the acceleration's names (a pitch channel: "pitch" against the "longitudinal" acceleration,
    the same physical bounds: a grade is steeper than no bank, and a body pitches less than it rolls)."""
    r = np.asarray(roll, float)
    t = np.asarray(time, float)
    out: dict = {"thresholds": {"max_abs_rad": MAX_ABS, "max_rate_rad_s": MAX_RATE, "max_drift_rad": MAX_DRIFT,
                                "max_unexplained": MAX_UNEXPLAINED,
                                "max_rad_per_g": MAX_PER_G}}
    ok = np.isfinite(r) & np.isfinite(t)
    if ok.sum() < 10:
        return out | {"plausible": False, "failed": ["finite"], "reason": f"fewer than 10 finite {label} samples"}
    r, t = r[ok], t[ok]
    failed = []
    out["abs_p999_rad"] = float(np.percentile(np.abs(r), 99.9))
    if out["abs_p999_rad"] > MAX_ABS:
        failed.append("range")
    if np.max(np.abs(r)) > 1e3:
        # not an angle in radians at all: the rate, drift and regression below would only overflow
        return out | {"plausible": False, "failed": failed or ["range"],
                      "reason": f"{label} reaches {np.max(np.abs(r)):.3g} rad: not an angle (range limit {MAX_ABS} rad)"}
    dt = np.diff(t)
    good = dt > 0
    rate = np.abs(np.diff(r))[good] / dt[good]
    out["rate_p99_rad_s"] = float(np.percentile(rate, 99)) if len(rate) else 0.0
    if out["rate_p99_rad_s"] > MAX_RATE:
        failed.append("rate")
    slope = float(np.polyfit(t - t[0], r, 1)[0]) if np.ptp(t) > 0 else 0.0
    out["drift_rad"] = slope * float(np.ptp(t))
    if abs(out["drift_rad"]) > MAX_DRIFT:
        failed.append("drift")
    ay = None if lateral_acceleration is None else np.asarray(lateral_acceleration, float)[ok]
    fin = None if ay is None else np.isfinite(ay) & (np.abs(ay) < 1e3)   # an acceleration a car can have
    if ay is not None and fin.sum() >= 10:
        ay, r = ay[fin], r[fin]
        A = np.column_stack([np.ones_like(ay), ay])
        coef, *_ = np.linalg.lstsq(A, r, rcond=None)
        spread = float(np.std(r))
        out["unexplained_share"] = float(np.std(r - A @ coef) / spread) if spread > 0 else 0.0
        per_g = f"{label}_per_{motion}_g_rad"
        out[per_g] = float(coef[1] * 9.81)
        if (spread >= MAX_ABS / 10 and out["unexplained_share"] > MAX_UNEXPLAINED) or abs(out[per_g]) > MAX_PER_G:
            failed.append(motion)
    names = {"range": f"|{label}| reaches {out['abs_p999_rad']:.2f} rad (> {MAX_ABS} rad)",
             "rate": f"{label} changes at {out['rate_p99_rad_s']:.2f} rad/s (99th percentile, > {MAX_RATE} rad/s)",
             "drift": f"{label} drifts {out['drift_rad']:+.2f} rad over the log (> {MAX_DRIFT} rad)",
             motion: f"{label} moves {out.get(f'{label}_per_{motion}_g_rad', 0):.2f} rad per g of {motion} "
                     f"acceleration (limit {MAX_PER_G}) and {100 * out.get('unexplained_share', 0):.0f} % of its "
                     f"spread is unrelated to it (limit {100 * MAX_UNEXPLAINED:.0f} %)"}
    reason = "; ".join(names[f] for f in failed) if failed else f"range, rate, drift and {motion} checks passed"
    return out | {"plausible": not failed, "failed": failed, "reason": reason}


def check_dataset(ds, channel: str = "roll") -> dict | None:
    """check() on a dataset's extra channel (None when the log has none): "roll" against vx omega as the
    lateral acceleration, "pitch" against dvx/dt - vy omega as the longitudinal one."""
    if channel not in ds.extras:
        return None
    with np.errstate(over="ignore", invalid="ignore"):   # a corrupt log's states: the check reports them
        if channel == "pitch":
            vx = ds.states[:, 3]
            a = (np.gradient(vx, ds.sample_time) if len(vx) > 1 else np.zeros_like(vx)) - ds.states[:, 4] * ds.states[:, 5]
            return {"channel": channel, **check(ds.extras[channel], ds.time, a, "pitch", "longitudinal")}
        ay = ds.states[:, 3] * ds.states[:, 5]
    return {"channel": channel, **check(ds.extras[channel], ds.time, ay)}
