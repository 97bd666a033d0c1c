"""Calibration runs read back: the evidence margin, detection thresholds and decision levels that runs of
`ddyn study gap` (the independent plant's calibration sweeps, results.json) measure, for scoring other runs
(`study gap --min-evidence-from/--thresholds-from/--detection-limits-from`) and for `ddyn diagnose --calibration`.

Its own module so that the diagnosis can read a calibration without importing the benchmark that makes one
(gap_independent imports diagnose). Everything here works on recorded results: a case's `effect`, `magnitude`,
`estimate`, `selected_without_gate`, `delta_bic_top`, `gate_ratio`; nothing is re-run.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from statistics import NormalDist

import numpy as np

from ddyn.analysis import candidates as C
from ddyn.errors import DdynError

NONE = "none"
TARGET_FALSE_ALARMS = 0.05
# A run that recorded no log length made logs of this many seconds (gap_independent.DURATION before `--duration`)
DURATION = 60.0


def with_gate(results: list[dict], threshold: float | None, margin: float = 0.0) -> list[dict]:
    """The results as the diagnosis would have given them with the gate at `threshold` (None: off) and the
    evidence margin `margin`: both only veto, the gate a whole selection, the margin the first effect (whose
    dBIC is the top candidate's), so top-1 and false alarms follow exactly from the recorded cases of a run
    with neither (a later effect the margin would also refuse does not change either score)."""
    out = []
    for r in results:
        if r["status"] != "ok":
            out.append(r)
            continue
        sel = r["selected_without_gate"]
        weak = bool(sel) and not r["delta_bic_top"] < -margin
        gated = threshold is not None and bool(sel) and r["gate_ratio"] <= threshold
        top1 = NONE if gated or weak or not sel else C.FAMILY.get(sel[0], sel[0])
        vetoed = gated or weak
        out.append(r | {"selected": [] if vetoed else sel, "top1": top1, "correct": top1 == r["effect"],
                        "gate_threshold": threshold, "min_evidence": margin}
                   # a vetoed selection leaves the refitted nominal: nothing of the oracle's gap closed
                   | ({"gap_vs_oracle": 0.0, "e_diagnosed": r["e_refit"]}
                      if vetoed and r.get("gap_vs_oracle") is not None else {}))
    return out


def calibrate_margin(results: list[dict], target: float = TARGET_FALSE_ALARMS) -> float:
    """The smallest evidence margin that leaves at most `target` of the effect-free cases with a selection."""
    none = [r for r in results if r["status"] == "ok" and r["effect"] == NONE]
    alarms = sorted(-r["delta_bic_top"] for r in none if r["selected_without_gate"])
    allowed = int(math.floor(target * len(none)))
    return 0.0 if len(alarms) <= allowed else float(alarms[len(alarms) - allowed - 1])



def runs(paths) -> list[dict]:
    """The results.json documents of one run's path or of several separated by commas."""
    if isinstance(paths, (str, Path)):
        paths = [p for p in str(paths).split(",") if p]
    return [json.loads(Path(p).read_text()) for p in paths]


def require_duration(paths, duration: float, what: str) -> None:
    """Refuse calibration runs recorded on logs of another length than `duration`: a dBIC sums over the held-out
    rows and a fit's spread shrinks with the rows, so a margin, threshold or decision level measured on 60 s logs
    is not one for 180 s logs (a run without a recorded duration made DURATION logs)."""
    for p, doc in zip([q for q in str(paths).split(",") if q], runs(paths)):
        got = float(doc["settings"].get("duration") or DURATION)
        if abs(got - duration) > 1e-9:
            raise DdynError(f"{what} {p}: its logs are {got:g} s, this run's {duration:g} s; calibrate on logs of "
                            "the same length (--duration)")


def margin_of(paths, target: float = TARGET_FALSE_ALARMS) -> float:
    """The evidence margin from several calibration runs pooled: the smallest margin leaving at most `target` of
    all their effect-free logs with a selection (calibrate_margin over the union). A run recorded with margin m
    shows no alarm weaker than m, so the pooled margin is never below the largest recorded one (record
    calibration runs with --min-evidence 0)."""
    docs = runs(paths)
    results = [r for d in docs for r in d["results"]]
    recorded = max(float(d["settings"].get("min_evidence") or 0.0) for d in docs)
    return max(recorded, calibrate_margin(results, target))



def calibrate(results: list[dict], target: float = TARGET_FALSE_ALARMS) -> float | None:
    """The smallest gate ratio that leaves at most `target` of the effect-free cases with a selection."""
    none = [r for r in results if r["status"] == "ok" and r["effect"] == NONE]
    if not none:
        return None
    alarms = sorted(r["gate_ratio"] for r in none if r["selected_without_gate"])
    allowed = int(math.floor(target * len(none)))
    if len(alarms) <= allowed:
        return None     # no gate needed
    return float(alarms[len(alarms) - allowed - 1])


RELIABLE_RATE = 0.95


def reliable_threshold(rows: list[dict], rate: float = RELIABLE_RATE, min_cases: int = 2,
                       min_levels: int = 2) -> float | None:
    """The measured detection threshold: the smallest drawn |magnitude| m such that the cases with |magnitude|
    >= m (at least min_cases of them, at at least min_levels distinct magnitudes) are identified (top-1) at >= rate;
    None when no such tail exists (never reliably identified in the drawn range). The tail is judged as the target
    scores it, as a whole: a rule that stopped at the first tail below the rate on the way down (this function
    until 2026-11-24) let one miss in a short tail near the top set the threshold whatever the many cases below it
    showed, so the more calibration seeds were pooled, the likelier such a miss and the higher the threshold
    (docs/gap_independent.md). min_levels: pooled sweeps share their magnitude grid, so a tail of one level (its
    top, where every seed's case sits) has as many cases as seeds; a threshold measured there only says the
    effect is found at the largest magnitude drawn (downforce's 4e-4, found 4/4 on the sweeps and 3/10 above it
    on blind seeds: until 2026-11-25 one level was enough)."""
    rows = sorted(rows, key=lambda r: abs(r["magnitude"]))
    mags = np.array([abs(r["magnitude"]) for r in rows])
    found = np.array([bool(r["correct"]) for r in rows], dtype=float)
    for i in range(0, len(rows) - min_cases + 1):
        if i > 0 and mags[i - 1] == mags[i]:
            continue    # equal magnitudes (pooled sweeps share their grid) enter the tail together
        if len(np.unique(mags[i:])) < min_levels:
            break
        if np.mean(found[i:]) >= rate:
            return float(mags[i])
    return None



def _rescored(paths, margin: float | None) -> list[dict]:
    """Every case of the runs, as the diagnosis gives it at `margin` (with_gate; None: as recorded)."""
    out = []
    for doc in runs(paths):
        results = doc["results"]
        if margin is not None:
            recorded = float(doc["settings"].get("min_evidence") or 0.0)
            if margin < recorded:
                raise DdynError(f"thresholds for margin {margin:g} from a run recorded with margin {recorded:g}: "
                                "a rescore can only raise the margin")
            results = with_gate(results, doc["settings"].get("gate"), margin)
        out += results
    return out


# The first effect added and the runner-up of its round with evidence closer than this (dBIC) are not told apart by
# the data: "not worth more than a bare mention" on Kass & Raftery's scale of BIC differences, a textbook constant,
# not tuned here. With detection limits such a first effect is reported, not claimed (diagnose's tie veto, which
# reads it from here; claim_precisions applies it to recorded runs).
AMBIGUITY_DBIC = 2.0


def _no_claim_log(r: dict, thresholds: dict) -> bool:
    """A log on which the calibration vouches for no claim: effect-free, or its hidden effect has no threshold or
    lies below it (the logs of the 5 % target)."""
    t = thresholds.get(r["effect"])
    return r["effect"] == NONE or t is None or abs(r["magnitude"]) < t


def claim_precisions(paths, margin: float | None = None, limits: dict | None = None,
                     thresholds: dict | None = None) -> dict:
    """{effect: {"claims", "right", "on_no_claim_logs"}}: the calibration logs where the diagnosis would claim the
    effect first, those that had it hidden, and those where no claim is vouched for (effect-free, or the hidden
    effect without a threshold or below it: _no_claim_log under `thresholds`, by default the measured ones).
    A claim: the first selection (top-1) at `margin`; with `limits` ({effect: the smallest |estimate| claimed}),
    also the top candidate's estimate at or above its effect's limit and its runner-up of another family more than
    AMBIGUITY_DBIC behind (diagnose's vetoes under limits; an effect without a limit is never claimed).

    A threshold says how reliably an effect is found where it is; this says how often a claim of it lands where
    nothing should be claimed (on 300 s Putnam logs downforce was named first on 5 of 22 banked, graded or
    heavier/lighter logs of one sweep, with estimates that clear any level its own logs give). A claim on another
    effect's log above that effect's threshold (a 40 ms steering lag named a 25 ms delay) is a top-1 miss there,
    scored by the top-1 and delay-vs-lag targets, not a claim on a no-claim log."""
    if thresholds is None:
        thresholds = _measured_thresholds(paths, margin)
    counts: dict = {}
    for r in _rescored(paths, margin):
        if r["status"] != "ok" or r["top1"] == NONE:
            continue
        e = r["top1"]
        if limits is not None:
            if limits.get(e) is None:
                continue
            if r.get("estimate_top") is not None and abs(r["estimate_top"]) < limits[e]:
                continue
            if r.get("runner_up_gap") is not None and r["runner_up_gap"] < AMBIGUITY_DBIC:
                continue
        c = counts.setdefault(e, {"claims": 0, "right": 0, "on_no_claim_logs": 0})
        c["claims"] += 1
        c["right"] += r["effect"] == e
        c["on_no_claim_logs"] += _no_claim_log(r, thresholds)
    return counts


def _measured_thresholds(paths, margin: float | None) -> dict:
    rows: dict = {}
    for r in _rescored(paths, margin):
        if r["status"] == "ok" and r["effect"] != NONE:
            rows.setdefault(r["effect"], []).append(r)
    return {e: reliable_threshold(rs) for e, rs in rows.items()}


def _precise(paths, margin: float | None, decision: bool) -> tuple[dict, dict]:
    """The measured thresholds with those of imprecise effects withdrawn, and the record: an effect whose claims
    (under the limits in force: the decision levels with `decision`, else the thresholds) land on no-claim logs
    more than 1 - RELIABLE_RATE of the time keeps no threshold. Withdrawing one makes its logs no-claim logs for
    the others, so repeated until nothing changes (at most once per effect). The record: the first round's claim
    counts (every effect with a measured threshold) and the effects withdrawn."""
    thresholds = _measured_thresholds(paths, margin)
    first: dict | None = None
    withdrawn: list = []
    for _ in range(len(thresholds) + 1):
        limits = _decision_levels(paths, thresholds) if decision else thresholds
        counts = claim_precisions(paths, margin, limits, thresholds)
        first = counts if first is None else first
        drop = {e for e, c in counts.items() if thresholds.get(e) is not None
                and c["on_no_claim_logs"] > (1.0 - RELIABLE_RATE) * c["claims"] + 1e-9}
        if not drop:
            break
        withdrawn += sorted(drop)
        thresholds = {e: None if e in drop else t for e, t in thresholds.items()}
    return thresholds, {"counts": first or {}, "withdrawn": withdrawn}


def precision_record(paths, margin: float | None = None, decision: bool = False) -> dict:
    """What a run with --claim-precision records beside its thresholds: {"counts": {effect: claim counts},
    "withdrawn": [effects]} (_precise)."""
    return _precise(paths, margin, decision)[1]


def thresholds_of(paths, margin: float | None = None, precision: bool = False, decision: bool = False) -> dict:
    """{effect: measured threshold} of one calibration run's results.json, or of several pooled: their cases of
    each effect together (reliable_threshold over the union). `paths`: a path, or several separated by commas.
    margin: the evidence margin the thresholds are for (each run's cases rescored with it, with_gate; a margin
    only vetoes, so it must be at least the runs' own); None: as recorded. precision: an effect also needs at
    most 1 - RELIABLE_RATE of the claims the diagnosis would make of it on the calibration to land on logs where
    no claim is vouched for (_precise, under the limits in force: the decision levels with `decision`, else the
    thresholds), or it has no threshold: found reliably where it is and seldom claimed where nothing should be,
    the two halves of "reliably identified"."""
    return _precise(paths, margin, decision)[0] if precision else _measured_thresholds(paths, margin)


# The decision limit's quantile: a case exactly at its threshold is estimated above the limit at the rate the
# threshold itself is measured at (one-sided normal quantile of RELIABLE_RATE, 1.645)
DECISION_Z = NormalDist().inv_cdf(RELIABLE_RATE)
# The calibration cases that measure the estimate's spread at a threshold: those within this factor of it.
DECISION_BAND = 2.0


def _decision_levels(paths, thresholds: dict, z: float = DECISION_Z, band: float = DECISION_BAND) -> dict:
    rows: dict = {}
    for doc in runs(paths):     # the hidden effect's estimate is recorded whatever was selected: no rescoring
        for r in doc["results"]:
            if r["status"] == "ok" and r["effect"] != NONE and r.get("estimate") is not None:
                rows.setdefault(r["effect"], []).append(r)
    limits = {}
    for eff, t in thresholds.items():
        if t is None:
            limits[eff] = None
            continue
        near = [abs(r["estimate"]) - abs(r["magnitude"]) for r in rows.get(eff, [])
                if t / band <= abs(r["magnitude"]) <= t * band]
        # too few cases to measure a spread: the threshold itself
        limits[eff] = t if len(near) < 2 else max(0.0, t + float(np.mean(near)) - z * float(np.std(near, ddof=1)))
    return limits


def decision_limits_of(paths, margin: float | None = None, z: float = DECISION_Z,
                       band: float = DECISION_BAND, precision: bool = False) -> dict:
    """{effect: decision limit} for the effects with a measured threshold (thresholds_of), the others None.

    The threshold is a true magnitude (above it the calibration named the effect in >= 95 % of its logs); a claim
    can only be judged by the estimate. Using the threshold as the limit on the estimate (until 2026-11-25)
    withholds about half of the right finds at the threshold itself, whose estimates scatter around it (blind
    7317-7319: 4 of 5 misses above the thresholds). Currie's (1968) split of a detection limit: the decision
    level L_C is the estimate's (1 - 0.95) quantile for an effect exactly at the detection limit L_D, here the
    threshold: L_C = L_D + bias - z sd, bias and sd of (|estimate| - |magnitude|) over the calibration cases of
    that effect within a factor `band` of the threshold (where the estimate's error is measured near the
    decision; its spread is roughly constant in absolute terms there). Never negative. precision: an effect
    whose claims under these levels land where nothing should be claimed too often gets none (thresholds_of)."""
    thresholds = _precise(paths, margin, True)[0] if precision else _measured_thresholds(paths, margin)
    return _decision_levels(paths, thresholds, z, band)


# What a calibration run records of the diagnosis it scored and `ddyn diagnose --calibration` takes over: the margin
# and the limits measured under these settings hold under them only
CALIBRATED_SETTINGS = ("hold", "fit", "mass_inertia", "steer_servo", "nominal_effects", "evidence", "gate",
                       "pitch_channel", "roll_channel", "duration")


def calibrated_diagnosis(paths, precision: bool = True) -> dict:
    """The diagnosis that calibration runs (`study gap --case-set sweep ... --min-evidence 0`, comma-separated)
    calibrated, for `ddyn diagnose --calibration`: their diagnosis settings (CALIBRATED_SETTINGS, which pooled runs
    must share), their pooled evidence margin (margin_of), Currie's decision levels at that margin
    (decision_limits_of; diagnose.calibrated_settings adds that every effect they did not calibrate is never
    claimed), the log length they were measured on and the candidates read from channels. evidence: as recorded
    (None: the diagnosis's default). precision: only effects whose claims on the calibration seldom land where
    nothing should be claimed get a level (thresholds_of)."""
    names = [p for p in str(paths).split(",") if p]
    docs = runs(paths)
    first = docs[0]["settings"]
    for name, doc in zip(names[1:], docs[1:]):
        differ = [k for k in CALIBRATED_SETTINGS if doc["settings"].get(k) != first.get(k)]
        if differ:
            raise DdynError(f"--calibration: {name} differs from {names[0]} in {', '.join(differ)}; runs pooled "
                            "as one calibration must share their diagnosis settings")
    margin = margin_of(paths)
    return {"runs": names, "hold": bool(first.get("hold")), "fit": first.get("fit"),
            "mass_inertia": bool(first.get("mass_inertia")), "steer_servo": float(first.get("steer_servo") or 0.0),
            "nominal_effects": dict(first.get("nominal_effects") or {}),
            "evidence": first.get("evidence"), "gate": first.get("gate"),
            "min_evidence": margin, "detection_limits": decision_limits_of(paths, margin, precision=precision),
            "claim_precision": precision_record(paths, margin, decision=True) if precision else None,
            "duration": float(first.get("duration") or DURATION),
            "channel_candidates": [c for c, k in (("grade_from_pitch", "pitch_channel"), ("bank_from_roll",
                                                                                          "roll_channel"))
                                   if first.get(k)]}
