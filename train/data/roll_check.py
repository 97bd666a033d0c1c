"""Is a logged roll (or pitch) channel plausible enough to read the road's bank (grade) from it?

Why: a roll channel (an EKF's roll relative to gravity, or a value looked up in a map of the track) is the
road's bank, plus the body's roll on its springs when it is measured, so on a banked track it gives the bank
profile directly, with no fit along the track. The RACECAR Putnam log has a `roll` column that is not
trustworthy (shared/data/README.md: it spans -1.9 to 2.3 rad); the bank of a banked oval is not a sign of a
bad channel, although it moves with the lateral acceleration (the turns are both banked and fast: on the real
oval of the issue roll and vx omega correlate at -0.94, 1.15 rad per g across the lap). What tells them apart
is the road: its bank is the same at the same spot lap after lap, a broken channel's is not.

The rule with laps (the log drives a closed circuit and covers at least MIN_REPEAT of its lap on two laps or
more; positions along the lap from ddyn.data.laps, or the caller's). Every pass through a BIN-metre stretch of
the lap gives one visit (the mean channel and lateral acceleration a_y over its rows); visits are fitted as
bank(stretch) + k a_y (least squares, one bank per stretch and one body-roll gradient k: k is set by how the
channel differs between laps at the same spot as a_y does, never by the bank's match with the turns):

  range   the 99.9th percentile of |roll| is at most MAX_ABS (Talladega's 33 degrees plus a saloon's body
          roll), and the fitted bank nowhere steeper than MAX_BANK (35 degrees: no paved road is);
  rate    the 99th percentile of |d roll / dt| (over RATE_WINDOW, 0.25 s, so that a map's steps of a sample are
          not read as a rate) is at most MAX_RATE: banks change over tens of metres and body roll follows a_y
          within tenths of a second; a channel that moves faster is noise or wraps;
  repeat  the visits' RMS about the fit (degrees of freedom counted: a stretch's bank is fitted from its
          visits) is at most MAX_REPEAT_RMS: what position does not explain must be body roll (k a_y) plus
          noise. 1.4 degrees is an EKF roll's noise (0.2 degrees), a position off by the line's few metres on
          a bank ramp of 0.2 degrees per metre, a map's steps and a body roll that lags a_y, with margin; a
          drifting or jumping channel leaves tenths of a radian;
  drift   the laps' mean offsets from the fit (the same spot, lap after lap) span at most MAX_LAP_SHIFT: a road
          does not move, an integrating sensor's error does;
  body    |k| is at most MAX_BODY_PER_G, either sign (a channel may log roll either way round), unless it is
          undetermined: it fails only when beyond the limit by two of its standard errors. A saloon rolls 3-7
          degrees per g, the softest car about 10, a race car 1-2; more is a scaled or unrelated channel.

The rule without laps (no closed circuit, a single lap, or too little of the lap covered twice): a bank cannot
be told from a drift without a second pass, so the channel is judged by bounds alone, conservatively (a real
bank that follows the turns closely, as a banked oval's does, can fail the lateral check; a drifting or
unrelated channel never passes): range and rate as above, and

  drift   the linear trend over the log changes roll by at most MAX_DRIFT;
  lateral roll regressed on a constant and a_y: the slope at most MAX_PER_G rad per g (a bank of 0.6 rad taken
          at 0.6 g, the steepest pairing a banked turn gives), and the fit must leave at most MAX_UNEXPLAINED of
          roll's spread unless that spread is small (< MAX_ABS / 10): a channel unrelated to the car's motion,
          or scaled wrongly, is not the car's roll;
  gravity a pitch channel that fails the share above passes when its grade shows in the car's acceleration
          (gravity_fit: a_x on the drivetrain's terms and g sin(pitch), a coefficient of size GRAVITY_RANGE
          around the physical 1, GRAVITY_SIGMAS standard errors from 0). Why: on a grade of 5 degrees or more
          the channel spreads far beyond a body's pitch and the throttle, not the grade, sets most of a_x, so a
          map's or an IMU's grade failed the share on every log without laps (the study's 7.8 and 8.5 degree
          grades of 60 and 120 s); a channel unrelated to the road leaves a coefficient near 0.

Flat (either rule, a plausible channel only): the bank is below FLAT (3 degrees) nearly everywhere (the
99th percentile over the stretches, the channel's mean per stretch) once a body roll k a_y is taken off, for
the k within the limits that makes it flattest (with laps, k within two standard errors of its estimate; without,
any |k| <= MAX_BODY_PER_G). The verdict is then "flat": the channel is plausible, but says the road is flat,
and a bank read from it is never added (ddyn.gap.candidates.available).

A pitch channel is checked the same way against the longitudinal acceleration ("pitch", "longitudinal"), with
the same physical bounds (a grade is steeper than no bank, a body pitches less than it rolls). The thresholds
are physical bounds, not fitted to any log.
"""
from __future__ import annotations

import math

import numpy as np

MAX_ABS = 0.7            # rad
MAX_RATE = 1.0           # rad/s
RATE_WINDOW = 0.25       # s over which the rate is measured
MAX_DRIFT = 0.2          # rad over the log (no laps)
MAX_UNEXPLAINED = 0.9    # share of roll's standard deviation left by const + k a_y (no laps)
MAX_PER_G = 1.0          # rad/g (no laps)
MAX_BANK = math.radians(35.0)       # rad: the steepest paved bank (Talladega 33 degrees) with margin
BIN = 5.0                # m: one stretch of the lap (a bank changes over tens of metres)
MIN_REPEAT = 0.5         # share of the lap covered on two laps or more for the repeat rule
MAX_REPEAT_RMS = 0.025   # rad (1.4 degrees) of a visit about bank(position) + k a_y
MAX_LAP_SHIFT = 0.035    # rad (2 degrees) between the laps' mean offsets
MAX_BODY_PER_G = 0.25    # rad/g (14 degrees per g): the softest car's body roll with margin
# a pitch channel's grade shows in the longitudinal acceleration (gravity_fit) when its coefficient's size is
# within this range of the physical 1 (a pitch channel may carry body pitch, the drivetrain terms are
# approximate) and this many standard errors from 0
GRAVITY_RANGE = (0.5, 1.5)
GRAVITY_SIGMAS = 5.0
# rad: a bank below this nearly everywhere is no bank that matters: the size that matters of a bank or grade
# (ddyn.gap.limits.SIZES; fixed by the issue, not tuned). It was 0.5 degrees until 2026-11-29: on flat Putnam
# the body roll the k a_y term does not take off (a physics-engine car's roll lags a_y; a multi-body car's IMU)
# left 0.4-2.5 degrees, and a bank read from such channels was claimed on 5 flat logs of the family study (a
# banked oval's channels: 12-17 degrees)
FLAT = math.radians(3.0)
G = 9.81


def _thresholds() -> dict:
    return {"max_abs_rad": MAX_ABS, "max_rate_rad_s": MAX_RATE, "rate_window_s": RATE_WINDOW, "max_drift_rad": MAX_DRIFT,
            "max_unexplained": MAX_UNEXPLAINED, "max_rad_per_g": MAX_PER_G, "max_bank_rad": MAX_BANK,
            "bin_m": BIN, "min_repeat_cover": MIN_REPEAT, "max_repeat_rms_rad": MAX_REPEAT_RMS,
            "max_lap_shift_rad": MAX_LAP_SHIFT, "max_body_rad_per_g": MAX_BODY_PER_G, "flat_rad": FLAT}


def _flattest(b, a, k_lo, k_hi) -> tuple[float, float]:
    """(k, 99th percentile of |b - k a|) for the k in [k_lo, k_hi] that makes it smallest (b, a per stretch)."""
    if len(b) == 0:
        return 0.0, 0.0
    ks = np.unique(np.r_[np.linspace(k_lo, k_hi, 201), np.clip(0.0, k_lo, k_hi)])
    vals = np.percentile(np.abs(b[None, :] - ks[:, None] * a[None, :]), 99, axis=1)
    i = int(np.argmin(vals))
    return float(ks[i]), float(vals[i])


def _visits(key, values: list[np.ndarray]):
    """Means of each value over the rows sharing a key: (unique keys, [means], counts)."""
    uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    return uk, [np.bincount(inv, weights=v) / cnt for v in values], cnt


def gravity_fit(pitch, longitudinal_acceleration, throttle, speed) -> dict | None:
    """How the car's longitudinal acceleration follows a pitch channel's grade: a_x regressed on the drivetrain's
    terms (a constant, the throttle's positive part, its square and over the speed (a power limit), its negative
    part (the brake), the speed squared (drag)) and g sin(pitch). On a real grade the last coefficient is -1
    (climbing slows the car by g sin(grade)); a channel unrelated to the road gives about 0. None: too few rows."""
    y = np.asarray(longitudinal_acceleration, float)
    u = np.asarray(throttle, float)
    v = np.abs(np.asarray(speed, float))
    p = np.asarray(pitch, float)
    ok = np.isfinite(y) & np.isfinite(u) & np.isfinite(v) & np.isfinite(p) & (np.abs(y) < 1e3) & (np.abs(p) < 1e3)
    if ok.sum() < 50:
        return None
    y, u, v, p = y[ok], u[ok], v[ok], p[ok]
    up = np.maximum(u, 0.0)
    A = np.column_stack([np.ones_like(y), up, up * up, up / np.maximum(v, 5.0), np.minimum(u, 0.0), v * v,
                         G * np.sin(p)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    e = y - A @ coef
    dof = max(len(y) - A.shape[1], 1)
    try:
        cov = np.linalg.inv(A.T @ A) * float(e @ e) / dof
    except np.linalg.LinAlgError:
        return None
    se = float(math.sqrt(max(cov[-1, -1], 0.0)))
    return {"gravity_coefficient": float(coef[-1]), "gravity_coefficient_std": se}


def _gravity_shows(gf: dict | None) -> bool:
    """The channel's grade shows in the acceleration: its coefficient's size within GRAVITY_RANGE of the physical
    1 (either sign: a channel may log pitch either way round, as a roll channel may) and GRAVITY_SIGMAS standard
    errors from 0."""
    if not gf:
        return False
    c, se = abs(gf["gravity_coefficient"]), gf["gravity_coefficient_std"]
    return GRAVITY_RANGE[0] <= c <= GRAVITY_RANGE[1] and (se == 0.0 or c / se >= GRAVITY_SIGMAS)


def check(roll, time, lateral_acceleration=None, label: str = "roll", motion: str = "lateral",
          position=None, lap=None, lap_length: float | None = None, gravity: dict | None = None) -> dict:
    """The checks' figures and the verdict {plausible, flat, verdict, rule, failed: [names], reason: text}.
    label, motion: the channel's and the acceleration's names ("pitch" against the "longitudinal"
    acceleration). position (m along the lap, in [0, lap_length)), lap (lap number per row), lap_length: the
    rows' places on a closed circuit (the rule with laps); without them, or with too few laps, the rule
    without laps (position alone, e.g. the distance travelled, only bins the flatness check). gravity: a pitch
    channel's gravity_fit; when the grade shows in the acceleration (_gravity_shows) the rule without laps does
    not reject the channel for being unrelated to the acceleration."""
    r = np.asarray(roll, float)
    t = np.asarray(time, float)
    out: dict = {"thresholds": _thresholds()}
    ok = np.isfinite(r) & np.isfinite(t)
    if ok.sum() < 10:
        return out | {"plausible": False, "flat": False, "verdict": "implausible", "rule": "none",
                      "failed": ["finite"], "reason": f"fewer than 10 finite {label} samples"}
    r, t = r[ok], t[ok]
    failed = []
    out["abs_p999_rad"] = float(np.percentile(np.abs(r), 99.9))
    if out["abs_p999_rad"] > MAX_ABS:
        failed.append("range")
    if np.max(np.abs(r)) > 1e3:
        # not an angle in radians at all: the rate, drift and regression below would only overflow
        return out | {"plausible": False, "flat": False, "verdict": "implausible", "rule": "none",
                      "failed": failed or ["range"],
                      "reason": f"{label} reaches {np.max(np.abs(r)):.3g} rad: not an angle (range limit {MAX_ABS} rad)"}
    # the rate over RATE_WINDOW (not sample to sample: a map's small steps are one sample long)
    span = t <= t[-1] - RATE_WINDOW
    rate = np.abs(np.interp(t[span] + RATE_WINDOW, t, r) - r[span]) / RATE_WINDOW if np.all(np.diff(t) > 0) else \
        np.abs(np.diff(r))[np.diff(t) > 0] / np.diff(t)[np.diff(t) > 0]
    out["rate_p99_rad_s"] = float(np.percentile(rate, 99)) if len(rate) else 0.0
    if out["rate_p99_rad_s"] > MAX_RATE:
        failed.append("rate")
    a = np.zeros_like(r) if lateral_acceleration is None else np.asarray(lateral_acceleration, float)[ok]
    have_a = lateral_acceleration is not None
    a_ok = np.isfinite(a) & (np.abs(a) < 1e3)       # an acceleration a car can have
    if have_a and a_ok.sum() < 10:
        have_a = False
    a = np.where(a_ok, a, 0.0)
    pos = None if position is None else np.asarray(position, float)[ok]
    body = f"body_{label}"
    names: dict = {}
    laps = _lap_rule_inputs(pos, lap, lap_length, ok)
    if laps is not None:
        lp, lap_k, L = laps
        uk, (vr, va, vt), cnt = _visits(lap_k * 100000 + np.floor(lp / BIN).astype(np.int64), [r, a, t])
        vbin, vlap = uk % 100000, uk // 100000
        nb = int(math.ceil(L / BIN))
        laps_at = np.bincount(vbin, minlength=nb)
        rep = laps_at[vbin] >= 2                     # visits of stretches seen on two laps or more
        out["repeat_cover"] = float(np.mean(laps_at >= 2))
        out["laps"] = {"length_m": float(L), "laps_seen": int(len(np.unique(vlap)))}
        if out["repeat_cover"] < MIN_REPEAT:
            laps = None
            out["rule_note"] = (f"the log covers {100 * out['repeat_cover']:.0f} % of its lap on two laps or more "
                                f"(the repeat check needs {100 * MIN_REPEAT:.0f} %): checked without laps")
    if laps is not None:
        out["rule"] = "laps"
        b_rep, r_rep, a_rep = vbin[rep], vr[rep], va[rep]
        inv = np.unique(b_rep, return_inverse=True)[1]
        m_b = np.bincount(inv)

        def demean(v):
            return v - (np.bincount(inv, weights=v) / m_b)[inv]
        rc, ac = demean(r_rep), demean(a_rep)
        saa = float(ac @ ac)
        k = float(rc @ ac / saa) if have_a and saa > 1e-9 else 0.0
        e = rc - k * ac
        dof = max(len(e) - len(m_b) - (1 if have_a else 0), 1)
        rms = float(np.sqrt(e @ e / dof))
        k_se = float(rms / math.sqrt(saa)) if have_a and saa > 1e-9 else float("inf") if have_a else 0.0
        out["repeat_rms_rad"] = rms
        spread = float(np.std(r_rep))
        # the share of the channel's spread that neither the position nor the body roll explains
        out["unexplained_share"] = float(np.sqrt(e @ e / len(e)) / spread) if spread > 0 else 0.0
        # the laps' mean offsets at the same spots
        lap_of = vlap[rep]
        ul, li = np.unique(lap_of, return_inverse=True)
        offs = np.bincount(li, weights=e) / np.bincount(li)
        out["lap_shift_rad"] = float(np.ptp(offs)) if len(offs) > 1 else 0.0
        out["drift_rad"] = out["lap_shift_rad"]
        out[f"{body}_per_g_rad"] = k * G
        out[f"{body}_per_g_std_rad"] = k_se * G
        # the bank per stretch: all visits, body roll off
        sb, (br, ba), _ = _visits(vbin, [vr, va])
        bank = br - k * ba
        out["profile_max_rad"] = float(np.max(np.abs(bank)))
        out["profile_p99_rad"] = float(np.percentile(np.abs(bank), 99))
        if out["profile_max_rad"] > MAX_BANK and "range" not in failed:
            failed.append("range")
        if rms > MAX_REPEAT_RMS:
            failed.append("repeat")
        if out["lap_shift_rad"] > MAX_LAP_SHIFT:
            failed.append("drift")
        if have_a and abs(k * G) - 2 * k_se * G > MAX_BODY_PER_G:
            failed.append(body)
        if have_a:
            lo, hi = (k - 2 * k_se) * G, (k + 2 * k_se) * G
            lo, hi = max(lo, -MAX_BODY_PER_G), min(hi, MAX_BODY_PER_G)
            if lo > hi:
                lo = hi = float(np.clip(k * G, -MAX_BODY_PER_G, MAX_BODY_PER_G))
        else:
            lo = hi = 0.0
        kf, flat_p99 = _flattest(br, ba / G, lo, hi)
        names.update({
            "range": f"|{label}| reaches {out['abs_p999_rad']:.2f} rad, its profile {out['profile_max_rad']:.2f} rad "
                     f"(limits {MAX_ABS}, {MAX_BANK:.2f} rad)",
            "repeat": f"{label} differs by {rms:.3f} rad RMS between laps at the same spot, beyond a body {label} "
                      f"of {k * G:+.3f} rad per g (limit {MAX_REPEAT_RMS} rad): {100 * out['unexplained_share']:.0f} % "
                      f"of its spread unrelated to the position or to body {label}",
            "drift": f"{label} shifts {out['lap_shift_rad']:.3f} rad from lap to lap at the same spots "
                     f"(limit {MAX_LAP_SHIFT} rad)",
            body: f"body {label} of {k * G:+.3f} +- {k_se * G:.3f} rad per g of {motion} acceleration "
                  f"(limit {MAX_BODY_PER_G} rad per g)"})
        passed = (f"follows the lap ({out['laps']['laps_seen']} laps, {100 * out['repeat_cover']:.0f} % of the "
                  f"{L:.0f} m lap seen twice): {rms:.3f} rad RMS between laps, body {label} {k * G:+.3f} rad per g, "
                  f"profile up to {out['profile_max_rad']:.3f} rad")
    else:
        out["rule"] = "no laps"
        slope = float(np.polyfit(t - t[0], r, 1)[0]) if np.ptp(t) > 0 else 0.0
        out["drift_rad"] = slope * float(np.ptp(t))
        if abs(out["drift_rad"]) > MAX_DRIFT:
            failed.append("drift")
        if have_a:
            fin = a_ok
            ay, rr = a[fin], r[fin]
            A = np.column_stack([np.ones_like(ay), ay])
            coef, *_ = np.linalg.lstsq(A, rr, rcond=None)
            spread = float(np.std(rr))
            out["unexplained_share"] = float(np.std(rr - A @ coef) / spread) if spread > 0 else 0.0
            per_g = f"{label}_per_{motion}_g_rad"
            out[per_g] = float(coef[1] * G)
            unrelated = spread >= MAX_ABS / 10 and out["unexplained_share"] > MAX_UNEXPLAINED
            if gravity is not None:
                out["gravity"] = dict(gravity)
                if unrelated and _gravity_shows(gravity):
                    unrelated = False
                    out["gravity"]["waived"] = motion
            if unrelated or abs(out[per_g]) > MAX_PER_G:
                failed.append(motion)
        # flatness on stretches of BIN m (or a quarter second) of the path
        key = np.floor(pos / BIN).astype(np.int64) if pos is not None and np.all(np.isfinite(pos)) \
            else np.floor((t - t[0]) / 0.25).astype(np.int64)
        _, (br, ba), _ = _visits(key, [r, a])
        lim = MAX_BODY_PER_G if have_a else 0.0
        kf, flat_p99 = _flattest(br, ba / G, -lim, lim)
        names.update({
            "range": f"|{label}| reaches {out['abs_p999_rad']:.2f} rad (> {MAX_ABS} rad)",
            "drift": f"{label} drifts {out['drift_rad']:+.2f} rad over the log (> {MAX_DRIFT} rad)",
            motion: f"{label} moves {out.get(f'{label}_per_{motion}_g_rad', 0):.2f} rad per g of {motion} "
                    f"acceleration (limit {MAX_PER_G}) and {100 * out.get('unexplained_share', 0):.0f} % of its "
                    f"spread is unrelated to it (limit {100 * MAX_UNEXPLAINED:.0f} %)"})
        passed = f"range, rate, drift and {motion} checks passed (no laps to compare)"
        if out.get("gravity", {}).get("waived"):
            gv = out["gravity"]
            passed = (f"range, rate and drift checks passed (no laps to compare); {label} is unrelated to the "
                      f"{motion} acceleration's spread, but its grade shows in it: gravity coefficient "
                      f"{gv['gravity_coefficient']:+.2f} +- {gv['gravity_coefficient_std']:.2f} (physical -1, or +1 "
                      f"for a channel logged the other way round)")
    names["rate"] = f"{label} changes at {out['rate_p99_rad_s']:.2f} rad/s (99th percentile, > {MAX_RATE} rad/s)"
    out["flat_p99_rad"] = flat_p99
    out["flat_body_per_g_rad"] = kf
    flat = not failed and flat_p99 < FLAT
    if failed:
        reason = "; ".join(names[f] for f in failed)
    elif flat:
        reason = (f"flat: {label} within {flat_p99:.4f} rad of a body {label} of {kf:+.3f} rad per g nearly "
                  f"everywhere (below {FLAT:.4f} rad, {math.degrees(FLAT):.0f} degrees): no {'bank' if label == 'roll' else 'grade'} "
                  f"to read from it")
    else:
        reason = passed
    if "rule_note" in out:
        reason = f"{out['rule_note']}; {reason}"
    verdict = "implausible" if failed else "flat" if flat else "plausible"
    return out | {"plausible": not failed, "flat": flat, "verdict": verdict, "failed": failed, "reason": reason}


def _lap_rule_inputs(pos, lap, lap_length, ok):
    """(position, lap number, lap length) of the finite rows when the rule with laps can apply, else None."""
    if pos is None or lap is None or not lap_length or not np.isfinite(lap_length) or lap_length <= 0:
        return None
    lap_k = np.asarray(lap)[ok].astype(np.int64)
    if not np.all(np.isfinite(pos)) or len(np.unique(lap_k)) < 2:
        return None
    lap_k = lap_k - lap_k.min()
    return np.mod(pos, lap_length), lap_k, float(lap_length)


def check_dataset(ds, channel: str = "roll", laps=None) -> dict | None:
    """check() on a dataset's extra channel (None when the log has none): "roll" against vx omega as the
    lateral acceleration, "pitch" against dvx/dt - vy omega as the longitudinal one; positions from the log's
    own laps (ddyn.data.laps; laps: an already computed ddyn.data.laps.Laps of this log)."""
    if channel not in ds.extras:
        return None
    from ddyn.data import laps as LP

    lp = laps if laps is not None else LP.from_dataset(ds)
    where = {"position": lp.position, "lap": lp.lap if lp.circuit else None, "lap_length": lp.length}
    with np.errstate(over="ignore", invalid="ignore"):   # a corrupt log's states: the check reports them
        if channel == "pitch":
            vx = ds.states[:, 3]
            a = (np.gradient(vx, ds.sample_time) if len(vx) > 1 else np.zeros_like(vx)) - ds.states[:, 4] * ds.states[:, 5]
            gf = gravity_fit(ds.extras[channel], a, ds.states[:, 6], vx) if ds.states.shape[1] > 6 else None
            return {"channel": channel, "positions_from": lp.source,
                    **check(ds.extras[channel], ds.time, a, "pitch", "longitudinal", gravity=gf, **where)}
        ay = ds.states[:, 3] * ds.states[:, 5]
    return {"channel": channel, "positions_from": lp.source, **check(ds.extras[channel], ds.time, ay, **where)}
