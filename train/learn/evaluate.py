"""`ddyn evaluate`: how well a checkpoint predicts a dataset, and what it believes about the car.

Metrics (all on windows that lie inside one segment):
  one-step   RMSE and max |error| of the next vx, vy, omega;
  multi-step ADE and FDE of the position over the vehicle's evaluation horizon
             (300 ms for the 1:43 car, 600 ms full scale): from each window the
             network estimates coefficients once, which are then held constant
             while the model rolls forward with the logged inputs; ADE averages
             the position error over all steps and starts, FDE over the final steps;
  coefficients  mean, std and 5/95 percentiles of each estimate; relative error of
             the mean against the ground truth where it is known (simulated data:
             the plant's coefficients recorded by `ddyn simulate`; the papers' .npz:
             the vehicle file's reference_dataset_coefficients);
  guard saturation  share of estimates within 1 % of the range width of a guard
             bound, per coefficient (DDM): a pinned coefficient is a finding;
  reference  the one-step and multi-step figures of "nothing changes" (constant vx, vy
             and yaw rate; ddyn.learn.reference) on the same windows and starts: what
             a model has to beat to predict anything.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ddyn.data.dataset import Dataset
from ddyn.data.windows import TARGET_NAMES, make_windows, rollout_starts
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.networks import bound_shares, outside_range_shares
from ddyn.learn.reference import constant_motion_errors, format_reference
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.vehicle import Vehicle


def _t(a, dtype):
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _dtype(model) -> torch.dtype:
    return next(model.parameters()).dtype


def predict(model, history, state, inputs, batch: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Next states (n, 8) and coefficients (n, k) for windows, in batches."""
    dtype, preds, coeffs = _dtype(model), [], []
    with torch.no_grad():
        for i in range(0, len(history), batch):
            p, c = model(_t(history[i:i + batch], dtype), _t(state[i:i + batch], dtype),
                         _t(inputs[i:i + batch], dtype))
            preds.append(p.numpy())
            coeffs.append(c.numpy())
    return np.concatenate(preds), np.concatenate(coeffs)


def rollout_errors(model, ds: Dataset, tau: int, steps: int, max_starts: int = 20000) -> dict:
    """ADE and FDE (m) of positions over `steps` steps with coefficients held from each start."""
    k = rollout_starts(ds, tau, steps, max_starts)
    if len(k) == 0:
        return {"ade": float("nan"), "fde": float("nan"), "starts": 0}
    w = make_windows(ds, tau, k)
    dtype = _dtype(model)
    with torch.no_grad():
        c = model.coefficients(_t(w.history, dtype))
        x = _t(ds.states[k], dtype)
        errs = []
        for j in range(steps):
            x = model.step(x, _t(ds.inputs[k + j], dtype), c)
            errs.append(torch.linalg.norm(x[:, :2] - _t(ds.states[k + j + 1, :2], dtype), dim=1).numpy())
    e = np.array(errs)  # (steps, starts)
    return {"ade": float(e.mean()), "fde": float(e[-1].mean()), "starts": int(len(k))}


def ground_truth(ds: Dataset, vehicle: Vehicle) -> tuple[np.ndarray | None, str]:
    """The coefficients that produced ds, where known, and where they come from."""
    plant = ds.metadata.get("plant_coefficients")
    if plant:
        return np.array(json.loads(plant), dtype=float), "plant coefficients recorded by ddyn simulate"
    if (ds.metadata.get("import_format") == "ddm_npz" and ds.metadata.get("layout", "absolute_inputs") ==
            "absolute_inputs" and vehicle.reference_dataset_coefficients):
        # DYN-PP-ETHZ's dstates are the Euler chain of these coefficients (ddyn study fidelity); the
        # input-rates file (DYN-PP-ETHZMobil) is a chain of no known set (ddyn.analysis.track2_file)
        return vehicle.coefficient_vector("reference_dataset"), "vehicle file: reference_dataset_coefficients"
    if ds.metadata.get("import_format") == "ddm_npz":
        return None, "unknown (the Track-2 file is no chain of the model: ddyn study fidelity)"
    return None, "unknown (not simulated data)"


def coefficient_report(coeffs: np.ndarray, names: list[str], truth: np.ndarray | None,
                       ranges: dict | None) -> dict:
    out = {}
    for i, name in enumerate(names):
        c = coeffs[:, i]
        row = {"mean": float(c.mean()), "std": float(c.std()),
               "p05": float(np.percentile(c, 5)), "p95": float(np.percentile(c, 95))}
        if truth is not None and name in COEFF_NAMES:
            t = truth[COEFF_NAMES.index(name)]
            row["true"] = float(t)
            row["rel_error"] = float((c.mean() - t) / abs(t)) if t != 0 else None
        if ranges is not None:
            lower, upper = bound_shares(c, ranges["lo"][i], ranges["hi"][i])
            row["at_lower_bound"], row["at_upper_bound"] = float(lower), float(upper)
        out[name] = row
    return out


def evaluate(model, ckpt: dict, ds: Dataset) -> dict:
    v = checkpoint.vehicle_of(ckpt)
    if ds.vehicle and ds.vehicle != v.name:
        raise DdynError(f"dataset is for vehicle {ds.vehicle!r} but the checkpoint was trained for {v.name!r}")
    if abs(ds.sample_time - v.sample_time) > 1e-6 * v.sample_time:
        raise DdynError(f"dataset sample time {ds.sample_time} s differs from the model's {v.sample_time} s")
    tau = ckpt["config"]["tau"]
    w = make_windows(ds, tau)
    pred, coeffs = predict(model, w.history, w.state, w.inputs)
    err = pred[:, 3:6] - w.target
    steps = max(1, int(round(v.evaluation_horizon / v.sample_time)))
    truth, truth_source = ground_truth(ds, v)
    names = ckpt["architecture"]["outputs"]
    return {
        "samples": len(w),
        "rmse": dict(zip(TARGET_NAMES, np.sqrt((err ** 2).mean(axis=0)).tolist())),
        "max_error": dict(zip(TARGET_NAMES, np.abs(err).max(axis=0).tolist())),
        "horizon_s": steps * v.sample_time,
        **rollout_errors(model, ds, tau, steps),
        "coefficients": coefficient_report(coeffs, names, truth, ckpt.get("ranges")),
        # samples whose history leaves the trained feature range (held at its edge: networks.HistoryEncoder)
        "outside_range": outside_range_shares(model, w.history),
        "truth_source": truth_source,
        # which guard ranges the model was trained with (`ddyn train --ranges`; None: the vehicle file's)
        "guard_ranges": (ckpt.get("ranges") or {}).get("source"),
        "reference": constant_motion_errors(ds, tau, steps),
        "_series": {"time": ds.time[w.end_row + 1], "pred": pred[:, 3:6], "target": w.target,
                    "coeffs": coeffs},
    }


def public(metrics: dict) -> dict:
    """Metrics without the bulky series (what JSON reports and checkpoints keep)."""
    return {k: v for k, v in metrics.items() if not k.startswith("_")}


def format_summary(m: dict) -> str:
    lines = [f"samples {m['samples']}, one-step RMSE  vx {m['rmse']['vx']:.3e} m/s  vy {m['rmse']['vy']:.3e} m/s"
             f"  omega {m['rmse']['omega']:.3e} rad/s",
             f"  max |error|  vx {m['max_error']['vx']:.3e}  vy {m['max_error']['vy']:.3e}"
             f"  omega {m['max_error']['omega']:.3e}",
             f"  ADE {m['ade']:.3e} m  FDE {m['fde']:.3e} m over {m['horizon_s'] * 1000:.0f} ms"
             f" ({m['starts']} starts)",
             f"  coefficients (truth: {m['truth_source']}):"]
    held = m.get("outside_range")
    if held and held["any"] > 0:
        worst = sorted(((v, k) for k, v in held["features"].items() if v > 0), reverse=True)
        lines.insert(3, f"  inputs outside the trained range in {100 * held['any']:.1f} % of samples (held at its edge): "
                        + ", ".join(f"{k} {100 * v:.1f} %" for v, k in worst))
    for name, c in m["coefficients"].items():
        s = f"    {name:4s} mean {c['mean']:+.5g}  std {c['std']:.2g}"
        if c.get("rel_error") is not None:
            s += f"  true {c['true']:+.5g}  error {100 * c['rel_error']:+.2f} %"
        sat = c.get("at_lower_bound", 0) + c.get("at_upper_bound", 0)
        if sat > 0:
            s += f"  AT GUARD BOUND in {100 * sat:.1f} % of samples"
        lines.append(s)
    if m.get("reference"):
        lines.insert(3, format_reference(m["reference"]))
    if m.get("guard_ranges"):
        from ddyn.learn.guard_ranges import describe

        lines.append("  " + describe(m["guard_ranges"]))
    return "\n".join(lines)


def _run(args) -> int:
    from ddyn.data.importers import load_any

    model, ckpt = checkpoint.load(args.model)
    ds = load_any(args.data, vehicle=checkpoint.vehicle_of(ckpt))   # embedded file: it may live anywhere
    m = evaluate(model, ckpt, ds)
    print(format_summary(m))
    if args.out:
        from ddyn.learn.plots import plot_evaluation

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "metrics.json").write_text(json.dumps(public(m), indent=2))
        for p in plot_evaluation(m, ckpt, out):
            print(f"wrote {p}")
        print(f"wrote {out / 'metrics.json'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="one-step and multi-step errors, coefficients and guard saturation")
    p.add_argument("--model", required=True, help="checkpoint written by ddyn train")
    p.add_argument("--data", required=True, help="dataset in any supported format")
    p.add_argument("--out", help="directory for metrics.json and plots")
    p.set_defaults(func=_run)
