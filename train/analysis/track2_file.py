"""How each array of DYN-PP-ETHZMobil.npz (the paper's Track-2 file) was produced, as far as the
arrays themselves tell (shared/data/README.md gives the layout, not the recipe).

Each check is a hypothesis about one array, tested against the file:

* inputs are the rates of states[6:8]: states[6:, k+1] = states[6:, k] + Ts inputs[:, k];
* dstates rows 6-7 are the plain cumulative sum of inputs (no Ts): the rates used as increments;
* dstates rows 3-5 against states rows 3-5;
* states rows 3-5 as a one-step chain of the single-track model with the file's own throttle and
  steering, for the vehicle file's coefficient sets and for the best least-squares fit of all 17
  coefficients (a chain of the model has per-step errors at rounding level, as DYN-PP-ETHZ's dstates);
* how much of the vx change the drivetrain's form explains with the throttle at any lag of 0-15 steps
  (R^2 of the per-step vx change on T, T vx, 1, vx^2, vy omega).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ddyn.errors import DdynError
from ddyn.model import backends
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES
from ddyn.paths import shared_data_dir

CHANNELS = ("vx", "vy", "omega")


def _chain_errors(states: np.ndarray, rates: np.ndarray, c: np.ndarray, v, method: str) -> np.ndarray:
    """|one model step from states[:, k] with rates[:, k] - states[:, k+1]| for vx, vy, omega: (N-1, 3)."""
    substeps = v.rk4_substeps if method == "rk4" else 1
    nxt = backends.step_numpy(states[:, :-1].T, rates.T, c, v.known, v.sample_time, method, substeps)
    return np.abs(nxt - states[:, 1:].T)[:, 3:6]


def _summary(err: np.ndarray) -> dict:
    return {"median": dict(zip(CHANNELS, np.median(err, axis=0).tolist())),
            "max": dict(zip(CHANNELS, err.max(axis=0).tolist()))}


def best_fit(states: np.ndarray, rates: np.ndarray, v, method: str = "rk4", start: str = "true",
             max_evaluations: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """All 17 coefficients fitted by least squares to the one-step chain (vx, vy in 0.01 m/s and
    omega in 0.1 rad/s units); returns the coefficients and their per-step errors."""
    c0 = v.coefficient_vector(start)
    scale = np.array([0.01, 0.01, 0.1])

    def residual(c):
        substeps = v.rk4_substeps if method == "rk4" else 1
        nxt = backends.step_numpy(states[:, :-1].T, rates.T, c, v.known, v.sample_time, method, substeps)
        r = (nxt - states[:, 1:].T)[:, 3:6] / scale
        return np.nan_to_num(r, nan=1e6, posinf=1e6, neginf=-1e6).ravel()

    fit = least_squares(residual, c0, x_scale=np.maximum(np.abs(c0), 1e-3), max_nfev=max_evaluations)
    return fit.x, _chain_errors(states, rates, fit.x, v, method)


def drivetrain_r2(states: np.ndarray, ts: float, lags: range = range(16)) -> dict[int, float]:
    """R^2 of the per-step vx change regressed on the drivetrain's terms with the throttle `lag` steps later."""
    vx, vy, om, thr = states[3], states[4], states[5], states[6]
    dvx = np.diff(vx) / ts
    k = np.arange(0, len(dvx) - max(lags))
    out = {}
    for lag in lags:
        t = thr[k + lag]
        a = np.column_stack([t, t * vx[k], np.ones_like(t), vx[k] ** 2, vy[k] * om[k]])
        coef, *_ = np.linalg.lstsq(a, dvx[k], rcond=None)
        r = dvx[k] - a @ coef
        out[lag] = float(1.0 - r.var() / dvx[k].var())
    return out


def track2_provenance(path: Path | None = None, fit: bool = True) -> dict:
    path = path or shared_data_dir() / "reference" / "DYN-PP-ETHZMobil.npz"
    if not path.is_file():
        raise DdynError(f"the paper's Track-2 file not found: {path}")
    v = vehicle_mod.load("orca_1_43")
    with np.load(path) as npz:
        s, d, u = npz["states"], npz["dstates"], npz["inputs"]
    ts = v.sample_time
    report = {
        "inputs_integrate_to_states_6_7": float(np.abs(s[6:, 1:] - s[6:, :-1] - ts * u).max()),
        "dstates_6_7_minus_cumsum_of_inputs": float(np.abs(d[6:, 1:] - np.cumsum(u, axis=1)).max()),
        "dstates_6_7_max": float(np.abs(d[6:]).max()),
        "dstates_3_5_minus_states_3_5_max": dict(zip(CHANNELS, np.abs(d[3:6] - s[3:6]).max(axis=1).tolist())),
        "states_throttle_max": float(s[6].max()),
        "chain": {},
    }
    for coeff_set in ("true", "reference_dataset"):
        for method in ("euler", "rk4"):
            report["chain"][f"{coeff_set}/{method}"] = _summary(_chain_errors(s, u, v.coefficient_vector(coeff_set), v, method))
    if fit:
        c, err = best_fit(s, u, v)
        report["chain"]["least_squares_fit/rk4"] = _summary(err)
        report["least_squares_fit"] = dict(zip(COEFF_NAMES, c.tolist()))
    r2 = drivetrain_r2(s, ts)
    best = max(r2, key=r2.get)
    report["drivetrain_r2"] = {"best_lag_steps": best, "best": r2[best], "lag_0": r2[0]}
    return report


def format_report(r: dict) -> str:
    lines = ["DYN-PP-ETHZMobil.npz (the paper's Track-2 file): how each array was produced",
             f"  inputs are the rates of states rows 6-7 (largest departure {r['inputs_integrate_to_states_6_7']:.1e})",
             f"  dstates rows 6-7 = cumulative sum of inputs without Ts (largest departure "
             f"{r['dstates_6_7_minus_cumsum_of_inputs']:.1e}; they reach {r['dstates_6_7_max']:.2f}): not a throttle",
             "  dstates rows 3-5 depart from states by up to " + ", ".join(
                 f"{k} {x:.1f}" for k, x in r["dstates_3_5_minus_states_3_5_max"].items()),
             "  states rows 3-5 as a one-step chain of the single-track model (per-step |error|, median / max):"]
    for name, e in r["chain"].items():
        lines.append(f"    {name:28s} " + "  ".join(f"{k} {e['median'][k]:.3g} / {e['max'][k]:.3g}" for k in CHANNELS))
    if "least_squares_fit" in r:
        f = r["least_squares_fit"]
        lines.append(f"    (fitted Cm1 {f['Cm1']:.3g}, Cm2 {f['Cm2']:.3g}, Iz {f['Iz']:.3g}: not a physical drivetrain)")
    d = r["drivetrain_r2"]
    lines.append(f"  the drivetrain's terms explain R^2 = {d['lag_0']:.2f} of the vx change (best {d['best']:.2f} "
                 f"with the throttle {d['best_lag_steps']} steps later); throttle in states reaches "
                 f"{r['states_throttle_max']:.2f} (car limit 1)")
    return "\n".join(lines)
