"""The diagnosis's candidates beyond the one-parameter effects: bank and grade as profiles along the track,
and the bank read from a plausible logged roll channel.

Why: a constant bank or grade cannot stand for a road that is banked in the turns and flatter on the
straights (the issue's real oval: about 20 degrees in the turns, 9 on the front straight), and a road course
has both signs. So:

  bank_profile, grade_profile   the angle at knots along the track (on a known track, on its curvature
                                changes and between them: curvature_knots), linearly interpolated between them
                                (periodic along the lap when the track is known; otherwise along the distance
                                the log travelled), sign free; one parameter per knot the fit rows visit
                                (knots the fit part never reaches stay at zero: nothing could fit them);
  bank_from_roll                bank = gain x the log's roll channel, per row; tried only when the channel
                                passes ddyn.data.roll_check (the verdict is reported either way);
  grade_from_pitch              grade = gain x the log's pitch channel, the same way (a grade needs no lap:
                                on a log shorter than one the profile's knots stay unfitted, the channel does not).

A hypothesis with bank_profile or bank_from_roll keeps the nominal's tyre refit factors (HOLDS_REFIT); when either is
among the candidates, so does the constant bank_angle (holds_refit).

Their parameters enter ddyn.gap.fit.fit as scalar keys "NAME@i" (knot i), so the fit, the
held-out score (dk = the number of keys) and the greedy step treat them like any effect's. The profile
is reported by its peak (the signed knot of largest magnitude) and, in full, as `profile`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d

from ddyn.data import laps, roll_check
from ddyn.model import effects as E

PROFILE_OF = {"bank_profile": "bank_angle", "grade_profile": "grade"}
ROLL_OF = {"bank_from_roll": ("bank_angle", "roll"), "grade_from_pitch": ("grade", "pitch")}
EXTRA = tuple(PROFILE_OF) + tuple(ROLL_OF)
ALL = E.ALL_EFFECTS + EXTRA
# what a candidate stands for (so two candidates of one family are never selected together)
FAMILY = {**{n: n for n in E.ALL_EFFECTS}, **PROFILE_OF, **{k: v[0] for k, v in ROLL_OF.items()}}
MAIN_PARAM = {**E.MAIN_PARAM, "bank_profile": "peak", "grade_profile": "peak", "bank_from_roll": "gain",
              "grade_from_pitch": "gain"}
UNITS = {**E.UNITS, "bank_profile": "rad", "grade_profile": "rad", "bank_from_roll": "-", "grade_from_pitch": "-"}
UNIT = {"bank_profile": 0.01, "grade_profile": 0.01, "bank_from_roll": 0.1, "grade_from_pitch": 0.1,
        "gear_step": 0.05}   # fit scaling
BOUNDS = {"bank_profile": (-0.6, 0.6), "grade_profile": (-0.3, 0.3), "bank_from_roll": (-2.0, 2.0),
          "grade_from_pitch": (-2.0, 2.0), "gear_step": (-0.5, 1.0)}
GRID = {"bank_from_roll": (2.5, 5, 7.5, 10, 12.5),   # in units: gains 0.25-1.25
        "grade_from_pitch": (2.5, 5, 7.5, 10, 12.5),
        "gear_step": (-4, 2, 4, 8)}                  # force steps -0.2 to 0.4 between gears

KNOT_SPACING = 50.0      # m between knots: a bank changes over a turn entry (tens of metres), not faster
MIN_KNOTS, MAX_KNOTS = 4, 40
# Knots tied to the curvature (a known track): a road's bank changes where its curvature does (the transition
# spirals of a turn entry or exit), so a knot sits on every such change and one KNOT_SPACING/2 either side of it;
# the rest of the lap gets knots at most KNOT_SPACING apart. Uniform knots every ~50 m cut a 60 m bank ramp
# anywhere, and the interpolation alone then misses the turn's bank by up to 2 degrees next to the ramp
# (docs/gap.md). A change counts when the smoothed curvature differs by BREAK_CURVATURE (1/m) across
# KNOT_SPACING (a straight into a 500 m radius); more knots than MAX_KNOTS: the uniform layout.
BREAK_CURVATURE = 2e-3


# The tyre's refit factors (Df, Dr) stay at the nominal's in any hypothesis with a bank that follows the turns:
# in steady cornering a friction scale rho changes the lateral force by about rho m a_y, and a_y is nearly
# constant in a turn, so rho reads as a bank of about rho a_y / g rad there and the two cannot be told apart from
# the log (refitted, the oval's turn bank came out up to 11 degrees off with Df, Dr -27 %; held, within 2.6
# degrees: docs/gap.md). The nominal's tyre, identified where the road is flat, is the prior that
# separates them.
HOLDS_REFIT = ("bank_profile", "bank_from_roll")


def holds_refit(names, bank_family: bool = False) -> bool:
    """Whether a hypothesis (fit keys) keeps the nominal's refit factors (HOLDS_REFIT). bank_family: the constant
    bank_angle holds them too. diagnose sets it when a bank profile or the roll channel is among the candidates,
    so that the bank family is compared on one footing: a constant bank that may move the tyre while the profile
    may not can win by the tyre, not by being the better bank (on the banked oval with an identified nominal it
    beat the profile on 2 of 6 logs, 6 and 8 degrees off in the turns)."""
    held = HOLDS_REFIT + (("bank_angle",) if bank_family else ())
    return any(base(n) in held for n in names)


def base(key: str) -> str:
    """The candidate a fit key belongs to ("bank_profile@3" -> "bank_profile")."""
    return key.split("@", 1)[0]


@dataclass
class Layout:
    """Where each row is along the track and where the knots sit."""

    position: np.ndarray            # (N,) m
    length: float | None            # lap length (periodic) or None
    knots: np.ndarray               # (K,) m
    free: list                      # knot indices the fit rows inform
    source: str                     # "track NAME", "laps from x, y (...)" or "distance travelled (why)"
    roll: dict | None               # roll_check verdict of the log's roll channel (None: none logged)
    pitch: dict | None = None       # the same for its pitch channel

    def channel_check(self, channel: str) -> dict | None:
        return self.roll if channel == "roll" else self.pitch if channel == "pitch" else None


def _distance(ds) -> np.ndarray:
    """Distance travelled along the logged path, continuing across segments."""
    return laps.distance(ds.states[:, :2], ds.segment)


def _positions(ds, track, lp: laps.Laps) -> tuple[np.ndarray, float | None, str]:
    """(position of each row, lap length or None, where the positions come from): along the track when it is
    known; else along the log's own lap (ddyn.data.laps: the same spot gets the same position on every lap,
    whatever line was driven); else, on a log that drives no closed circuit, the distance travelled."""
    if track is not None:
        s, _ = track.project(ds.states[:, 0], ds.states[:, 1])
        return s, float(track.length), f"track {track.name}"
    if lp.circuit:
        return lp.position, float(lp.length), lp.source
    return _distance(ds), None, lp.source


def layout(ds, track, rows_fit: np.ndarray) -> Layout:
    lp = laps.from_dataset(ds)
    s, length, src = _positions(ds, track, lp)
    span = length if length is not None else max(float(s[-1]), 1.0)
    k = int(min(MAX_KNOTS, max(MIN_KNOTS, math.ceil(span / KNOT_SPACING))))
    knots = np.linspace(0.0, span, k, endpoint=length is None)   # periodic: the last knot wraps to the first
    tied = curvature_knots(track) if track is not None else None
    if tied is not None:
        knots, src = tied, src + ", knots tied to its curvature"
    k = len(knots)
    # a knot is free when fit rows lie on either of its two intervals (between its neighbours)
    sf = np.asarray(s)[rows_fit]
    if length is not None:
        prev, nxt = np.roll(knots, 1) - np.r_[length, np.zeros(k - 1)], np.roll(knots, -1) + np.r_[np.zeros(k - 1), length]
        sf = np.mod(sf, length)
        free = [i for i in range(k) if np.any(((sf > prev[i]) & (sf < nxt[i])) | (sf - length > prev[i])
                                               | (sf + length < nxt[i]))]
    else:
        prev, nxt = np.r_[-np.inf, knots[:-1]], np.r_[knots[1:], np.inf]
        free = [i for i in range(k) if np.any((sf > prev[i]) & (sf < nxt[i]))]
    roll = roll_check.check_dataset(ds, "roll", lp)
    pitch = roll_check.check_dataset(ds, "pitch", lp)
    return Layout(np.asarray(s, float), length, knots, free, src, roll, pitch)


def curvature_knots(track) -> np.ndarray | None:
    """Knots (m, ascending in [0, lap)) on the track's curvature changes and KNOT_SPACING/2 either side, the
    gaps filled at most KNOT_SPACING apart; None when the track has no such change or needs more than
    MAX_KNOTS (then the uniform layout)."""
    L = float(track.length)
    if L < 4 * KNOT_SPACING:       # a lap shorter than the smoothing windows (a model car's track)
        return None
    h = 0.5 * KNOT_SPACING
    g = np.arange(0.0, L, 1.0)
    kappa = np.asarray(track.curvature_at(g), float)
    n = int(h)
    kappa = np.convolve(np.r_[kappa[-n:], kappa, kappa[:n]], np.ones(n) / n, mode="same")[n:-n]
    change = np.abs(np.roll(kappa, -n) - np.roll(kappa, n))           # across +-h, periodic
    # a change point: the largest change within +-KNOT_SPACING, above the threshold
    w = int(KNOT_SPACING)
    top = (change >= 0.98 * maximum_filter1d(change, size=2 * w + 1, mode="wrap")) & (change >= BREAK_CURVATURE)
    if not top.any():
        return None
    if top.all():
        return None
    # one change point per run of (near-)maxima: the run's middle (a step in the curvature gives a plateau)
    i0 = int(np.flatnonzero(~top)[0])
    rot = np.roll(top, -i0)                    # starts on a point that is no change point
    edges = np.flatnonzero(np.diff(np.r_[rot, False].astype(int)))    # run j: (edges[2j], edges[2j + 1]]
    base = [float(np.mod(0.5 * (a + 1 + b) + i0, len(g))) * (L / len(g)) for a, b in zip(edges[::2], edges[1::2])]
    knots = np.unique(np.round(np.mod([b + o for b in base for o in (-h, 0.0, h)], L), 6))
    out = []
    for a, b in zip(knots, np.r_[knots[1:], knots[0] + L]):
        m = max(1, math.ceil((b - a) / KNOT_SPACING - 1e-9))
        out += [a + (b - a) * j / m for j in range(m)]
    out = np.sort(np.mod(out, L))
    return out if len(out) <= MAX_KNOTS else None


def available(name: str, lay: Layout | None) -> bool:
    """Whether the candidate can be tried on this log."""
    if name in PROFILE_OF:
        return lay is not None and len(lay.free) > 0
    if name in ROLL_OF:
        verdict = _channel_verdict(name, lay)
        # a channel that says the road is flat adds no bank (grade): never read one from it
        return verdict is not None and bool(verdict["plausible"]) and not verdict.get("flat", False)
    return True


def _channel_verdict(name: str, lay: Layout | None) -> dict | None:
    """The plausibility verdict of a channel candidate's channel (None: no layout or no such channel logged)."""
    return None if lay is None else lay.channel_check(ROLL_OF[name][1])


def keys(name: str, lay: Layout | None) -> tuple[str, ...]:
    """The fit's scalar parameter keys of a candidate."""
    if name in PROFILE_OF:
        return tuple(f"{name}@{i}" for i in lay.free)
    return (name,)


def unit(key: str) -> float | None:
    return UNIT.get(base(key))


def bounds(key: str) -> tuple[float, float] | None:
    return BOUNDS.get(base(key))


def effect_set(values: dict, lay: Layout | None) -> E.EffectSet:
    """The EffectSet of fit values keyed as above (plain effects by name)."""
    plain = {k: v for k, v in values.items() if k in E.MAIN_PARAM}
    specs = [{"effect": k, "params": {E.MAIN_PARAM[k]: float(v)}} for k, v in plain.items()]
    for name, effect in PROFILE_OF.items():
        ks = [k for k in values if base(k) == name]
        if not ks:
            continue
        angle = np.zeros(len(lay.knots))
        for k in ks:
            angle[int(k.split("@")[1])] = float(values[k])
        specs = [sp for sp in specs if sp["effect"] != effect]   # one family is never selected twice
        specs.append({"effect": effect, "params": {"profile": "linear",
                                                   "breaks": [[float(a), float(b)] for a, b in zip(lay.knots, angle)]}})
    for name, (effect, channel) in ROLL_OF.items():
        if name in values:
            specs = [sp for sp in specs if sp["effect"] != effect]
            specs.append({"effect": effect, "params": {"profile": "channel", "channel": channel,
                                                       "amplitude": float(values[name])}})
    return E.EffectSet.of(specs)


def attach(lm: E.LogModel, lay: Layout | None) -> None:
    """Give the log predictor the rows' track positions (for profiles)."""
    if lay is not None:
        lm.position, lm.track_length = lay.position, lay.length


def summary(name: str, values: dict, std: dict, lay: Layout | None) -> tuple[float, float, dict | None]:
    """(main value, its std, the full profile or None) of a fitted candidate."""
    if name not in PROFILE_OF:
        return float(values[name]), float(std.get(name, float("nan"))), None
    ks = keys(name, lay)
    vals = np.array([values.get(k, 0.0) for k in ks])
    i = int(np.argmax(np.abs(vals))) if len(vals) else 0
    angle = np.zeros(len(lay.knots))
    sd = np.full(len(lay.knots), float("nan"))
    for k in ks:
        j = int(k.split("@")[1])
        angle[j], sd[j] = values.get(k, 0.0), std.get(k, float("nan"))
    peak = float(vals[i]) if len(vals) else 0.0
    return peak, float(std.get(ks[i], float("nan"))) if ks else float("nan"), {
        "knots_m": lay.knots.tolist(), "angle_rad": angle.tolist(), "std_rad": sd.tolist(),
        "free": list(lay.free), "periodic_length_m": lay.length, "position_from": lay.source}


def magnitude(name: str, value: float, lay: Layout | None) -> float:
    """A fitted candidate's size in its family's unit, the one detection limits are set in: a channel
    candidate's gain times the channel's largest reading (its 99.9th percentile |angle|: the bank or grade the
    candidate reads at its steepest, body roll or pitch included), every other candidate's main value (a
    profile's peak)."""
    if name in ROLL_OF:
        verdict = _channel_verdict(name, lay)
        if verdict and "abs_p999_rad" in verdict:
            return abs(value) * float(verdict["abs_p999_rad"])
    return value


def profile_at(profile: dict, s) -> np.ndarray:
    """A reported profile (summary's third value) evaluated at positions s."""
    knots, angle = np.asarray(profile["knots_m"]), np.asarray(profile["angle_rad"])
    L = profile["periodic_length_m"]
    if L:
        return np.interp(np.mod(s, L), knots, angle, period=L)
    return np.interp(s, knots, angle)
