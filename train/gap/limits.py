"""This log's own detection limits: the smallest effect of each family the diagnosis would find on it.

Why: a threshold measured on one plant's 60 s logs says nothing about a user's 900 s log of another car, and a
margin that is a fixed number of dBIC lets a systematic mismatch through on a long log (its spurious gain grows
with the rows) while it is needlessly strict on a short one. Both are modelled here from the log itself, at no
more cost than a few one-step evaluations:

  size that matters   per family, fixed and not tuned (SIZES; the issue that asked for them): delays and lag
                      40 ms, mass 10 %, bank and grade 3 degrees, yaw-rate bias 0.01 rad/s, tyre wear 10 % of
                      the grip lost over the log, downforce 10 % more tyre load at the log's top speed, tyre
                      relaxation 1 m, combined slip a coupling of 0.5.
  evidence at a size  the held-out gain an effect of that size would give on THIS log: the change dr it makes
                      to the refitted nominal's normalised one-step predictions on the held-out rows, with the
                      part the tyre refit (Df, Dr) could take up projected out (least squares across the
                      channels, each weighted by its residual variance), so gain per channel
                      g = |dr_perp|^2 / (n s^2). An effect of size t * size, present in the log and found, raises
                      the concentrated log-likelihood by n sum_c ln(1 + t^2 g_c).
  margin              min_evidence + min_evidence_per_row * n_heldout: a constant (the extended BIC's own
                      penalty is added by the criterion) and a part that grows with the rows, the form a
                      systematic plant mismatch's spurious gain takes (a calibration sets both); a family is
                      claimed only above that plus its own family_margins_per_row * n_heldout.
  limit               the smallest t * size whose expected dBIC, -n sum ln(1 + t^2 g) + dk ln n + 2 ln m, clears
                      -margin: "a steering delay below 31 ms would not be found on this log". Linear in the
                      effect (t^2 g): exact for small effects, a bound's order of magnitude for large ones.

The profile and channel candidates of a family take the family's limit in the form the log can show: a bank or
grade that varies along the lap (as every closed circuit's must) can only be learned where the fit part of the
log drove, so unless a plausible roll (pitch) channel carries it to every row, the limit is the larger of its
constant form (a bank of one angle everywhere) and its profile form (the same angle only on the held-out rows
whose track position the fit part's knots cover: none covered, none found).

A bank's limit is the larger of its constant form's and its form in the turns (turn_shape: banked into the turns
as a road is, steepest in the tightest), whose gain is what is left once the tyre refit (Df, Dr) has taken up
what it can: a friction scale changes the lateral force by about rho m a_y, and a bank that follows the turns
reads the same (candidates.HOLDS_REFIT). On the study's Putnam logs a bank of 3.5 degrees in the turns paid
nothing, with the map's exact bank as a channel and the tyre refitted (dBIC +3; held, +78: an exploration with
the flatness check and the refit hold switched off by hand), while the constant
form stated a limit of 3 degrees; the turns form states 4 to 6 degrees there.

A limit is also never below what a claim needs: with a decision level (a calibration's share of the size that
matters, or an absolute detection limit) an estimate under it is reported, not claimed, so the stated limit is
at least that level; a family the calibration never claims has no limit ("no ... of any size would be found").
"""
from __future__ import annotations

import math

import numpy as np

from ddyn.gap import candidates as C

# the size that matters per family: (value, unit, how it is read); "per-log" sizes depend on the log (below)
SIZES = {"steer_delay": 0.040, "throttle_delay": 0.040, "steer_lag": 0.040, "mass_offset": 0.10,
         "bank_angle": math.radians(3.0), "grade": math.radians(3.0), "yaw_rate_bias": 0.01,
         "tire_relaxation": 1.0, "combined_slip": 0.5}
WEAR_LOST = 0.10            # tyre wear: this share of the grip lost over the log
DOWNFORCE_LOAD = 0.10       # downforce: this much more tyre load at the log's top speed
WORDS = {"steer_delay": "steering delay", "throttle_delay": "throttle delay", "steer_lag": "steering lag",
         "mass_offset": "mass offset", "bank_angle": "bank", "grade": "grade", "yaw_rate_bias": "yaw-rate bias",
         "tire_relaxation": "tyre relaxation length", "combined_slip": "combined-slip coupling",
         "tire_wear": "tyre wear", "downforce": "downforce"}
# the bank in the turns (turn_shape): a road's bank changes over tens of metres, ten wheelbases of a full-scale car
# (the plant's bank_profile smooths its curvature over about 30 m: the AV-21's wheelbase is 2.97 m), and a scale
# model's track in proportion; below a tenth of the log's mean speed the yaw rate over the speed is no curvature
TURN_SMOOTHING_WHEELBASES = 10.0
TURN_MIN_SPEED_SHARE = 0.1
BOUND_WORDS = {"turns": "a bank in the turns, which the tyre refit takes up"}
LIMIT_CAP = 1e3             # t above this: the log carries no information on the family (limit reported as None)


def size_that_matters(family: str, ctx: dict) -> float | None:
    """The family's size that matters in its main parameter's unit on a log (ctx: Problem.ctx); None: the
    family has none fixed (drivetrain shapes)."""
    if family in SIZES:
        return SIZES[family]
    if family == "tire_wear":       # exp(-rate T) = 1 - WEAR_LOST over the log
        return -math.log(1.0 - WEAR_LOST) / ctx["duration"]
    if family == "downforce":       # 1 + k v_max^2 = 1 + DOWNFORCE_LOAD
        return DOWNFORCE_LOAD / ctx["v_max"] ** 2
    return None


def in_words(family: str, value: float) -> str:
    """A size in the unit a user reads (ms, %, degrees, ...)."""
    if family in ("steer_delay", "throttle_delay", "steer_lag"):
        return f"{1e3 * value:.0f} ms"
    if family in ("bank_angle", "grade"):
        return f"{math.degrees(value):.1f} degrees"
    if family == "mass_offset":
        return f"{100 * value:.0f} %"
    if family == "yaw_rate_bias":
        return f"{value:.3g} rad/s"
    if family == "tire_relaxation":
        return f"{value:.2g} m"
    return f"{value:.3g}"


def margin_of(config, n_heldout: int) -> float:
    """The evidence margin on a log with n_heldout held-out rows (DiagnosisConfig.min_evidence, min_evidence_per_row)."""
    return float(config.min_evidence) + float(getattr(config, "min_evidence_per_row", 0.0)) * int(n_heldout)


def _projected_gain(prob, base_rho, dr: np.ndarray, held: bool, var: np.ndarray) -> np.ndarray:
    """g per channel: the squared held-out change dr (n, 3; normalised) left after the refit factors' own
    changes are projected out (none when the hypothesis holds the refit), over n times the channel variance."""
    n = dr.shape[0]
    if not held and len(prob.refit):
        rows, r0 = prob.rows_held, prob.residuals({}, base_rho, prob.rows_held)
        cols = []
        for j in range(len(prob.refit)):
            rho = np.array(base_rho, float)
            rho[j] += 0.01
            cols.append((prob.residuals({}, rho, rows) - r0) / np.sqrt(var))
        S = np.stack([c.ravel() for c in cols], axis=1)
        y = (dr / np.sqrt(var)).ravel()
        coef, *_ = np.linalg.lstsq(S, y, rcond=None)
        dr = (y - S @ coef).reshape(n, 3) * np.sqrt(var)
    return np.sum(dr ** 2, axis=0) / (n * var)


def profile_coverage(prob, family: str, candidates=()) -> np.ndarray | None:
    """Which held-out rows a profile of `family` (bank_angle, grade) could be learned on: those whose track
    position lies next to a knot the fit rows inform (ddyn.gap.candidates.Layout.free). None: no restriction (not
    a profiled family, no layout, or a plausible channel candidate of the family carries it to every row)."""
    lay = getattr(prob, "layout", None)
    if lay is None or family not in C.PROFILE_OF.values():
        return None
    if any(C.FAMILY[c] == family and c in C.ROLL_OF and C.available(c, lay) for c in candidates):
        return None
    s = np.asarray(lay.position, float)[prob.rows_held]
    knots = np.asarray(lay.knots, float)
    if lay.length is not None:
        s = np.mod(s, lay.length)
    i = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(knots) - 1)   # the knot at or before s
    j = (i + 1) % len(knots) if lay.length is not None else np.minimum(i + 1, len(knots) - 1)
    free = np.zeros(len(knots), bool)
    free[list(lay.free)] = True
    return free[i] | free[j]


def turn_shape(time, states, wheelbase: float) -> np.ndarray:
    """A bank that follows the turns, per row of a log (time (N,), states (N, >= 6): vx, vy, omega in columns 3-5),
    peak 1: the path's curvature (yaw rate over speed) averaged over TURN_SMOOTHING_WHEELBASES wheelbases
    travelled, over its largest value where the car moves (TURN_MIN_SPEED_SHARE). The shape of
    ddyn.plants.commonroad_st.bank_profile, read from the log instead of a track map; zeros on a log shorter
    than the averaging or one that does not move."""
    vx, om = np.abs(np.asarray(states, float)[:, 3]), np.asarray(states, float)[:, 5]
    t = np.asarray(time, float)
    v_min = TURN_MIN_SPEED_SHARE * max(float(np.mean(vx)), 1e-9)
    moving = vx >= v_min
    kappa = np.where(moving, om / np.maximum(vx, v_min), 0.0)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * np.diff(t).clip(0.0))])
    window = TURN_SMOOTHING_WHEELBASES * float(wheelbase)
    if not np.any(moving) or window <= 0 or s[-1] <= window:
        return np.zeros(len(vx))
    step = window / 30.0                       # the curvature on a grid of 30 points per window
    grid = np.arange(0.0, s[-1], step)
    on_grid = np.interp(grid, s, kappa)
    half = 15
    smooth = np.convolve(np.pad(on_grid, half, mode="edge"), np.ones(2 * half + 1) / (2 * half + 1), mode="valid")
    shape = np.interp(s, grid, smooth)
    peak = float(np.max(np.abs(shape[moving])))
    return shape / peak if peak > 0 else np.zeros(len(vx))


def gains(prob, base_rho, families, candidates=()) -> dict:
    """{family: (size that matters, g per channel (3,), g of its profile form or None, its form: "evidence", or
    "turns" for a bank in the turns)} on the held-out rows of
    prob (refit factors base_rho). g: the normalised gain an effect of the size that matters would give (module
    docstring); the profile form's: the same effect on the rows profile_coverage leaves, zero elsewhere. The bank's
    g is the smaller of its constant form's and its form in the turns (turn_shape) with the tyre refit projected
    out: a bank that follows the turns is taken up by the refitted grip (candidates.HOLDS_REFIT), on the nominal
    and on every hypothesis that refits, whatever a hypothesis of the bank holds."""
    rows = prob.rows_held
    r0 = prob.residuals({}, base_rho, rows)
    var = np.maximum(np.mean(r0 ** 2, axis=0), 1e-12)
    out = {}
    for fam in families:
        size = size_that_matters(fam, prob.ctx)
        if size is None:
            continue
        try:
            r1 = prob.residuals({fam: size}, base_rho, rows)
        except (ValueError, FloatingPointError):
            continue
        dr = r0 - r1     # what the effect, were it in the log, would add to the nominal's residual
        if not np.all(np.isfinite(dr)):
            continue
        held = C.holds_refit((fam,), prob.bank_family_held)
        cover = profile_coverage(prob, fam, candidates)
        g_profile = None if cover is None else _projected_gain(prob, base_rho, dr * cover[:, None], held, var)
        g, form = _projected_gain(prob, base_rho, dr, held, var), "evidence"
        if fam == "bank_angle":
            # the effect of a bank on a one-step prediction is that of the bank at the row: linear per row
            p = prob.nominal.vehicle.known
            shape = turn_shape(prob.ds.time, prob.ds.states, p.lf + p.lr)
            g_turns = _projected_gain(prob, base_rho, dr * shape[rows][:, None], False, var)
            if np.sum(g_turns) < np.sum(g):
                g, form = g_turns, "turns"
        out[fam] = (size, g, g_profile, form)
    return out


def limit(size: float, g, n: int, margin: float, dk: int = 1, m: int = 1, weight=1.0) -> float | None:
    """The smallest t * size with -n sum w ln(1 + t^2 g) + dk ln n + 2 ln m <= -margin; None: beyond LIMIT_CAP.
    weight: the effective rows per held-out row of each channel (Problem.row_weight), as the evidence counts them."""
    g = np.maximum(np.asarray(g, float), 0.0)
    w = np.broadcast_to(np.asarray(weight, float), g.shape)
    need = margin + dk * math.log(max(n, 2)) + 2.0 * math.log(max(m, 1))

    def gain(t):
        return float(n * np.sum(w * np.log1p(t * t * g)))

    if gain(LIMIT_CAP) < need:
        return None
    lo, hi = 0.0, LIMIT_CAP
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gain(mid) < need else (lo, mid)
    return hi * size


def log_limits(prob, base_rho, families, margins: dict, m: int, levels: dict | None = None,
               candidates=()) -> dict:
    """{family: {size_that_matters, limit (None: not found at any size), gain (3,), unit, sentence, bound_by}} for
    this log at each family's claim margin (margins {family: dBIC}) with m candidates in the first round.
    levels: {family: the smallest estimate claimed, or None: never claimed}; a family absent has no level.
    candidates: the diagnosis's candidate names (whether a channel carries a bank or grade to every row)."""
    n = len(prob.rows_held)
    levels = levels or {}
    out = {}
    for fam, (size, g, g_profile, form) in gains(prob, base_rho, families, candidates).items():
        lim = limit(size, g, n, margins[fam], 1, m, prob.row_weight)
        bound_by = form
        if g_profile is not None and lim is not None:
            lim_p = limit(size, g_profile, n, margins[fam], 1, m, prob.row_weight)
            lim, bound_by = (None, "coverage") if lim_p is None else (max(lim, lim_p), "coverage" if lim_p > lim
                                                                      else bound_by)
        if fam in levels:
            level = levels[fam]
            if level is None:
                lim, bound_by = None, "not claimable"
            elif lim is not None and abs(level) > lim:
                lim, bound_by = abs(level), "decision level"
        word = WORDS.get(fam, fam.replace("_", " "))
        why = {"not claimable": " (the calibration never claims it)",
               "coverage": " (the held-out part drives where the fit part did not: a profile cannot be learned)",
               "turns": " (a bank that follows the turns reads as a change of tyre grip)"}
        out[fam] = {"size_that_matters": size, "limit": lim, "gain_at_size": [float(x) for x in g],
                    "unit": C.UNITS.get(fam, ""), "limit_over_size": None if lim is None else lim / size,
                    "bound_by": bound_by,
                    "sentence": (f"no {word} of any size in range would be found on this log"
                                 + why.get(bound_by, "") if lim is None else
                                 f"a {word} below {in_words(fam, lim)} would not be found on this log "
                                 f"(size that matters: {in_words(fam, size)}; set by {BOUND_WORDS.get(bound_by, 'its ' + bound_by)})")}
    return out
