"""`ddyn study gap --plant commonroad-mb`: the diagnosis scored on CommonRoad's multi-body plant.

Why: the single-track drift plant (gap_independent.py) is independent code but shares the project model's
structure; the multi-body model (ddyn.data.commonroad_mb_plant: roll, lateral load transfer over four wheels,
combined slip) does not, and it carries the two effects the single-track plant lacked: tyre relaxation (the
tyres' slip angles built up over a relaxation length) and a stepped gearbox (gear_step: the drive force steps
at each shift, with a torque interruption). The cases, scores and report are gap_independent's (run_case,
score, markdown); this module only plans the cases and names the plant.

Cases: SLOTS cycle (the new effects first, so a short run holds them; a quarter of the slots effect-free), on
Putnam, 60 s logs, magnitudes log-uniform over EFFECT_RANGES (random sign where gap_independent.SIGNED). The
nominal is the mapped vehicle file commonroad_vehicle2_mb.json; the candidates are the eleven default effects
plus gear_step (CANDIDATES; gear_step is otherwise opt-in, `diagnose --candidates extended`). Case seeds are
7000 + 100000 seed + case.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ddyn.analysis import diagnose as D
from ddyn.analysis import gap_independent as G
from ddyn.analysis.parallel import run_cases
from ddyn.data import commonroad_plant as CP
from ddyn.model import effects as E

NONE = G.NONE
EFFECT_RANGES = {**G.EFFECT_RANGES, "tire_relaxation": (1.0, 5.0), "gear_step": (0.1, 0.4)}
SLOTS = ("tire_relaxation", "gear_step", NONE, "steer_delay", "throttle_delay", "steer_lag", NONE,
         "mass_offset", "downforce", "bank_angle", "grade", NONE)
CANDIDATES = E.EFFECT_NAMES + ("gear_step",)
PLANT_MODEL = "vehicle_dynamics_mb (multi-body, 29 states)"


def plan(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng([seed, 29])
    cases = []
    for i in range(n):
        eff = SLOTS[i % len(SLOTS)]
        mag = 0.0
        if eff != NONE:
            lo, hi = EFFECT_RANGES[eff]
            mag = math.exp(rng.uniform(math.log(lo), math.log(hi)))
            if eff in G.SIGNED and rng.uniform() < 0.5:
                mag = -mag
        cases.append({"case": i, "effect": eff, "magnitude": mag, "seed": int(7000 + seed * 100000 + i),
                      "start_fraction": float(rng.uniform()), "target_speed": float(rng.uniform(*G.SPEEDS)),
                      "grade_phase": float(rng.uniform(0, 2 * math.pi)), "plant": "mb",
                      "candidates": list(CANDIDATES)})
    return cases


def run(n_cases: int, seed: int, jobs: int = 1, progress: bool = True, hold: bool = False,
        fit: str | None = None, thresholds: dict | None = None) -> dict:
    CP.require_commonroad()
    t0 = time.perf_counter()
    cases = [c | {"hold": hold, "fit": fit, "coefficients": None} for c in plan(n_cases, seed)]
    results = run_cases(G.run_case, cases, jobs, desc="gap-benchmark (commonroad-mb)", progress=progress)
    seconds = time.perf_counter() - t0
    settings = {"plant": "commonroad-mb", "plant_model": PLANT_MODEL, "cases": n_cases, "seed": seed, "jobs": jobs,
                "min_evidence": D.MIN_EVIDENCE, "calibration_seed": seed in G.CALIBRATION_SEEDS,
                "calibration_seeds": list(G.CALIBRATION_SEEDS),
                "case_seeds": f"{cases[0]['seed']}-{cases[-1]['seed']}" if cases else "", "duration": G.DURATION,
                "track": G.TRACK, "effect_ranges": EFFECT_RANGES, "speeds": G.SPEEDS, "gate": D.NO_GAP_GATE,
                "hold": hold, "nominal": "mapped (commonroad_vehicle2_mb.json)", "identification": None,
                "fit": fit or D.DEFAULT_FIT, "thresholds": thresholds, "candidates": list(CANDIDATES)}
    sc = G.score(results, thresholds)
    doc = {"settings": settings, **sc, "results": results, "seconds": seconds,
           "calibrated_gate": G.calibrate(results), "calibrated_margin": G.calibrate_margin(results)}
    return doc | {"markdown": G.markdown(sc, settings, seconds)}
