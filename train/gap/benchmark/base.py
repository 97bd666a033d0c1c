"""The benchmarks behind one interface: which plants there are, which case sets each runs, and one entry point to run
a benchmark and one to score a recorded run again.

Every plant module implements the same four steps: plan the cases (`plan*`: the hidden effect, its magnitude, the
log's seed, each case carrying the run's DiagnosisConfig), run a case (`run_case`: make the log, diagnose it,
record what a score needs), score the recorded cases (`score`) and render them (`markdown`); their `run` ties the
four together and returns the results.json document. The scoring rules (thresholds, margins, decision levels,
claim precision) are ddyn.gap.calibration's, shared by all.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.gap.calibration import Calibration, with_gate
from ddyn.gap.config import BenchmarkConfig, DiagnosisConfig


@dataclass(frozen=True)
class Plant:
    name: str
    case_sets: tuple[str, ...]
    about: str


PLANTS = {p.name: p for p in (
    Plant("own", ("putnam",), "logs of the project's own model (the easy case; 'putnam' is its one case set)"),
    Plant("commonroad", ("putnam", "sweep", "above", "oval", "drivetrain", "eiv-check", "mass-check"),
          "CommonRoad's single-track drift model, an independent plant"),
    Plant("commonroad-mb", ("putnam",), "CommonRoad's multi-body model (29 states, tyre relaxation, gear steps)"),
    Plant("putnam-log", ("putnam",), "the real AV-21 Putnam log: nominal identified on its first half"),
)}
DEFAULT_CASES = {"own": 1170, "commonroad": 40, "commonroad-mb": 20, "sweep": 64, "oval": 8, "drivetrain": 8,
                 "eiv-check": 10, "mass-check": 7}
# what every plant module implements (test_gap_benchmarks checks it): plan the cases, run one, score the recorded
# cases, render the score; `run` ties them together into a results.json document
INTERFACE = ("plan", "run_case", "score", "markdown", "run")
MODULES = {"own": "ddyn.gap.benchmark.own", "commonroad": "ddyn.gap.benchmark.commonroad",
           "commonroad-mb": "ddyn.gap.benchmark.multibody", "case_sets": "ddyn.gap.benchmark.case_sets"}


def run(plant: str, case_set: str, out: Path, seed: int | None, cases: int | None, config: DiagnosisConfig | None,
        bench: BenchmarkConfig, calibration: Calibration | None = None, duration: float | None = None,
        jobs: int = 1, progress: bool = True) -> dict:
    """Run one benchmark and return its results.json document (written by the caller). A calibration sets the
    diagnosis's settings (its applied config), the thresholds scored against and the log length."""
    if plant not in PLANTS:
        raise DdynError(f"--plant {plant}: expected one of {', '.join(PLANTS)}")
    if case_set not in PLANTS[plant].case_sets:
        raise DdynError(f"--case-set {case_set}: the {plant} plant runs {', '.join(PLANTS[plant].case_sets)}")
    if (bench.pitch_channel or bench.roll_channel) and (plant != "commonroad" or case_set not in ("putnam", "sweep",
                                                                                                 "above")):
        raise DdynError("pitch_channel, roll_channel: the single-track plant's putnam, sweep and above case sets only "
                        "(the oval set has its own roll-channel slots)")
    if duration is not None and (plant != "commonroad" or case_set not in ("putnam", "sweep", "above")):
        raise DdynError("--duration: the single-track plant's putnam, sweep and above case sets only")
    thresholds, cal_record = None, None
    if calibration is not None:
        if plant not in ("commonroad", "commonroad-mb") or case_set not in ("putnam", "sweep", "above"):
            raise DdynError("--calibration: the CommonRoad plants' putnam, sweep and above case sets only")
        from ddyn.gap.calibration import _differs

        if config is not None and _differs(calibration, config):
            raise DdynError(f"--calibration {calibration.name}: the config's {', '.join(_differs(calibration, config))} "
                            "differ from the calibration's settings (leave them out: the calibration sets them)")
        if duration is not None and abs(duration - calibration.duration) > 1e-9:
            raise DdynError(f"--duration {duration:g}: calibration {calibration.name} was made on "
                            f"{calibration.duration:g} s logs")
        stale = calibration.stale()
        if stale:
            raise DdynError(stale)
        config, thresholds, duration = calibration.applied(), calibration.thresholds, calibration.duration
        cal_record = calibration.summary() | {"claim_record": calibration.claim_record}
    if plant in ("own", "putnam-log") and config is not None and config != DiagnosisConfig():
        raise DdynError(f"--config: the {plant} benchmark scores the default diagnosis; its [diagnosis] settings "
                        "are not taken (only [benchmark] vehicles for the own model)")
    n = cases or (DEFAULT_CASES.get(case_set) if case_set != "putnam" else None) or DEFAULT_CASES.get(plant, 40)
    if plant == "own":
        from ddyn.gap.benchmark import own

        return own.run(n, out, own.DEFAULT_SEED if seed is None else seed, progress=progress,
                       vehicles=bench.vehicles, jobs=jobs)
    if plant == "putnam-log":
        from ddyn.gap.benchmark import own

        summary = own.run_real(out)
        return {"settings": {"plant": plant}, "real": summary, "markdown": own.real_markdown(summary)}
    from ddyn.gap.benchmark import commonroad as G

    if case_set == "eiv-check":
        return G.eiv_check(n, G.EIV_SEED if seed is None else seed, jobs, hold=(config or DiagnosisConfig()).hold is True)
    if case_set == "mass-check":
        return G.mass_check(n, G.EIV_SEED if seed is None else seed, jobs, progress=progress)
    seed = G.DEFAULT_SEED if seed is None else seed
    if case_set in ("oval", "drivetrain"):
        from ddyn.gap.benchmark import case_sets

        return case_sets.run(case_set, n, seed, config, bench.nominal, jobs, progress)
    if plant == "commonroad-mb":
        from ddyn.gap.benchmark import multibody

        doc = multibody.run(n, seed, config, bench, jobs, progress, thresholds)
    else:
        doc = G.run(n, seed, config, bench, jobs, progress, case_set, thresholds, duration, cal_record)
    if cal_record:
        doc["settings"] |= {"decision_limits": True, "claim_precision": calibration.claim_record}
        doc["markdown"] = G.markdown({k: doc[k] for k in ("summary", "per_effect")}, doc["settings"], doc["seconds"])
    return doc


def rescore(out: Path, calibration: Calibration | None = None, cases: int | None = None,
            min_evidence: float | None = None) -> dict:
    """Score and tabulate the cases of OUT/results.json again, without re-running them: the first `cases` only,
    at another evidence margin, or against a calibration's thresholds and margin (a margin only vetoes, so it can
    be raised, never lowered; detection limits need each case re-run)."""
    path = out / "results.json"
    try:
        doc = json.loads(path.read_text())
        settings = doc["settings"]
    except FileNotFoundError:
        raise DdynError(f"{path}: not found (a `ddyn gap benchmark --out {out}` run writes it)") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DdynError(f"{path}: not a benchmark's results.json ({e})") from None
    plant, case_set = settings.get("plant", "own"), settings.get("case_set", "putnam")
    if cases:
        doc["results"] = doc["results"][:cases]
        settings["cases"] = len(doc["results"])
    if plant not in ("commonroad", "commonroad-mb") and "case_set" not in settings:   # the own model
        from ddyn.gap.benchmark import own

        if calibration is not None or min_evidence is not None:
            raise DdynError("rescore: a calibration or margin applies to the CommonRoad plants' runs only")
        doc.update(own.score(doc["results"]))
        return doc | {"markdown": own._write(doc, doc["nominal"], out)}
    if case_set in ("oval", "drivetrain"):
        from ddyn.gap.benchmark import case_sets

        doc.update(case_sets.score(doc["results"]))
        doc["markdown"] = case_sets.markdown({k: doc[k] for k in ("summary", "per_group")}, settings, doc["seconds"])
        return doc
    from ddyn.gap.benchmark import commonroad as G

    margin = settings.get("min_evidence") or 0.0
    if calibration is not None:
        if abs(float(settings.get("duration") or G.DURATION) - calibration.duration) > 1e-9:
            raise DdynError(f"rescore: the run's logs are {settings.get('duration')} s, calibration "
                            f"{calibration.name}'s {calibration.duration:g} s")
        margin = calibration.margin
        settings["thresholds"] = calibration.thresholds
        settings["calibration"] = calibration.summary()
        settings["claim_precision"] = calibration.claim_record
    if min_evidence is not None:
        margin = min_evidence
    if margin < (settings.get("min_evidence") or 0.0) - 1e-12:
        raise DdynError(f"rescore: margin {margin:g} is below the run's own {settings.get('min_evidence'):g}: a "
                        "rescore can only raise the margin")
    doc["results"] = with_gate(doc["results"], settings.get("gate"), margin)
    settings["min_evidence"] = margin
    doc.update(G.score(doc["results"], settings.get("thresholds")))
    doc["markdown"] = G.markdown({k: doc[k] for k in ("summary", "per_effect")}, settings, doc["seconds"])
    return doc
