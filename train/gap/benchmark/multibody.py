"""`ddyn study gap --plant commonroad-mb`: the diagnosis scored on CommonRoad's multi-body plant.

Why: the single-track drift plant (commonroad.py) is independent code but shares the project model's
structure; the multi-body model (ddyn.plants.commonroad_mb: roll, lateral load transfer over four wheels,
combined slip) does not, and it carries the two effects the single-track plant lacked: tyre relaxation (the
tyres' slip angles built up over a relaxation length) and a stepped gearbox (gear_step: the drive force steps
at each shift, with a torque interruption). The cases, scores and report are commonroad.py's (run_case,
score, markdown); this module only plans the cases and names the plant.

Cases: SLOTS cycle (driven at DRIVER_GRIP) (the new effects first, so a short run holds them; a quarter of the slots effect-free), on
Putnam, 60 s logs, magnitudes log-uniform over EFFECT_RANGES (random sign where commonroad.SIGNED). The
nominal is the mapped vehicle file commonroad_vehicle2_mb.json or, nominal="identified", its 17 coefficients
fitted on an effect-free multi-body log (identified_coefficients: commonroad.py's fit, IDENT_SEED); the
candidates are the eleven default effects plus gear_step (CANDIDATES; gear_step is otherwise opt-in,
`candidates = "extended"`). Case seeds are 7000 + 100000 seed + case.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ddyn.gap import hold_estimate as HE
from ddyn.gap.benchmark import commonroad as G
from ddyn.gap.benchmark.parallel import run_cases
from ddyn.gap.calibration import calibrate, calibrate_margin
from ddyn.gap.config import BenchmarkConfig, DiagnosisConfig
from ddyn.gap.fit import fit as fit_problem
from ddyn.gap.problem import DEFAULT_REFIT, Problem, nominal_from_vehicle
from ddyn.gap.selection import diagnose
from ddyn.plants import commonroad_mb as MB
from ddyn.plants import commonroad_st as CP
from ddyn.model import effects as E

NONE = G.NONE
EFFECT_RANGES = {**G.EFFECT_RANGES, "tire_relaxation": (0.5, 2.5), "gear_step": (0.1, 0.4)}
# the driver's speed profile uses this share of the mapped nominal's grip (the single-track plant's driver: 0.8):
# the multi-body car loses grip earlier (lateral load transfer over four wheels) and at 0.8 the driver lost it
# on Putnam at 21-23 m/s without any effect (seed 880207000); chosen on that log, before any case was diagnosed
DRIVER_GRIP = 0.65
SLOTS = ("tire_relaxation", "gear_step", NONE, "steer_delay", "throttle_delay", "steer_lag", NONE,
         "mass_offset", "downforce", "bank_angle", "grade", NONE)
CANDIDATES = E.EFFECT_NAMES + ("gear_step",)
PLANT_MODEL = "vehicle_dynamics_mb (multi-body, 29 states)"
# the effect-free multi-body log the identified nominal is fitted on: a log seed no case, calibration or check
# uses (case seeds are 7000 + 100000 seed + case; the single-track plant's identification log is 9000)
IDENT_SEED = 9100


def identification_log(seed: int, duration: float):
    """The effect-free multi-body log for the identified nominal: driven as the cases are (DRIVER_GRIP), at the
    default target speed, from the start line."""
    return MB.make_log(G.TRACK, CP.PlantEffects(), seed, CP.LogSettings(duration=duration, driver_grip=DRIVER_GRIP))


def identified_coefficients(hold: bool = False) -> tuple[np.ndarray, dict]:
    """Option (b) for the multi-body plant: the single-track plant's identification (commonroad.py's fit,
    within the mapped file's ranges) on an effect-free multi-body log, starting from commonroad_vehicle2_mb.json."""
    return G.identified_coefficients(hold, MB.NOMINAL_VEHICLE, identification_log, IDENT_SEED)


# a multi-body case is run, scored and rendered as a single-track one (the case carries plant "mb")
run_case, score, markdown = G.run_case, G.score, G.markdown


def plan(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng([seed, 29])
    cases = []
    for i in range(n):
        eff = SLOTS[i % len(SLOTS)]
        mag = G.draw_magnitude(rng, eff, EFFECT_RANGES)
        cases.append({"case": i, "effect": eff, "magnitude": mag, "seed": int(7000 + seed * 100000 + i),
                      "start_fraction": float(rng.uniform()), "target_speed": float(rng.uniform(*G.SPEEDS)),
                      "grade_phase": float(rng.uniform(0, 2 * math.pi)), "plant": "mb", "driver_grip": DRIVER_GRIP,
                      "candidates": list(CANDIDATES)})
    return cases


def run(n_cases: int, seed: int, config: DiagnosisConfig | None = None, bench: BenchmarkConfig | None = None,
        jobs: int = 1, progress: bool = True, thresholds: dict | None = None) -> dict:
    """bench.nominal: "mapped" (commonroad_vehicle2_mb.json) or "identified" (identified_coefficients, fitted once
    per run with the run's hold and carried by every case). config: the diagnosis's settings; its candidates are
    CANDIDATES (the eleven effects and the gear step)."""
    CP.require_commonroad()
    config = (config or DiagnosisConfig()).with_(candidates=CANDIDATES)
    bench = bench or BenchmarkConfig()
    t0 = time.perf_counter()
    coeffs, ident = None, None
    if bench.nominal == "identified":
        coeffs, ident = identified_coefficients(config.hold is True)
    cases = [c | {"config": config.to_dict(), "coefficients": None if coeffs is None else coeffs.tolist()}
             for c in plan(n_cases, seed)]
    results = run_cases(G.run_case, cases, jobs, desc="gap-benchmark (commonroad-mb)", progress=progress)
    seconds = time.perf_counter() - t0
    settings = {"plant": "commonroad-mb", "plant_model": PLANT_MODEL, "car": MB.NOMINAL_VEHICLE.stem,
                "cases": n_cases, "seed": seed, "jobs": jobs, "diagnosis": config.to_dict(),
                "benchmark": bench.to_dict(), "calibration_seed": seed in G.CALIBRATION_SEEDS,
                "calibration_seeds": list(G.CALIBRATION_SEEDS),
                "case_seeds": f"{cases[0]['seed']}-{cases[-1]['seed']}" if cases else "", "duration": G.DURATION,
                "track": G.TRACK, "effect_ranges": EFFECT_RANGES, "speeds": G.SPEEDS, "identification": ident,
                "sample_time": G.load_vehicle(MB.NOMINAL_VEHICLE).sample_time,
                "nominal": ("mapped (commonroad_vehicle2_mb.json)" if bench.nominal == "mapped" else
                            f"identified (on an effect-free multi-body log, seed {IDENT_SEED})"),
                "thresholds": thresholds, "candidates": list(CANDIDATES),
                "hold": config.hold, "fit": config.fit, "gate": config.gate, "min_evidence": config.min_evidence,
                "detection_limits": config.detection_limits}
    sc = G.score(results, thresholds)
    doc = {"settings": settings, **sc, "results": results, "seconds": seconds,
           "calibrated_gate": calibrate(results), "calibrated_margin": calibrate_margin(results)}
    return doc | {"markdown": G.markdown(sc, settings, seconds)}


# ----------------------------------------------------------------------------------------------- the hold estimate

HOLD_PERIODS = (0.01, 0.02, 0.04, 0.08)   # s: DBW units at 100, 50, 25 (the log's rate) and 12.5 Hz
HOLD_SEEDS = (31, 32, 33)                 # effect-free single-track plant logs (used for nothing else)


def hold_check(periods=HOLD_PERIODS, seeds=HOLD_SEEDS, duration: float = 60.0) -> dict:
    """`hold = "estimate"` on effect-free logs of the single-track plant whose DBW unit runs at another
    rate than the log: the fitted hold delay (the effective delay of a zero-order hold of period P is P / 2; the
    steering servo adds about SERVO_TAU) and the period read from the commands' step structure."""
    from ddyn.model.vehicle import load as load_vehicle

    veh = load_vehicle(CP.NOMINAL_VEHICLE)
    rows = []
    for period in periods:
        for seed in seeds:
            ds = CP.make_log(G.TRACK, CP.PlantEffects(), seed, CP.LogSettings(duration=duration, dbw_period=period))
            nom = nominal_from_vehicle(veh, ds)
            est = HE.estimate(lambda h: Problem(ds, nom, DiagnosisConfig().fit_fraction, DEFAULT_REFIT, hold=h),
                              lambda pr: fit_problem(pr, ()), ds.sample_time)
            steps = HE.detect_period(ds)
            rows.append({"dbw_period": period, "seed": seed, "hold": est["hold"], "at_bound": est["at_bound"],
                         "zoh_delay": period / 2, "detected_period": steps["period_s"],
                         "cost_range": max(c for _, c in est["grid"]) - min(c for _, c in est["grid"])})
    lines = [f"Hold estimate on effect-free single-track plant logs ({duration:.0f} s, seeds "
             f"{', '.join(map(str, seeds))}; log at 25 Hz):", "",
             "| DBW period (s) | its ZOH delay P/2 (s) | fitted hold (s) per seed | at the bound (Ts/2) | period from the "
             "step structure (s) |", "|---|---|---|---|---|"]
    for period in periods:
        rs = [r for r in rows if r["dbw_period"] == period]
        holds = ", ".join(f"{r['hold']:.4f}" for r in rs)
        found = ", ".join(f"{r['detected_period']:g}" for r in rs)
        lines.append(f"| {period:g} | {period / 2:g} | {holds} | {sum(r['at_bound'] for r in rs)}/{len(rs)} | {found} |")
    return {"rows": rows, "markdown": "\n".join(lines) + "\n"}


# ----------------------------------------------------------------------------------------------- gear steps

GEAR_CHECK = ((0.0, 41), (0.15, 42), (0.25, 43), (0.35, 44))      # (step, seed) on the single-track plant
GEAR_CANDIDATES = ("gear_step", "throttle_map", "brake_gain", "mass_offset", "throttle_delay")


def gear_check(cases=GEAR_CHECK, duration: float = 60.0) -> dict:
    """The gear_step candidate on single-track plant logs with a stepped gearbox (and one without): the
    one-step diagnosis with the hold, the vx-related candidates only (the power limit left out: CommonRoad's own
    92 kW limit is in every log, docs/gap.md)."""
    from ddyn.model.vehicle import load as load_vehicle

    veh = load_vehicle(CP.NOMINAL_VEHICLE)
    rows = []
    for step, seed in cases:
        ds = CP.make_log(G.TRACK, CP.PlantEffects(gear_step=step), seed, CP.LogSettings(duration=duration))
        d = diagnose(ds, nominal_from_vehicle(veh, ds), DiagnosisConfig(candidates=GEAR_CANDIDATES, hold=True))
        g = next(c for c in d["candidates"] if c["effect"] == "gear_step")
        shifts = int(np.sum(np.diff(ds.extras["true_gear"]) != 0)) if step else None
        rows.append({"step": step, "seed": seed, "selected": d["selected"], "estimate": g["params"]["step"],
                     "dbic": g["delta_bic"], "shifts": shifts})
    lines = ["| gear step (plant) | shifts in the log | selected | gear_step estimate | its dBIC |", "|---|---|---|---|---|"]
    lines += [f"| {r['step']:g} | {r['shifts'] if r['shifts'] is not None else '-'} | {', '.join(r['selected']) or 'none'} "
              f"| {r['estimate']:.3f} | {r['dbic']:.1f} |" for r in rows]
    return {"rows": rows, "markdown": "\n".join(lines) + "\n"}
