"""The fitting problem: the nominal model on a log, its one-step residuals under a hypothesis of effects, split
into fit and held-out rows (`Problem`), and where the nominal comes from (a vehicle file or a checkpoint)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace as _replace
from pathlib import Path

import numpy as np

from ddyn.data.dataset import Dataset
from ddyn.errors import DdynError
from ddyn.gap import candidates as C
from ddyn.gap import eiv
from ddyn.gap.config import parse_fit_spec
from ddyn.model import effects as E
from ddyn.model.single_track import COEFF_NAMES, N_COEFF
from ddyn.model.vehicle import Vehicle

CHANNELS = ("vx", "vy", "omega")
UNITS = {"vx": "m/s", "vy": "m/s", "omega": "rad/s"}
DEFAULT_REFIT = ("Df", "Dr")
OE_STEPS = 10   # output error: the rollout length each fit row starts (0.4 s at 25 Hz)


@dataclass
class Nominal:
    vehicle: Vehicle
    coeffs: np.ndarray          # (17,) or (N, 17)
    valid: np.ndarray           # (N,) rows whose coefficients are defined
    method: str
    substeps: int
    label: str
    # effects the vehicle file says the car itself carries (Vehicle.effects): a hypothesis of the same effect
    # is what comes on top of them
    effects: dict = field(default_factory=dict)


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
    if vehicle.effects:
        label += " with its effects " + ", ".join(f"{k} {v:g}" for k, v in vehicle.effects.items())
    return Nominal(vehicle, coeffs, np.ones(len(ds), bool), method, substeps, label, dict(vehicle.effects))


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
            # errors in variables (ddyn.gap.eiv): every step starts from a local polynomial estimate of the
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
        self.row_weight = np.ones(3)     # effective rows per held-out row, per channel (set_row_weight)
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
        if self.nominal.effects:    # the car's own (Vehicle.effects): a hypothesis adds to them
            values = {**values, **{k: values.get(k, 0.0) + v for k, v in self.nominal.effects.items()}}
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
        w = self.row_weight if np.ndim(rss) == 1 else 1.0
        return float(-0.5 * n * np.sum(w * np.log(rss / n + self.floor ** 2)))

    def set_row_weight(self, res: np.ndarray) -> None:
        """Count each channel's held-out rows as (1 - r) / (1 + r) independent ones, r the lag-1 autocorrelation
        of `res` (the refitted nominal's held-out one-step residuals, (n, 3)) clipped to [0, MAX_ROW_CORRELATION]:
        the effective sample size of an AR(1) series. Why: the extended BIC counts every row as independent, but
        coloured sensor noise and slow unmodelled drifts make neighbouring rows' errors alike, and a candidate that
        follows the noise's persistence (a mass offset trading vx for a slower yaw response) then gains evidence
        in proportion to the log's length. The fitted values' uncertainty already uses the same long-run variance
        factor. Weights are set once per log, so every hypothesis is scored on the same count."""
        r = np.asarray(res, float)
        out = np.ones(r.shape[1])
        for i in range(r.shape[1]):
            a, b = r[:-1, i], r[1:, i]
            den = math.sqrt(float(np.dot(a - a.mean(), a - a.mean()) * np.dot(b - b.mean(), b - b.mean())))
            rho = float(np.dot(a - a.mean(), b - b.mean())) / den if den > 0 else 0.0
            rho = min(max(rho, 0.0), MAX_ROW_CORRELATION)
            out[i] = (1.0 - rho) / (1.0 + rho)
        self.row_weight = out

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



# the largest lag-1 residual correlation set_row_weight uses: 0.99 keeps at least 1/199 of the rows
MAX_ROW_CORRELATION = 0.99


def _starts(prob: Problem, rows: np.ndarray, steps: int, max_starts: int) -> np.ndarray:
    seg, valid = prob.ds.segment, prob.nominal.valid
    n = len(prob.ds)
    ok = rows[(rows + steps < n)]
    ok = ok[(seg[np.minimum(ok + steps, n - 1)] == seg[ok]) & valid[ok]]
    if len(ok) > max_starts:
        ok = ok[np.linspace(0, len(ok) - 1, max_starts).astype(int)]
    return ok


def track_for(name: str | None, ds: Dataset):
    """The track for the by-position breakdown and the profile candidates: the one named (a name or a user's
    files, errors shown), else the log's own when it is a known track (None when it is not)."""
    from ddyn.model.track_files import open_track
    from ddyn.model.tracks import TRACK_NAMES, load_track

    if name:
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
