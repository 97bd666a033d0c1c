"""Held-out scores: one-step and rollout errors, the measurement-noise floor, and the share of the gap closed."""
from __future__ import annotations

import numpy as np

from ddyn.gap.problem import CHANNELS, Problem
from ddyn.model import effects as E


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
