"""Where the nominal model is wrong: its error by channel, operating region, track position and time."""
from __future__ import annotations

import numpy as np

from ddyn.gap.heldout import _chan, _noise_floor, rollout_errors
from ddyn.gap.problem import CHANNELS, UNITS, Problem, _starts


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
