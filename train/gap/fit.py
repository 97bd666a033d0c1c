"""The fit: an effect hypothesis's main parameters and the nominal's refit factors, least squares on the fit rows
(grid scan of the new parameter, then scipy's trust-region reflective solver), with a Gauss-Newton uncertainty
scaled by the residuals' long-run variance factor (one-step residuals are not independent)."""
from __future__ import annotations

import time as _time
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ddyn.gap import candidates as C
from ddyn.gap.problem import GRID_UNITS, Problem, _bounds, _param_unit


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
