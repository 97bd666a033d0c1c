"""`ddyn gap benchmark --plant commonroad`: the diagnosis scored on logs of an independent plant.

The own-model benchmark (own.py) makes its logs with the model code the diagnosis
fits: an inverse crime, the easy case. Here each case is a log of CommonRoad's single-track
drift model (ddyn.plants.commonroad_st: 1 kHz RK4, DBW-held commands, noise on every logged
state) on Putnam, with one hidden effect in physical form or none, and the nominal model is
the plant's parameters mapped onto the project's model (train/vehicles/plants/commonroad_vehicle2.json)
or, --nominal identified, coefficients fitted on an effect-free plant log (identified_coefficients).
Results and how to reproduce them: docs/gap.md.

Cases: effects cycled with three effect-free slots in ten; |magnitude| log-uniform over
EFFECT_RANGES (random sign where SIGNED; bank and grade are peaks of profiles along the track),
random start position and target speed. Case seeds are 1000 + 100000 seed + case.

Scores: top-1 effect (first added; "none" if none) before and after the no-gap gate (the
diagnosis records what it would have selected without it), false alarms on effect-free logs,
relative parameter error (scalar effects only: a bank or grade profile has no single true
value the constant fit could match), gap closed above the noise floor and as a share of the
whole held-out error, the refitted nominal's error over the noise floor.

Seeds: CALIBRATION_SEEDS choose the gate threshold (calibrate()); DEFAULT_SEED is scored and
chose nothing.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.gap import candidates as C
from ddyn.gap.benchmark.parallel import run_cases
from ddyn.gap.benchmark.seeds import CALIBRATION_SEEDS, seen_seeds
from ddyn.gap.calibration import DURATION as RECORDED_DURATION
from ddyn.gap.calibration import NONE, RELIABLE_RATE, calibrate, calibrate_margin, reliable_threshold
from ddyn.gap.config import AMBIGUITY_DBIC, ANY_OTHER, BenchmarkConfig, DiagnosisConfig
from ddyn.gap.fit import fit as fit_problem
from ddyn.gap.heldout import normalised_mse
from ddyn.gap.problem import OE_STEPS, Problem, nominal_from_vehicle
from ddyn.gap.selection import diagnose
from ddyn.model.vehicle import load as load_vehicle
from ddyn.plants import commonroad_mb as MB
from ddyn.plants import commonroad_st as CP

TRACK = "putnam"
EFFECT_RANGES = {"steer_delay": (0.02, 0.12), "throttle_delay": (0.05, 0.3), "steer_lag": (0.03, 0.2),
                 "mass_offset": (0.05, 0.3), "downforce": (5e-5, 4e-4), "bank_angle": (0.02, 0.1),
                 "grade": (0.01, 0.06)}
SIGNED = ("mass_offset", "bank_angle", "grade")
PROFILED = ("bank_angle", "grade")
SLOTS = tuple(EFFECT_RANGES) + (NONE, NONE, NONE)
DURATION = RECORDED_DURATION   # s of log per case (1500 rows at 25 Hz); `study gap --duration` sets another
SPEEDS = (20.0, 26.0)          # m/s: range of the driver's target speed
IDENT_SEED = 9000              # the effect-free log the identified nominal is fitted on (neither set)
IDENT_DURATION = 120.0
DEFAULT_SEED = 4242            # the default run's seed; scored since (seen_seeds.json): no longer blind
# the oracle: the project's model given the hidden effect at its true value. Only where the plant's effect and
# the model's candidate share one parameter with the same meaning: every effect of this set but the profiles
# (a profile along the track has no single value; the multi-body plant's gear steps and tyre relaxation,
# multibody.py, are not the candidates' forms)
ORACLE_EFFECTS = tuple(e for e in EFFECT_RANGES if e not in PROFILED)


def draw_magnitude(rng: np.random.Generator, eff: str, ranges: dict) -> float:
    """A case's effect size: log-uniform in the effect's range, either sign for SIGNED effects (0 for NONE).
    The draws' order is part of every plan's reproducibility: do not reorder."""
    if eff == NONE:
        return 0.0
    lo, hi = ranges[eff]
    mag = math.exp(rng.uniform(math.log(lo), math.log(hi)))
    if eff in SIGNED and rng.uniform() < 0.5:
        mag = -mag
    return mag


def plan(n: int, seed: int = DEFAULT_SEED) -> list[dict]:
    rng = np.random.default_rng(seed)
    length = 1.0   # start position as a fraction of the lap (the track is loaded in the worker)
    cases = []
    for i in range(n):
        eff = SLOTS[i % len(SLOTS)]
        mag = draw_magnitude(rng, eff, EFFECT_RANGES)
        cases.append({"case": i, "effect": eff, "magnitude": mag, "seed": int(1000 + seed * 100000 + i),
                      "start_fraction": float(rng.uniform(0, length)),
                      "target_speed": float(rng.uniform(*SPEEDS)), "grade_phase": float(rng.uniform(0, 2 * math.pi))})
    return cases


SWEEP_LEVELS = 8               # magnitudes per effect in the threshold sweep (plan_sweep)


def sweep_grid(eff: str, levels: int = SWEEP_LEVELS) -> list[float]:
    """The sweep's |magnitudes| of one effect: log-spaced over its whole EFFECT_RANGES, largest first."""
    lo, hi = EFFECT_RANGES[eff]
    return [lo * (hi / lo) ** (k / (levels - 1)) for k in range(levels - 1, -1, -1)]


def plan_sweep(n: int, seed: int, levels: int = SWEEP_LEVELS) -> list[dict]:
    """The threshold sweep (`--case-set sweep`): one effect per log, each effect at `levels` magnitudes spread
    over its range, so that every effect gets enough draws to measure its detection threshold (the mixed plan
    gives each ~3 per 30 cases, and one miss at a large magnitude erases the threshold). Rounds of the seven
    effects and one effect-free log; round k draws every effect at its k-th largest grid magnitude (random
    sign where SIGNED), so a run cut short has measured the thresholds from the top down, the way
    reliable_threshold reads them. Start, speed and grade phase drawn as in plan(). Case seeds are
    3000 + 100000 seed + case (plan() uses 1000 + ...). For calibration seeds only: the thresholds it measures
    score other (blind) runs through a calibration (ddyn gap calibrate)."""
    rng = np.random.default_rng([seed, 3])
    effects = tuple(EFFECT_RANGES)
    slots = effects + (NONE,)
    grids = {e: sweep_grid(e, levels) for e in effects}
    cases = []
    for i in range(n):
        eff, level = slots[i % len(slots)], (i // len(slots)) % levels
        mag = 0.0
        if eff != NONE:
            mag = grids[eff][level] * (-1.0 if eff in SIGNED and rng.uniform() < 0.5 else 1.0)
        cases.append({"case": i, "effect": eff, "magnitude": mag, "seed": int(3000 + seed * 100000 + i),
                      "sweep_level": level, "start_fraction": float(rng.uniform()),
                      "target_speed": float(rng.uniform(*SPEEDS)), "grade_phase": float(rng.uniform(0, 2 * math.pi))})
    return cases


def plan_above(n: int, seed: int, thresholds: dict) -> list[dict]:
    """`--case-set above`: only the effects with a measured threshold, each log's magnitude log-uniform between
    its threshold and the top of its range (random sign where SIGNED), so that the target "top-1 >= 95 % above
    the measured thresholds" is scored on more than the few logs a mixed plan puts there. Effects cycled; start,
    speed and grade phase drawn as in plan(). Case seeds 2000 + 100000 seed + case (plan() uses 1000 + ...)."""
    effects = tuple(e for e in EFFECT_RANGES if thresholds.get(e) is not None)
    if not effects:
        raise DdynError("--case-set above needs measured thresholds (a calibration's, --calibration)")
    rng = np.random.default_rng([seed, 4])
    cases = []
    for i in range(n):
        eff = effects[i % len(effects)]
        lo, hi = float(thresholds[eff]), EFFECT_RANGES[eff][1]
        mag = math.exp(rng.uniform(math.log(lo), math.log(max(hi, lo))))
        if eff in SIGNED and rng.uniform() < 0.5:
            mag = -mag
        cases.append({"case": i, "effect": eff, "magnitude": mag, "seed": int(2000 + seed * 100000 + i),
                      "start_fraction": float(rng.uniform()), "target_speed": float(rng.uniform(*SPEEDS)),
                      "grade_phase": float(rng.uniform(0, 2 * math.pi))})
    return cases


def identified_coefficients(hold: bool = False, vehicle_file=None, make_ident_log=None,
                            seed: int = IDENT_SEED) -> tuple[np.ndarray, dict]:
    """The nominal the issue's option (b) asks for: the 17 coefficients least-squares fitted to one-step
    predictions of an effect-free plant log (seed), starting from the mapped vehicle file, each within the
    file's range (coefficients that are zero there, the shifts G, K and Cm2, stay zero: they are fitted as
    factors). The same fit as own.identify(within_ranges=True), written out here because
    own.py imports this module. vehicle_file, make_ident_log(seed, duration): another plant's mapped file
    and its effect-free log (the multi-body plant: multibody.identified_coefficients); default the single-track
    plant's."""
    from ddyn.model.single_track import COEFF_NAMES

    vehicle_file = vehicle_file or CP.NOMINAL_VEHICLE
    veh = load_vehicle(vehicle_file)
    if make_ident_log is None:
        log = CP.make_log(TRACK, CP.PlantEffects(), seed, CP.LogSettings(duration=IDENT_DURATION))
    else:
        log = make_ident_log(seed, IDENT_DURATION)
    start = veh.true_vector()
    prob = Problem(log, nominal_from_vehicle(veh, log, start), 0.95, refit=COEFF_NAMES, hold=hold)
    lo, hi = veh.range_arrays()
    safe = np.where(start != 0, start, 1.0)
    f_lo = np.where(start != 0, np.minimum(lo / safe, hi / safe), 0.5)
    f_hi = np.where(start != 0, np.maximum(lo / safe, hi / safe), 1.5)
    f = fit_problem(prob, (), rho_bounds=(f_lo - 1.0, f_hi - 1.0))
    c = start * (1.0 + f.rho)
    # a coefficient the fit pushed to its range's edge is not identified, only bounded
    at_edge = [n for i, n in enumerate(COEFF_NAMES)
               if start[i] != 0 and min(c[i] - lo[i], hi[i] - c[i]) <= 1e-4 * (hi[i] - lo[i])]
    return c, {"seed": seed, "rows": len(log), "hold": hold, "vehicle_file": Path(vehicle_file).name,
               "plant": log.metadata.get("plant"),
               "relative_change": {n: float(f.rho[i]) for i, n in enumerate(COEFF_NAMES)},
               "at_range_edge": at_edge}


# When the driver loses the car on every one of `tries` seeds at the drawn speed, as many more tries follow, each this
# much slower (not below SLOWEST_RETRY): a long log (`--duration 300`) passes every corner several times, and the
# largest effects (a 30 % lighter car on the same drive force, a 0.2 s throttle delay) then lost the car on 6 of 64
# sweep logs, so the cases that were dropped were the ones most easily diagnosed. The speed used is recorded.
RETRY_SLOWER = 2.0             # m/s
SLOWEST_RETRY = 14.0           # m/s


def make_case_log(case: dict, tries: int = 3):
    """The case's log; another seed when the hidden effect makes the driver lose the car, then a lower target speed
    (RETRY_SLOWER)."""
    from ddyn.model.tracks import load_track

    track = load_track(TRACK)
    fx = {} if case["effect"] == NONE else {case["effect"]: case["magnitude"]}
    effects = CP.PlantEffects(**fx, grade_phase=case["grade_phase"])
    seed, err = case["seed"], None
    speeds = [case["target_speed"]] * tries + [max(SLOWEST_RETRY, case["target_speed"] - RETRY_SLOWER * (k + 1))
                                               for k in range(tries)]
    for speed in speeds:
        try:
            settings = CP.LogSettings(duration=case.get("duration", DURATION), target_speed=speed,
                                      start_s=case["start_fraction"] * track.length,
                                      driver_grip=case.get("driver_grip"),
                                      roll_channel=bool(case.get("roll_channel", False)),
                                      pitch_channel=bool(case.get("pitch_channel", False)))
            if case.get("plant") == "mb":   # the multi-body plant (multibody.py)
                return MB.make_log(track, effects, seed, settings), seed, None
            return CP.make_log(track, effects, seed, settings), seed, None
        except DdynError as e:
            err, seed = str(e), seed + 7919
    return None, seed, err


def run_case(case: dict) -> dict:
    ds, seed, err = make_case_log(case)
    out = dict(case)
    if ds is None:
        return out | {"status": "simulation failed", "error": err}
    veh = load_vehicle(MB.NOMINAL_VEHICLE if case.get("plant") == "mb" else CP.NOMINAL_VEHICLE)
    t0 = time.perf_counter()
    coeffs = np.asarray(case["coefficients"]) if case.get("coefficients") is not None else None
    # the run's settings travel with the case: a worker (another process, a Dask node) diagnoses with exactly them
    diag = diagnose(ds, nominal_from_vehicle(veh, ds, coeffs), DiagnosisConfig.from_dict(case["config"]),
                    truth={case["effect"]: case["magnitude"]} if case["effect"] in ORACLE_EFFECTS else None)
    seconds = time.perf_counter() - t0
    g = diag["gate"]
    # a bank or grade found as a profile along the track (or from the roll channel) is that effect found
    top1 = C.FAMILY.get(diag["selected"][0], diag["selected"][0]) if diag["selected"] else NONE
    top1_ungated = (C.FAMILY.get(g["selected_without_gate"][0], g["selected_without_gate"][0])
                    if g["selected_without_gate"] else NONE)
    est = perr = None
    true_cand: dict = {}
    if case["effect"] != NONE:
        pick = next(c for c in diag["candidates"] if c["effect"] == case["effect"])
        est = next(iter(pick["params"].values()))
        if case["effect"] in PROFILED:
            # a bank or grade: the size of the family's best candidate (constant, profile or channel), what a
            # detection limit is compared with (candidates.magnitude)
            best = next(c for c in diag["candidates"] if C.FAMILY.get(c["effect"], c["effect"]) == case["effect"])
            est = best.get("magnitude", next(iter(best["params"].values())))
        if case["effect"] not in PROFILED:
            perr = abs(est - case["magnitude"]) / abs(case["magnitude"])
        # the hidden effect's own candidate in round 1: a miss with a right estimate but dBIC > 0 is weak
        # held-out evidence, a miss with a wrong estimate or at a range edge a wrong fit (docs: threshold sweep)
        true_cand = {"delta_bic_true": pick["delta_bic"], "at_bound_true": pick["at_bound"],
                     "rank_true": [c["effect"] for c in diag["candidates"]].index(case["effect"]) + 1}
        if "delta_bic_one_step" in pick:    # --evidence multistep: the one-step figure of the same fit, to compare
            true_cand["delta_bic_true_one_step"] = pick["delta_bic_one_step"]
    m = diag["model"]
    first = diag["candidates"][0]
    return out | {
        "status": "ok", "seed_used": seed, "target_speed_used": float(ds.metadata.get("target_speed", "nan")),
        "rows": len(ds), "selected": diag["selected"], "top1": top1,
        "correct": top1 == case["effect"], "top1_without_gate": top1_ungated,
        "correct_without_gate": top1_ungated == case["effect"],
        "selected_without_gate": g["selected_without_gate"], "gate_ratio": g["ratio"], "gate_threshold": g["threshold"],
        "min_evidence": g["min_evidence"],
        # the best candidate that paid but fell below its detection limit (DiagnosisConfig.detection_limits)
        "below_limit": (diag.get("below_limit") or {}).get("effect"),
        # with limits: the first effect withheld because a rival's evidence was as good (diagnose.AMBIGUITY_DBIC)
        "not_told_apart": ([t["effect"], t["rival"]] if (t := diag.get("not_told_apart")) else None),
        "estimate": est, "param_error": perr, **true_cand,
        # the first candidate's figures: what "gap closed" said before the gate could veto it
        "gap_closed_pct": m["gap_closed_pct"], "error_reduction_pct": m["error_reduction_pct"],
        "gap_closed_pct_top_candidate": first["gap_closed_pct"],
        "error_reduction_pct_top_candidate": first["error_reduction_pct"],
        "delta_bic_top": first["delta_bic"], "top_candidate": first["effect"], "at_bound_top": first["at_bound"],
        # the top candidate's size (what a limit compares): tells a wrong effect's claim from its withholding
        "estimate_top": first.get("magnitude", next(iter(first["params"].values()))),
        "delta_bic_top_one_step": first.get("delta_bic_one_step"),
        "unexplained": diag.get("unexplained"), **oracle_figures(diag, case),
        "rival": (diag.get("rival") or {}).get("effect"),
        # how far the best candidate's runner-up of another family is behind it (dBIC): what tells the two apart
        "runner_up": (diag.get("runner_up") or {}).get("effect"),
        "runner_up_gap": (diag.get("runner_up") or {}).get("evidence_difference"),
        "rmse_over_noise_floor": diag["where"]["rmse_over_noise_floor"], "diagnose_seconds": seconds,
    }


def oracle_figures(diag: dict, case: dict) -> dict:
    """The diagnosis's gap closed against the oracle's, on the held-out normalised one-step MSE above the refitted
    nominal's (what the effect library adds beyond the refit of Df, Dr): (E_refit - E_diagnosed) / (E_refit -
    E_oracle), where the oracle is the model with the hidden effect at its true value (diagnose(truth=...)).
    Also the same for the hidden effect's own round-1 fit (its value estimated: an oracle that knows only which
    effect). None where the oracle does not improve on the refitted nominal (no gap to close)."""
    t = diag.get("truth")
    if not t:
        return {}
    scale = diag["method"]["channel_scale"]

    def e(rmse: dict) -> float:
        return normalised_mse(rmse, scale)

    e_refit = e(diag["nominal"]["refit_only"]["rmse"])
    e_diag = e(diag["model"]["heldout"]["rmse_after"])
    e_orc = e(t["rmse_after"])
    own = next(c for c in diag["candidates"] if c["effect"] == case["effect"])
    e_own = e(own["heldout"]["rmse_after"])
    gain = e_refit - e_orc
    ok = gain > 1e-12 * e_refit
    return {"e_refit": e_refit, "e_diagnosed": e_diag, "e_oracle": e_orc, "e_own_fit": e_own,
            "oracle_delta_bic": t["delta_bic"], "oracle_gap_closed_pct": t["gap_closed_pct"],
            "gap_vs_oracle": (e_refit - e_diag) / gain if ok else None,
            "own_fit_vs_oracle": (e_refit - e_own) / gain if ok else None}


# ----------------------------------------------------------------------------------------------- errors in variables

EIV_SEED = 12                  # effect-free logs of the errors-in-variables check (neither calibrates nor scores)


def _fit_mass(ds, veh, mode: str, hold: bool, states=None, mass_inertia: bool = False,
              nominal_effects: dict | None = None) -> dict:
    """The mass offset (Df, Dr refitted) that a fit of `mode` gives on ds; states: the rows the steps start
    from instead of the logged ones (the noise-free truth: what the fit would give without errors in variables);
    mass_inertia: the candidate scales Iz with the mass (DiagnosisConfig.mass_inertia)."""
    from ddyn.model import effects as E

    prob = Problem(ds, nominal_from_vehicle(veh, ds), DiagnosisConfig().fit_fraction, hold=hold, fit_mode=mode,
                     mass_inertia=mass_inertia, nominal_effects=nominal_effects)
    if states is not None:
        prob.lm_fit = E.LogModel(ds.time, ds.segment, states, ds.inputs, veh.known, ds.sample_time,
                                 prob.nominal.method, prob.nominal.substeps)
    f = fit_problem(prob, ("mass_offset",))
    return {"mass_offset": f.values["mass_offset"], "std": f.std["mass_offset"],
            "refit": {n: 1.0 + float(r) for n, r in zip(prob.refit, f.rho)}}


def eiv_case(case: dict) -> dict:
    ds, seed, err = make_case_log(case)
    if ds is None:
        return case | {"status": "simulation failed", "error": err}
    veh = load_vehicle(CP.NOMINAL_VEHICLE)
    truth = ds.states.copy()
    for i, c in enumerate(("vx", "vy", "omega")):
        truth[:, 3 + i] = ds.extras[f"true_{c}"]
    hold = bool(case.get("hold", True))
    fits = {"one-step (logged states)": _fit_mass(ds, veh, "one-step", hold),
            "one-step from the noise-free states": _fit_mass(ds, veh, "one-step", hold, truth),
            "smoothed": _fit_mass(ds, veh, "smoothed", hold),
            "output-error": _fit_mass(ds, veh, "output-error", hold)}
    return case | {"status": "ok", "seed_used": seed, "fits": fits}


def eiv_check(n_logs: int = 10, seed: int = EIV_SEED, jobs: int = 1, hold: bool = True,
              progress: bool = True) -> dict:
    """Is the mass offset found on effect-free logs an errors-in-variables bias? The mass offset fitted
    (alone, Df and Dr refitted, as the diagnosis fits a candidate) on n_logs effect-free plant logs four ways:
    one-step from the logged (noisy) states, one-step from the noise-free states (no errors in variables at
    all, same targets), from smoothed states, and by output error."""
    cases = [c | {"effect": NONE, "magnitude": 0.0, "hold": hold} for c in plan(n_logs, seed)]
    res = run_cases(eiv_case, cases, jobs, desc="errors in variables", progress=progress)
    ok = [r for r in res if r["status"] == "ok"]
    modes = list(ok[0]["fits"]) if ok else []
    summary = {m: {"median": _median([r["fits"][m]["mass_offset"] for r in ok]),
                   "median_abs": _median([abs(r["fits"][m]["mass_offset"]) for r in ok]),
                   "min": min(r["fits"][m]["mass_offset"] for r in ok),
                   "max": max(r["fits"][m]["mass_offset"] for r in ok)} for m in modes}
    lines = [f"Mass offset fitted on {len(ok)} effect-free logs of the independent plant (seed {seed}, "
             f"{DURATION:.0f} s each, command hold {'modelled' if hold else 'not modelled'}; Df, Dr refitted):", "",
             "| fit | median | median abs | min | max |", "|---|---|---|---|---|"]
    lines += [f"| {m} | {v['median']:+.3f} | {v['median_abs']:.3f} | {v['min']:+.3f} | {v['max']:+.3f} |"
              for m, v in summary.items()]
    return {"settings": {"logs": n_logs, "seed": seed, "hold": hold, "duration": DURATION,
                         "oe_steps": OE_STEPS}, "summary": summary, "results": res,
            "markdown": "\n".join(lines) + "\n"}


MASS_CHECK_OFFSETS = (0.0, 0.15, -0.15, 0.25, -0.25, 0.08, -0.08)   # cycled over the logs of the mass check


def mass_case(case: dict) -> dict:
    ds, seed, err = make_case_log(case)
    if ds is None:
        return case | {"status": "simulation failed", "error": err}
    veh = load_vehicle(CP.NOMINAL_VEHICLE)
    fits = {f"{mode}, Iz {'scaled' if mi else 'fixed'}": _fit_mass(ds, veh, mode, True, mass_inertia=mi)["mass_offset"]
            for mode in ("one-step", "output-error") for mi in (False, True)}
    # the nominal given the plant's own power limit (CommonRoad's acceleration cap a_max v_switch / v times the
    # nominal mass), which the mapped vehicle file lacks
    p = CP.commonroad_parameters()
    limit = {"power_limit": p.longitudinal.a_max * p.longitudinal.v_switch * veh.known.mass}
    fits |= {f"{mode}, Iz scaled, nominal power limit": _fit_mass(ds, veh, mode, True, mass_inertia=True,
                                                                   nominal_effects=limit)["mass_offset"]
             for mode in ("one-step", "output-error")}
    return case | {"status": "ok", "seed_used": seed, "fits": fits}


def mass_check(n_logs: int = 7, seed: int = EIV_SEED, jobs: int = 1, progress: bool = True) -> dict:
    """Is the plant's mass offset found with the right sign? The mass offset fitted alone (Df, Dr refitted, the
    hold modelled) on logs with MASS_CHECK_OFFSETS hidden, by one-step and output-error fits, with the
    candidate's Iz fixed (diagnose's default) or scaled with the mass (mass_inertia)."""
    cases = [c | {"effect": "mass_offset" if MASS_CHECK_OFFSETS[i % len(MASS_CHECK_OFFSETS)] else NONE,
                  "magnitude": MASS_CHECK_OFFSETS[i % len(MASS_CHECK_OFFSETS)]}
             for i, c in enumerate(plan(n_logs, seed))]
    res = run_cases(mass_case, cases, jobs, desc="mass offset", progress=progress)
    ok = [r for r in res if r["status"] == "ok"]
    modes = list(ok[0]["fits"]) if ok else []
    lines = [f"Mass offset fitted alone on {len(ok)} plant logs (seed {seed}, {DURATION:.0f} s each, command hold "
             "modelled; Df, Dr refitted):", "", "| hidden | " + " | ".join(modes) + " |",
             "|---" * (len(modes) + 1) + "|"]
    lines += [f"| {r['magnitude']:+.2f} | " + " | ".join(f"{r['fits'][m]:+.3f}" for m in modes) + " |" for r in ok]
    err = {m: _median([abs(r["fits"][m] - r["magnitude"]) for r in ok]) for m in modes}
    lines += ["| median abs error | " + " | ".join(f"{err[m]:.3f}" for m in modes) + " |"]
    return {"settings": {"logs": n_logs, "seed": seed, "duration": DURATION, "offsets": MASS_CHECK_OFFSETS},
            "median_abs_error": err, "results": res, "markdown": "\n".join(lines) + "\n"}


def cost_profile(case: dict, effect: str, values, hold: bool = True, fit: str = "output-error",
                 mass_inertia: bool = True, steer_servo: float = CP.SERVO_TAU,
                 nominal_effects: dict | None = None) -> list[dict]:
    """Why a fit lands where it does: on the case's log, the cost the fit minimises (fit rows, the fit mode's
    residuals) and the held-out one-step sum of squares the evidence is scored with, at each value of one
    effect's main parameter, the refit factors at the nominal's refit (diagnose's settings otherwise: the
    threshold sweep's by default, the plant's power limit in the nominal unless nominal_effects is given)."""
    ds, _, err = make_case_log(case)
    if ds is None:
        raise DdynError(f"case {case['case']}: {err}")
    veh = load_vehicle(CP.NOMINAL_VEHICLE)
    if nominal_effects is None:
        p = CP.commonroad_parameters()
        nominal_effects = {"power_limit": p.longitudinal.a_max * p.longitudinal.v_switch * veh.known.mass}
    prob = Problem(ds, nominal_from_vehicle(veh, ds), DiagnosisConfig().fit_fraction, hold=hold, fit_mode=fit,
                     mass_inertia=mass_inertia, steer_servo=steer_servo, nominal_effects=nominal_effects)
    rho = fit_problem(prob, ()).rho
    return [{"value": float(v),
             "fit_cost": float(np.sum(prob.fit_residuals({effect: float(v)}, rho, prob.rows_fit) ** 2)),
             "heldout_rss": float(np.sum(prob.residuals({effect: float(v)}, rho, prob.rows_held) ** 2))}
            for v in values]


def cost_minima(case: dict, effect: str, values, **kw) -> dict:
    """cost_profile's two minima: where the fit goes and where the held-out evidence is best."""
    prof = cost_profile(case, effect, values, **kw)
    return {"case": case["case"], "effect": effect, "true": case["magnitude"],
            "fit_minimum": min(prof, key=lambda r: r["fit_cost"])["value"],
            "heldout_minimum": min(prof, key=lambda r: r["heldout_rss"])["value"], "profile": prof}


# ----------------------------------------------------------------------------------------------- scoring

MAX_DURATION = 900.0           # s: the longest log a case may ask for (the plant holds the whole run in memory)
DELAY_LAG = ("steer_delay", "steer_lag")


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def _rate(rows, key):
    return float(np.mean([bool(r[key]) for r in rows])) if rows else None


def oracle_summary(rows: list[dict]) -> dict:
    """Gap closed against the oracle's (oracle_figures) over the cases that have one: every such case (a miss
    closes nothing), the identified ones, and the hidden effect's own fit; how many have no oracle gain (the
    true value does not improve on the refitted nominal) and in how many the oracle itself pays on the held-out
    part (its dBIC < 0)."""
    orc = [r for r in rows if "e_oracle" in r]
    good = [r for r in orc if r.get("gap_vs_oracle") is not None]
    # capped: a case whose diagnosis closes more than the oracle (further effects, or a wrong one fitting the
    # plant's own mismatch) counts as 100 %, so that such cases cannot make up for misses in the median
    return {"oracle_cases": len(orc), "oracle_no_gain": len(orc) - len(good),
            "oracle_pays": sum(1 for r in orc if r["oracle_delta_bic"] < 0),
            "median_gap_vs_oracle": _median([min(r["gap_vs_oracle"], 1.0) for r in good]),
            "median_gap_vs_oracle_uncapped": _median([r["gap_vs_oracle"] for r in good]),
            # strict: only a right top-1 closes anything (a wrong effect that lowers the error counts 0)
            "median_gap_vs_oracle_strict": _median([min(r["gap_vs_oracle"], 1.0) if r["correct"] else 0.0
                                                    for r in good]),
            "median_gap_vs_oracle_found": _median([min(r["gap_vs_oracle"], 1.0) for r in good if r["correct"]]),
            "median_own_fit_vs_oracle": _median([min(r["own_fit_vs_oracle"], 1.0) for r in good])}


def delay_vs_lag(rows: list[dict]) -> dict:
    """Steering delay and steering lag told apart: of the cases with either hidden whose top-1 is either, the
    share naming the right one; plus how often each was named the other. Also the same where the diagnosis
    claims to tell them apart: without the other as its rival (diagnose.AMBIGUITY_DBIC), and how many it flags."""
    dl = [r for r in rows if r["effect"] in DELAY_LAG]
    named = [r for r in dl if r["top1"] in DELAY_LAG]
    flagged = [r for r in named if r.get("rival") in DELAY_LAG]
    claimed = [r for r in named if r not in flagged]
    return {"cases": len(dl), "named_either": len(named),
            "told_apart": float(np.mean([r["correct"] for r in named])) if named else None,
            "flagged_not_told_apart": len(flagged) if any("rival" in r for r in named) else None,
            "told_apart_where_claimed": (float(np.mean([r["correct"] for r in claimed]))
                                         if claimed and any("rival" in r for r in named) else None),
            "delay_named_lag": sum(r["effect"] == "steer_delay" and r["top1"] == "steer_lag" for r in dl),
            "lag_named_delay": sum(r["effect"] == "steer_lag" and r["top1"] == "steer_delay" for r in dl)}


def score(results: list[dict], thresholds: dict | None = None) -> dict:
    """thresholds: {effect: measured threshold} from ANOTHER run (a calibration seed) to score top-1 above; the
    thresholds measured on these results are reported beside them (scoring above one's own thresholds would be
    >= 95 % by construction)."""
    ok = [r for r in results if r["status"] == "ok"]
    none = [r for r in ok if r["effect"] == NONE]
    eff = [r for r in ok if r["effect"] != NONE]
    per = {}
    for e in dict.fromkeys([*EFFECT_RANGES, *(r["effect"] for r in eff)]):   # and the MB set's (multibody.py)
        rows = [r for r in eff if r["effect"] == e]
        if not rows:
            continue
        found = [r for r in rows if r["correct"]]
        wrong = {}
        for r in rows:
            if not r["correct"]:
                wrong[r["top1"]] = wrong.get(r["top1"], 0) + 1
        per[e] = {"cases": len(rows), "drawn": [min(abs(r["magnitude"]) for r in rows),
                                                max(abs(r["magnitude"]) for r in rows)],
                  "top1": _rate(rows, "correct"), "top1_without_gate": _rate(rows, "correct_without_gate"),
                  "median_param_error": _median([r["param_error"] for r in found]),
                  "median_param_error_all": _median([r["param_error"] for r in rows]),
                  "median_ratio": _median([r["gate_ratio"] for r in rows]), "mistaken_for": wrong,
                  "measured_threshold": reliable_threshold(rows),
                  # every case, largest |magnitude| first: what was picked and the hidden effect's own evidence
                  "ladder": [[r["magnitude"], r["top1"], r.get("delta_bic_true"), r.get("estimate")]
                             for r in sorted(rows, key=lambda r: -abs(r["magnitude"]))],
                  "threshold_used": None if thresholds is None else thresholds.get(e),
                  **oracle_summary(rows)}
        if thresholds is not None:
            above = [r for r in rows if thresholds.get(e) is not None and abs(r["magnitude"]) >= thresholds[e]]
            per[e] |= {"above_threshold": len(above), "top1_above_threshold": _rate(above, "correct"),
                       "top1_above_threshold_count": sum(bool(r["correct"]) for r in above),
                       "median_param_error_above": _median([r["param_error"] for r in above if r["correct"]])}
    above_all = [r for r in eff if thresholds is not None and thresholds.get(r["effect"]) is not None
                 and abs(r["magnitude"]) >= thresholds[r["effect"]]]
    below = [r for r in eff if thresholds is not None and r not in above_all]
    return {"summary": {
        "thresholds_from": None if thresholds is None else "given",
        "above_threshold_cases": len(above_all) if thresholds is not None else None,
        "top1_above_thresholds": _rate(above_all, "correct") if thresholds is not None else None,
        "median_param_error_above_thresholds": _median([r["param_error"] for r in above_all if r["correct"]]),
        # below-threshold logs count as effect-free for false alarms (the target): anything selected
        # other than the hidden effect
        "below_threshold_cases": len(below) if thresholds is not None else None,
        "any_selected_below_thresholds": _rate(below, "selected") if below else None,
        "wrong_selected_below_thresholds": (float(np.mean([bool(r["selected"]) and not r["correct"]
                                                           for r in below])) if below else None),
        # the target as worded: of the effect-free and below-threshold logs together, the share with any
        # effect selected (a right one below threshold counts too)
        "any_selected_none_or_below": (_rate(none + below, "selected") if thresholds is not None and none + below
                                       else None),
        "delay_vs_lag": delay_vs_lag(eff),
        "edge_verdicts": sum(1 for r in ok if r.get("unexplained") and not r["selected"]),
        # with detection limits: logs where a paying effect was reported and not claimed (below its limit, first
        # or after others; or, first, not told apart from a rival)
        "withheld_below_limit": sum(1 for r in ok if r.get("below_limit")),
        "withheld_not_told_apart": sum(1 for r in ok if r.get("not_told_apart")),
        **oracle_summary(eff),
        "median_gap_vs_oracle_above_thresholds": (_median([min(r["gap_vs_oracle"], 1.0) for r in above_all
                                                           if r.get("gap_vs_oracle") is not None])
                                                  if thresholds is not None else None),
        "cases": len(results), "simulated": len(ok), "effect_cases": len(eff), "none_cases": len(none),
        "top1": _rate(eff, "correct"), "top1_without_gate": _rate(eff, "correct_without_gate"),
        "false_alarm_rate": _rate(none, "selected"), "false_alarm_rate_without_gate": _rate(none, "selected_without_gate"),
        "none_selected_effects": sorted({e for r in none for e in r["selected_without_gate"]}),
        "median_param_error": _median([r["param_error"] for r in eff if r["correct"]]),
        "median_gap_closed_pct_none": _median([r["gap_closed_pct_top_candidate"] for r in none]),
        "median_error_reduction_pct_none": _median([r["error_reduction_pct_top_candidate"] for r in none]),
        "median_gap_closed_pct_found": _median([r["gap_closed_pct"] for r in eff if r["correct"]]),
        "median_error_reduction_pct_found": _median([r["error_reduction_pct"] for r in eff if r["correct"]]),
        "median_ratio_none": _median([r["gate_ratio"] for r in none]),
        "max_ratio_none": max((r["gate_ratio"] for r in none), default=None),
        "gate_threshold": next((r["gate_threshold"] for r in ok), None),
        "min_evidence": next((r.get("min_evidence", 0.0) for r in ok), 0.0),
        "median_diagnose_seconds": _median([r["diagnose_seconds"] for r in ok]),
    }, "per_effect": per}


def _f(x, pct=False) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.0f} %" if pct else f"{x:.3g}"


def _delay_lag_line(d: dict) -> str:
    return (f"Steering delay vs lag: of {d['cases']} cases with either hidden, {d['named_either']} were named one of "
            f"the two, the right one in {_f(d['told_apart'], True)}; delay named lag {d['delay_named_lag']}, lag "
            f"named delay {d['lag_named_delay']}."
            + (f" The diagnosis flagged {d['flagged_not_told_apart']} of them as not told apart (the other within "
               f"{AMBIGUITY_DBIC:g} dBIC); where it did not, the right one in "
               f"{_f(d['told_apart_where_claimed'], True)}." if d.get("flagged_not_told_apart") is not None else ""))


def _threshold_line(s: dict, per: dict) -> str:
    if s.get("top1_above_thresholds") is None and s.get("above_threshold_cases") is None:
        return "Top-1 above measured thresholds: no thresholds given (--calibration)."
    return (f"Above the thresholds measured on the calibration run ({s['above_threshold_cases']} cases): top-1 "
            f"{_f(s['top1_above_thresholds'], True)}, median parameter error "
            f"{_f(s['median_param_error_above_thresholds'], True)}; below them ({s['below_threshold_cases']} "
            f"cases) any effect selected in {_f(s['any_selected_below_thresholds'], True)}, a wrong one in "
            f"{_f(s['wrong_selected_below_thresholds'], True)}; effect-free and below-threshold logs together: any "
            f"effect selected in {_f(s.get('any_selected_none_or_below'), True)}. Range-edge verdicts (\"not explained by the effect "
            f"library\"): {s['edge_verdicts']}."
            + (f" Reported, not claimed (detection limits): below a limit on {s['withheld_below_limit']} logs, not "
               f"told apart from a rival on {s['withheld_not_told_apart']}."
               if s.get("withheld_below_limit") or s.get("withheld_not_told_apart") else ""))


def _oracle_line(s: dict) -> str:
    if not s.get("oracle_cases"):
        return "Gap closed against the oracle: no case with an oracle (ORACLE_EFFECTS)."
    return (f"Gap closed against the oracle (the model given the hidden effect at its true value; "
            f"{s['oracle_cases']} cases of {', '.join(ORACLE_EFFECTS)}; the oracle does not improve on the refitted "
            f"nominal in {s['oracle_no_gain']}, pays on the held-out part in {s['oracle_pays']}; each case capped at "
            f"100 %): "
            f"median {_f(s['median_gap_vs_oracle'], True)} over every case with a gain (a miss closes nothing; "
            f"uncapped {_f(s.get('median_gap_vs_oracle_uncapped'), True)}; counting only a right top-1 "
            f"{_f(s.get('median_gap_vs_oracle_strict'), True)}), "
            f"{_f(s.get('median_gap_vs_oracle_above_thresholds'), True)} above the thresholds, "
            f"{_f(s['median_gap_vs_oracle_found'], True)} where the effect was identified; the hidden effect's own "
            f"fit (its value estimated) {_f(s['median_own_fit_vs_oracle'], True)}.")


def _precision_text(record: dict) -> str:
    counts = ", ".join(f"{e} {c['on_no_claim_logs']}/{c['claims']} ({c['right']} right)"
                       for e, c in sorted(record["counts"].items()))
    return counts + (f"; withdrawn: {', '.join(record['withdrawn'])}" if record["withdrawn"] else "")


def _limits_text(limits: dict) -> str:
    return ", ".join(f"{'every other effect' if e == ANY_OTHER else e} "
                     f"{'none (never claimed)' if v is None else f'{v:.3g}'}" for e, v in limits.items())


def markdown(sc: dict, settings: dict, seconds: float) -> str:
    s = sc["summary"]
    gate = s["gate_threshold"]
    seen = settings["seed"] in seen_seeds()
    lines = [f"Independent plant (CommonRoad {settings.get('plant_model', 'vehicle_dynamics_std')}, parameters_vehicle2) on {TRACK}, "
             f"{settings.get('duration', DURATION):.0f} s logs; seed {settings['seed']} "
             + ("(a calibration seed: chooses the gate, not a blind test)" if settings["calibration_seed"]
                else "(seen: scored before and looked at since, not blind)" if seen else "(blind: chose nothing)")
             + f"; {s['cases']} cases ({s['cases'] - s['simulated']} not simulated), {s['effect_cases']} with an "
             f"effect, {s['none_cases']} effect-free; {seconds / 60:.1f} min with {settings['jobs']} job(s).", "",
             f"No-gap gate: {'off' if gate is None else f'{gate:.4g}x the noise floor'}; evidence margin "
             f"dBIC < -{s['min_evidence']:g}; command hold "
             f"{'modelled (hold)' if settings.get('hold') else 'not modelled'}; nominal "
             f"{settings.get('nominal', 'mapped')}; fit {settings.get('fit') or 'one-step'}"
             + ("; mass offset scales Iz (mass_inertia)" if settings.get("mass_inertia") else "")
             + (f"; held-out evidence {settings['evidence']} (evidence)"
                if settings.get("evidence", "one-step") != "one-step" else "")
             + (f"; steering servo {settings['steer_servo']:g} s in the nominal" if settings.get("steer_servo") else "")
             + (f"; nominal effects {settings['nominal_effects']}" if settings.get("nominal_effects") else "")
             + ("; every log carries a pitch channel, grade_from_pitch among the candidates (pitch_channel)"
                if settings.get("pitch_channel") else "")
             + ("; every log carries a roll channel, bank_from_roll among the candidates (roll_channel)"
                if settings.get("roll_channel") else "")
             + (f"; {'decision' if settings.get('decision_limits') else 'detection'} limits "
                f"{_limits_text(settings['detection_limits'])} (an effect found below its limit is not claimed"
                f"{'; the limits are the decision levels below the thresholds' if settings.get('decision_limits') else ''})"
                if settings.get("detection_limits") else "")
             + (f"; thresholds only for effects whose calibration claims landed on logs where nothing should be "
                f"claimed in <= {1 - RELIABLE_RATE:.0%} (claim precision; such claims/claims: "
                f"{_precision_text(settings['claim_precision'])})"
                if settings.get("claim_precision") else "")
             + ".", "",
             "| metric | as diagnosed, gate off | with the gate and margin above |", "|---|---|---|",
             f"| top-1 identification (effect cases) | {_f(s['top1_without_gate'], True)} | {_f(s['top1'], True)} |",
             f"| false alarms on effect-free logs | {_f(s['false_alarm_rate_without_gate'], True)} | "
             f"{_f(s['false_alarm_rate'], True)} |", "",
             f"Effects selected on effect-free logs (without the gate): {', '.join(s['none_selected_effects']) or 'none'}. "
             f"On them the top candidate claims a median {_f(s['median_gap_closed_pct_none'])} % of the gap above the "
             f"noise floor closed, which is {_f(s['median_error_reduction_pct_none'])} % of the whole held-out error; "
             f"the refitted nominal's error is a median {_f(s['median_ratio_none'])}x (max {_f(s['max_ratio_none'])}x) "
             f"the noise floor.", "",
             _delay_lag_line(s["delay_vs_lag"]), "",
             _threshold_line(s, sc["per_effect"]), "",
             _oracle_line(s), "",
             f"Identified cases: median parameter error {_f(s['median_param_error'], True)} (scalar effects), gap closed "
             f"{_f(s['median_gap_closed_pct_found'])} % above the floor = {_f(s['median_error_reduction_pct_found'])} % "
             f"of the whole error. Diagnosis median {_f(s['median_diagnose_seconds'])} s per log.", "",
             "| effect | cases | drawn abs range | measured threshold (these cases) | threshold used | top-1 without "
             "gate | top-1 with gate | param error (found) | param error (all) | nominal / floor | mistaken for (with "
             "gate) | gap closed vs oracle (all / found) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for e, p in sc["per_effect"].items():
        lines.append(f"| {e} | {p['cases']} | {_f(p['drawn'][0])}-{_f(p['drawn'][1])} | "
                     f"{_f(p.get('measured_threshold')) if p.get('measured_threshold') is not None else 'never'} | "
                     f"{_f(p.get('threshold_used'))} | "
                     f"{_f(p['top1_without_gate'], True)} | {_f(p['top1'], True)} | "
                     f"{_f(p['median_param_error'], True) if e not in PROFILED else 'n/a (profile)'} | "
                     f"{_f(p['median_param_error_all'], True) if e not in PROFILED else 'n/a'} | "
                     f"{_f(p['median_ratio'])} | "
                     + (", ".join(f"{k} {v}" for k, v in sorted(p["mistaken_for"].items())) or "-") + " | "
                     + (f"{_f(p.get('median_gap_vs_oracle'), True)} / {_f(p.get('median_gap_vs_oracle_found'), True)}"
                        if p.get("oracle_cases") else "n/a") + " |")
    if settings.get("case_set") == "sweep":
        lines += ["", ladder_markdown(sc["per_effect"])]
    return "\n".join(lines) + "\n"


def ladder_markdown(per: dict) -> str:
    """The threshold sweep per effect, largest magnitude first: top-1 (a tick when right), the hidden effect's own
    round-1 dBIC (< 0: it pays on the held-out part) and its estimate; the measured threshold is where the
    unbroken run of ticks from the top ends."""
    lines = ["| effect | measured threshold | cases, largest first: magnitude -> top-1 (own dBIC, estimate) |",
             "|---|---|---|"]
    for e, p in per.items():
        cells = [f"{m:.3g} -> {'OK' if t == e else t} ({_f(d)}, {_f(x)})" for m, t, d, x in p.get("ladder", [])]
        thr = p.get("measured_threshold")
        lines.append(f"| {e} | {'never' if thr is None else _f(thr)} | " + "; ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(n_cases: int, seed: int = DEFAULT_SEED, config: DiagnosisConfig | None = None,
        bench: BenchmarkConfig | None = None, jobs: int = 1, progress: bool = True, case_set: str = "putnam",
        thresholds: dict | None = None, duration: float | None = None, calibration: dict | None = None) -> dict:
    """case_set: "putnam" (plan(): effects cycled, magnitudes drawn), "sweep" (plan_sweep(): the threshold
    sweep) or "above" (plan_above(): only effects with a threshold, drawn above it). config: the diagnosis's
    settings (every case carries them). bench: the nominal ("mapped": the vehicle file, "identified":
    identified_coefficients), the channels the logs carry, the effects whose cases are run (drawn as in the whole
    plan: same case numbers and seeds, the others skipped). thresholds: the detection thresholds scored against
    (a calibration's). duration: seconds of log per case (None: DURATION). calibration: what the run records of
    the calibration it applied."""
    CP.require_commonroad()
    config = config or DiagnosisConfig()
    bench = bench or BenchmarkConfig()
    duration = DURATION if duration is None else float(duration)
    if not 0 < duration <= MAX_DURATION:
        raise DdynError(f"--duration {duration:g}: expected 0 < seconds <= {MAX_DURATION:g}")
    if case_set not in ("putnam", "sweep", "above"):
        raise DdynError(f"case set {case_set!r}: expected putnam, sweep or above")
    if case_set == "above" and not thresholds:
        raise DdynError("case set above: needs thresholds (--calibration)")
    t0 = time.perf_counter()
    coeffs, ident = None, None
    if bench.nominal == "identified":
        coeffs, ident = identified_coefficients(config.hold is True)
    effects = bench.effects or None
    if effects is not None:
        bad = [e for e in effects if e not in EFFECT_RANGES and e != NONE]
        if bad:
            raise DdynError(f"effects: unknown {', '.join(bad)}; expected some of {', '.join(EFFECT_RANGES)}, none")
    # pitch_channel (roll_channel): every log carries the plant's pitch (roll) channel and the diagnosis may read
    # the grade (bank) from it
    from_channels = tuple(c for c, on in (("grade_from_pitch", bench.pitch_channel),
                                          ("bank_from_roll", bench.roll_channel)) if on and c not in config.candidates)
    config = config.with_(candidates=config.candidates + from_channels)
    extra = {"pitch_channel": bench.pitch_channel, "roll_channel": bench.roll_channel}
    cases = [c | {"config": config.to_dict(), "coefficients": None if coeffs is None else coeffs.tolist(),
                  "duration": duration} | extra
             for c in (plan_sweep(n_cases, seed) if case_set == "sweep" else
                       plan_above(n_cases, seed, thresholds or {}) if case_set == "above" else
                       plan(n_cases, seed))
             if effects is None or c["effect"] in effects]
    if not cases:
        raise DdynError("effects: no case of the plan has these effects")
    results = run_cases(run_case, cases, jobs, desc=f"gap-benchmark (commonroad, {case_set})", progress=progress)
    seconds = time.perf_counter() - t0
    settings = {"plant": "commonroad", "car": CP.NOMINAL_VEHICLE.stem, "case_set": case_set, "cases": n_cases,
                "seed": seed, "jobs": jobs, "diagnosis": config.to_dict(), "benchmark": bench.to_dict(),
                "sweep_levels": SWEEP_LEVELS if case_set == "sweep" else None,
                "calibration_seed": seed in CALIBRATION_SEEDS, "calibration_seeds": list(CALIBRATION_SEEDS),
                "case_seeds": f"{cases[0]['seed']}-{cases[-1]['seed']}", "duration": duration, "track": TRACK,
                "sample_time": load_vehicle(CP.NOMINAL_VEHICLE).sample_time, "effect_ranges": EFFECT_RANGES, "speeds": SPEEDS,
                "nominal": bench.nominal, "identification": ident, "thresholds": thresholds,
                "pitch_channel": bench.pitch_channel, "roll_channel": bench.roll_channel, "calibration": calibration,
                # the flat names the markdown and older readers use
                "hold": config.hold, "fit": config.fit, "gate": config.gate, "min_evidence": config.min_evidence,
                "detection_limits": config.detection_limits, "mass_inertia": config.mass_inertia,
                "steer_servo": config.steer_servo, "nominal_effects": config.nominal_effects,
                "evidence": config.evidence, "effects": None if effects is None else list(effects)}
    sc = score(results, thresholds)
    doc = {"settings": settings, **sc, "results": results, "seconds": seconds,
           "calibrated_gate": calibrate(results), "calibrated_margin": calibrate_margin(results)}
    return doc | {"markdown": markdown(sc, settings, seconds)}
