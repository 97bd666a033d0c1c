"""Leave one plant family out: calibrate the diagnosis on the other families, score it blind on the one left out.

Why: a threshold or margin chosen on one plant and scored on new seeds of it says nothing about a user's car. Here
every family (ddyn.gap.benchmark.families) is in turn the new plant: its logs choose nothing.

The campaign (plan): per family, logs that vary what a real one varies: the car (the family's parameter sets),
log length (DURATIONS), drive-by-wire rate (DBW_PERIODS), sensor noise level and colour, target speed, track
(Putnam, or with --tracks road a full-size random road course per log; the banked oval for half the bank logs)
and the roll and pitch channels (CHANNEL_KINDS), of one kind per log: one attitude source gives both, an IMU its
roll and pitch, a map its bank and grade, a broken estimator both broken. (Until 2026-11-30 no log carried a pitch
channel, so a grade could only be found as a profile along laps, and every MuJoCo log carried an IMU roll whatever
its kind: the plant ignored it.)
Each log holds one effect (EFFECTS, drawn between MAGNITUDES times its size that matters, ddyn.gap.limits.SIZES)
or none (NONE_SHARE of the logs). The nominal is the user's: the family's vehicle file for that car.

Two passes, both on the same cached logs:
  pass 1   every log diagnosed uncalibrated (margin 0, no decision levels): what each family's candidates
           estimate and what their evidence is;
  fold     for each family, the calibration of the OTHER families' pass-1 records (calibrate): a decision level
           per effect family (a share of its size that matters, from LEVEL_GRID, or None: never claimed), each
           the one whose first claims on those records are right most often net of the false ones (first claims
           on effect-free logs or on logs whose effect is below its size), with the margins that go with it;
           then the margin per held-out row: the smallest leaving at most 5 % of their no-claim logs with a
           first claim. (Until 2026-11-29 a level was the 5th percentile of |estimate| / truth over the logs
           holding the effect at its size: failed estimates set it, bank and grade at 0.03-0.04 of their size,
           and a third of the held-out family's no-claim logs got a claim.);
  pass 2   the left-out family's logs diagnosed under its fold's calibration: what is scored (score).

The scores follow the issue's reading: on logs of SCORED_FROM_DURATION s or more every log holding an effect at
or above its size counts; shorter ones count when the effect is also above the log's own stated limit. The
worst family is the headline, not the mean.
"""
from __future__ import annotations

import hashlib
import json
import math
import pickle
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.gap import candidates as C
from ddyn.gap import limits as L
from ddyn.gap.benchmark import families as F
from ddyn.gap.config import AMBIGUITY_DBIC, ANY_OTHER, DiagnosisConfig
from ddyn.model import effects as E

NONE = "none"
# the effect families scored (the ten minus none): each has a size that matters in ddyn.gap.limits
EFFECTS = ("steer_delay", "throttle_delay", "steer_lag", "mass_offset", "downforce", "tire_wear", "bank_angle",
           "grade", "yaw_rate_bias", "tire_relaxation")
SIGNED = ("mass_offset", "bank_angle", "grade", "yaw_rate_bias")
PROFILED = ("bank_angle", "grade")      # estimated as profiles: a parameter error is not defined
NONE_SHARE = 0.25
MAGNITUDES = (0.6, 3.0)                 # times the size that matters, log-uniform: about a third below it
DURATIONS = ((60.0, 0.45), (120.0, 0.35), (300.0, 0.20))     # s, share of the logs
DBW_PERIODS = (0.01, 0.02, 0.04, 0.05)  # s: 100, 50, 25 (the log's rate) and 20 Hz drive-by-wire units
NOISE_SCALES = (0.5, 2.0)
NOISE_COLOURS = (0.0, 0.6)
SPEEDS = (18.0, 27.0)
# a case whose driver loses the car (off the track, spun: ddyn.errors.CarLostError) is driven again using these
# shares of the nominal's grip in turn, as a test driver slows down after a spin; the first attempt is the plant's
# default (ddyn.data.simulate.DEFAULT_GRIP, 0.8). The log records the share it was driven at (driver_grip), the
# result the failed attempts (redriven). Until 2026-12-01 such cases were dropped: 31 of the 100 multi-body logs
# of seed 8606 and 17 of its 25 600-900 s ones, the fastest and the longest, so the family scored was the tamest.
REDRIVE_GRIPS = (0.7, 0.6)
CHANNEL_KINDS = ("none", "imu", "map", "broken")
OVAL_SHARE = 0.5                        # bank logs on the banked oval (its own bank), the rest on Putnam
# the track of every log not on the oval (--tracks): "putnam", the track every rule and calibration was chosen on;
# or "road", a full-size random road course per log (road:SEED, ddyn.model.track_random.road_course, the log's own
# seed), tracks no rule has seen: the held-out-track check of a recorded study's folds (--folds-from)
TRACK_SETS = ("putnam", "road")
SCORED_FROM_DURATION = 300.0
MIN_LEVEL_LOGS = 3
# the decision levels a calibration chooses among (shares of the size that matters; None: never claimed). Not
# above 1: a family whose claims need more than its size that matters is not claimable (the reading)
LEVEL_GRID = (None, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
LEVEL_SWEEPS = 2
TARGET_FALSE_ALARMS = 0.05
# the defaults are the README's study (results/gap_lofo.json): `ddyn gap lofo --out D` remakes it
DEFAULT_LOGS = 100
DEFAULT_SEED = 8606


def base_config() -> DiagnosisConfig:
    """The diagnosis the study calibrates: the hold from the log's command steps, every one-parameter effect and the
    bank and grade profiles and channels (drivetrain shapes are not scored: no size that matters). The mass offset
    keeps Iz (mass_inertia False): with Iz scaled, as every family's heavier car has it, the candidate is a
    longitudinal gain alone, and in the study it took grades for a heavier car and claimed more no-claim logs."""
    return DiagnosisConfig(hold="steps", candidates=E.EFFECT_NAMES + C.EXTRA)


def _channel_kinds() -> tuple:
    from ddyn.plants import commonroad_st as CP

    return CHANNEL_KINDS if getattr(CP, "CHANNEL_KINDS", None) else (False, True)


def plan(family: str, n: int, seed: int, durations=DURATIONS, tracks: str = "putnam") -> list[dict]:
    """n cases of one family: the effect, its magnitude and the campaign settings, all drawn from `seed`
    (durations: ((seconds, share), ...) of the log lengths; tracks: one of TRACK_SETS)."""
    if tracks not in TRACK_SETS:
        raise DdynError(f"unknown track set {tracks!r}; expected one of {', '.join(TRACK_SETS)}")
    rng = np.random.default_rng([seed, sum(map(ord, family))])
    effects = [e for e in EFFECTS if e in F.supported_effects(family)]
    sets = F.params_sets(family)
    kinds = _channel_kinds()
    n_none = int(round(NONE_SHARE * n))
    slots = [NONE] * n_none + [effects[i % len(effects)] for i in range(n - n_none)]
    rng.shuffle(slots)
    lengths, weights = zip(*durations)
    out = []
    for i, eff in enumerate(slots):
        duration = float(rng.choice(lengths, p=np.array(weights) / sum(weights)))
        speed = float(rng.uniform(*SPEEDS))
        track = "oval" if eff == "bank_angle" and rng.random() < OVAL_SHARE else "putnam"
        if track == "putnam" and tracks == "road":      # drawn from the log's seed: the other draws stay the same
            track = f"road:{seed * 1000 + i}"
        u = float(math.exp(rng.uniform(math.log(MAGNITUDES[0]), math.log(MAGNITUDES[1]))))
        sign = -1.0 if eff in SIGNED and rng.random() < 0.5 else 1.0
        size = _planned_size(eff, duration, speed)
        out.append({"family": family, "case": i, "effect": eff, "track": track,
                    "magnitude": (0.0 if eff == NONE or track == "oval" else sign * u * size),
                    "params": str(rng.choice(sets)), "seed": int(seed * 1000 + i), "duration": duration,
                    "dbw_period": float(rng.choice(DBW_PERIODS)), "noise_scale": float(rng.uniform(*NOISE_SCALES)),
                    "noise_color": float(rng.choice(NOISE_COLOURS)), "target_speed": speed,
                    "roll_channel": kinds[int(rng.integers(len(kinds)))]})
        out[-1]["pitch_channel"] = out[-1]["roll_channel"]    # one attitude source: the same kind
    return out


def _planned_size(eff: str, duration: float, speed: float) -> float:
    if eff == NONE:
        return 0.0
    return L.size_that_matters(eff, {"duration": duration, "v_max": speed})


def make_case_log(case: dict, make_log=None):
    """The case's log, driven again at REDRIVE_GRIPS while the driver loses the car (the last loss is raised). The
    log's metadata "redriven" lists the failed attempts (empty: the first went round). make_log: F.make_log's
    signature (tests give a stand-in)."""
    from ddyn.errors import CarLostError
    from ddyn.plants import commonroad_st as CP

    make_log = make_log or F.make_log
    effects = {} if case["effect"] == NONE or case["track"] == "oval" else {case["effect"]: case["magnitude"]}
    settings = CP.LogSettings(duration=case["duration"], noise_scale=case["noise_scale"],
                              noise_color=case["noise_color"], target_speed=case["target_speed"],
                              dbw_period=case["dbw_period"], roll_channel=case["roll_channel"],
                              pitch_channel=case["pitch_channel"])
    track = case["track"]
    if track == "oval":
        from ddyn.model.track_oval import oval_track

        track = oval_track()
    elif track.startswith("road:"):
        from ddyn.model.track_random import road_course

        track = road_course(int(track.split(":", 1)[1]))
    failed = []
    for grip in (None,) + REDRIVE_GRIPS:
        try:
            ds = make_log(case["family"], track, CP.PlantEffects(**effects), case["seed"],
                          replace(settings, driver_grip=grip), case["params"])
        except CarLostError as e:
            failed.append(f"grip {'default' if grip is None else grip}: {str(e).splitlines()[0]}")
            if len(failed) > len(REDRIVE_GRIPS):
                raise CarLostError(f"{failed[0]}; driven again at grip {', '.join(map(str, REDRIVE_GRIPS))}: "
                                   f"{str(e).splitlines()[0]}") from None
            continue
        ds.metadata["redriven"] = json.dumps(failed)
        return ds


# what makes a case's log: its cache file is named by them, so a campaign of another size (another shuffle of
# the same seeds) never reads a log made for another case
LOG_FIELDS = ("family", "effect", "track", "magnitude", "params", "seed", "duration", "dbw_period", "noise_scale",
              "noise_color", "target_speed", "roll_channel", "pitch_channel")


def cache_name(case: dict) -> str:
    key = hashlib.sha256(json.dumps([case[k] for k in LOG_FIELDS]).encode()).hexdigest()[:12]
    return f"{case['family']}-{case['seed']}-{key}.pkl"


def _cached_log(case: dict, cache: Path | None):
    path = None if cache is None else cache / cache_name(case)
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes()), 0.0
    t0 = time.perf_counter()
    ds = make_case_log(case)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(ds))
    return ds, time.perf_counter() - t0


def _oval_bank_peak() -> float:
    from ddyn.model.track_oval import oval_track

    return float(np.max(np.abs(oval_track().bank)))


# the plants' ground truth of a road profile, per row of the log
TRUE_PROFILE = {"bank_angle": "true_bank", "grade": "true_grade"}


def log_truth(case: dict, ds) -> float:
    """The size of the effect the log holds. A bank or a grade is a profile along the road (banked into the turns,
    a grade in waves) and its drawn magnitude is the profile's peak over the whole track: a log that drives part of a
    lap may never reach it (seed 8606's 60-120 s Putnam logs drove banks of 1.1-2.2 degrees of peaks of 3.7-8.3), so
    a profile's size is the largest the car drove over (the plant's true_bank or true_grade), with the drawn sign;
    on the banked oval, its own banking. Without that column (a plant that does not record it), the drawn peak."""
    oval = case["track"] == "oval"
    drawn = _oval_bank_peak() if oval else case["magnitude"]
    col = TRUE_PROFILE.get("bank_angle" if oval else case["effect"])
    if col is None or col not in ds.extras:
        return drawn
    peak = float(np.max(np.abs(np.asarray(ds.extras[col], float))))
    return math.copysign(peak, drawn) if drawn else peak


def run_case(case: dict) -> dict:
    """Make (or read the cached) log of a case and diagnose it under case["config"]; what a score needs."""
    from ddyn.gap.problem import nominal_from_vehicle
    from ddyn.gap.selection import diagnose
    from ddyn.model.vehicle import load as load_vehicle

    cache = Path(case["cache"]) if case.get("cache") else None
    try:
        ds, sim_s = _cached_log(case, cache)
    except (DdynError, FloatingPointError, ValueError, RuntimeError) as e:
        return case | {"status": "simulation failed", "error": str(e).splitlines()[0] if str(e) else repr(e)}
    veh = load_vehicle(F.nominal_vehicle(case["family"], case["params"]))
    t0 = time.perf_counter()
    track = None
    if case["track"] == "oval" and case.get("track_known"):
        from ddyn.model.track_oval import oval_track

        track = oval_track()
    try:
        d = diagnose(ds, nominal_from_vehicle(veh, ds), DiagnosisConfig.from_dict(case["config"]), track=track)
    except DdynError as e:
        return case | {"status": "diagnosis failed", "error": str(e)}
    fams: dict = {}
    for c in d["candidates"]:      # best first: the first of each family is its best
        fam = C.FAMILY.get(c["effect"], c["effect"])
        if fam not in fams:
            fams[fam] = {"candidate": c["effect"], "delta_bic": c["delta_bic"], "at_bound": c["at_bound"],
                         "size": float(c.get("magnitude", next(iter(c["params"].values()))))}
    top = d["candidates"][0]
    truth = log_truth(case, ds)
    return {k: v for k, v in case.items() if k not in ("config", "cache")} | {
        "status": "ok", "true_magnitude": truth,
        "driver_grip": float(ds.metadata.get("driver_grip", "nan")),
        "redriven": len(json.loads(ds.metadata.get("redriven", "[]"))),
        "rows": len(ds), "sample_time": float(ds.sample_time), "heldout_rows": d["split"]["heldout_rows"],
        "candidates_tried": len(d["candidates"]), "families": fams,
        "top": C.FAMILY.get(top["effect"], top["effect"]), "delta_bic_top": top["delta_bic"],
        "runner_up_gap": (d.get("runner_up") or {}).get("evidence_difference"),
        "claimed": [C.FAMILY.get(s, s) for s in d["selected"]],
        "unclaimed": [e["effect"] for e in d["model"].get("unclaimed", [])],
        "limits": {f: {"size": v["size_that_matters"], "limit": v["limit"], "gain": v["gain_at_size"],
                       "bound_by": v.get("bound_by")}
                   for f, v in d["limits"].items()},
        "margin": d["gate"]["min_evidence"], "verdict": d["verdict"],
        "seconds_simulation": sim_s, "seconds_diagnosis": time.perf_counter() - t0,
    }


# ----------------------------------------------------------------------------------------------- calibration

def _size(r: dict, fam: str) -> float | None:
    lim = r["limits"].get(fam)
    return None if lim is None else lim["size"]


def _matters(r: dict) -> bool:
    s = _size(r, r["effect"])
    return s is not None and abs(r["true_magnitude"]) >= s * (1 - 1e-9)


def _no_claim_log(r: dict) -> bool:
    return r["effect"] == NONE or not _matters(r)


def _tail_levels(records: list[dict]) -> dict:
    """{family: the 5th percentile of |estimate| / truth over the logs holding it at or above its size, or None
    with fewer than MIN_LEVEL_LOGS such logs}: where the search of decision_levels starts."""
    out = {}
    for fam in EFFECTS:
        ratios = [abs(r["families"][fam]["size"]) / abs(r["true_magnitude"]) for r in records
                  if r["status"] == "ok" and r["effect"] == fam and _matters(r) and fam in r["families"]]
        out[fam] = (min(1.0, float(np.quantile(ratios, TARGET_FALSE_ALARMS))) if len(ratios) >= MIN_LEVEL_LOGS
                    else None)
    return out


def _reaches_level(r: dict, fam: str, levels: dict) -> bool:
    """A pass-1 record's estimate of `fam` could be claimed under `levels`: the family has a level, its estimate
    is off its range edge and at least that share of its size that matters."""
    share, size, f = levels.get(fam), _size(r, fam), r["families"].get(fam)
    return not (share is None or size is None or f is None or f["at_bound"] or abs(f["size"]) < share * size)


def _tied(r: dict) -> bool:
    """Round one's first and its runner-up of another family are not told apart (AMBIGUITY_DBIC)."""
    return r["runner_up_gap"] is not None and r["runner_up_gap"] < AMBIGUITY_DBIC


def first_claim(r: dict, levels: dict, margins: dict, rounds: int = 3) -> str | None:
    """The family a pass-1 record's log would be claimed for first under `levels` and `margins`: its families
    best evidence first, as the diagnosis's rounds go (one that pays but is not claimed is a nuisance, and the
    search goes on, at most `rounds` rounds: max_effects's first plus max_unclaimed). An approximation: the later
    rounds' evidence is read from round one's, without the refit around the nuisance."""
    ranked = sorted(r["families"].items(), key=lambda kv: kv[1]["delta_bic"])
    for i, (fam, f) in enumerate(ranked[:rounds]):
        if f["delta_bic"] >= 0:
            return None
        if not _reaches_level(r, fam, levels) or -f["delta_bic"] / r["heldout_rows"] <= margins.get(fam, 0.0):
            continue
        if i == 0 and _tied(r):
            continue
        return fam
    return None


def _net_right(records: list[dict], levels: dict) -> int:
    """First claims right on the logs holding an effect at its size, less first claims on no-claim logs, under
    `levels` and the family margins that go with them."""
    margins = family_margins(records, levels)
    net = 0
    for r in records:
        c = first_claim(r, levels, margins)
        if _no_claim_log(r):
            net -= c is not None
        else:
            net += c == r["effect"]
    return net


def decision_levels(records: list[dict]) -> dict:
    """{family: share of its size that matters, or None} from pass-1 records (module docstring): coordinate
    search over LEVEL_GRID from the tail levels, LEVEL_SWEEPS sweeps, of the families with at least MIN_LEVEL_LOGS
    logs at their size (the others: None); among levels as good, a claimable one and then the higher."""
    ok = [r for r in records if r["status"] == "ok"]
    levels = _tail_levels(ok)
    searched = [fam for fam in EFFECTS if levels[fam] is not None]     # too few logs of it: never claimed
    for _ in range(LEVEL_SWEEPS):
        for fam in searched:
            scored = [((_net_right(ok, {**levels, fam: s}), s is not None, s or 0.0), s) for s in LEVEL_GRID]
            levels[fam] = max(scored, key=lambda t: t[0])[1]
    return levels


def _would_claim_first(r: dict, levels: dict) -> float | None:
    """The margin per held-out row below which the log's first candidate would be claimed (None: never, by its
    size, its range edge or a tie)."""
    if not _reaches_level(r, r["top"], levels) or _tied(r):
        return None
    return max(0.0, -r["delta_bic_top"] / r["heldout_rows"])


def _alarm_logs(records: list[dict]) -> list[dict]:
    """The logs where a first claim of the top candidate's family would be a false one: effect-free logs, and logs
    whose effect is below its size when another family comes first (the true family's claims there are its
    decision level's to stop, not a margin's: the effect is real)."""
    return [r for r in records if r["status"] == "ok" and
            (r["effect"] == NONE or (not _matters(r) and r["top"] != r["effect"]))]


def family_margins(records: list[dict], levels: dict, target: float = TARGET_FALSE_ALARMS) -> dict:
    """{family: margin per held-out row}: each family's own, the smallest leaving its false first claims out of the
    alarm logs (_alarm_logs), except the `target` share of those logs with the largest evidence, which stay alarms
    (a systematic mismatch pays as one or two families, so one family's spurious gains do not raise every other
    family's margin). Families that never come first falsely get 0."""
    logs = _alarm_logs(records)
    alarms = sorted(((m, r["top"]) for r in logs if (m := _would_claim_first(r, levels)) is not None), reverse=True)
    allowed = int(math.floor(target * len(logs)))
    out = {fam: 0.0 for fam in EFFECTS}
    for m, fam in alarms[allowed:]:
        out[fam] = max(out.get(fam, 0.0), m * (1 + 1e-9))
    return out


def calibrate(records: list[dict]) -> dict:
    levels = decision_levels(records)
    return {"decision_levels": levels, "family_margins_per_row": family_margins(records, levels),
            "families": sorted({r["family"] for r in records}), "logs": len(records)}


def applied_config(cal: dict) -> DiagnosisConfig:
    return base_config().with_(family_margins_per_row={**cal["family_margins_per_row"], ANY_OTHER: 0.0},
                               decision_levels={**cal["decision_levels"], ANY_OTHER: None})


# ----------------------------------------------------------------------------------------------- score

def _scored(r: dict) -> bool:
    """A log with an effect counts in the scoring: at or above its size, and on logs shorter than
    SCORED_FROM_DURATION also at or above the log's own stated limit (issue 33 item 4)."""
    if not _matters(r):
        return False
    if r["duration"] >= SCORED_FROM_DURATION:
        return True
    lim = r["limits"].get(r["effect"], {}).get("limit")
    return lim is not None and abs(r["true_magnitude"]) >= lim


def score(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["status"] == "ok"]
    eff = [r for r in ok if r["effect"] != NONE]

    sc = [r for r in eff if _scored(r)]
    right = [r for r in sc if r["claimed"][:1] == [r["effect"]]]
    none = [r for r in ok if r["effect"] == NONE]
    below = [r for r in eff if not _matters(r)]
    dl = [r for r in sc if r["effect"] in ("steer_delay", "steer_lag")
          and r["claimed"][:1] and r["claimed"][0] in ("steer_delay", "steer_lag")]
    perr = {}
    for r in sc:
        if r["effect"] in PROFILED or r["effect"] not in r["families"]:
            continue
        perr.setdefault(r["effect"], []).append(abs(r["families"][r["effect"]]["size"] - r["true_magnitude"])
                                                / abs(r["true_magnitude"]))
    above_limit = [r for r in eff if (lim := r["limits"].get(r["effect"], {}).get("limit")) is not None
                   and abs(r["true_magnitude"]) >= lim]
    stated = [(v["limit"] is not None and v["limit"] <= v["size"]) for r in ok for f, v in r["limits"].items()
              if f in EFFECTS]
    per_effect = {}
    for e in EFFECTS:
        es = [r for r in sc if r["effect"] == e]
        if es:
            per_effect[e] = {"scored": len(es), "right": sum(r["claimed"][:1] == [e] for r in es),
                             "wrong": sum(bool(r["claimed"]) and r["claimed"][0] != e for r in es),
                             "missed": sum(not r["claimed"] for r in es)}
    all_err = [x for v in perr.values() for x in v]
    return {
        "logs": len(rows), "ok": len(ok), "failed": len(rows) - len(ok),
        "redriven": sum(bool(r.get("redriven")) for r in ok),
        "scored": len(sc), "first_right": len(right), "first_right_rate": len(right) / len(sc) if sc else None,
        "effect_free": len(none), "effect_free_claimed": sum(bool(r["claimed"]) for r in none),
        "below_size": len(below), "below_size_claimed": sum(bool(r["claimed"]) for r in below),
        "delay_vs_lag": {"told": len(dl), "right": sum(r["claimed"][0] == r["effect"] for r in dl)},
        "param_error_median": statistics.median(all_err) if all_err else None,
        "param_error_median_per_effect": {e: statistics.median(v) for e, v in perr.items()},
        "limits_hold": {"above_stated_limit": len(above_limit),
                        "found": sum(r["claimed"][:1] == [r["effect"]] for r in above_limit),
                        "limit_at_or_below_size": sum(stated), "limit_statements": len(stated)},
        "per_effect": per_effect,
    }


def _rate(a, b):
    return f"{a}/{b}" + (f" ({100 * a / b:.0f} %)" if b else "")


def _seeds(doc: dict) -> list:
    seed = doc["settings"]["seed"]
    return seed if isinstance(seed, list) else [seed]


def markdown(doc: dict) -> str:
    seed = doc["settings"]["seed"]
    seed = f"seeds {', '.join(map(str, seed))}, pooled" if isinstance(seed, list) else f"seed {seed}"
    lines = [f"# Leave one plant family out ({doc['settings']['logs_per_family']} logs per family, {seed})", "",
             "Each family scored blind under the calibration of the others (ddyn.gap.benchmark.lofo)."
             + (" The calibrations are those of the study in {results} (seed {seed}, {logs_per_family} logs per "
                "family): ".format(**doc["settings"]["folds_from"])
                + ("that study's own logs are pooled too, each family's scored under the fold made from the other "
                   "families' logs." if doc["settings"]["folds_from"]["seed"] in _seeds(doc)
                   else "no log of this campaign chose anything.")
                if doc["settings"].get("folds_from") else ""), "",
             "| left out | simulated | largest family margin/row | claimable | first effect right | effect-free claimed "
             "| below size claimed | delay vs lag | median param error | found above stated limit | limit <= size |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for fam, f in doc["folds"].items():
        s, cal = f["score"], f["calibration"]
        claimable = sum(v is not None for v in cal["decision_levels"].values())
        pe = s["param_error_median"]
        lh = s["limits_hold"]
        top = max(cal["family_margins_per_row"].items(), key=lambda kv: kv[1])
        # logs the plant could not drive (the driver lost the car at every grip) are not scored: say how many, and
        # how many went round only when driven again more gently
        redriven = f" ({s['redriven']} re-driven)" if s.get("redriven") else ""
        lines.append(f"| {fam} | {s['ok']}/{s['logs']}{redriven} | {top[1]:.3g} ({top[0]}) | {claimable}/{len(EFFECTS)} | "
                     f"{_rate(s['first_right'], s['scored'])} | {_rate(s['effect_free_claimed'], s['effect_free'])} | "
                     f"{_rate(s['below_size_claimed'], s['below_size'])} | "
                     f"{_rate(s['delay_vs_lag']['right'], s['delay_vs_lag']['told'])} | "
                     f"{'-' if pe is None else f'{100 * pe:.0f} %'} | {_rate(lh['found'], lh['above_stated_limit'])} | "
                     f"{_rate(lh['limit_at_or_below_size'], lh['limit_statements'])} |")
    w = doc.get("worst")
    if w:
        lines += ["", f"Worst family: {w['family']} ({w['why']})."]
    lines += misses_markdown(doc.get("pass2", []))
    if doc.get("skipped"):
        lines += ["", "Not run: " + "; ".join(f"{k}: {v}" for k, v in doc["skipped"].items()) + "."]
    return "\n".join(lines) + "\n"


def _first(r: dict) -> str:
    return r["claimed"][0] if r["claimed"] else "none"


def misses(rows: list[dict]) -> dict:
    """The logs behind the rates, as score() counts them: {"scored_not_right": scored logs whose first claim is
    not their effect, "claimed_no_claim": effect-free logs and logs below their effect's size with a claim}."""
    ok = [r for r in rows if r["status"] == "ok"]
    eff = [r for r in ok if r["effect"] != NONE]
    return {"scored_not_right": [r for r in eff if _scored(r) and r["claimed"][:1] != [r["effect"]]],
            "claimed_no_claim": [r for r in ok if _no_claim_log(r) and r["claimed"]]}


def misses_markdown(rows: list[dict]) -> list[str]:
    """The misses as a table per kind (where a user looks first when a family's rate falls short)."""
    m = misses(rows)
    out = []
    head = ("| family | case | effect | true size | limit | s | track | channel | first claim | top candidate "
            "(dBIC) |", "|---|---|---|---|---|---|---|---|---|---|")
    for key, title in (("scored_not_right", "Scored logs whose first claim is not their effect"),
                       ("claimed_no_claim", "Effect-free logs and logs below the size that matters with a claim")):
        rs = sorted(m[key], key=lambda r: (r["family"], r["effect"], r.get("case", 0)))
        out += ["", f"{title} ({len(rs)}):"]
        if not rs:
            continue
        out += ["", *head]
        for r in rs:
            lim = r["limits"].get(r["effect"], {}).get("limit") if r["effect"] != NONE else None
            top = r.get("families", {}).get(r.get("top"), {})
            out.append(f"| {r['family']} | {r.get('case', '-')} | {r['effect']} | {r['true_magnitude']:.4g} | "
                       f"{'-' if lim is None else f'{lim:.3g}'} | {r['duration']:g} | {r.get('track', '-')} | "
                       f"{r.get('roll_channel', '-')} | {_first(r)} | {r.get('top', '-')} "
                       f"({top.get('delta_bic', float('nan')):.1f}) |")
    return out


def worst(folds: dict) -> dict | None:
    rated = [(f["score"]["first_right_rate"], fam) for fam, f in folds.items()
             if f["score"]["first_right_rate"] is not None]
    if not rated:
        return None
    rate, fam = min(rated)
    return {"family": fam, "first_right_rate": rate,
            "why": f"first effect right on {100 * rate:.0f} % of its scored logs, the lowest"}


def recorded_folds(doc: dict, path: Path, families: list[str], seed: int) -> dict:
    """{family: its fold's calibration} of a recorded study (its results.json `doc`), for scoring another campaign
    under them (run(folds_from=...)); one DdynError line naming the file and what is missing or wrong."""
    try:
        folds = {fam: doc["folds"][fam]["calibration"] for fam in doc["folds"]}
        recorded_seed = doc["settings"]["seed"]
        doc["all_families_calibration"]["decision_levels"]
    except (KeyError, TypeError) as e:
        raise DdynError(f"{path}: not a leave-one-family-out study's results.json (no {e})") from None
    missing = [fam for fam in families if fam not in folds]
    if missing:
        raise DdynError(f"{path}: no fold for {', '.join(missing)} (it left out {', '.join(folds) or 'none'})")
    if recorded_seed == seed:
        raise DdynError(f"--seed {seed}: the recorded study's own campaign; score another seed (its logs are the "
                        "ones its calibrations and their rules were chosen on)")
    return folds


def _fold_calibrations(doc: dict) -> dict:
    return {fam: f.get("calibration") for fam, f in doc.get("folds", {}).items()}


def pooled(docs: list[tuple[dict, Path]]) -> dict:
    """One document of several campaigns each scored blind under the SAME recorded study's folds (`--folds-from`
    runs with different seeds), and optionally that recorded study itself: their pass-2 records joined and every
    family scored again on the union. Why: a campaign of 30 logs per family scores 11-16 of them, so one log moves a
    family's rate by 6-9 points; more blind campaigns under the same calibration narrow that without choosing
    anything. The recorded study's own pass 2 may join: each family's logs in it were scored under the fold made
    from the OTHER families' logs, the very calibrations the campaigns were scored under, so per family they are as
    blind as a campaign's. Refused (one DdynError line naming the file): no --folds-from campaign, a document that
    is neither such a campaign nor the study they were scored under (same seed, same fold calibrations), another
    recorded study or other diagnosis settings than the first, a seed twice, or a family missing from one of them."""
    if len(docs) < 2:
        raise DdynError("ddyn gap pool: give two or more campaigns' results.json (each a --folds-from run, or the "
                        "study they were scored under)")
    seeds, rows = [], []
    for doc, path in docs:
        try:
            doc["settings"]["seed"], doc["settings"]["base_config"], doc["pass2"], doc["folds"]
        except (KeyError, TypeError) as e:
            raise DdynError(f"{path}: not a leave-one-family-out study's results.json (no {e})") from None
    campaigns = [(doc, path) for doc, path in docs if doc["settings"].get("folds_from")]
    if not campaigns:
        raise DdynError(f"{docs[0][1]}: not scored under a recorded study's folds (a --folds-from run); give at least "
                        "one --folds-from campaign, its own calibration chose on its logs")
    ref, ref_path = campaigns[0][0]["settings"]["folds_from"], campaigns[0][1]
    first, first_path = docs[0]
    for doc, path in docs:
        st, ff = doc["settings"], doc["settings"].get("folds_from")
        if not ff and (st["seed"] != ref["seed"] or _fold_calibrations(doc) != _fold_calibrations(campaigns[0][0])):
            raise DdynError(f"{path}: not scored under a recorded study's folds (a --folds-from run) nor the study "
                            f"{ref_path} was scored under (seed {ref['seed']}); its own calibration chose on its "
                            "logs, so it cannot be pooled as blind")
        if ff and ff != ref:
            raise DdynError(f"{path}: scored under {ff['results']} (seed {ff['seed']}), {ref_path} under "
                            f"{ref['results']} (seed {ref['seed']})")
        if st["base_config"] != first["settings"]["base_config"]:
            raise DdynError(f"{path}: its diagnosis settings (base_config) differ from {first_path}'s")
        if st["seed"] in seeds:
            raise DdynError(f"{path}: seed {st['seed']} is pooled twice")
        if set(doc["folds"]) != set(first["folds"]):
            raise DdynError(f"{path}: families {', '.join(doc['folds'])}, {first_path} has {', '.join(first['folds'])}")
        seeds.append(st["seed"])
        rows += doc["pass2"]
    folds = {fam: {"calibration": f["calibration"], "score": score([r for r in rows if r["family"] == fam])}
             for fam, f in first["folds"].items()}
    settings = {**first["settings"], "seed": seeds, "folds_from": ref,
                "logs_per_family": sum(d["settings"]["logs_per_family"] for d, _ in docs),
                # the campaigns' track sets, all of them: a pool of Putnam and road campaigns is not either alone
                "tracks": "+".join(sorted({d["settings"].get("tracks", "putnam") for d, _ in docs})),
                "pooled": [str(p) for _, p in docs]}
    doc = {"settings": settings, "skipped": first.get("skipped", {}), "folds": folds, "worst": worst(folds),
           "all_families_calibration": first["all_families_calibration"], "pass1": [], "pass2": rows,
           "seconds": sum(d.get("seconds", 0.0) for d, _ in docs)}
    doc["markdown"] = markdown(doc)
    return doc


def run(families: list[str], n: int, seed: int, out: Path, jobs: int = 1, progress: bool = True,
        durations=DURATIONS, folds_from: dict | None = None, tracks: str = "putnam") -> dict:
    """The study: plan, pass 1, folds, pass 2; the results document (written by the caller).
    folds_from: {"doc": a recorded study's results.json, "path": where it was read}: no pass 1, each family's logs
    of this campaign are scored under that study's fold calibration for it (made from the OTHER families' logs of
    the recorded campaign): the check on logs that neither the calibrations nor the choices behind their rules
    saw (another seed), still with each family left out."""
    from ddyn.gap.benchmark.parallel import run_cases

    t0 = time.perf_counter()
    skipped = {}
    use = []
    for fam in families:
        ok, why = F.available(fam)
        (use.append(fam) if ok else skipped.__setitem__(fam, why))
    if len(use) < 2:
        raise DdynError(f"leave-one-family-out needs at least two families that run here; have {use or 'none'} "
                        f"({'; '.join(f'{k}: {v}' for k, v in skipped.items())})")
    cache = out / "logs"
    cfg = base_config().to_dict()
    # pass 1 reads round one only (what the calibration reads): one effect, no nuisance rounds
    first_round = base_config().with_(max_effects=1, max_unclaimed=0).to_dict()
    cases = [c | {"config": first_round, "cache": str(cache)}
             for fam in use for c in plan(fam, n, seed, durations, tracks)]
    recorded = None
    if folds_from is not None:
        recorded = recorded_folds(folds_from["doc"], folds_from["path"], use, seed)
    pass1 = [] if recorded else run_cases(run_case, cases, jobs, "pass 1 (uncalibrated)", progress)
    folds, second = {}, []
    for fam in use:
        cal = recorded[fam] if recorded else calibrate([r for r in pass1 if r["family"] != fam])
        folds[fam] = {"calibration": cal}
        conf = applied_config(cal).to_dict()
        second += [c | {"config": conf, "cache": str(cache)} for c in cases if c["family"] == fam]
    pass2 = run_cases(run_case, second, jobs, "pass 2 (left-out family, its fold's calibration)", progress)
    for fam in use:
        folds[fam]["score"] = score([r for r in pass2 if r["family"] == fam])
    doc = {"settings": {"families": use, "logs_per_family": n, "seed": seed, "base_config": cfg,
                        "effects": list(EFFECTS), "durations": [list(d) for d in durations],
                        "dbw_periods": list(DBW_PERIODS), "noise_scales": list(NOISE_SCALES), "tracks": tracks},
           "skipped": skipped, "folds": folds, "worst": worst(folds),
           "all_families_calibration": (folds_from["doc"]["all_families_calibration"] if recorded
                                        else calibrate(pass1)),
           "pass1": pass1, "pass2": pass2, "seconds": time.perf_counter() - t0}
    if recorded:
        rs = folds_from["doc"]["settings"]
        doc["settings"]["folds_from"] = {"results": str(folds_from["path"]), "seed": rs["seed"],
                                         "logs_per_family": rs["logs_per_family"]}
    doc["markdown"] = markdown(doc)
    return doc
