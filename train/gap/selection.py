"""The diagnosis: where a model's error on a log lies, which unmodelled effect causes it, how far it shrinks.

The nominal model is a vehicle file's coefficients (or given ones) or a DDM/DPM checkpoint's
per-window estimates; the effects are those of ddyn.model.effects, composed on the same physics.

Where    one-step residuals (vx, vy, omega) and multi-step position errors (ADE over the
         vehicle's evaluation horizon) of the nominal model, broken down by channel, by
         operating region (speed, lateral acceleration, front/rear slip angle, throttle/brake,
         steering rate), by position along the track (when a track is known) and by time; the
         bins that hold a much larger share of the error than of the samples are named.
Which    the log's transitions are split by time: the first `fit_fraction` fit, the rest is
         held out. Every candidate effect's main parameter is fitted (grid scan, then
         scipy.optimize.least_squares on the one-step residuals normalised per channel), with
         the nominal tyre peak forces Df, Dr refitted as factors under every hypothesis, "none"
         included (so an effect must explain more than a re-identified tyre). Score: held-out
         Gaussian log-likelihood (per-channel variances concentrated out); extended BIC difference
         dBIC = -2 dLL + dk ln(n_heldout) + 2 ln(m) against the current model (m candidates tried in
         the round: the EBIC prior over which effect, Chen & Chen 2008); an effect is added while
         the best candidate has dBIC < 0 (greedy, at most max_effects). Uncertainty: the
         Gauss-Newton covariance at the fit, scaled by the residuals' long-run variance factor
         (1 + 2 sum of autocorrelations, Bartlett window) because one-step residuals are not
         independent.
How far  held-out one-step RMSE per channel and ADE/FDE before (nominal as given) and after;
         gap_closed_pct = share of the nominal's held-out excess error removed, the excess being
         the normalised mean squared error above a measurement-noise floor estimated from the
         residuals' variance and lag-1 autocovariance, white sensor noise being fed through the
         nominal one-step map's Jacobian (see _noise_floor).

Output (ddyn.gap.report): DIR/diagnosis.json, DIR/diagnosis.md and PNG plots (where.png, residuals.png, which.png).
diagnosis.json ("schema": "ddyn-diagnosis 1"):
  config          the DiagnosisConfig the diagnosis ran under (every setting; `ddyn gap diagnose` adds
                  "calibration": the calibration applied, or none, and why)
  selected        [effect names], in the order added; [] means none is significant
  verdict         one line: the selected effects with estimate +- uncertainty, or "none: ..."; "none: not
                  explained by the effect library" when the best candidate pays for itself only from an edge
                  of its search range (such an estimate is a bound, never the verdict)
  unexplained     that candidate {effect, params, delta_bic}, or None
  not_told_apart  with detection limits: the first effect {effect, params, delta_bic, rival, rival_params,
                  rival_delta_bic, evidence_difference} when the runner-up of another family is within
                  AMBIGUITY_DBIC of it: reported, not selected (a claim needs a choice the data make), else None
  rival           the runner-up of the first effect's round (another family) when its dBIC is within
                  AMBIGUITY_DBIC of the first's: {effect, params, delta_bic, evidence_difference}, else None
                  (the verdict then says the two are not told apart)
  runner_up       the same for the best candidate of round 1 whatever the distance (None: no other family)
  truth           with diagnose(truth=...) (benchmarks): that hypothesis's held-out scores, else None
  candidates      best first (by dBIC), one per effect tried alone against the refitted nominal:
                  effect, params {name: value}, uncertainty {name: std}, unit, at_bound (the estimate sits
                  on an edge of its search range), refit {coefficient: factor},
                  heldout {rmse_before, rmse_refit_only, rmse_after: {vx, vy, omega}, ade_before, ade_after,
                  fde_before, fde_after}, gap_closed_pct, error_reduction_pct, delta_bic, delta_loglik,
                  lr_p_value, significant (dBIC < 0), fit_seconds, delta_bic_one_step (with --evidence multistep or
                  endpoint: the one-step dBIC of the same fit, for comparison)
  model           the selected combination refitted jointly: effects [{effect, params, uncertainty, unit, at_bound}],
                  refit, heldout (as above), gap_closed_pct, error_reduction_pct
  greedy          the selection steps: best candidate, its dBIC, whether it was added
  gate            the no-gap gate: ratio (refitted nominal's held-out normalised MSE / the noise floor's),
                  threshold (None: off), gated, selected_without_gate
  where           one_step_rmse, noise_floor_rmse, rmse_over_noise_floor {vx, vy, omega}; ade (m) and
                  horizon_steps; multi_step_rmse (over the horizon), multi_step_final_rmse (at its end)
                  {vx, vy, omega}; factors {speed, lateral_acceleration, front_slip, rear_slip, throttle_brake,
                  steering_rate, time, [track_position]: [{bin, samples_share, error_share, rmse, ade,
                  multi_step_rmse}]};
                  summary [sentences naming the regions that hold most of the error]
  method.evidence "one-step", "multistep:N: ..." or "endpoint:N: ..." (--evidence; what delta_bic scores)
  nominal, split, method, data, seconds: what was compared, how, on what (split.heldout_from_time: s after
                  the log's first row)
"""
from __future__ import annotations

import math
import time as _time

import numpy as np
from scipy import stats

from ddyn.data.dataset import Dataset
from ddyn.gap import candidates as C
from ddyn.gap import eiv, hold_estimate
from ddyn.gap import limits as L
from ddyn.gap.config import AMBIGUITY_DBIC, ANY_OTHER, DiagnosisConfig, parse_evidence_spec
from ddyn.gap.fit import Fit, fit
from ddyn.gap.heldout import _chan, _gap, _noise_floor, _norm_mse, _rms, heldout_summary
from ddyn.gap.problem import GRID_UNITS, OE_STEPS, Nominal, Problem, _starts, at_bound
from ddyn.gap.where import where

SCHEMA = "ddyn-diagnosis 1"


def _score(prob: Problem, base: dict, cand: dict, dk: int, m: int) -> dict:
    """Held-out log-likelihood gain and extended BIC difference (m: candidates tried in the round)."""
    n = len(prob.rows_held)
    dll = prob.loglik(cand["rss"], n) - prob.loglik(base["rss"], n)
    dbic = -2.0 * dll + dk * math.log(n) + 2.0 * math.log(max(m, 1))
    out = {"delta_loglik": dll, "delta_bic": dbic, "lr_p_value": float(stats.chi2.sf(max(2 * dll, 0.0), dk))}
    if prob.ev_steps:   # the multi-step evidence decides; the one-step figures are kept for comparison
        nw = len(prob.ev_starts)
        if prob.ev_endpoint:    # one (roughly independent) sample per window: its last step; the penalty counts windows
            rc, rb, n_pen = cand["ms_rss"][-1:], base["ms_rss"][-1:], nw
        else:   # every step of every window; the penalty counts the held-out rows the windows predict (one each)
            rc, rb, n_pen = cand["ms_rss"], base["ms_rss"], nw * prob.ev_steps
        dll_ms = prob.loglik(rc, nw) - prob.loglik(rb, nw)
        dbic_ms = -2.0 * dll_ms + dk * math.log(n_pen) + 2.0 * math.log(max(m, 1))
        out = {"delta_loglik": dll_ms, "delta_bic": dbic_ms,
               "lr_p_value": float(stats.chi2.sf(max(2 * dll_ms, 0.0), dk)),
               "delta_bic_one_step": dbic, "delta_loglik_one_step": dll}
    return out


def diagnose(ds: Dataset, nominal: Nominal, config: DiagnosisConfig | None = None, *, track=None, progress=None,
             truth: dict | None = None, **settings) -> dict:
    """The diagnosis of a log against a nominal model under `config` (DiagnosisConfig(): the defaults): the
    diagnosis.json document (see ddyn.gap.report) plus private series for the plots (keys starting with "_").
    track: a Track for the by-position breakdown and the profile candidates. progress: called with each
    candidate's name after its fit. truth: {effect: value} a benchmark knows the log holds; its held-out error at
    exactly that value (the refit factors fitted around it, as under every hypothesis) is reported as `truth`
    (the oracle the diagnosis's gap closed is compared with). settings: DiagnosisConfig fields that replace the
    config's (validated as the config is), e.g. diagnose(log, nominal, hold=True)."""
    cfg = DiagnosisConfig() if config is None else config
    if settings:
        cfg = cfg.with_(**settings)
    fit_fraction, refit, max_effects, max_starts = cfg.fit_fraction, cfg.refit, cfg.max_effects, cfg.max_starts
    gate, limits, margin, hold = cfg.gate, cfg.detection_limits, float(cfg.min_evidence), cfg.hold
    candidates = cfg.candidates
    t0 = _time.perf_counter()
    hold_info = None
    if hold == "estimate":      # the hold delay fitted on the nominal (ddyn.gap.hold_estimate)
        hold_info = hold_estimate.estimate(lambda h: Problem(ds, nominal, fit_fraction, refit, hold=h),
                                           lambda pr: fit(pr, ()), ds.sample_time)
        hold_info["dbw_period_from_steps"] = hold_estimate.detect_period(ds)
        hold = hold_info["hold"]
    elif hold == "steps":       # half the command period the log's step structure shows (ddyn.gap.hold_estimate)
        hold_info = hold_estimate.from_steps(ds)
        hold = hold_info["hold"]
    prob = Problem(ds, nominal, fit_fraction, refit, hold=hold, fit_mode=cfg.fit, mass_inertia=cfg.mass_inertia,
                   steer_servo=cfg.steer_servo, nominal_effects=cfg.nominal_effects)
    prob.layout = C.layout(ds, track, prob.rows_fit)
    C.attach(prob.lm, prob.layout)
    prob.set_evidence(*parse_evidence_spec(cfg.evidence))
    candidates = tuple(c for c in candidates if C.available(c, prob.layout))
    prob.bank_family_held = any(c in C.HOLDS_REFIT for c in candidates)
    v = nominal.vehicle
    steps = max(1, int(round(v.evaluation_horizon / ds.sample_time)))
    starts = _starts(prob, prob.rows_held, steps, max_starts)
    nr = len(prob.refit)
    before = heldout_summary(prob, {}, np.zeros(nr), starts, steps)
    base_fit = fit(prob, ())
    base = heldout_summary(prob, {}, base_fit.rho, starts, steps)
    if cfg.evidence_rows == "effective":     # every hypothesis's evidence counts the same effective rows
        prob.set_row_weight(base["res"])

    def evaluate(f: Fit, ref: dict, m: int, dk: int = 1) -> dict:
        h = heldout_summary(prob, f.values, f.rho, starts, steps)
        return {"heldout": h, **_score(prob, ref, h, dk, m)}

    def described(name: str, f: Fit) -> dict:
        val, sd, prof = C.summary(name, f.values, f.std, prob.layout)
        return {"effect": name, "params": {C.MAIN_PARAM[name]: val}, "uncertainty": {C.MAIN_PARAM[name]: sd},
                "unit": C.UNITS[name], "at_bound": at_bound(name, val, prob.ctx),
                **({"profile": prof} if prof is not None else {}),
                # a channel candidate's gain is not its size: the angle it reads (what a limit is set in)
                **({"magnitude": C.magnitude(name, val, prob.layout)} if name in C.ROLL_OF else {})}

    def entry(name: str, f: Fit, ev: dict) -> dict:
        h = ev["heldout"]
        return {**described(name, f),
                "refit": {n: 1.0 + float(r) for n, r in zip(prob.refit, f.rho)},
                "heldout": {"rmse_before": _chan(before["rmse"]), "rmse_refit_only": _chan(base["rmse"]),
                            "rmse_after": _chan(h["rmse"]), "ade_before": before["ade"], "ade_after": h["ade"],
                            "fde_before": before["fde"], "fde_after": h["fde"]},
                "gap_closed_pct": None, "error_reduction_pct": None, "_res": h["res"],
                "delta_bic": ev["delta_bic"], "delta_loglik": ev["delta_loglik"], "lr_p_value": ev["lr_p_value"],
                "significant": bool(ev["delta_bic"] < 0), "fit_seconds": f.seconds,
                **({"delta_bic_one_step": ev["delta_bic_one_step"]} if "delta_bic_one_step" in ev else {})}

    # round 1: every candidate alone (against the refitted nominal)
    first = []
    fits = {}
    for name in candidates:
        f = fit(prob, C.keys(name, prob.layout), start_rho=base_fit.rho, scan=name if name in GRID_UNITS else None)
        fits[name] = f
        first.append(entry(name, f, evaluate(f, base, len(candidates), len(f.names))))
        if progress:
            progress(name)
    first.sort(key=lambda c: c["delta_bic"])
    # round 1's runner-up: its best candidate of another family than the first, and how far behind it is
    r = next((c for c in first[1:] if C.FAMILY[c["effect"]] != C.FAMILY[first[0]["effect"]]), None)
    runner_up = (None if r is None else {"effect": r["effect"], "params": r["params"], "delta_bic": r["delta_bic"],
                                         "evidence_difference": r["delta_bic"] - first[0]["delta_bic"]})

    # this log's own detection limits at its margin (ddyn.gap.limits): what the report states, and with decision
    # levels relative to the size that matters, what a claim's estimate must clear
    margin = L.margin_of(cfg, len(prob.rows_held))
    families = list(dict.fromkeys(C.FAMILY[c] for c in candidates))

    def claim_margin(family: str) -> float:
        """What a family must pay to be claimed: the margin plus its own per-row margin (family_margins_per_row)."""
        has, per_row = _limit_of(family, cfg.family_margins_per_row)
        return margin + (float(per_row or 0.0) * len(prob.rows_held) if has else 0.0)

    def level_of(name: str) -> tuple[bool, float | None]:
        """(has a decision level, the level or None: never claimed) of a candidate on this log: the config's
        absolute detection_limits, else its decision_levels as a share of the family's size that matters."""
        has, lim = _limit_of(name, limits)
        if has:
            return has, lim
        has, share = _limit_of(name, cfg.decision_levels)
        if not has:
            return False, None
        size = L.size_that_matters(C.FAMILY[name], prob.ctx)
        return True, None if share is None or size is None else share * size

    # the stated limits: what the evidence could show, and never below what a claim needs (a decision level)
    levels = {f: lv for f in families for has, lv in [level_of(f)] if has}
    log_limits = L.log_limits(prob, base_fit.rho, families, {f: claim_margin(f) for f in families},
                              len(candidates), levels=levels, candidates=candidates)

    # greedy: add the best while it pays for itself. An effect that pays but is not claimed (an estimate on an
    # edge of its range, below its decision level, or not told apart from a rival) is kept in the model as a
    # nuisance, reported, and the search goes on for the others: a mismatch the library only approximates must
    # not hide a real effect behind it.
    selected: list[str] = []
    nuisance: list[str] = []
    current, current_h = base_fit, base
    steps_log = []
    unexplained = None      # the first candidate that paid for itself only from an edge of its range
    below_limit = None      # the first that paid for itself with a value below its detection limit
    not_told_apart = None   # under detection limits: the first effect when a rival's evidence is as good
    rounds = 0
    while len(selected) < max_effects and rounds < max_effects + cfg.max_unclaimed:
        rounds += 1
        taken = {C.FAMILY[n] for n in selected + nuisance}
        pool = [c for c in candidates if C.FAMILY[c] not in taken]
        if not pool:
            break
        trials = []
        for name in pool:
            if not selected and not nuisance:
                f = fits[name]
            else:
                f = fit(prob, current.names + C.keys(name, prob.layout), start={**current.values, **fits[name].values},
                        start_rho=current.rho)
            ev = evaluate(f, current_h, len(pool), len(C.keys(name, prob.layout)))
            trials.append((ev["delta_bic"], name, f, ev))
        trials.sort(key=lambda t: t[0])
        dbic, name, f, ev = trials[0]
        pays = bool(dbic < -margin)
        # an estimate on an edge of its range is a bound, not an estimate: the effect stands in for a mismatch
        # the library does not hold, so it is never the verdict
        main_value = C.summary(name, f.values, f.std, prob.layout)[0]   # a profile: its peak
        edge = pays and at_bound(name, main_value, prob.ctx)
        size = C.magnitude(name, main_value, prob.layout)      # a channel candidate: the angle it reads
        has_level, level = level_of(name)
        short_of_level = has_level and (level is None or abs(size) < level)
        weak = pays and not edge and (short_of_level or not dbic < -claim_margin(C.FAMILY[name]))
        # under detection limits a claim must also be a choice the data make: a first effect whose runner-up of
        # another family is within AMBIGUITY_DBIC of it is reported, not claimed (on the four calibration sweeps at
        # their margin every such first effect lay below its threshold, and 4 of the 7 were the wrong one)
        tie = bool((limits or cfg.decision_levels) and not selected and not nuisance and pays and not edge
                   and not weak and runner_up and first[0]["effect"] == name
                   and runner_up["evidence_difference"] < AMBIGUITY_DBIC)
        claimed = pays and not edge and not weak and not tie
        steps_log.append({"added": name if claimed else None, "nuisance": name if pays and not claimed else None,
                          "best_candidate": name, "delta_bic": dbic, "margin": margin, "at_bound": edge,
                          "below_limit": weak, "not_told_apart": tie, "after": selected + nuisance + [name]})
        if not pays:
            break
        if edge and unexplained is None:
            unexplained = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic}
        if weak and below_limit is None:
            # what stops the claim: the estimate's size (its decision level) or the evidence (its family's margin)
            below_limit = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic,
                           "limit": level, "blocked_by": "level" if short_of_level else "margin",
                           "claim_margin": claim_margin(C.FAMILY[name]),
                           **({"magnitude": size} if name in C.ROLL_OF else {})}
        if tie and not_told_apart is None:
            not_told_apart = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic,
                              "rival": runner_up["effect"], "rival_params": runner_up["params"],
                              "rival_delta_bic": runner_up["delta_bic"],
                              "evidence_difference": runner_up["evidence_difference"]}
        (selected if claimed else nuisance).append(name)
        current, current_h = f, ev["heldout"]

    # the noise floor: from the residuals of the best model evaluated (closest to pure sensor noise)
    best_res = min([current_h["res"]] + [c["_res"] for c in first], key=lambda r: _norm_mse(prob, _rms(r)))
    floor = _noise_floor(prob, best_res)
    # the no-gap gate: the refitted nominal's held-out error against the noise floor (both normalised MSE)
    e_floor = float(np.mean(floor / prob.scale ** 2))
    ratio = _norm_mse(prob, base["rmse"]) / e_floor if e_floor > 0 else math.inf
    gated = gate is not None and bool(selected) and ratio <= gate
    gate_info = {"ratio": ratio, "threshold": gate, "gated": gated, "selected_without_gate": list(selected),
                 "min_evidence": margin, "margin_rule": {"min_evidence": cfg.min_evidence,
                                                         "min_evidence_per_row": cfg.min_evidence_per_row,
                                                         "heldout_rows": int(len(prob.rows_held))},
                 "detection_limits": limits, "decision_levels": cfg.decision_levels,
                 "rule": "select nothing when the refitted nominal's held-out normalised one-step MSE is at most "
                         "`threshold` times the estimated noise floor's"}
    if gated:
        selected, current, current_h = [], base_fit, base
    for c in first:
        c["gap_closed_pct"], c["error_reduction_pct"] = _gap(prob, before, {"rmse": _rms(c.pop("_res"))}, floor)
    gap, red = _gap(prob, before, current_h, floor)
    # the first effect's rival: round 1's runner-up when within AMBIGUITY_DBIC of it
    rival = None
    if selected and runner_up and first[0]["effect"] == selected[0] and runner_up["evidence_difference"] < AMBIGUITY_DBIC:
        rival = runner_up
    truth_info = None
    if truth:
        tf = fit(prob, (), start_rho=base_fit.rho, fixed=dict(truth))
        th = heldout_summary(prob, tf.values, tf.rho, starts, steps)
        t_gap, t_red = _gap(prob, before, th, floor)
        truth_info = {"values": dict(truth), "refit": {n: 1.0 + float(r) for n, r in zip(prob.refit, tf.rho)},
                      "rmse_after": _chan(th["rmse"]), "gap_closed_pct": t_gap, "error_reduction_pct": t_red,
                      **_score(prob, base, th, len(truth), 1)}
    final = {"effects": [described(n, current) for n in selected],
             # effects that paid but are not claimed, kept in the model so the search could go on past them
             "unclaimed": [] if gated else [described(n, current) for n in nuisance],
             "refit": {n: 1.0 + float(r) for n, r in zip(prob.refit, current.rho)},
             "heldout": {"rmse_before": _chan(before["rmse"]), "rmse_after": _chan(current_h["rmse"]),
                         "ade_before": before["ade"], "ade_after": current_h["ade"],
                         "fde_before": before["fde"], "fde_after": current_h["fde"]},
             "gap_closed_pct": gap, "error_reduction_pct": red}
    w = where(prob, steps, max_starts, track, floor)
    series = {"where": w.pop("_series"), "held_time": prob.ds.time[prob.rows_held + 1],
              "res_before": before["res"], "res_after": current_h["res"]}
    return {
        "schema": SCHEMA,
        "config": cfg.to_dict(),
        "selected": selected,
        "verdict": (f"none: the nominal's held-out error is within the noise floor ({ratio:.3g}x <= gate {gate:g}x); "
                    f"without the gate: {', '.join(gate_info['selected_without_gate'])}" if gated else
                    _unexplained_verdict(unexplained) if not selected and unexplained else
                    "none: " + _below_limit_verdict(below_limit) if not selected and below_limit else
                    "none: " + _not_told_apart_verdict(not_told_apart) if not selected and not_told_apart else
                    "none: no candidate effect pays for its parameters on the held-out data"
                    + (f" by the evidence margin (dBIC < -{margin:g})" if margin else "") if not selected else
                    "; ".join(f"{e['effect']} {next(iter(e['params']))} = {next(iter(e['params'].values())):.4g} "
                              f"+- {next(iter(e['uncertainty'].values())):.2g} {e['unit']}"
                              + (" (AT THE EDGE of its range: a stand-in for another mismatch, not an estimate)"
                                 if e["at_bound"] else "") for e in final["effects"])
                    + (f" (or {rival['effect']}: its held-out evidence is within {rival['evidence_difference']:.1f} "
                       f"dBIC of the first effect's, < {AMBIGUITY_DBIC:g}: not told apart)" if rival else "")
                    + (f"; the rest is{_unexplained_verdict(unexplained)[5:]}"
                       if selected and unexplained else "")
                    + (f"; then {_below_limit_verdict(below_limit)}" if selected and below_limit else "")
                    # a tie that came first is not claimed, and the claims after it must not read as "none"
                    + (f"; first {_not_told_apart_verdict(not_told_apart)}" if selected and not_told_apart else "")),
        "unexplained": unexplained,
        "below_limit": below_limit,
        # this log's detection limits per family at its margin (ddyn.gap.limits), and the sentences a report prints
        "limits": log_limits,
        "not_told_apart": not_told_apart,
        "rival": rival,
        "runner_up": runner_up,
        "candidates": first,
        "model": final,
        "greedy": steps_log,
        "gate": gate_info,
        "truth": truth_info,
        "where": w,
        "nominal": {"source": nominal.label, "vehicle": v.name, "method": nominal.method,
                    "substeps": nominal.substeps, "refit_under_every_hypothesis": list(prob.refit),
                    "refit_held_by": [c for c in candidates if C.holds_refit((c,), prob.bank_family_held)],
                    "command_hold_delay": prob.hold, "hold_estimate": hold_info,
                    "mass_offset_scales_iz": prob.mass_inertia, "steer_servo_tau": prob.steer_servo,
                    "nominal_effects": prob.nominal_effects, "vehicle_effects": dict(nominal.effects),
                    "refit_only": {"rmse": _chan(base["rmse"]), "factors": {n: 1.0 + float(r) for n, r in
                                                                             zip(prob.refit, base_fit.rho)}}},
        "split": {"fit_fraction": fit_fraction, "fit_rows": int(len(prob.rows_fit)),
                  "heldout_rows": int(len(prob.rows_held)), "heldout_from_time": float(ds.time[prob.rows_held[0]] - ds.time[0]),
                  "rollout_starts": int(len(starts)), "horizon_s": steps * ds.sample_time},
        "method": {"fit": {"one-step": "scipy.optimize.least_squares (trf) on one-step residuals normalised per "
                                       "channel, after a grid scan of the new parameter",
                           "smoothed": "as one-step, each step starting from a leave-the-target-out local quadratic "
                                       f"estimate of (vx, vy, omega) (+-{eiv.HALF_WIDTH} samples; errors in variables)",
                           "output-error": f"as one-step, on the (vx, vy, omega) of {OE_STEPS}-step rollouts from each "
                                           "fit row",
                           "mixed": f"as output-error, except {', '.join(prob.one_step_in_mixed)}: its value fitted "
                                    "one-step, then held while the rest is fitted by output error"}[prob.fit_mode],
                   "fit_mode": prob.fit_mode if prob.fit_mode != "mixed" else
                   "mixed:" + ",".join(prob.one_step_in_mixed),
                   "criterion": "held-out extended BIC: dBIC = -2 dLL + dk ln(n_heldout) + 2 ln(candidates in the "
                                "round) < 0, greedy",
                   "evidence_rows": {"mode": cfg.evidence_rows,
                                     "weight_per_channel": _chan(prob.row_weight)},
                   "evidence": (f"{prob.evidence_name}: dLL of {prob.ev_steps}-step open-loop rollouts from "
                                f"{len(prob.ev_starts)} non-overlapping held-out windows "
                                + ("(only each window's last step, a variance per channel; the penalty counts windows)"
                                   if prob.ev_endpoint else "(a variance per horizon step and channel)")
                                if prob.ev_steps else "one-step"),
                   "uncertainty": "Gauss-Newton covariance x long-run variance factor of the residuals",
                   "gap_closed": "share of the held-out normalised one-step MSE above an estimated noise floor removed",
                   "noise_floor": _chan(floor), "channel_scale": _chan(prob.scale)},
        "data": {"source": ds.source, "rows": len(ds), "sample_time": ds.sample_time,
                 "effects_in_metadata": ds.metadata.get("effects"),
                 # track positions of the bank/grade profiles; the roll channel's plausibility (bank_from_roll)
                 # and the pitch channel's (grade_from_pitch)
                 "positions_from": prob.layout.source, "profile_knots": len(prob.layout.knots),
                 "roll_channel": prob.layout.roll, "pitch_channel": prob.layout.pitch},
        "seconds": _time.perf_counter() - t0,
        "_series": series,
    }


def _limit_of(name: str, limits: dict | None):
    """(has a limit, the limit or None: never claimed) of an effect's family."""
    family = C.FAMILY.get(name, name)
    if not limits or (family not in limits and ANY_OTHER not in limits):
        return False, None
    return True, limits[family] if family in limits else limits[ANY_OTHER]


def _below_limit_verdict(b: dict) -> str:
    (pn, pv), = b["params"].items()
    if b.get("blocked_by") == "margin":      # big enough, but its evidence is short of its family's margin
        limit = f"short of the dBIC -{b['claim_margin']:.1f} a {C.FAMILY[b['effect']].replace('_', ' ')} must pay here"
    else:
        limit = ("not reliably identified in the calibration (or not calibrated)" if b["limit"] is None
                 else f"below its detection limit {b['limit']:.4g}")
    size = (f" (a {C.FAMILY[b['effect']].replace('_', ' ')} of {b['magnitude']:.4g} rad at the channel's largest "
            "reading)" if "magnitude" in b else "")
    return (f"{b['effect']} pays on the held-out data (dBIC {b['delta_bic']:.1f}) with {pn} = {pv:.4g}{size}, "
            f"{limit}: not claimed")


def _not_told_apart_verdict(t: dict) -> str:
    (pn, pv), = t["params"].items()
    (rn, rv), = t["rival_params"].items()
    return (f"{t['effect']} ({pn} = {pv:.4g}, dBIC {t['delta_bic']:.1f}) and {t['rival']} ({rn} = {rv:.4g}, dBIC "
            f"{t['rival_delta_bic']:.1f}) pay on the held-out data within {t['evidence_difference']:.1f} dBIC of "
            f"each other (< {AMBIGUITY_DBIC:g}): not told apart, not claimed")


def _unexplained_verdict(u: dict) -> str:
    (pn, pv), = u["params"].items()
    return (f"none: not explained by the effect library (the best candidate, {u['effect']}, pays for itself only "
            f"from the edge of its range: {pn} = {pv:.4g}, dBIC {u['delta_bic']:.1f})")




# ----------------------------------------------------------------------------------------------- report
