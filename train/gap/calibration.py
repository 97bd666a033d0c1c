"""Calibration: the one scoring library of the gap diagnosis, and the calibration artifact.

The rules, on recorded benchmark cases (a case's `effect`, `magnitude`, `estimate`, `selected_without_gate`,
`delta_bic_top`, `gate_ratio`; nothing is re-run): the margin rule (`calibrate_margin`: the smallest evidence
margin leaving <= 5 % of the effect-free logs with a selection), the threshold rule (`reliable_threshold`: the
smallest magnitude whose whole tail, over at least two magnitude levels, is found first at >= 95 %), Currie's
decision levels below the thresholds, and claim precision (an effect keeps its threshold only while <= 5 % of the
claims it would make land where nothing should be claimed).

The artifact (`Calibration`, `ddyn gap calibrate`): one JSON file with the settings the sweeps diagnosed with,
the margin, thresholds, decision levels and claim record they give, the plant, car, track, the log lengths and
sample time it covers, the seeds, and the version of the fitting code that made it. Calibrations the project
stands behind ship in `ddyn/gap/calibrations/` and load by name; `ddyn gap diagnose` uses one that covers the log.
"""
from __future__ import annotations

import datetime
import json
import math
import subprocess
from dataclasses import dataclass, fields
from pathlib import Path
from statistics import NormalDist

import numpy as np

from ddyn.gap import candidates as C
from ddyn.gap.config import AMBIGUITY_DBIC
from ddyn.errors import DdynError

NONE = "none"
TARGET_FALSE_ALARMS = 0.05
# A run that recorded no log length made logs of this many seconds (commonroad.DURATION before `--duration`)
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
    """The results.json documents of one run's path or of several separated by commas (or the documents
    themselves, a list of dicts)."""
    if isinstance(paths, list) and all(isinstance(p, dict) for p in paths):
        return paths
    if isinstance(paths, (str, Path)):
        paths = [p for p in str(paths).split(",") if p]
    return [json.loads(Path(p).read_text()) for p in paths]


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
    (docs/gap.md). min_levels: pooled sweeps share their magnitude grid, so a tail of one level (its
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


# ----------------------------------------------------------------------------------------------- the artifact

SCHEMA = "ddyn-gap-calibration 1"
SHIPPED_DIR = Path(__file__).resolve().parent / "calibrations"
# how far a log's length may be from the calibration's: a dBIC sums over the held-out rows, so a margin measured
# on 60 s logs does not hold on 90 s ones
LENGTH_TOLERANCE = 0.1
# the code whose behaviour a calibration measures: the diagnosis's fitting and selection, the model it composes
# effects on, and the plant that made the sweeps' logs. Hashed without comments and docstrings (ast), so a
# calibration goes stale when what the code does changes, not when its words do.
FITTING_MODULES = ("ddyn.gap.config", "ddyn.gap.candidates", "ddyn.gap.problem", "ddyn.gap.fit", "ddyn.gap.heldout",
                   "ddyn.gap.selection", "ddyn.gap.limits", "ddyn.gap.eiv", "ddyn.gap.hold_estimate",
                   "ddyn.data.roll_check", "ddyn.data.laps", "ddyn.model.effects",
                   "ddyn.model.single_track", "ddyn.model.integrators", "ddyn.model.mathns", "ddyn.model.backends",
                   "ddyn.model.vehicle", "ddyn.data.dataset")
# What makes the plants' logs besides the plant modules themselves: the driver, its speed profile and the sensor
# noise (ddyn.data.simulate), the tracks (Putnam's file reader, the banked oval, the road courses) and the
# identification behind the MuJoCo car's nominal (ddyn.gap.benchmark.commonroad). Until 2026-12-01 none of them was
# hashed, so a change to the driver kept a calibration "current" whose logs it no longer drove.
LOG_MODULES = ("ddyn.data.simulate", "ddyn.data.vehicle_ref", "ddyn.model.tracks", "ddyn.model.track_files",
               "ddyn.model.track_oval", "ddyn.model.track_random", "ddyn.gap.benchmark.commonroad")
PLANT_MODULES = {"commonroad": ("ddyn.plants.commonroad_st",) + LOG_MODULES,
                 "commonroad-mb": ("ddyn.plants.commonroad_st", "ddyn.plants.commonroad_mb") + LOG_MODULES,
                 # a travelling calibration: every plant family's code and the study that drew their logs
                 "families": ("ddyn.plants.commonroad_st", "ddyn.plants.commonroad_mb", "ddyn.plants.mujoco_car",
                              "ddyn.gap.benchmark.families", "ddyn.gap.benchmark.lofo", "ddyn.gap.baseline")
                 + LOG_MODULES}
# The ddyn modules the hashed ones import that cannot change what a calibration measures, and why; every other
# import of a hashed module must be hashed too (tests/python/test_gap_calibrations.py checks it).
NOT_MEASURED = {
    "ddyn.errors": "error types and messages",
    "ddyn.paths": "where files are",
    "ddyn.gap.calibration": "this module: the sweeps' rules and the artifact; the families' rules are lofo.py's",
    "ddyn.gap.benchmark.parallel": "runs the same cases in processes or on Dask, results in case order",
    "ddyn.gap.benchmark.seeds": "the seed ledger: which seeds have been looked at",
    "ddyn.gap.where": "where the error lies along the log: reported, never read by the selection",
    "ddyn.data.windows": "history windows of a DDM nominal (--model); calibrations diagnose with vehicle files",
    "ddyn.learn.checkpoint": "a DDM nominal (--model); calibrations diagnose with vehicle files",
    "ddyn.learn.networks": "a DDM nominal (--model); calibrations diagnose with vehicle files",
    "ddyn.learn.training": "a DDM nominal (--model); calibrations diagnose with vehicle files",
}
# the plants' vehicle files (train/vehicles/plants): the cars the plants drive and the nominal each case is
# diagnosed with (the MuJoCo car's identified one among them), hashed as parsed JSON so that only a value moves it
PLANT_FILES = ("vehicles/plants/*.json",)


def _stripped(source: str) -> str:
    import ast

    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(getattr(body[0], "value", None), ast.Constant) and isinstance(body[0].value.value, str):
            body[0] = ast.Pass()
    return ast.dump(tree, include_attributes=False)


def code_version(modules) -> str:
    """sha256 (first 16 hex digits) of what the modules' code does (comments and docstrings left out)."""
    import hashlib
    import importlib.util

    h = hashlib.sha256()
    for name in modules:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise DdynError(f"code version: module {name} not found")
        h.update(name.encode())
        h.update(_stripped(Path(spec.origin).read_text()).encode())
    return h.hexdigest()[:16]


def data_version(patterns, root: Path = Path(__file__).resolve().parents[1]) -> str:
    """sha256 (first 16 hex digits) of the JSON files matching `patterns` under `root` (train/), each parsed and
    dumped with sorted keys: a value that changes moves it, a re-indented file does not."""
    import hashlib

    h = hashlib.sha256()
    for path in sorted({p for pat in patterns for p in root.glob(pat)}):
        try:
            value = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise DdynError(f"code version: {path}: not readable JSON ({e})") from None
        h.update(path.relative_to(root).as_posix().encode())
        h.update(json.dumps(value, sort_keys=True).encode())
    return h.hexdigest()[:16]


def current_code_version(plant: str) -> dict:
    """{"fitting": the diagnosis's code, "plant": the code and vehicle files that make the plant's logs}."""
    modules = PLANT_MODULES.get(plant, ())
    plant_version = _combined(code_version(modules), data_version(PLANT_FILES)) if modules else code_version(())
    return {"fitting": code_version(FITTING_MODULES), "plant": plant_version}


def _combined(*versions: str) -> str:
    import hashlib

    return hashlib.sha256("/".join(versions).encode()).hexdigest()[:16]


def _stale(cal) -> str | None:
    """Why a calibration no longer describes the code (another fitting or plant code than it records), or None."""
    now = current_code_version(cal.plant)
    changed = [k for k in ("fitting", "plant") if cal.code_version.get(k) != now[k]]
    return (f"calibration {cal.name} was made by other {' and '.join(changed)} code ({cal.code_version}) than "
            f"the current ({now}): make it again with its command ({cal.made.get('command', '?')})"
            if changed else None)


def _commit() -> str | None:
    """The checkout's short commit (recorded in a calibration), or None outside a git checkout."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=False).stdout.strip() or None
    except OSError:
        return None


@dataclass(frozen=True)
class Calibration:
    """What `ddyn gap calibrate` writes: the settings the sweeps diagnosed with (margin 0, no limits), and what
    they measured under them. Applied (`applied`), it is those settings with the evidence margin and the decision
    levels of its precise thresholds as the limits; every effect it gives no level is reported, never claimed."""

    name: str
    diagnosis: dict            # DiagnosisConfig.to_dict() of the sweeps
    margin: float
    thresholds: dict           # {effect: threshold or None} after the claim-precision rule (what is scored)
    measured_thresholds: dict  # before it
    decision_levels: dict      # {effect: level or None}: the limits on the estimates
    claim_record: dict         # {"counts": {effect: claims}, "withdrawn": [effects]}
    plant: str
    car: str
    track: str
    duration: float            # s of log per case
    sample_time: float
    seeds: tuple
    cases: int
    channels: tuple            # "pitch", "roll": channels the sweeps' logs carried
    code_version: dict
    made: dict                 # commit, date, command
    source: str = ""           # where it was loaded from

    def covers(self, length: float, sample_time: float) -> tuple[bool, str]:
        """(covers a log of this length and sample time, why or why not)."""
        lo, hi = self.length_range
        if abs(sample_time - self.sample_time) > 0.01 * self.sample_time:
            return False, f"{self.name} was made on logs sampled every {self.sample_time:g} s, this log {sample_time:g} s"
        if not lo <= length <= hi:
            return False, (f"{self.name} covers {lo:.0f}-{hi:.0f} s logs ({self.duration:g} s +- "
                           f"{100 * LENGTH_TOLERANCE:.0f} %), this log is {length:.0f} s")
        return True, (f"{self.name} covers {lo:.0f}-{hi:.0f} s logs at {self.sample_time:g} s (made on {self.plant}, "
                      f"{self.car}, {self.track}; seeds {', '.join(map(str, self.seeds))})")

    @property
    def length_range(self) -> tuple[float, float]:
        return self.duration * (1 - LENGTH_TOLERANCE), self.duration * (1 + LENGTH_TOLERANCE)

    def applied(self):
        """The DiagnosisConfig this calibration vouches for: its sweeps' settings, its margin, its decision levels
        (every other effect reported, never claimed), its channel candidates."""
        from ddyn.gap.config import ANY_OTHER, DiagnosisConfig

        base = DiagnosisConfig.from_dict(self.diagnosis, f"calibration {self.name}")
        extra = tuple(c for c, ch in (("grade_from_pitch", "pitch"), ("bank_from_roll", "roll"))
                      if ch in self.channels and c not in base.candidates)
        return base.with_(min_evidence=float(self.margin), candidates=base.candidates + extra,
                          detection_limits={**self.decision_levels, ANY_OTHER: None})

    def stale(self) -> str | None:
        """Why this calibration no longer describes the code (another fitting or plant code), or None."""
        return _stale(self)

    def summary(self) -> dict:
        """What a report records of the calibration it applied."""
        return {"name": self.name, "source": self.source, "margin": self.margin,
                "decision_levels": self.decision_levels, "thresholds": self.thresholds, "plant": self.plant,
                "car": self.car, "track": self.track, "log_lengths_s": list(self.length_range),
                "sample_time": self.sample_time, "code_version": self.code_version}

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "source"}
        return {"schema": SCHEMA, **{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}}


def from_runs(name: str, docs: list[dict], command: str = "") -> Calibration:
    """The calibration of sweep runs (results.json documents of `ddyn gap benchmark --case-set sweep` with margin 0
    and no limits) pooled: their shared settings, the pooled margin, the thresholds and decision levels at that
    margin under the claim-precision rule."""
    if not docs:
        raise DdynError("calibration: no sweep runs")
    first = docs[0]["settings"]
    keys = ("plant", "duration", "diagnosis", "track", "pitch_channel", "roll_channel", "nominal", "car")
    for i, doc in enumerate(docs[1:], 1):
        differ = [k for k in keys if doc["settings"].get(k) != first.get(k)]
        if differ:
            raise DdynError(f"calibration: run {i} differs from run 0 in {', '.join(differ)}; runs pooled as one "
                            "calibration must share their settings")
    for i, doc in enumerate(docs):
        s = doc["settings"]
        if s.get("case_set") != "sweep" or (s.get("diagnosis") or {}).get("min_evidence") or \
                (s.get("diagnosis") or {}).get("detection_limits"):
            raise DdynError(f"calibration: run {i} is not a sweep recorded with margin 0 and no limits")
    if not first.get("sample_time"):
        raise DdynError("calibration: the sweep runs record no sample_time (runs of an older version: run them again)")
    margin = margin_of(docs)
    commit = _commit()
    return Calibration(
        name=name, diagnosis=dict(first["diagnosis"]), margin=float(margin),
        thresholds=thresholds_of(docs, margin, precision=True, decision=True),
        measured_thresholds=thresholds_of(docs, margin),
        decision_levels=decision_limits_of(docs, margin, precision=True),
        claim_record=precision_record(docs, margin, decision=True),
        plant=first["plant"], car=first.get("car", "?"), track=first.get("track", "?"),
        duration=float(first.get("duration") or DURATION), sample_time=float(first["sample_time"]),
        seeds=tuple(int(d["settings"]["seed"]) for d in docs), cases=sum(len(d["results"]) for d in docs),
        channels=tuple(ch for ch in ("pitch", "roll") if first.get(f"{ch}_channel")),
        code_version=current_code_version(first["plant"]),
        made={"commit": commit, "date": datetime.date.today().isoformat(), "command": command})


def write(cal: Calibration, path: str | Path) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(cal.to_dict(), indent=1, default=float) + "\n")
    return p


def load(name_or_path: str | Path) -> Calibration:
    """A shipped calibration by name (calibrations/NAME.json) or a calibration file; errors name the file/key."""
    p = Path(name_or_path)
    if not p.is_file():
        shipped = SHIPPED_DIR / f"{name_or_path}.json"
        if not shipped.is_file():
            names = ", ".join(shipped_names()) or "none"
            raise DdynError(f"calibration {name_or_path}: no such file, nor a shipped calibration (shipped: {names})")
        p = shipped
    try:
        raw = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DdynError(f"{p}: not a calibration file: {e}") from None
    if isinstance(raw, dict) and raw.get("schema") == SCHEMA_TRAVELLING:
        return _load_travelling(raw, p)
    if not isinstance(raw, dict) or raw.get("schema") != SCHEMA:
        raise DdynError(f"{p}: not a calibration file (schema {raw.get('schema') if isinstance(raw, dict) else None!r}, "
                        f"expected {SCHEMA!r}; `ddyn gap calibrate` writes one)")
    want = {f.name for f in fields(Calibration)} - {"source"}
    missing = sorted(want - set(raw))
    if missing:
        raise DdynError(f"{p}: key(s) {', '.join(missing)} missing")
    try:
        cal = Calibration(**{k: tuple(v) if k in ("seeds", "channels") else v for k, v in raw.items() if k in want},
                          source=str(p))
        cal.applied()   # its settings validate
    except (TypeError, ValueError) as e:
        raise DdynError(f"{p}: {e}") from None
    return cal


SCHEMA_TRAVELLING = "ddyn-gap-calibration 2"


@dataclass(frozen=True)
class TravellingCalibration:
    """A calibration that applies to any log length (`ddyn gap lofo --calibration-out`): made on every plant
    family's logs of several lengths, rates and cars, it holds each effect family's evidence margin per held-out
    row and decision levels as shares of each effect family's size that matters, so both scale with the log (ddyn.gap.limits);
    what it is worth on a plant it never saw is its leave-one-family-out score (`lofo`)."""

    name: str
    diagnosis: dict            # the applied DiagnosisConfig (family_margins_per_row, decision_levels)
    families: tuple
    logs: int
    durations: tuple           # (shortest, longest) s of the logs it was made on
    sample_time: float
    lofo: dict                 # the worst left-out family's score under the same rules
    code_version: dict
    made: dict
    source: str = ""

    plant = "families"

    @property
    def duration(self) -> float:       # covering() prefers the calibration nearest a log's length
        return math.sqrt(self.durations[0] * self.durations[1])

    def covers(self, length: float, sample_time: float) -> tuple[bool, str]:
        if abs(sample_time - self.sample_time) > 0.01 * self.sample_time:
            return False, (f"{self.name} was made on logs sampled every {self.sample_time:g} s, this log "
                           f"{sample_time:g} s (its margin is per held-out row)")
        lo, hi = self.durations
        where = (f"inside the {lo:.0f}-{hi:.0f} s it was made on" if lo <= length <= hi else
                 f"outside the {lo:.0f}-{hi:.0f} s it was made on: its margin and levels scale with the log, "
                 "extrapolated")
        return True, (f"{self.name} travels: made on {', '.join(self.families)} ({self.logs} logs), this "
                      f"{length:.0f} s log is {where}")

    def applied(self):
        from ddyn.gap.config import DiagnosisConfig

        return DiagnosisConfig.from_dict(self.diagnosis, f"calibration {self.name}")

    def stale(self) -> str | None:
        return _stale(self)

    def summary(self) -> dict:
        d = self.diagnosis
        return {"name": self.name, "source": self.source, "kind": "travelling",
                "margin": float(d.get("min_evidence") or 0.0), "margin_per_row": d.get("min_evidence_per_row"),
                "family_margins_per_row": d.get("family_margins_per_row"),
                "decision_levels": {}, "decision_shares": d.get("decision_levels"),
                "families": list(self.families), "log_lengths_s": list(self.durations),
                "sample_time": self.sample_time, "code_version": self.code_version, "lofo": self.lofo}

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "source"}
        return {"schema": SCHEMA_TRAVELLING, **{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}}


def travelling_from_study(name: str, doc: dict, diagnosis: dict, command: str = "") -> TravellingCalibration:
    """The calibration of a leave-one-family-out study's pass 1 over every family (ddyn.gap.benchmark.lofo);
    diagnosis: the DiagnosisConfig it applies, as a dict (lofo.applied_config of the study's calibration)."""
    cal = doc["all_families_calibration"]
    ok = [r for r in doc["pass1"] if r["status"] == "ok"]
    if not ok:
        raise DdynError("calibration: the study has no diagnosed logs")
    commit = _commit()
    w = doc.get("worst") or {}
    worst = {"family": w.get("family"), **(doc["folds"][w["family"]]["score"] if w.get("family") else {})}
    worst.pop("per_effect", None)
    return TravellingCalibration(
        name=name, diagnosis=dict(diagnosis), families=tuple(cal["families"]), logs=len(ok),
        durations=(min(r["duration"] for r in ok), max(r["duration"] for r in ok)),
        sample_time=float(ok[0].get("sample_time") or 0.04), lofo=worst,
        code_version=current_code_version("families"),
        made={"commit": commit, "date": datetime.date.today().isoformat(), "command": command,
              "seed": doc["settings"]["seed"], "logs_per_family": doc["settings"]["logs_per_family"]})


def _load_travelling(raw: dict, p: Path) -> TravellingCalibration:
    want = {f.name for f in fields(TravellingCalibration)} - {"source"}
    missing = sorted(want - set(raw))
    if missing:
        raise DdynError(f"{p}: key(s) {', '.join(missing)} missing")
    try:
        cal = TravellingCalibration(**{k: tuple(v) if k in ("families", "durations") else v
                                       for k, v in raw.items() if k in want}, source=str(p))
        cal.applied()
    except (TypeError, ValueError) as e:
        raise DdynError(f"{p}: {e}") from None
    return cal


def shipped_names() -> list[str]:
    return sorted(f.stem for f in SHIPPED_DIR.glob("*.json"))


def covering(length: float, sample_time: float) -> tuple[Calibration | None, str]:
    """The shipped calibration that covers a log (the one whose length is closest), and why; or None and why not."""
    cals = [load(n) for n in shipped_names()]
    fits = [(abs(c.duration - length), c) for c in cals if c.covers(length, sample_time)[0]]
    if fits:
        c = min(fits, key=lambda t: t[0])[1]
        return c, "the shipped calibration that covers this log: " + c.covers(length, sample_time)[1]
    if not cals:
        return None, "no calibration ships with this version"
    return None, "no shipped calibration covers this log (" + "; ".join(c.covers(length, sample_time)[1] for c in cals) + ")"


# the settings a calibration's margin and levels hold under: a config that differs in one of them is not the one it
# measured (candidates may differ: every effect it gives no level is reported, never claimed)
CALIBRATED_KEYS = ("fit_fraction", "refit", "hold", "fit", "evidence", "mass_inertia", "steer_servo",
                   "nominal_effects", "gate")


def _differs(cal: Calibration, config) -> list[str]:
    mine = config.to_dict()
    return [k for k in CALIBRATED_KEYS if mine[k] != cal.diagnosis.get(k)]


def _adds_to_the_nominal(cal: Calibration) -> list[str]:
    """The calibration's settings that describe a car (a servo, effects in the nominal): they come from the user's
    config, never from a calibration on its own."""
    return [k for k in ("steer_servo", "nominal_effects") if cal.diagnosis.get(k)]


def choose(length: float, sample_time: float, config=None, requested: str | None = None):
    """(calibration or None, the DiagnosisConfig to diagnose with, why) for a log of `length` s sampled every
    `sample_time` s. requested: a calibration's name or file (used; refused when it does not cover the log or its
    settings differ from `config`'s), "none" (uncalibrated), or None: a shipped one that covers the log and whose
    settings `config` (when given) shares; else uncalibrated, saying why."""
    from ddyn.gap.config import DiagnosisConfig

    if requested == "none":
        return None, config or DiagnosisConfig(), "uncalibrated: asked for (--calibration none)"
    if requested:
        cal = load(requested)
        stale = cal.stale()
        if stale:
            raise DdynError(stale)
        ok, why = cal.covers(length, sample_time)
        if not ok:
            raise DdynError(f"calibration {requested}: {why}; calibrate on logs like this one (`ddyn gap calibrate "
                            f"--duration {length:.0f}`) or diagnose uncalibrated (--calibration none)")
        if config is None and _adds_to_the_nominal(cal):
            raise DdynError(f"calibration {cal.name} was made with {' and '.join(_adds_to_the_nominal(cal))} in the "
                            "nominal: they describe a car, so they come from your config (--config with the same "
                            "settings), never from a calibration")
        if config is not None and _differs(cal, config):
            raise DdynError(f"calibration {cal.name}: the config's {', '.join(_differs(cal, config))} differ from the "
                            "calibration's settings (leave them out: the calibration sets them)")
        return cal, cal.applied(), "as asked: " + why
    cal, why = covering(length, sample_time)
    if cal is None:
        return None, config or DiagnosisConfig(), "uncalibrated: " + why
    if cal.stale():
        return None, config or DiagnosisConfig(), f"uncalibrated: {cal.stale()}"
    if config is None and _adds_to_the_nominal(cal):
        return None, DiagnosisConfig(), (f"uncalibrated: {cal.name} would cover this log, but it was made with "
                                         f"{' and '.join(_adds_to_the_nominal(cal))} in the nominal, which only a "
                                         "config describing this car can give")
    if config is not None and _differs(cal, config):
        return None, config, (f"uncalibrated: {cal.name} would cover this log, but the config's "
                              f"{', '.join(_differs(cal, config))} differ from its settings")
    applied = cal.applied()
    if config is not None:    # the user's other choices (candidates, max effects) stay
        applied = applied.with_(candidates=tuple(dict.fromkeys(config.candidates + applied.candidates)),
                                max_effects=config.max_effects, max_starts=config.max_starts)
    return cal, applied, why
