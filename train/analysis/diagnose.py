"""`ddyn diagnose`: where a model's error on a log lies, which unmodelled effect causes it, how far it shrinks.

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

Output: DIR/diagnosis.json, DIR/diagnosis.md and PNG plots (where.png, residuals.png, which.png).
diagnosis.json ("schema": "ddyn-diagnosis 1"):
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

import argparse
import json
import math
import time as _time
from dataclasses import dataclass, replace as _replace
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from ddyn.analysis import candidates as C
from ddyn.analysis import eiv, hold_estimate
from ddyn.analysis.calibration import AMBIGUITY_DBIC, calibrated_diagnosis
from ddyn.data.dataset import Dataset
from ddyn.errors import DdynError
from ddyn.model import effects as E
from ddyn.model.single_track import COEFF_NAMES, N_COEFF
from ddyn.model.vehicle import Vehicle
from ddyn.model.vehicle import load as load_vehicle

CHANNELS = ("vx", "vy", "omega")
UNITS = {"vx": "m/s", "vy": "m/s", "omega": "rad/s"}
DEFAULT_REFIT = ("Df", "Dr")
DEFAULT_FIT_FRACTION = 0.6
# The no-gap gate (issue 14): when the refitted nominal's held-out normalised one-step MSE is at most this many
# times the estimated noise floor's, nothing is selected, whatever the dBIC says: a gap inside the noise is no gap.
# None: off. The value is calibrated on effect-free logs of the independent plant's calibration seeds
# (docs/gap_independent.md), never on the scored seed.
NO_GAP_GATE: float | None = None
# Evidence margin: an effect is added only when dBIC < -MIN_EVIDENCE (0: the plain EBIC rule). On an independent
# plant the nominal's own structural mismatch makes spurious effects pay for themselves by a few to a few tens of
# dBIC; the margin is calibrated like the gate (docs/gap_independent.md) and stays 0 by default.
MIN_EVIDENCE = 0.0
# Detection limits {effect: smallest |value| claimed, or None: never claimed}: an effect that pays on the held-out
# data with a value below its limit is reported, not selected, and the greedy stops there (a limit of detection).
# The limits come from calibration runs (`ddyn study gap --detection-limits-from`, `diagnose --detection-limits`):
# the detection thresholds measured there (below them the calibration found the effect in under 95 % of its logs,
# so a selection there is not one the calibration vouches for), or with `--decision-limits` the decision levels
# below them (an effect at its threshold is estimated above its level 95 % of the time; Currie's L_C for the
# threshold's L_D). None by default (no limits).
DETECTION_LIMITS: dict | None = None
# AMBIGUITY_DBIC (calibration.py, where recorded runs are scored by the same rule): the first effect added and the
# runner-up of its round with evidence closer than this are not told apart by the data. The diagnosis still adds
# the first (the selection is unchanged) and names the other as its rival, so a report never states a choice the
# held-out data cannot make (docs/gap_independent.md).
# What the fit compares (errors in variables, ddyn.analysis.eiv): "one-step" the step from the logged state,
# "smoothed" the step from a local polynomial estimate of the state that leaves out the sample being predicted,
# "output-error" OE_STEPS-step rollouts from the logged states. Held-out scores are one-step in every mode.
# "mixed": output error, except that a steering delay's value is fitted one-step first (then held while the rest,
# the refit factors among it, is fitted by output error): on the CommonRoad plant the output-error cost's minimum
# over the steering delay lies up to 0.08 s off the truth while the one-step cost's lies within 0.012 s
# (docs/gap_independent.md, the threshold sweep), and the refit by output error keeps every hypothesis on the
# footing of the nominal's output-error refit.
# "mixed:EFFECT,...": the same with those effects' values fitted one-step (downforce: on the calibration sweeps'
# 16 downforce logs its output-error estimate is a median 100 % and 71 % off (seeds 11, 13: zero, or several
# times the truth), the one-step estimate 33 % and 18 %; docs/gap_independent.md).
FIT_MODES = ("one-step", "smoothed", "output-error", "mixed")
ONE_STEP_IN_MIXED = ("steer_delay",)
DEFAULT_FIT = "one-step"
OE_STEPS = 10
# `diagnose --dbw`: the settings for drive-by-wire logs (commands held between samples), chosen on the
# independent plant's calibration seed 11 only (docs/gap_independent.md): the hold modelled, output error, and the
# evidence margin that left none of seed 11's effect-free logs with a selection. Not the default: logs whose
# commands ramp (the project's simulator, the own-model benchmark) must not get the hold, and output error costs
# about four times the one-step diagnosis.
# What the held-out evidence scores (issue 14, opt-in): "one-step" (default) the one-step residuals of the held-out
# rows; "multistep:N" N-step open-loop rollouts from the logged state at every N-th held-out row (non-overlapping
# windows that start after the fit/held-out cut, so no window sees a fit row), with a Gaussian variance per
# horizon step and channel concentrated out. A slow longitudinal effect (a mass offset, downforce) changes one
# 40 ms step by less than vx's sensor noise but accumulates over a window (docs/gap_independent.md).
# "endpoint:N" the same windows, but only each window's N-th-step error is scored and the penalty counts windows:
# the errors within a window are correlated (one disturbance carries through the rollout), so scoring all N steps
# as independent overstates the evidence (effect-free logs selected on seed 11); one endpoint per window is
# roughly one independent sample.
EVIDENCE_MODES = ("one-step", "multistep", "endpoint")
DEFAULT_EVIDENCE = "one-step"
MULTISTEP_DEFAULT_STEPS = 25
DBW_PRESET = {"hold": True, "fit": "output-error", "min_evidence": 13.02}
SCHEMA = "ddyn-diagnosis 1"


# ----------------------------------------------------------------------------------------------- the nominal

@dataclass
class Nominal:
    vehicle: Vehicle
    coeffs: np.ndarray          # (17,) or (N, 17)
    valid: np.ndarray           # (N,) rows whose coefficients are defined
    method: str
    substeps: int
    label: str


def parse_fit_spec(text: str | None) -> tuple[str, tuple[str, ...]]:
    """(fit mode, effects fitted one-step in "mixed") of a --fit spec: a FIT_MODES name, or "mixed:EFFECT,..."."""
    text = (text or DEFAULT_FIT).strip()
    mode, _, rest = text.partition(":")
    if mode not in FIT_MODES or (rest and mode != "mixed"):
        raise DdynError(f"unknown fit {text!r}; expected {', '.join(FIT_MODES)} or mixed:EFFECT,...")
    if mode != "mixed":
        return mode, ()
    effects = tuple(e.strip() for e in rest.split(",") if e.strip()) if rest else ONE_STEP_IN_MIXED
    bad = [e for e in effects if e not in C.ALL]
    if bad or not effects:
        raise DdynError(f"--fit {text}: unknown effect(s) {', '.join(bad) or '(none given)'}")
    return mode, effects


def parse_evidence_spec(text: str | None) -> tuple[int, bool]:
    """--evidence: "one-step" -> (0, False); "multistep[:N]" -> (N, False); "endpoint[:N]" -> (N, True), N >= 2
    (default MULTISTEP_DEFAULT_STEPS)."""
    if text in (None, "", "one-step"):
        return 0, False
    name, _, n = text.partition(":")
    if name not in ("multistep", "endpoint"):
        raise DdynError(f"unknown evidence {text!r}; expected one-step, multistep[:N] or endpoint[:N]")
    try:
        steps = int(n) if n else MULTISTEP_DEFAULT_STEPS
    except ValueError:
        raise DdynError(f"--evidence {text!r}: N must be an integer") from None
    if steps < 2:
        raise DdynError(f"--evidence {text!r}: N must be >= 2 (N = 1 is the one-step evidence)")
    return steps, name == "endpoint"


def nominal_from_vehicle(vehicle: Vehicle, ds: Dataset, coeffs=None, method: str | None = None,
                         substeps: int | None = None) -> Nominal:
    if coeffs is None:
        coeffs, label = vehicle.true_vector(), f"vehicle file {vehicle.name} (true_coefficients)"
    else:
        coeffs, label = np.asarray(coeffs, float), f"vehicle {vehicle.name} with given coefficients"
    if coeffs.shape != (N_COEFF,):
        raise DdynError(f"coefficients: expected {N_COEFF} values in the order {', '.join(COEFF_NAMES)}")
    method = method or ds.metadata.get("method", "euler")
    if substeps is None:
        substeps = int(ds.metadata.get("substeps", vehicle.rk4_substeps if method == "rk4" else 1))
    return Nominal(vehicle, coeffs, np.ones(len(ds), bool), method, substeps, label)


def nominal_from_checkpoint(path: str | Path, ds: Dataset) -> Nominal:
    """Per-row coefficients of a DDM (or a DPM, mapped onto the 17) estimated from each row's history."""
    import torch

    from ddyn.data.windows import make_windows, valid_end_rows
    from ddyn.learn import checkpoint

    model, ckpt = checkpoint.load(path)
    v = checkpoint.vehicle_of(ckpt)
    tau = int(ckpt["config"]["tau"])
    rows = valid_end_rows(ds, tau)
    if len(rows) == 0:
        raise DdynError(f"the log has no {tau}-row history window for the checkpoint")
    w = make_windows(ds, tau, rows)
    dtype = next(model.parameters()).dtype
    with torch.no_grad():
        est = np.concatenate([model.coefficients(torch.as_tensor(w.history[i:i + 8192], dtype=dtype)).double().numpy()
                              for i in range(0, len(rows), 8192)])
    coeffs = np.tile(v.true_vector() if v.true_coefficients else np.zeros(N_COEFF), (len(ds), 1))
    if ckpt["kind"] == "ddm":
        coeffs[rows] = est
    else:   # DPM: Pacejka B, C, D, E per axle and Frx directly; no shifts; Iz given
        names = ckpt["architecture"]["outputs"]
        coeffs[rows] = 0.0
        for i, n in enumerate(names[:-1]):
            coeffs[rows, COEFF_NAMES.index(n)] = est[:, i]
        coeffs[rows, COEFF_NAMES.index("Cr0")] = -est[:, names.index("Frx")]
        coeffs[rows, COEFF_NAMES.index("Iz")] = float(ckpt["dpm_iz"])
    valid = np.zeros(len(ds), bool)
    valid[rows] = True
    arch = ckpt["architecture"]
    return Nominal(v, coeffs, valid, arch.get("method", "euler"), int(arch.get("substeps", 1)),
                   f"{ckpt['kind'].upper()} checkpoint {Path(path).name} (coefficients per row, history {tau})")


# ----------------------------------------------------------------------------------------------- hypotheses

def _param_unit(name: str, ctx: dict) -> float:
    """Typical magnitude of an effect's main parameter on this log (the fit's scaling unit)."""
    if C.unit(name) is not None:
        return C.unit(name)
    dt, v, T = ctx["dt"], ctx["v_ref"], ctx["duration"]
    return {"steer_delay": dt, "throttle_delay": dt, "steer_lag": dt, "bank_angle": 0.01, "grade": 0.01,
            "downforce": 0.1 / v ** 2, "combined_slip": 0.1, "tire_relaxation": v * dt, "tire_wear": 0.1 / T,
            "yaw_rate_bias": 0.01, "mass_offset": 0.01, "throttle_map": 0.1, "brake_gain": 0.05,
            "power_limit": 10.0 * ctx.get("mass", 1000.0)}[name]


def _bounds(name: str, ctx: dict) -> tuple[float, float]:
    if C.bounds(name) is not None:
        return C.bounds(name)
    dt, vmax, T = ctx["dt"], ctx["v_max"], ctx["duration"]
    return {"steer_delay": (0.0, 12 * dt), "throttle_delay": (0.0, 12 * dt), "steer_lag": (0.0, 12 * dt),
            "bank_angle": (-0.3, 0.3), "grade": (-0.3, 0.3), "downforce": (0.0, 3.0 / vmax ** 2),
            "combined_slip": (0.0, 5.0), "tire_relaxation": (0.0, 12 * dt * vmax), "tire_wear": (0.0, 3.0 / T),
            "yaw_rate_bias": (-0.5, 0.5), "mass_offset": (-0.5, 1.0), "throttle_map": (-1.0, 1.0),
            "brake_gain": (-0.8, 2.0), "power_limit": (0.0, 1000.0 * ctx.get("mass", 1000.0))}[name]


def at_bound(name: str, value: float, ctx: dict) -> bool:
    """The estimate sits on a non-zero edge of its search range: the effect is likely standing in for a
    different mismatch (its value is then a bound, not an estimate)."""
    lo, hi = _bounds(name, ctx)
    tol = 1e-3 * (hi - lo)
    return any(b != 0.0 and abs(value - b) <= tol for b in (lo, hi))


GRID_UNITS = {"steer_delay": (0.5, 1, 2, 3, 5, 8), "throttle_delay": (0.5, 1, 2, 3, 5, 8),
              "steer_lag": (0.5, 1, 2, 3, 5, 8), "downforce": (0.5, 1, 2, 4), "combined_slip": (1, 3, 6, 12),
              "tire_relaxation": (0.1, 0.2, 0.3, 0.5, 0.75, 1, 1.5, 2, 3, 5, 8), "tire_wear": (0.5, 1, 2, 4),
              # power in 10 W/kg: 20-500 W/kg (a city car to a race car); throttle map and brake gain both ways
              "power_limit": (2, 4, 6, 8, 10, 14, 20, 30, 50), "throttle_map": (-5, -2, 2, 5),
              "brake_gain": (-6, -3, 3, 6, 12), **C.GRID}


class Problem:
    """One-step residuals of the nominal model plus effects on a log, split into fit and held-out rows."""

    def __init__(self, ds: Dataset, nominal: Nominal, fit_fraction: float, refit=DEFAULT_REFIT, hold: bool = False,
                 fit_mode: str = "one-step", mass_inertia: bool = False, steer_servo: float = 0.0,
                 nominal_effects: dict | None = None):
        self.ds, self.nominal = ds, nominal
        # mass_offset scales Iz with the mass (EffectSet.mass_inertia): with Df, Dr refitted it is then what a
        # heavier car with load-proportional tyre forces is, a change of the longitudinal response only
        self.mass_inertia = bool(mass_inertia)
        # a known steering servo (a DBW data sheet's first-order time constant) in the nominal; a steer_lag
        # hypothesis replaces it (the servo's time constant is then the estimate), a steer_delay adds to it
        self.steer_servo = float(steer_servo)
        # effects the nominal itself carries ({name: main parameter}, e.g. a data sheet's power limit); a hypothesis
        # of the same effect replaces the value
        self.nominal_effects = dict(nominal_effects or {})
        if self.steer_servo:
            self.nominal_effects.setdefault("steer_lag", self.steer_servo)
        # "mixed:EFFECT,...": which effects' values are fitted one-step (parse_fit_spec)
        self.fit_mode, self.one_step_in_mixed = parse_fit_spec(fit_mode)
        # commands held between samples (a drive-by-wire unit) while the model ramps them: on average the held
        # command lags the ramp by half a sample, so every hypothesis gets that delay on both commands and the
        # delay candidates estimate what comes on top of the hold
        # (hold: True for the half sample, or the hold delay in seconds: hold_estimate)
        self.hold = 0.5 * ds.sample_time if hold is True else float(hold or 0.0)
        self._hold_values = {"steer_delay": self.hold, "throttle_delay": self.hold} if self.hold else {}
        p = nominal.vehicle.known
        self.lm = E.LogModel.of(ds, p, nominal.method, nominal.substeps)
        # the fit's predictor (fit_residuals); held-out scores, the noise floor and "where" stay one-step from
        # the logged states whatever the fit, so that every fit mode is judged by the same yardstick
        self.lm_fit = self.lm
        if self.fit_mode == "smoothed":
            # errors in variables (ddyn.analysis.eiv): every step starts from a local polynomial estimate of the
            # state that leaves out the sample it predicts; the targets stay the measurements
            sm, _ = eiv.smooth_states(ds.states, ds.segment)
            self.lm_fit = E.LogModel(ds.time, ds.segment, sm, ds.inputs, p, ds.sample_time, nominal.method,
                                     nominal.substeps)
        self._oe_cache: dict = {}
        self.one_step_now = False    # "mixed": fit() sets it while it fits a steering delay one-step
        k = ds.transition_index()
        k = k[nominal.valid[k]]
        if len(k) < 50:
            raise DdynError(f"only {len(k)} usable transitions in the log; the diagnosis needs at least 50")
        cut = int(round(len(k) * fit_fraction))
        if not 20 <= cut <= len(k) - 20:
            raise DdynError(f"fit fraction {fit_fraction} leaves too few rows to fit or to hold out")
        self.rows_all, self.rows_fit, self.rows_held = k, k[:cut], k[cut:]
        self.target = ds.states[:, 3:6]
        self.ev_steps, self.ev_starts = 0, np.zeros(0, int)     # the multi-step evidence (set_evidence)
        self.ev_endpoint = False
        self.refit = tuple(refit)
        self.refit_idx = [COEFF_NAMES.index(n) for n in self.refit]
        vx = np.abs(ds.states[k, 3])
        self.layout: C.Layout | None = None    # track positions for profile candidates (set by diagnose)
        self.bank_family_held = False          # the constant bank holds the refit too (candidates.holds_refit)
        self.ctx = {"dt": ds.sample_time, "v_ref": max(float(np.mean(vx)), 1e-3), "mass": float(p.mass),
                    "v_max": max(float(np.max(vx)), 1e-3), "duration": max(float(ds.time[-1] - ds.time[0]), 1.0)}
        res = self.target[self.rows_fit + 1] - self.predict({}, np.zeros(0), self.rows_fit)
        rms = np.sqrt(np.mean(res ** 2, axis=0))
        change = np.sqrt(np.mean((self.target[k + 1] - self.target[k]) ** 2, axis=0))
        self.floor = 1e-6 * np.maximum(change, 1e-12)
        self.scale = np.maximum(rms, 1e3 * self.floor)

    def coeffs(self, rho: np.ndarray):
        c = self.nominal.coeffs
        if len(rho) == 0 or not np.any(rho):
            return c
        c = c.copy()
        c[..., self.refit_idx] *= 1.0 + np.asarray(rho)
        return c

    def effects(self, values: dict) -> E.EffectSet:
        """The effects of a hypothesis, with the command hold's half-sample delays added when hold is on."""
        if self._hold_values:
            values = {**values, **{k: values.get(k, 0.0) + v for k, v in self._hold_values.items()}}
        if self.nominal_effects:
            values = {**self.nominal_effects, **values}
        fx = C.effect_set(values, self.layout)
        return _replace(fx, mass_inertia=True) if self.mass_inertia and fx.mass_offset else fx

    def predict(self, values: dict, rho: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return self.lm.one_step(self.effects(values), rows, self.coeffs(rho))

    def residuals(self, values: dict, rho, rows) -> np.ndarray:
        return (self.target[rows + 1] - self.predict(values, rho, rows)) / self.scale

    def fit_residuals(self, values: dict, rho, rows) -> np.ndarray:
        """The residuals the fit minimises, (n, 3) normalised per channel: one-step ("one-step", "smoothed": from
        the logged or the smoothed states), or "output-error": the (vx, vy, omega) of OE_STEPS-step rollouts
        from each row against the log, every step weighted 1/sqrt(OE_STEPS) so the cost is on the one-step
        scale."""
        if self.fit_mode not in ("output-error", "mixed") or self.one_step_now:
            return (self.target[rows + 1] - self.lm_fit.one_step(self.effects(values), rows, self.coeffs(rho))) \
                / self.scale
        key = (int(rows[0]), int(rows[-1]), len(rows))
        if key not in self._oe_cache:
            starts = _starts(self, rows, OE_STEPS, 10 ** 9)
            self._oe_cache[key] = (starts, np.stack([self.target[starts + j + 1] for j in range(OE_STEPS)]))
        starts, truth = self._oe_cache[key]
        pred = self.lm_fit.rollout(self.effects(values), starts, OE_STEPS, self.coeffs(rho), whole_state=True)
        return ((truth - pred[..., 3:6]) / (self.scale * math.sqrt(OE_STEPS))).reshape(-1, 3)

    def rss(self, values: dict, rho, rows) -> np.ndarray:
        r = self.target[rows + 1] - self.predict(values, rho, rows)
        return np.sum(r ** 2, axis=0)

    def loglik(self, rss: np.ndarray, n: int) -> float:
        """Gaussian log-likelihood with per-channel variances concentrated out (constants dropped); rss (3,) or,
        for the multi-step evidence, (steps, 3): a variance per horizon step and channel (n: windows)."""
        return float(-0.5 * n * np.sum(np.log(rss / n + self.floor ** 2)))

    def set_evidence(self, steps: int, endpoint: bool = False) -> None:
        """The multi-step evidence's windows: every `steps`-th held-out row starts a rollout of `steps` steps
        that stays in its segment and in the log; the held-out rows follow the fit rows, so no window holds a fit
        row's target (steps 0: the one-step evidence). endpoint: score only each window's last step."""
        self.ev_steps = int(steps)
        self.ev_endpoint = bool(endpoint) and self.ev_steps > 0
        self.ev_starts = np.zeros(0, int)
        if self.ev_steps:
            self.ev_starts = _starts(self, self.rows_held[::self.ev_steps], self.ev_steps, 10 ** 9)
            if len(self.ev_starts) < 5:
                raise DdynError(f"--evidence {self.evidence_name}: only {len(self.ev_starts)} held-out windows; "
                                "the held-out part is too short for this N")

    @property
    def evidence_name(self) -> str:
        return f"{'endpoint' if self.ev_endpoint else 'multistep'}:{self.ev_steps}" if self.ev_steps else "one-step"

    def multistep_rss(self, values: dict, rho) -> np.ndarray:
        """(steps, 3): sum over the evidence windows of the squared (vx, vy, omega) error at each horizon step."""
        s, n = self.ev_starts, self.ev_steps
        pred = self.lm.rollout(self.effects(values), s, n, self.coeffs(rho), whole_state=True)[..., 3:6]
        truth = np.stack([self.target[s + j + 1] for j in range(n)])
        return np.sum((truth - pred) ** 2, axis=1)


@dataclass
class Fit:
    names: tuple
    values: dict
    rho: np.ndarray
    std: dict
    rho_std: np.ndarray
    cost: float
    seconds: float


def _long_run_factor(res: np.ndarray, lags: int = 20) -> float:
    """1 + 2 sum_k (1 - k/(L+1)) rho_k, averaged over channels (>= 1)."""
    out = []
    for r in res.T:
        r = r - r.mean()
        v = float(np.dot(r, r))
        if v <= 0:
            continue
        s = sum((1 - j / (lags + 1)) * float(np.dot(r[:-j], r[j:])) / v for j in range(1, min(lags, len(r) - 1) + 1))
        out.append(1 + 2 * s)
    return max(1.0, float(np.mean(out))) if out else 1.0


def fit(prob: Problem, names: tuple, start: dict | None = None, start_rho=None, scan: str | None = None,
        rho_bounds=None, fixed: dict | None = None) -> Fit:
    """Fit the main parameters of `names` (and the refit factors, 1 + rho, rho within rho_bounds (lo, hi),
    default +-0.5) on the fit rows; `fixed`: further effect values held as given."""
    t0 = _time.perf_counter()
    names = tuple(names)
    start = dict(start or {})
    fixed = dict(fixed or {})
    one_step = [n for n in names if n in prob.one_step_in_mixed]
    if prob.fit_mode == "mixed" and one_step and not prob.one_step_now:
        # those effects' values from the one-step cost, then everything else by output error around them
        prob.one_step_now = True
        try:
            f1 = fit(prob, names, start, start_rho, scan, rho_bounds, fixed)
        finally:
            prob.one_step_now = False
        held_vals = {n: f1.values[n] for n in one_step}
        rest = tuple(n for n in names if n not in one_step)
        f2 = fit(prob, rest, {**start, **f1.values}, f1.rho, None, rho_bounds, {**fixed, **held_vals})
        return Fit(names, {**f2.values, **held_vals}, f2.rho, {**f2.std, **{n: f1.std[n] for n in one_step}},
                   f2.rho_std, f2.cost, _time.perf_counter() - t0)
    units = np.array([_param_unit(n, prob.ctx) for n in names])
    rlo, rhi = (np.full(len(prob.refit), -0.5), np.full(len(prob.refit), 0.5)) if rho_bounds is None else rho_bounds
    # a bank that follows the turns keeps the nominal's tyre (candidates.HOLDS_REFIT: the two are confounded)
    held = C.holds_refit(names, prob.bank_family_held)
    nr = 0 if held else len(prob.refit)
    rlo, rhi = list(rlo)[:nr], list(rhi)[:nr]
    lo = np.array([_bounds(n, prob.ctx)[0] for n in names] + rlo)
    hi = np.array([_bounds(n, prob.ctx)[1] for n in names] + rhi)
    rows = prob.rows_fit
    rho0 = np.zeros(nr) if start_rho is None or held else np.asarray(start_rho, float)

    def unpack(z):
        vals = {**fixed, **{n: float(z[i] * units[i]) for i, n in enumerate(names)}}
        return vals, (np.zeros(len(prob.refit)) if held else np.asarray(z[len(names):], float) * 0.1)

    def fun(z):
        vals, rho = unpack(z)
        return prob.fit_residuals(vals, rho, rows).ravel()

    x0 = np.array([start.get(n, 0.0) / units[i] for i, n in enumerate(names)] + list(rho0 / 0.1))
    if scan is not None:   # coarse grid over the new effect's parameter, others at their start values
        i = names.index(scan)
        grid = [0.0] + [g for g in GRID_UNITS.get(scan, ()) if lo[i] <= g * units[i] <= hi[i]]
        best = None
        for g in grid:
            x = x0.copy()
            x[i] = g
            c = float(np.sum(fun(x) ** 2))
            if best is None or c < best[0]:
                best = (c, g)
        x0[i] = best[1]
    zlo, zhi = lo / np.r_[units, np.full(nr, 0.1)], hi / np.r_[units, np.full(nr, 0.1)]
    x0 = np.clip(x0, zlo, zhi)
    if len(x0) == 0:
        return Fit(names, dict(fixed), np.zeros(len(prob.refit)) if held else np.zeros(0), {}, np.zeros(0),
                   float(np.sum(fun(x0) ** 2)) / 2, 0.0)
    sol = optimize.least_squares(fun, x0, bounds=(zlo, zhi), method="trf", x_scale=1.0, max_nfev=200)
    vals, rho = unpack(sol.x)
    m, k = sol.fun.size, len(sol.x)
    std_z = np.full(k, np.nan)
    try:
        J = sol.jac
        cov = np.linalg.pinv(J.T @ J) * (2 * sol.cost / max(m - k, 1))
        cov *= _long_run_factor(sol.fun.reshape(-1, 3))
        std_z = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except (np.linalg.LinAlgError, ValueError):
        pass
    std = {n: float(std_z[i] * units[i]) for i, n in enumerate(names)}
    rho_std = np.zeros(len(prob.refit)) if held else std_z[len(names):] * 0.1
    return Fit(names, vals, rho, std, rho_std, float(sol.cost), _time.perf_counter() - t0)


# ----------------------------------------------------------------------------------------------- scores

def _starts(prob: Problem, rows: np.ndarray, steps: int, max_starts: int) -> np.ndarray:
    seg, valid = prob.ds.segment, prob.nominal.valid
    n = len(prob.ds)
    ok = rows[(rows + steps < n)]
    ok = ok[(seg[np.minimum(ok + steps, n - 1)] == seg[ok]) & valid[ok]]
    if len(ok) > max_starts:
        ok = ok[np.linspace(0, len(ok) - 1, max_starts).astype(int)]
    return ok


def rollout_errors(prob: Problem, values: dict, rho, starts: np.ndarray, steps: int,
                   channels: bool = False):
    """Position error (steps, n_starts) of rollouts from `starts`; channels: also the multi-step residuals of
    (vx, vy, omega), (steps, n_starts, 3)."""
    if len(starts) == 0:
        return (np.zeros((steps, 0)), np.zeros((steps, 0, 3))) if channels else np.zeros((steps, 0))
    pred = prob.lm.rollout(prob.effects(values), starts, steps, prob.coeffs(rho),
                           whole_state=channels)
    truth = np.stack([prob.ds.states[starts + j + 1] for j in range(steps)])
    pos = np.linalg.norm(pred[..., :2] - truth[..., :2], axis=-1)
    return (pos, truth[..., 3:6] - pred[..., 3:6]) if channels else pos


def _state_jacobian(prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Mean J and mean J**2 (elementwise) over the log of d(vx, vy, omega)_k+1 / d(vx, vy, omega)_k of the
    nominal one-step map (central differences): how a state's sensor noise reaches the next prediction."""
    if getattr(prob, "_jac", None) is None:
        rows, ds, lm = prob.rows_all, prob.ds, prob.lm
        c = prob.nominal.coeffs[rows] if prob.nominal.coeffs.ndim == 2 else prob.nominal.coeffs
        x = ds.states[rows]
        J = np.empty((len(rows), 3, 3))
        for j in range(3):
            h = 1e-6 * max(float(np.sqrt(np.mean(x[:, 3 + j] ** 2))), 1e-3)
            xp, xm = x.copy(), x.copy()
            xp[:, 3 + j] += h
            xm[:, 3 + j] -= h
            step = lambda s: E.step_numpy(s, ds.inputs[rows], c, lm.p, lm.dt, lm.method, lm.substeps,  # noqa: E731
                                          E.EffectSet(), None, E.Aux())[:, 3:6]
            J[:, :, j] = (step(xp) - step(xm)) / (2 * h)
        prob._jac = (J.mean(axis=0), (J ** 2).mean(axis=0))
    return prob._jac


def _noise_floor(prob: Problem, res: np.ndarray) -> np.ndarray:
    """Per channel: one-step MSE a perfect model would leave under white sensor noise of variances s2.

    With r_k = n_k+1 - J n_k (+ model error m_k): E r_i^2 = s2_i + sum_j J2_ij s2_j, and the lag-1
    autocovariance is -J_ii s2_i (+ that of m). Slowly varying model error cancels in g0 - g1, so
    s2 solves (diag(1 + J_ii) + J2) s2 = g0 - g1; the floor is (I + J2) s2 (<= g0). With J = I this is
    the MA(1) rule 2 (g0 - g1) / 3."""
    r = res - res.mean(axis=0)
    g0 = np.mean(r * r, axis=0)
    g1 = np.mean(r[1:] * r[:-1], axis=0)
    mj, mj2 = _state_jacobian(prob)
    try:
        s2 = np.linalg.solve(np.diag(1.0 + np.diag(mj)) + mj2, g0 - g1)
    except np.linalg.LinAlgError:
        s2 = (g0 - g1) / 3.0
    return np.clip((np.eye(3) + mj2) @ np.maximum(s2, 0.0), 0.0, g0)


def heldout_summary(prob: Problem, values: dict, rho, starts, steps) -> dict:
    rows = prob.rows_held
    res = prob.target[rows + 1] - prob.predict(values, rho, rows)
    e = rollout_errors(prob, values, rho, starts, steps)
    out = {"rss": np.sum(res ** 2, axis=0), "rmse": np.sqrt(np.mean(res ** 2, axis=0)), "res": res,
           "ade": float(e.mean()) if e.size else float("nan"), "fde": float(e[-1].mean()) if e.size else float("nan")}
    if prob.ev_steps:
        out["ms_rss"] = prob.multistep_rss(values, rho)
    return out


def _rms(res: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(res ** 2, axis=0))


def normalised_mse(rmse: dict, scale: dict) -> float:
    """The held-out normalised MSE of a report's per-channel RMSE ({vx, vy, omega}) with its channel scales
    (`method.channel_scale`): what gap closed is measured on, for benchmarks comparing reports."""
    return float(np.mean([(rmse[c] / scale[c]) ** 2 for c in CHANNELS]))


def _norm_mse(prob: Problem, rmse: np.ndarray) -> float:
    return float(np.mean((rmse / prob.scale) ** 2))


def _gap(prob: Problem, before: dict, after: dict, floor: np.ndarray) -> tuple[float | None, float]:
    eb, ea = _norm_mse(prob, before["rmse"]), _norm_mse(prob, after["rmse"])
    ef = min(float(np.mean(floor / prob.scale ** 2)), ea)
    gap = 100.0 * (eb - ea) / (eb - ef) if eb - ef > 1e-12 * max(eb, 1e-300) else None
    return gap, 100.0 * (eb - ea) / eb if eb > 0 else 0.0


def _chan(a) -> dict:
    return {c: float(v) for c, v in zip(CHANNELS, a)}


# ----------------------------------------------------------------------------------------------- where

def _quartile_bins(x: np.ndarray, names: tuple[str, ...], unit: str, fmt: str = "{:.3g}"):
    edges = np.quantile(x, [0.25, 0.5, 0.75])
    idx = np.searchsorted(edges, x, side="right")
    lo = np.r_[x.min(), edges]
    hi = np.r_[edges, x.max()]
    labels = [f"{names[i]} ({fmt.format(lo[i])}-{fmt.format(hi[i])} {unit})" for i in range(4)]
    return idx, labels


def _factors(prob: Problem, rows: np.ndarray, track) -> dict:
    ds = prob.ds
    st = ds.states[rows]
    c = prob.nominal.coeffs[rows] if prob.nominal.coeffs.ndim == 2 else prob.nominal.coeffs
    alpha = prob.lm._alpha(st, st[:, 7], c)
    out = {}
    out["speed"] = _quartile_bins(st[:, 3], ("low speed", "medium-low speed", "medium-high speed", "high speed"),
                                  "m/s")
    out["lateral_acceleration"] = _quartile_bins(np.abs(st[:, 3] * st[:, 5]),
                                                 ("gentle cornering", "moderate cornering", "hard cornering",
                                                  "hardest cornering"), "m/s2 |vx omega|")
    out["front_slip"] = _quartile_bins(np.abs(alpha[:, 0]), ("small front slip", "moderate front slip",
                                                             "large front slip", "largest front slip"), "rad")
    out["rear_slip"] = _quartile_bins(np.abs(alpha[:, 1]), ("small rear slip", "moderate rear slip",
                                                            "large rear slip", "largest rear slip"), "rad")
    T = st[:, 6]
    pos = T[T > 0]
    mid = float(np.median(pos)) if len(pos) else 0.0
    idx = np.where(T < 0, 0, np.where(T <= mid, 1, 2))
    out["throttle_brake"] = (idx, ["braking (T < 0)", f"light throttle (0-{mid:.3g})", f"heavy throttle (> {mid:.3g})"])
    out["steering_rate"] = _quartile_bins(np.abs(ds.inputs[rows, 1]), ("steady steering", "slow steering",
                                                                       "fast steering", "fastest steering"), "rad/s")
    t = ds.time[rows] - ds.time[0]
    edges = np.linspace(t.min(), t.max() + 1e-9, 11)
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, 9)
    out["time"] = (idx, [f"time {edges[i]:.1f}-{edges[i + 1]:.1f} s" for i in range(10)])
    if track is not None:
        s, _ = track.project(ds.states[rows, 0], ds.states[rows, 1])
        edges = np.linspace(0, track.length, 11)
        idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, 9)
        out["track_position"] = (idx, [f"track {edges[i]:.0f}-{edges[i + 1]:.0f} m" for i in range(10)])
    return out


def where(prob: Problem, steps: int, max_starts: int, track=None, floor=None) -> dict:
    """Error of the nominal model by channel, operating region, track position and time."""
    rows = prob.rows_all
    res = prob.target[rows + 1] - prob.predict({}, np.zeros(len(prob.refit)), rows)
    fl = _noise_floor(prob, res) if floor is None else floor
    # squared error in units of the noise floor: channels far above their noise weigh most
    err = np.sum(res ** 2 / np.maximum(fl, (0.05 * prob.scale) ** 2), axis=1)
    total = float(err.sum()) or 1.0
    starts = _starts(prob, rows, steps, max_starts)
    pos_err, ms_res = rollout_errors(prob, {}, np.zeros(len(prob.refit)), starts, steps, channels=True)
    ade = pos_err.mean(axis=0)
    start_pos = np.searchsorted(rows, starts)
    fac = _factors(prob, rows, track)
    rmse = np.sqrt(np.mean(res ** 2, axis=0))
    noise = np.sqrt(fl)
    over = rmse / np.maximum(noise, 1e-300)
    out = {"one_step_rmse": _chan(rmse), "noise_floor_rmse": _chan(noise),
           "rmse_over_noise_floor": {c: (float(r) if np.isfinite(r) and n > 0 else None)
                                     for c, r, n in zip(CHANNELS, over, noise)},
           "ade": float(ade.mean()) if len(ade) else None, "horizon_steps": steps,
           # multi-step residuals of the nominal by channel: RMSE over the whole horizon and at its end
           "multi_step_rmse": _chan(np.sqrt(np.mean(ms_res ** 2, axis=(0, 1)))) if len(ade) else None,
           "multi_step_final_rmse": _chan(np.sqrt(np.mean(ms_res[-1] ** 2, axis=0))) if len(ade) else None,
           "factors": {}}
    notable = []
    for fname, (idx, labels) in fac.items():
        bins = []
        for b, label in enumerate(labels):
            m = idx == b
            if not m.any():
                continue
            sm = idx[start_pos] == b if len(start_pos) else np.zeros(0, bool)
            row = {"bin": label, "samples_share": float(m.mean()), "error_share": float(err[m].sum() / total),
                   "rmse": _chan(np.sqrt(np.mean(res[m] ** 2, axis=0))),
                   "ade": float(ade[sm].mean()) if sm.any() else None,
                   "multi_step_rmse": _chan(np.sqrt(np.mean(ms_res[:, sm] ** 2, axis=(0, 1)))) if sm.any() else None}
            bins.append(row)
            if row["samples_share"] >= 0.05:
                notable.append((row["error_share"] / row["samples_share"], fname, row))
        out["factors"][fname] = bins
    notable.sort(key=lambda x: -x[0])
    words = []
    for ratio, fname, row in notable[:4]:
        if ratio < 1.3:
            break
        words.append(f"{row['bin']}: {100 * row['samples_share']:.0f} % of the samples hold "
                     f"{100 * row['error_share']:.0f} % of the one-step error ({ratio:.1f}x its share)")
    i = int(np.argmax(np.where(noise > 0, over, np.inf)))
    c = CHANNELS[i]
    words.insert(0, f"channel {c}: one-step RMSE {rmse[i]:.3g} {UNITS[c]}, "
                    + (f"{over[i]:.1f}x the estimated noise floor" if noise[i] > 0 else "no measurable noise")
                    + " (" + ", ".join(f"{CHANNELS[j]} {over[j]:.1f}x" for j in range(3) if noise[j] > 0) + ")")
    out["summary"] = words if len(words) > 1 else words + ["the error is spread evenly over the operating regions"]
    out["_series"] = {"time": prob.ds.time[rows + 1], "res": res, "err": err, "x": prob.ds.states[rows, 0],
                      "y": prob.ds.states[rows, 1], "factors": fac}
    return out


# ----------------------------------------------------------------------------------------------- which + how far

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


def diagnose(ds: Dataset, nominal: Nominal, fit_fraction: float = DEFAULT_FIT_FRACTION,
             candidates=E.EFFECT_NAMES, refit=DEFAULT_REFIT, max_effects: int = 3, track=None,
             max_starts: int = 400, progress=None, gate: float | None | str = "default", hold: bool = False,
             min_evidence: float | None = None, fit_mode: str | None = None, mass_inertia: bool = False,
             steer_servo: float = 0.0, nominal_effects: dict | None = None, evidence: str | None = None,
             truth: dict | None = None, detection_limits: dict | None | str = "default") -> dict:
    """truth: {effect: value} a benchmark knows the log holds; its held-out error at exactly that value (the
    refit factors fitted around it, as under every hypothesis) is reported as `truth` (the oracle the
    diagnosis's gap closed is compared with). evidence: what the held-out score compares (EVIDENCE_MODES:
    "one-step" by default, "multistep[:N]").
    gate: the no-gap gate's ratio (NO_GAP_GATE by default; None: off). hold: the log's commands were held
    between samples (drive-by-wire), not ramped as the model integrates them (see Problem). min_evidence: an
    effect is added only when its dBIC < -min_evidence (default MIN_EVIDENCE). fit_mode: what the fit compares
    (FIT_MODES, default DEFAULT_FIT). mass_inertia, steer_servo: see Problem. detection_limits: {effect family:
    limit or None} (DETECTION_LIMITS by default); an effect not in it has no limit."""
    gate = NO_GAP_GATE if gate == "default" else gate
    limits = DETECTION_LIMITS if detection_limits == "default" else detection_limits
    margin = MIN_EVIDENCE if min_evidence is None else float(min_evidence)
    fit_mode = fit_mode or DEFAULT_FIT
    t0 = _time.perf_counter()
    hold_info = None
    if hold == "estimate":      # the hold delay fitted on the nominal (ddyn.analysis.hold_estimate)
        hold_info = hold_estimate.estimate(lambda h: Problem(ds, nominal, fit_fraction, refit, hold=h),
                                           lambda pr: fit(pr, ()), ds.sample_time)
        hold_info["dbw_period_from_steps"] = hold_estimate.detect_period(ds)
        hold = hold_info["hold"]
    prob = Problem(ds, nominal, fit_fraction, refit, hold=hold, fit_mode=fit_mode, mass_inertia=mass_inertia,
                   steer_servo=steer_servo, nominal_effects=nominal_effects)
    prob.layout = C.layout(ds, track, prob.rows_fit)
    C.attach(prob.lm, prob.layout)
    prob.set_evidence(*parse_evidence_spec(evidence))
    candidates = tuple(c for c in candidates if C.available(c, prob.layout))
    prob.bank_family_held = any(c in C.HOLDS_REFIT for c in candidates)
    v = nominal.vehicle
    steps = max(1, int(round(v.evaluation_horizon / ds.sample_time)))
    starts = _starts(prob, prob.rows_held, steps, max_starts)
    nr = len(prob.refit)
    before = heldout_summary(prob, {}, np.zeros(nr), starts, steps)
    base_fit = fit(prob, ())
    base = heldout_summary(prob, {}, base_fit.rho, starts, steps)

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

    # greedy: add the best while it pays for itself
    selected: list[str] = []
    current, current_h = base_fit, base
    steps_log = []
    unexplained = None      # the best candidate when it paid for itself only from an edge of its range
    below_limit = None      # the best candidate when it paid for itself with a value below its detection limit
    not_told_apart = None   # under detection limits: the first effect when a rival's evidence is as good
    while len(selected) < max_effects:
        pool = [c for c in candidates if C.FAMILY[c] not in {C.FAMILY[n] for n in selected}]
        if not pool:
            break
        trials = []
        for name in pool:
            if not selected:
                f = fits[name]
            else:
                f = fit(prob, current.names + C.keys(name, prob.layout), start={**current.values, **fits[name].values},
                        start_rho=current.rho)
            ev = evaluate(f, current_h, len(pool), len(C.keys(name, prob.layout)))
            trials.append((ev["delta_bic"], name, f, ev))
        trials.sort(key=lambda t: t[0])
        dbic, name, f, ev = trials[0]
        # an estimate on an edge of its range is a bound, not an estimate: the effect stands in for a mismatch
        # the library does not hold, so it is never the verdict (and the greedy step stops there)
        main_value = C.summary(name, f.values, f.std, prob.layout)[0]   # a profile: its peak
        edge = bool(dbic < -margin) and at_bound(name, main_value, prob.ctx)
        size = C.magnitude(name, main_value, prob.layout)      # a channel candidate: the angle it reads
        weak = bool(dbic < -margin) and not edge and _below_limit(name, size, limits)
        # under detection limits a claim must also be a choice the data make: a first effect whose runner-up of
        # another family is within AMBIGUITY_DBIC of it is reported, not claimed (on the four calibration sweeps at
        # their margin every such first effect lay below its threshold, and 4 of the 7 were the wrong one)
        tie = bool(limits and not selected and dbic < -margin and not edge and not weak and runner_up
                   and first[0]["effect"] == name and runner_up["evidence_difference"] < AMBIGUITY_DBIC)
        steps_log.append({"added": name if dbic < -margin and not edge and not weak and not tie else None,
                          "best_candidate": name, "delta_bic": dbic, "at_bound": edge, "below_limit": weak,
                          "not_told_apart": tie, "after": selected + [name]})
        if edge:
            unexplained = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic}
            break
        if weak:
            below_limit = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic,
                           "limit": _limit_of(name, limits)[1],
                           **({"magnitude": size} if name in C.ROLL_OF else {})}
            break
        if tie:
            not_told_apart = {"effect": name, "params": {C.MAIN_PARAM[name]: main_value}, "delta_bic": dbic,
                              "rival": runner_up["effect"], "rival_params": runner_up["params"],
                              "rival_delta_bic": runner_up["delta_bic"],
                              "evidence_difference": runner_up["evidence_difference"]}
            break
        if not dbic < -margin:
            break
        selected.append(name)
        current, current_h = f, ev["heldout"]

    # the noise floor: from the residuals of the best model evaluated (closest to pure sensor noise)
    best_res = min([current_h["res"]] + [c["_res"] for c in first], key=lambda r: _norm_mse(prob, _rms(r)))
    floor = _noise_floor(prob, best_res)
    # the no-gap gate: the refitted nominal's held-out error against the noise floor (both normalised MSE)
    e_floor = float(np.mean(floor / prob.scale ** 2))
    ratio = _norm_mse(prob, base["rmse"]) / e_floor if e_floor > 0 else math.inf
    gated = gate is not None and bool(selected) and ratio <= gate
    gate_info = {"ratio": ratio, "threshold": gate, "gated": gated, "selected_without_gate": list(selected),
                 "min_evidence": margin, "detection_limits": limits,
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
        "selected": selected,
        "verdict": (f"none: the nominal's held-out error is within the noise floor ({ratio:.3g}x <= gate {gate:g}x); "
                    f"without the gate: {', '.join(gate_info['selected_without_gate'])}" if gated else
                    _unexplained_verdict(unexplained) if not selected and unexplained else
                    "none: " + _below_limit_verdict(below_limit) if not selected and below_limit else
                    "none: " + _not_told_apart_verdict(not_told_apart) if not_told_apart else
                    "none: no candidate effect pays for its parameters on the held-out data"
                    + (f" by the evidence margin (dBIC < -{margin:g})" if margin else "") if not selected else
                    "; ".join(f"{e['effect']} {next(iter(e['params']))} = {next(iter(e['params'].values())):.4g} "
                              f"+- {next(iter(e['uncertainty'].values())):.2g} {e['unit']}"
                              + (" (AT THE EDGE of its range: a stand-in for another mismatch, not an estimate)"
                                 if e["at_bound"] else "") for e in final["effects"])
                    + (f" (or {rival['effect']}: its held-out evidence is within {rival['evidence_difference']:.1f} "
                       f"dBIC of the first effect's, < {AMBIGUITY_DBIC:g}: not told apart)" if rival else "")
                    + (f"; the rest is not explained by the effect library ({_unexplained_verdict(unexplained)[5:]})"
                       if selected and unexplained else "")
                    + (f"; then {_below_limit_verdict(below_limit)}" if selected and below_limit else "")),
        "unexplained": unexplained,
        "below_limit": below_limit,
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
                    "nominal_effects": prob.nominal_effects,
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


# the key of detection limits for every effect without an entry of its own ({"*": None}: only the effects the
# calibration measured a threshold for are ever claimed)
ANY_OTHER = "*"


def _limit_of(name: str, limits: dict | None):
    """(has a limit, the limit or None: never claimed) of an effect's family."""
    family = C.FAMILY.get(name, name)
    if not limits or (family not in limits and ANY_OTHER not in limits):
        return False, None
    return True, limits[family] if family in limits else limits[ANY_OTHER]


def _below_limit(name: str, value: float, limits: dict | None) -> bool:
    """An effect's size (a profile's peak, a channel's angle: candidates.magnitude) under its detection limit;
    never for an effect without one."""
    has, limit = _limit_of(name, limits)
    return has and (limit is None or abs(value) < limit)


def _below_limit_verdict(b: dict) -> str:
    (pn, pv), = b["params"].items()
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


def public(diag: dict) -> dict:
    return {k: v for k, v in diag.items() if not k.startswith("_")}


# ----------------------------------------------------------------------------------------------- report

def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.3g}" if 1e-2 <= abs(x) < 1e4 or x == 0 else f"{x:.3e}"


def _roll_line(d: dict) -> str:
    r = d["data"].get("roll_channel")
    if r is None:
        return ("Roll channel: none logged (bank only from the fitted profiles)."
                + _pitch_line(d["data"].get("pitch_channel")))
    p = d["data"].get("pitch_channel")
    return (f"Roll channel: {'plausible, bank_from_roll tried' if r['plausible'] else 'NOT plausible, not used'} "
            f"({r['reason']})." + _pitch_line(p))


def _pitch_line(p: dict | None) -> str:
    if p is None:
        return ""
    return (f" Pitch channel: {'plausible, grade_from_pitch tried' if p['plausible'] else 'NOT plausible, not used'} "
            f"({p['reason']}).")


def _calibration_lines(d: dict) -> list[str]:
    c = d.get("calibration")
    if not c:
        return []
    limits = ", ".join(f"{e} {_fmt(v)}" for e, v in c["detection_limits"].items() if v is not None and e != ANY_OTHER)
    return [f"Calibrated by {', '.join(c['runs'])} ({c['duration']:g} s logs): evidence margin dBIC < "
            f"-{c['min_evidence']:.3g}; decision levels {limits or 'none'}; every other effect reported, never "
            "claimed.", ""]


def markdown(d: dict, figures: list[str]) -> str:
    m = d["model"]
    h = m["heldout"]
    lines = [f"# Diagnosis of {d['data']['source']}", "",
             f"Nominal: {d['nominal']['source']} ({d['nominal']['method']}); {d['data']['rows']} rows; "
             f"fit on {d['split']['fit_rows']}, held out {d['split']['heldout_rows']} (from t = "
             f"{d['split']['heldout_from_time']:.1f} s).", "",
             f"**Selected: {', '.join(d['selected']) if d['selected'] else 'none'}** — {d['verdict']}", "",
             *_calibration_lines(d), _roll_line(d), "",
             "## How far (held-out)", "",
             "| | vx (m/s) | vy (m/s) | omega (rad/s) | ADE (m) | FDE (m) |", "|---|---|---|---|---|---|",
             "| nominal | " + " | ".join(_fmt(h["rmse_before"][c]) for c in CHANNELS)
             + f" | {_fmt(h['ade_before'])} | {_fmt(h['fde_before'])} |",
             "| with selected effects | " + " | ".join(_fmt(h["rmse_after"][c]) for c in CHANNELS)
             + f" | {_fmt(h['ade_after'])} | {_fmt(h['fde_after'])} |", "",
             f"Gap closed: {_fmt(m['gap_closed_pct'])} % of the held-out error above the estimated noise floor, "
             f"which is {_fmt(m['error_reduction_pct'])} % of the whole normalised one-step error (the refitted "
             f"nominal's error is {d['gate']['ratio']:.3g}x the noise floor"
             + (f"; no-gap gate at {d['gate']['threshold']:g}x: {'closed' if d['gate']['gated'] else 'open'}"
                if d['gate']['threshold'] is not None else "") + ").", "",
             "## Where (nominal model, whole log)", ""]
    w = d["where"]
    lines += ["| nominal | vx (m/s) | vy (m/s) | omega (rad/s) |", "|---|---|---|---|"]
    for label, key in (("one-step RMSE", "one_step_rmse"), ("noise floor (est.)", "noise_floor_rmse"),
                       (f"multi-step RMSE ({w['horizon_steps']} steps)", "multi_step_rmse"),
                       ("multi-step RMSE at the horizon", "multi_step_final_rmse")):
        if w.get(key):
            lines.append(f"| {label} | " + " | ".join(_fmt(w[key][c]) for c in CHANNELS) + " |")
    lines += [""] + [f"- {s}" for s in w["summary"]]
    lines += ["", "## Which (each candidate alone against the refitted nominal, best first)", "",
              "| effect | estimate | +- | dBIC | gap closed % | vx | vy | omega | ADE |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in d["candidates"]:
        (pn, pv), = c["params"].items()
        hh = c["heldout"]
        edge = " (at bound)" if c["at_bound"] else ""
        lines.append(f"| {c['effect']}{' **' if c['significant'] else ''} | {pn} = {_fmt(pv)} {c['unit']}{edge} | "
                     f"{_fmt(c['uncertainty'][pn])} | {c['delta_bic']:.1f} | {_fmt(c['gap_closed_pct'])} | "
                     + " | ".join(_fmt(hh["rmse_after"][ch]) for ch in CHANNELS) + f" | {_fmt(hh['ade_after'])} |")
    lines += ["", "dBIC < 0 (marked **): the effect pays for its parameter on the held-out part. Tyre peak forces "
              f"({', '.join(d['nominal']['refit_under_every_hypothesis']) or 'none'}) are refitted under every "
              "hypothesis. \"at bound\": the estimate sits on an edge of its search range, so the effect is "
              "standing in for some other mismatch and its value is a bound, not an estimate.", ""]
    lines += [f"![{Path(f).stem}]({Path(f).name})" for f in figures]
    return "\n".join(lines) + "\n"


def plots(d: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = d["_series"]
    w = s["where"]
    paths = []
    facs = d["where"]["factors"]
    n = len(facs)
    fig, axes = plt.subplots((n + 1) // 2, 2, figsize=(12, 2.6 * ((n + 1) // 2)))
    for ax, (name, bins) in zip(axes.ravel(), facs.items()):
        x = np.arange(len(bins))
        ax.bar(x - 0.2, [b["samples_share"] for b in bins], 0.4, label="samples", color="0.7")
        ax.bar(x + 0.2, [b["error_share"] for b in bins], 0.4, label="one-step error", color="C3")
        ax.set_xticks(x, [b["bin"].split(" (")[0] for b in bins], rotation=20, fontsize=7)
        ax.set_title(name.replace("_", " "), fontsize=9)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle("Where: share of samples and of the nominal model's one-step error")
    fig.tight_layout()
    paths.append(out / "where.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    for i, (ax, c) in enumerate(zip(axes, CHANNELS)):
        ax.plot(w["time"], w["res"][:, i], lw=0.6, color="0.5", label="nominal (whole log)")
        ax.plot(s["held_time"], s["res_after"][:, i], lw=0.6, color="C0", label="with selected effects (held out)")
        ax.set_ylabel(f"{c} residual ({UNITS[c]})")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("One-step residuals")
    fig.tight_layout()
    paths.append(out / "residuals.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    cands = d["candidates"]
    y = np.arange(len(cands))
    ax1.barh(y, [max(min(-c["delta_bic"], 1e6), -1e6) for c in cands],
             color=["C2" if c["significant"] else "0.6" for c in cands])
    ax1.set_yticks(y, [c["effect"] for c in cands])
    ax1.invert_yaxis()
    ax1.set_xscale("symlog")
    ax1.set_xlabel("-dBIC on held-out data (> 0: pays for itself)")
    ax1.set_title("Which effect")
    sc = ax2.scatter(w["x"], w["y"], c=np.log10(w["err"] + 1e-12), s=3, cmap="magma")
    ax2.set_aspect("equal")
    ax2.set_title("Where on the track: log10 normalised one-step error")
    fig.colorbar(sc, ax=ax2)
    fig.tight_layout()
    paths.append(out / "which.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return [str(p) for p in paths]


def write_report(d: dict, out: str | Path, with_plots: bool = True) -> dict[str, str]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = plots(d, out) if with_plots else []
    (out / "diagnosis.json").write_text(json.dumps(public(d), indent=2, default=float))
    (out / "diagnosis.md").write_text(markdown(d, figs))
    return {"json": str(out / "diagnosis.json"), "markdown": str(out / "diagnosis.md"), "figures": figs}


# ----------------------------------------------------------------------------------------------- CLI

def _coefficients_arg(text: str | None):
    if not text:
        return None
    p = Path(text)
    raw = json.loads(p.read_text()) if p.is_file() else json.loads(text)
    if isinstance(raw, dict):
        raw = raw.get("coefficients", raw)
        return np.array([float(raw[k]) for k in COEFF_NAMES])
    return np.array(raw, float)


def load_inputs(args):
    from ddyn.data.importers import load_any

    if args.model:
        from ddyn.learn import checkpoint

        # the checkpoint's embedded vehicle file, not its name: the file may live outside train/vehicles
        ds = load_any(args.data, vehicle=checkpoint.vehicle_of(checkpoint.read(args.model)))
        nominal = nominal_from_checkpoint(args.model, ds)
    else:
        vehicle = load_vehicle(args.vehicle)
        ds = load_any(args.data, vehicle=vehicle)   # the loaded file, not a second look-up by name
        try:
            coeffs = _coefficients_arg(args.coefficients)
        except (json.JSONDecodeError, KeyError, ValueError, TypeError) as e:
            raise DdynError(f"--coefficients: {e}") from None
        nominal = nominal_from_vehicle(vehicle, ds, coeffs, args.method, args.substeps)
    return ds, nominal


def _track(name: str | None, ds: Dataset):
    from ddyn.model.track_files import open_track
    from ddyn.model.tracks import TRACK_NAMES, load_track

    if name:  # asked for on the command line: a name or a user's files, errors shown
        return open_track(name)
    name = ds.metadata.get("track")
    if name == "oval":   # the banked oval (ddyn.model.track_oval): made, not read
        return open_track(name)
    if name in (None, "", "none") or name not in TRACK_NAMES:
        return None
    try:
        return load_track(name)
    except DdynError:
        return None


def fit_spec_arg(text: str) -> str:
    """argparse type of --fit: the spec as given, checked (parse_fit_spec)."""
    import argparse

    try:
        parse_fit_spec(text)
    except DdynError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _hold_arg(text: str):
    if text != "estimate":
        raise argparse.ArgumentTypeError("--hold takes no value or 'estimate'")
    return text


def nominal_effects_arg(text: str | None) -> dict:
    """--nominal-effects "power_limit=92000,steer_lag=0.01": {effect: main parameter}."""
    return {e.effect: float(e.value) for e in E.parse_effects(text)} if text else {}


def detection_limits_arg(text: str | None) -> dict | None:
    """--detection-limits: JSON {effect: limit or null} inline or in a file, or the results.json of a `ddyn study
    gap --detection-limits-from` run (its settings' `detection_limits`: calibration runs' measured thresholds, or
    their decision levels when run with --decision-limits)."""
    if not text:
        return None
    if text.strip().startswith("{"):
        limits = json.loads(text)
    else:
        path = Path(text)
        if not path.is_file():
            raise DdynError(f"--detection-limits: {text} is neither JSON nor a file")
        limits = json.loads(path.read_text())
        # a `ddyn study gap --detection-limits-from` run's results.json: the limits its settings record
        if isinstance(limits.get("settings"), dict):
            if not limits["settings"].get("detection_limits"):
                raise DdynError(f"--detection-limits: {text} is a run recorded without detection limits")
            limits = limits["settings"]["detection_limits"]
    bad = [e for e in limits if e not in C.ALL and e not in C.FAMILY.values() and e != ANY_OTHER]
    if bad:
        raise DdynError(f"--detection-limits: unknown effect(s) {', '.join(bad)}")
    return {e: None if v is None else float(v) for e, v in limits.items()}


# how far a log's length may be from the calibration's: a dBIC sums over the held-out rows, so a margin measured
# on 60 s logs does not hold on 90 s ones
CALIBRATION_LENGTH_TOLERANCE = 0.1


def calibrated_settings(args, ds) -> dict:
    """--calibration RUNS: the diagnosis the calibration runs scored (gap_independent.calibrated_diagnosis), put
    into args where the user gave nothing; a setting given otherwise, --detection-limits, --dbw, --candidates or
    a log of another length than the calibration's is refused (the margin and the limits hold only as calibrated)."""
    if args.detection_limits or args.dbw or args.candidates:
        raise DdynError("--calibration sets the margin, the limits and the candidates: not with --detection-limits, "
                        "--dbw or --candidates")
    cal = calibrated_diagnosis(args.calibration)
    # every effect the calibration did not sweep is reported, never claimed; its recorded evidence or the default
    cal |= {"detection_limits": cal["detection_limits"] | {ANY_OTHER: None},
            "evidence": cal["evidence"] or DEFAULT_EVIDENCE}
    length = len(ds) * ds.sample_time
    if abs(length - cal["duration"]) > CALIBRATION_LENGTH_TOLERANCE * cal["duration"]:
        raise DdynError(f"--calibration: measured on {cal['duration']:g} s logs, this log is {length:.0f} s; "
                        f"calibrate on logs of its length (`ddyn study gap --case-set sweep --duration "
                        f"{length:.0f}`) or cut the log")
    def off(gate):      # a run's gate None and diagnose's --gate 0 both mean no gate
        return "off" if gate is None or gate <= 0 else gate

    given = {"hold": (args.hold, False), "fit": (args.fit, None), "mass_inertia": (args.mass_inertia, False),
             "steer_servo": (args.steer_servo, 0.0), "evidence": (args.evidence, None),
             "nominal_effects": (nominal_effects_arg(args.nominal_effects) or None, None),
             "min_evidence": (args.min_evidence, None),
             "gate": (None if args.gate is None else off(args.gate), None)}
    wanted = cal | {"gate": off(cal["gate"]), "nominal_effects": cal["nominal_effects"] or None}
    clash = [k for k, (v, default) in given.items() if v != default and v != wanted[k]]
    if clash:
        raise DdynError(f"--calibration: {', '.join('--' + k.replace('_', '-') for k in clash)} differ from the "
                        "calibration's (leave them out: the calibration sets them)")
    args.hold, args.fit, args.mass_inertia = cal["hold"], cal["fit"], cal["mass_inertia"]
    args.steer_servo, args.evidence, args.min_evidence = cal["steer_servo"], cal["evidence"], cal["min_evidence"]
    args.nominal_effects = ",".join(f"{k}={v!r}" for k, v in cal["nominal_effects"].items()) or None
    args.gate = 0.0 if cal["gate"] is None else cal["gate"]
    return cal


def _run(args) -> int:
    ds, nominal = load_inputs(args)
    # the default library is the eleven one-parameter effects the benchmarks calibrated and scored;
    # "extended" adds the profiles and the drivetrain (opt-in: on the independent plant power_limit finds the
    # plant's own 92 kW limit on every log, docs/gap_independent.md)
    if not args.candidates:
        cands = E.EFFECT_NAMES
    elif args.candidates.strip() == "extended":
        cands = C.ALL
    else:
        cands = tuple(c.strip() for c in args.candidates.split(","))
    bad = [c for c in cands if c not in C.ALL]
    if bad:
        raise DdynError(f"unknown candidate effect(s) {', '.join(bad)}; expected {', '.join(C.ALL)}")
    refit = () if args.refit in ("", "none") else tuple(x.strip() for x in args.refit.split(","))
    bad = [c for c in refit if c not in COEFF_NAMES]
    if bad:
        raise DdynError(f"--refit: unknown coefficient(s) {', '.join(bad)}")
    calibration = None
    if args.calibration:    # the settings, margin and decision levels of calibration runs (calibrated_settings)
        calibration = calibrated_settings(args, ds)
        cands = tuple(cands) + tuple(c for c in calibration["channel_candidates"] if c not in cands)
    gate = "default" if args.gate is None else (None if args.gate <= 0 else args.gate)
    if args.dbw:        # the preset fills what was not given explicitly
        args.hold = args.hold or True
        args.fit = args.fit or DBW_PRESET["fit"]
        args.min_evidence = DBW_PRESET["min_evidence"] if args.min_evidence is None else args.min_evidence
    d = diagnose(ds, nominal, args.fit_fraction, cands, refit, args.max_effects, _track(args.track, ds), gate=gate,
                 hold=args.hold, min_evidence=args.min_evidence, fit_mode=args.fit, mass_inertia=args.mass_inertia,
                 steer_servo=args.steer_servo, nominal_effects=nominal_effects_arg(args.nominal_effects),
                 evidence=args.evidence, detection_limits=(calibration["detection_limits"] if calibration else
                                                           detection_limits_arg(args.detection_limits)))
    if calibration:
        d["calibration"] = {k: calibration[k] for k in ("runs", "duration", "min_evidence", "detection_limits")}
    paths = write_report(d, args.out, not args.no_plots)
    if calibration:
        print(_calibration_lines(d)[0])
    print(f"selected: {', '.join(d['selected']) if d['selected'] else 'none'} ({d['verdict']})")
    h = d["model"]["heldout"]
    print("held-out one-step RMSE " + ", ".join(f"{c} {h['rmse_before'][c]:.3e} -> {h['rmse_after'][c]:.3e}"
                                                for c in CHANNELS)
          + f"; ADE {h['ade_before']:.3e} -> {h['ade_after']:.3e} m; gap closed {_fmt(d['model']['gap_closed_pct'])} % "
          f"of the error above the noise floor, {_fmt(d['model']['error_reduction_pct'])} % of the whole error "
          f"(nominal {d['gate']['ratio']:.3g}x the noise floor)")
    for s in d["where"]["summary"]:
        print(f"  where: {s}")
    print(f"wrote {paths['json']}, {paths['markdown']} and {len(paths['figures'])} figures in {d['seconds']:.1f} s")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("diagnose", help="where a model's error lies, which unmodelled effect causes it, "
                                               "how far it shrinks", description=__doc__.splitlines()[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--vehicle", help="vehicle name or JSON file: its true_coefficients are the nominal model")
    src.add_argument("--model", help="a DDM/DPM checkpoint: its per-window coefficients are the nominal model")
    p.add_argument("--data", required=True, help="log in any supported format (canonical, DDM .npz, RACECAR csv)")
    p.add_argument("--out", required=True, help="output directory (diagnosis.json, diagnosis.md, PNGs)")
    p.add_argument("--coefficients", help="with --vehicle: nominal coefficients, JSON {name: value} or list, "
                                          "or a file holding it")
    p.add_argument("--method", choices=("euler", "rk4"), default=None,
                   help="discretisation (default: the log's, else euler)")
    p.add_argument("--substeps", type=int, default=None)
    p.add_argument("--track", default=None, help="track for the by-position breakdown (default: the log's)")
    p.add_argument("--fit-fraction", type=float, default=DEFAULT_FIT_FRACTION,
                   help="share of the log (by time) to fit on; the rest is held out (default 0.6)")
    p.add_argument("--candidates", default=None,
                   help="comma-separated effects to try; 'extended': the eleven effects plus the bank/grade "
                        "profiles, bank from roll, grade from pitch and the drivetrain (default: the eleven effects)")
    p.add_argument("--refit", default=",".join(DEFAULT_REFIT),
                   help="nominal coefficients refitted (as factors) under every hypothesis (default Df,Dr; 'none')")
    p.add_argument("--max-effects", type=int, default=3)
    p.add_argument("--hold", nargs="?", const=True, default=False, type=_hold_arg, metavar="estimate",
                   help="the log's throttle and steering were held between samples (a drive-by-wire unit): the "
                        "nominal gets half a sample of delay on both, delay estimates are on top of it; "
                        "'--hold estimate': the hold delay fitted from the log instead (at most half a sample; "
                        "on the independent plant it does not resolve the DBW rate: docs/gap_independent.md)")
    p.add_argument("--dbw", action="store_true",
                   help="a drive-by-wire log: --hold --fit {fit} --min-evidence {min_evidence:g} (calibrated on the "
                        "independent plant; explicit --fit/--min-evidence win)".format(**DBW_PRESET))
    p.add_argument("--detection-limits", default=None, metavar="JSON|FILE",
                   help="a limit of detection per effect: {\"steer_lag\": 0.15, \"downforce\": null, ...} "
                        "(\"*\": every effect without an entry) inline or "
                        "in a file, or a `ddyn study gap --detection-limits-from` run's results.json (its "
                        "settings.detection_limits: the calibration runs' thresholds, or their decision levels "
                        "with --decision-limits); an effect found below its "
                        "limit (null: always), or not told apart from a rival, is reported, not selected")
    p.add_argument("--calibration", default=None, metavar="RESULTS_JSON[,...]",
                   help="diagnose as these calibration runs scored it (`ddyn study gap --case-set sweep ... "
                        "--min-evidence 0` on logs of this log's length): their settings (hold, fit, servo, nominal "
                        "effects, ...), their pooled evidence margin and Currie's decision levels below their "
                        "detection thresholds; effects they did not calibrate are reported, never claimed")
    p.add_argument("--mass-inertia", action="store_true",
                   help="the mass_offset candidate scales the yaw inertia with the mass (with Df, Dr refitted it "
                        "then changes only the longitudinal response, as a heavier car with load-proportional "
                        "tyre forces does; not in --dbw: on the independent plant it then reads the nominal's "
                        "missing power limit as a mass, docs/gap_independent.md)")
    p.add_argument("--steer-servo", type=float, default=0.0, metavar="TAU",
                   help="a known steering servo in the nominal: first-order lag of TAU s (e.g. from the DBW data "
                        "sheet); steer_lag then estimates the servo's time constant, steer_delay what comes on top")
    p.add_argument("--nominal-effects", default=None, metavar="SPEC",
                   help="effects the nominal itself has, e.g. a data sheet's 'power_limit=92000' (main parameters, "
                        "key=value); a hypothesis of the same effect replaces the value")
    p.add_argument("--fit", type=fit_spec_arg, default=None, metavar="|".join(FIT_MODES) + "[:EFFECTS]",
                   help=f"what the fit compares (default {DEFAULT_FIT}): one-step predictions from the logged states, "
                        "from smoothed states (errors in variables), or output-error rollouts of "
                        f"{OE_STEPS} steps, or mixed (output error, a steering delay's value fitted one-step; "
                        "mixed:EFFECT,... those effects' values, e.g. mixed:downforce); "
                        "held-out scores are one-step in every mode unless --evidence says otherwise")
    p.add_argument("--min-evidence", type=float, default=None, metavar="DBIC",
                   help=f"add an effect only when its dBIC < -DBIC (default {MIN_EVIDENCE:g}: the plain rule)")
    p.add_argument("--evidence", default=None, metavar="one-step|multistep[:N]|endpoint[:N]",
                   help="the held-out evidence (default one-step): 'multistep:N' scores N-step open-loop rollouts "
                        f"from non-overlapping held-out windows (default N {MULTISTEP_DEFAULT_STEPS}; an experiment "
                        "for slow longitudinal effects, not calibrated: docs/gap_independent.md); 'endpoint:N' the "
                        "same windows, only each window's last step scored (one sample per window, the penalty "
                        "counts windows)")
    p.add_argument("--gate", type=float, default=None, metavar="RATIO",
                   help="no-gap gate: select nothing when the nominal's held-out error is at most RATIO times the "
                        f"noise floor (default {NO_GAP_GATE}; 0: off)")
    p.add_argument("--no-plots", action="store_true")
    p.set_defaults(func=_run)
