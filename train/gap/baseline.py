"""The effects a car shows on every one of its effect-free logs: its own, folded into its vehicle file's nominal.

Why: a nominal identified on effect-free logs of a car with no single-track equivalent (the MuJoCo car, whose
contact tyres' force grows with slip velocity, so with speed) keeps a mismatch that every log of that car shows;
the diagnosis then names it on every log, effect or not. What a user with such a car does is what this module
does: diagnose the car's own effect-free logs, and take an effect claimed first on every one of them, at a
consistent size, as part of the car. It goes into the vehicle file's "effects" (ddyn.model.vehicle.Vehicle.effects)
and a later diagnosis reports what comes on top of it (ddyn.gap.problem.Problem.effects). The diagnosis refits the
tyre peaks (Df, Dr) under every hypothesis, so the effect was found together with its refit factors: those go into
the file's coefficients with it (refit_factors), or the nominal alone would predict worse than before.

An effect is the car's own when it is the first claim on at least MIN_LOGS effect-free logs and on more than half
of them, with one sign and sizes within a factor CONSISTENT of each other; its value is their median. A log that
names something else or nothing does not veto it: a slow log cannot tell a downforce from the tyre peaks (its
speed hardly varies), so it says nothing on it. Anything else (no majority, sizes apart, one log's claim) is left
to the diagnosis: it is what one log shows, not what the car is.
"""
from __future__ import annotations

import statistics

from ddyn.errors import DdynError
from ddyn.gap import candidates as C
from ddyn.gap.config import DiagnosisConfig
from ddyn.model import effects as E

MIN_LOGS = 2
CONSISTENT = 1.5


def config() -> DiagnosisConfig:
    """The diagnosis run on the effect-free logs: every one-parameter effect and the profiles, uncalibrated."""
    return DiagnosisConfig(hold="estimate", candidates=E.EFFECT_NAMES + C.EXTRA)


def first_claims(logs, vehicle) -> list[dict]:
    """Per log: the first claimed effect and its main parameter (effect None: nothing claimed)."""
    from ddyn.gap.problem import nominal_from_vehicle
    from ddyn.gap.selection import diagnose

    out = []
    for ds in logs:
        d = diagnose(ds, nominal_from_vehicle(vehicle, ds), config())
        first = d["selected"][:1]
        if not first:
            out.append({"effect": None, "value": None, "verdict": d["verdict"]})
            continue
        cand = next(c for c in d["candidates"] if c["effect"] == first[0])
        value = cand["params"].get(E.MAIN_PARAM.get(first[0], ""), None)
        out.append({"effect": first[0], "value": None if value is None else float(value),
                    "refit": dict(cand.get("refit", {})), "verdict": d["verdict"]})
    return out


def refit_factors(claims: list[dict]) -> dict:
    """{coefficient: the median refit factor} of the claims (those of the car's own effect)."""
    names = sorted({n for c in claims for n in c.get("refit", {})})
    return {n: float(statistics.median(c["refit"][n] for c in claims if n in c.get("refit", {}))) for n in names}


def consistent_effect(claims: list[dict]) -> tuple[dict, list[dict]]:
    """({effect: value}, the claims that name it) when one one-parameter effect is the first claim on at least
    MIN_LOGS logs and on more than half of them, with one sign and sizes within CONSISTENT; else ({}, [])."""
    if len(claims) < MIN_LOGS:
        raise DdynError(f"the car's own effects need at least {MIN_LOGS} effect-free logs, got {len(claims)}")
    names = [c["effect"] for c in claims if c["effect"] is not None]
    best = max(set(names), key=names.count, default=None)
    if best is None or best not in E.MAIN_PARAM:
        return {}, []
    mine = [c for c in claims if c["effect"] == best]
    if len(mine) < MIN_LOGS or 2 * len(mine) <= len(claims):
        return {}, []
    values = [c["value"] for c in mine]
    if any(v is None or v == 0 for v in values) or len({v > 0 for v in values}) != 1:
        return {}, []
    mags = sorted(abs(v) for v in values)
    if mags[-1] > CONSISTENT * mags[0]:
        return {}, []
    return {best: float(statistics.median(values))}, mine
