"""`ddyn denoise`: split a log into a physical part and a noise part (EKF-FTHD), or smooth it (Savitzky-Golay).

    ddyn denoise DATA [--model CKPT | --vehicle NAME] [--method ekf|savgol] -o OUT.csv
                 [--finetune head|all] [--coloured-noise] [--q-range LO HI] [--r-range LO HI]

Methods (both work per segment: no filter ever reads across a gap):

* ekf (EKF-FTHD, ddyn.learn.ekf_layer): an extended Kalman filter and RTS smoother over vx, vy, omega
  with the shared single-track model, coefficients from a DDM checkpoint (the Physics Guard's
  estimate per sample) or the vehicle file's true coefficients, and Q, R learned by maximum
  innovation likelihood inside bounded guards. Procedure:
    1. Savitzky-Golay pre-smoothing gives the first linearisation trajectory; Q starts at the mean
       square one-step residual of the model along it, R at the vehicle's nominal sensor noise;
    2. Q and R are fitted on the innovation NLL (L-BFGS; chunks of CHUNK rows filtered in
       parallel) with the model linearised, batched over time, about that trajectory and the
       DDM's coefficients evaluated on it. With --finetune the DDM's head (or all its weights)
       is fitted jointly (Adam, FINETUNE_ITERATIONS steps, in the first pass only);
    3. the whole log is filtered and smoothed (each segment in one piece);
    4. steps 2-3 repeat about the smoothed trajectory (RELINEARISATIONS passes in all: the iterated
       extended Kalman smoother).
  The physical part is the smoothed estimate; the noise part is measurement minus physical part.
  --coloured-noise adds a first-order Gauss-Markov (AR(1)) measurement-noise state per channel
  (see EKFLayer); the physical part is then the smoothed vehicle state alone.
* savgol: scipy.signal.savgol_filter per segment and channel, polynomial order 2, the window
  chosen per channel by exact leave-one-out cross-validation of the linear smoother (LOO
  residual = residual / (1 - h0), h0 the filter's centre weight) over odd windows 5 .. 51 (at
  most the longest segment's length), pooled over segments; a segment shorter than the window
  uses the largest odd window that fits. This is the baseline (and the EKF's first
  linearisation trajectory).

Output: OUT.csv in the canonical format (write_canonical): vx, vy, omega replaced by the physical
part; x, y, yaw, throttle, steering and inputs unchanged; extras raw_vx, raw_vy, raw_omega (the
input's values, or its own raw_* if the input was itself denoised), noise_vx, noise_vy,
noise_omega (raw minus physical), for ekf std_vx, std_vy, std_omega (the smoother's posterior
standard deviation), and every extra of the input (true_* included). Beside it, OUT.denoise.json
(method, windows or learned Q/R and the NLL history) and, when a DDM checkpoint is given,
OUT.ranges.json with suggested coefficient ranges (rule in `suggest_ranges`), computed from the
checkpoint's DDM (as fine-tuned, with --finetune) on the denoised data.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ddyn.data.dataset import Dataset, write_canonical
from ddyn.errors import DdynError
from ddyn.learn.ekf_layer import (
    CHANNELS,
    EKFLayer,
    NoiseRanges,
    chunk_index,
    default_ranges,
    fit_noise,
    scatter_back,
    velocity_step,
)
from ddyn.model.single_track import COEFF_NAMES
from ddyn.model.vehicle import Vehicle
from ddyn.model.vehicle import load as load_vehicle

VEL = (3, 4, 5)                 # columns of vx, vy, omega in Dataset.states
METHODS = ("ekf", "savgol")
SAVGOL_ORDER = 2
SAVGOL_WINDOWS = tuple(range(5, 52, 2))
CHUNK = 50                      # rows per chunk while learning Q and R
RELINEARISATIONS = 3
FINETUNE = ("head", "all")
FIT_ITERATIONS = (20, 6, 6)     # optimiser steps per relinearisation (L-BFGS; Adam when fine-tuning)
FIT_LR = 0.05
FINETUNE_ITERATIONS = (150,)    # Adam steps fine-tuning the DDM, per pass (passes beyond: Q, R only)
FINETUNE_LR = 1e-3
# suggested coefficient ranges
RANGE_PERCENTILES = (1.0, 99.0)
RANGE_MARGIN = 0.25             # widen the percentile interval by this fraction of its width on each side
RANGE_MIN_WIDTH = 0.02          # ... computed from at least this fraction of the vehicle range's width
PINNED_TOL = 0.01               # a percentile within this fraction of the range width of a bound is pinned


# ----------------------------------------------------------------------------- Savitzky-Golay

def _segments(seg: np.ndarray) -> list[tuple[int, int]]:
    bounds = np.flatnonzero(np.diff(seg) != 0) + 1
    starts = np.concatenate([[0], bounds]).astype(int)
    ends = np.concatenate([bounds, [len(seg)]]).astype(int)
    return list(zip(starts, ends))


def savgol_window(signal: np.ndarray, segments: list[tuple[int, int]], order: int = SAVGOL_ORDER,
                  windows=SAVGOL_WINDOWS) -> tuple[int | None, dict]:
    """The window minimising the exact leave-one-out CV error of the Savitzky-Golay smoother."""
    from scipy.signal import savgol_coeffs, savgol_filter

    longest = max(b - a for a, b in segments)
    cv = {}
    for w in windows:
        if w <= order + 1 or w > longest:
            continue
        h0 = float(savgol_coeffs(w, order)[w // 2])
        num, cnt = 0.0, 0
        for a, b in segments:
            if b - a < w:
                continue
            x = signal[a:b]
            r = (x - savgol_filter(x, w, order, mode="interp"))[w // 2: len(x) - w // 2]
            num += float(np.sum((r / (1.0 - h0)) ** 2))
            cnt += len(r)
        if cnt:
            cv[w] = num / cnt
    if not cv:
        return None, cv
    return min(cv, key=cv.get), cv


def savgol_apply(signal: np.ndarray, segments: list[tuple[int, int]], window: int | None,
                 order: int = SAVGOL_ORDER) -> np.ndarray:
    """Smooth each segment on its own; segments shorter than the window use the largest odd window
    that fits (left as they are below order + 2 rows)."""
    from scipy.signal import savgol_filter

    out = signal.astype(float).copy()
    if window is None:
        return out
    for a, b in segments:
        n = b - a
        w = min(window, n if n % 2 else n - 1)
        if w <= order + 1:
            continue
        out[a:b] = savgol_filter(signal[a:b], w, order, mode="interp")
    return out


def savgol_denoise(ds: Dataset, order: int = SAVGOL_ORDER, windows=SAVGOL_WINDOWS) -> tuple[np.ndarray, dict]:
    """Smoothed (N, 3) vx, vy, omega and the windows chosen."""
    segs = _segments(ds.segment)
    out = np.empty((len(ds), 3))
    info = {"order": order, "window": {}, "rule": "exact leave-one-out CV over odd windows "
            f"{windows[0]}..{windows[-1]}, pooled over segments, per channel"}
    for j, (col, name) in enumerate(zip(VEL, CHANNELS)):
        w, _ = savgol_window(ds.states[:, col], segs, order, windows)
        info["window"][name] = w
        out[:, j] = savgol_apply(ds.states[:, col], segs, w, order)
    return out, info


# ----------------------------------------------------------------------------- coefficients

@dataclass
class CoefficientSource:
    """Where the filter's model takes its 17 coefficients from."""

    kind: str                                  # "ddm" or "vehicle"
    vehicle: Vehicle
    method: str = "euler"
    substeps: int = 1
    model: torch.nn.Module | None = None       # DDM (kind "ddm")
    tau: int = 1
    label: str = ""
    extra: dict = field(default_factory=dict)

    def coefficients(self, velocities: torch.Tensor, ds: Dataset) -> torch.Tensor:
        """(N, 17) coefficients for the step from every row, the DDM reading histories built from
        `velocities` (N, 3) and the logged throttle, steering and rates (rows before a segment's
        tau-th repeat the segment's first row)."""
        n = len(ds)
        if self.kind == "vehicle":
            return torch.as_tensor(self.vehicle.true_vector(), dtype=velocities.dtype).expand(n, -1)
        feats = torch.cat([velocities, torch.as_tensor(np.column_stack([ds.states[:, 6:8], ds.inputs]),
                                                       dtype=velocities.dtype)], dim=1)
        rows = history_rows(ds.segment, self.tau)
        return self.model.coefficients(feats[torch.as_tensor(rows)])


def history_rows(segment: np.ndarray, tau: int) -> np.ndarray:
    """(N, tau) rows of the history ending at each row, clamped to the row's segment start."""
    n = len(segment)
    seg_start = np.zeros(n, dtype=np.int64)
    for a, b in _segments(segment):
        seg_start[a:b] = a
    k = np.arange(n)[:, None] + np.arange(-tau + 1, 1)[None, :]
    return np.maximum(k, seg_start[:, None])


def source_from_checkpoint(path: str | Path) -> CoefficientSource:
    from ddyn.learn import checkpoint

    model, ckpt = checkpoint.load(path)
    if ckpt["kind"] != "ddm":
        raise DdynError(f"{path}: the EKF needs a DDM checkpoint (17 guarded coefficients), not {ckpt['kind']}")
    arch = ckpt["architecture"]
    return CoefficientSource("ddm", checkpoint.vehicle_of(ckpt), arch["method"], int(arch["substeps"]), model,
                             int(ckpt["config"]["tau"]), f"DDM checkpoint {path}", {"ckpt": ckpt})


def source_from_vehicle(vehicle: Vehicle | str, method: str = "euler") -> CoefficientSource:
    v = load_vehicle(vehicle) if isinstance(vehicle, str) else vehicle
    if v.true_coefficients is None:
        raise DdynError(f"vehicle {v.name!r} has no true coefficients; give a DDM checkpoint (--model)")
    substeps = v.rk4_substeps if method == "rk4" else 1
    return CoefficientSource("vehicle", v, method, substeps, label=f"vehicle {v.name} true coefficients")


# ----------------------------------------------------------------------------- EKF-FTHD

@dataclass
class EKFSettings:
    ranges: NoiseRanges | None = None          # default: default_ranges(vehicle)
    chunk: int = CHUNK
    relinearisations: int = RELINEARISATIONS
    iterations: tuple = FIT_ITERATIONS
    lr: float = FIT_LR
    finetune: str | None = None                # "head" or "all": also fine-tune the DDM on the innovation NLL
    finetune_lr: float = FINETUNE_LR
    finetune_iterations: tuple = FINETUNE_ITERATIONS
    learn: bool = True                         # False: keep the noise model as given (`state`, or q, r)
    q: np.ndarray | None = None
    r: np.ndarray | None = None
    state: dict | None = None                  # an EKFLayer state_dict (e.g. learned on training data)
    coloured: bool = False                     # AR(1) measurement-noise states (see EKFLayer)


def ekf_denoise(ds: Dataset, source: CoefficientSource, settings: EKFSettings | None = None,
                nominal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Smoothed (N, 3) velocities, their posterior std (N, 3), and a report."""
    s = settings or EKFSettings()
    ranges = s.ranges or default_ranges(source.vehicle)
    dtype = torch.float64
    v = source.vehicle
    if abs(ds.sample_time - v.sample_time) > 1e-4 * v.sample_time:
        raise DdynError(f"dataset sample time {ds.sample_time} s differs from vehicle {v.name}'s {v.sample_time} s")
    layer = EKFLayer(v.known, ds.sample_time, ranges, source.method, source.substeps,
                     q_init=s.q, r_init=s.r, dtype=dtype, coloured=s.coloured)
    if s.state is not None:
        layer.load_state_dict(s.state)
    if s.learn and s.q is None and s.r is None and s.state is None:
        # start from the nominal sensor noise where the vehicle states it (inside the range)
        sigma = np.array([v.sensor_noise_std.get(c, np.nan) for c in CHANNELS])
        if np.all(np.isfinite(sigma)):
            lo_r, hi_r = np.array(ranges.r_lo), np.array(ranges.r_hi)
            layer.r.set(np.clip(sigma ** 2, lo_r, hi_r))
    z_all = torch.as_tensor(ds.states[:, VEL], dtype=dtype)
    exo_all = torch.as_tensor(np.column_stack([ds.states[:, 6:8], ds.inputs]), dtype=dtype)
    if nominal is None:
        nominal, sg_info = savgol_denoise(ds)
    else:
        sg_info = None
    if s.learn and s.q is None and s.state is None:
        # start Q at the mean square one-step residual of the model along the pre-smoothed
        # trajectory (it still holds noise, so this errs towards following the measurements)
        with torch.no_grad():
            nom0 = torch.as_tensor(nominal, dtype=dtype)
            pred = velocity_step(nom0, exo_all, source.coefficients(nom0, ds), v.known, ds.sample_time,
                                 source.method, source.substeps)
        k = np.flatnonzero(ds.segment[1:] == ds.segment[:-1])
        resid = nominal[k + 1] - pred.numpy()[k]
        if len(k):
            layer.q.set(np.clip(np.mean(resid ** 2, axis=0), ranges.q_lo, ranges.q_hi))
    fit_idx, fit_mask = chunk_index(ds.segment, s.chunk)
    run_idx, run_mask = chunk_index(ds.segment, None)
    head_params = []
    if s.finetune and source.kind == "ddm":
        if s.finetune not in FINETUNE:
            raise DdynError(f"finetune must be one of {', '.join(FINETUNE)}, got {s.finetune!r}")
        head_params = list((source.model.head if s.finetune == "head" else source.model).parameters())
    report = {"coefficients": source.label, "discretisation": source.method, "substeps": source.substeps,
              "ranges": ranges.as_dict(), "chunk": s.chunk, "relinearisations": s.relinearisations,
              "initial_nominal": "Savitzky-Golay" if sg_info else "given", "finetune": bool(head_params),
              "fits": []}
    start = time.perf_counter()
    if source.model is not None:
        source.model.eval()
    for it in range(max(1, s.relinearisations)):
        nom = torch.as_tensor(nominal, dtype=dtype)
        if s.learn:
            zf, ef, nf = z_all[fit_idx], exo_all[fit_idx], nom[fit_idx]
            mf = torch.as_tensor(fit_mask, dtype=dtype)

            def coeff_fn():
                return source.coefficients(nom, ds)[torch.as_tensor(fit_idx)]

            tune = bool(head_params) and it < len(s.finetune_iterations)
            if tune:
                coeff_call, iters, extra = coeff_fn, s.finetune_iterations[it], head_params
            else:
                with torch.no_grad():
                    fixed = coeff_fn()
                coeff_call, extra = (lambda: fixed), ()  # noqa: E731
                iters = s.iterations[min(it, len(s.iterations) - 1)]
            fit = fit_noise(layer, zf, ef, coeff_call, nf, mf, iterations=iters, lr=s.lr,
                            extra_params=extra, extra_lr=s.finetune_lr)
            report["fits"].append({"relinearisation": it, "iterations": fit.iterations,
                                   "nll_start": fit.nll_history[0], "nll_end": fit.nll_history[-1],
                                   "finetuned": tune, "q": fit.q.tolist(), "r": fit.r.tolist()})
        with torch.no_grad():
            coeffs = source.coefficients(nom, ds)
            res = layer(z_all[run_idx], exo_all[run_idx], coeffs[torch.as_tensor(run_idx)], nominal=nom[run_idx],
                        mask=torch.as_tensor(run_mask, dtype=dtype), linearisation="nominal", smooth=True)
        nominal = scatter_back(res.physical.numpy(), run_idx, run_mask, len(ds))
        report.setdefault("nll_full", []).append(float(res.nll))
    var = scatter_back(torch.diagonal(res.P_smoothed, dim1=-2, dim2=-1)[..., :3].numpy(), run_idx, run_mask, len(ds))
    with torch.no_grad():
        report["q"] = layer.q().numpy().tolist()
        report["r"] = layer.r().numpy().tolist()
    report["q_at_bound"] = _at_bound(report["q"], ranges.q_lo, ranges.q_hi, ranges.scale)
    report["r_at_bound"] = _at_bound(report["r"], ranges.r_lo, ranges.r_hi, ranges.scale)
    if layer.coloured:
        with torch.no_grad():
            report["coloured_phi"] = layer.phi().numpy().tolist()
            report["coloured_var"] = layer.c().numpy().tolist()
    report["_layer_state"] = {k: v.detach().clone() for k, v in layer.state_dict().items()}
    report["seconds"] = time.perf_counter() - start
    report["savgol"] = sg_info
    return nominal, np.sqrt(np.maximum(var, 0.0)), report


def _at_bound(vals, lo, hi, scale) -> list[str | None]:
    out = []
    for v, a, b in zip(vals, lo, hi):
        if scale == "log":
            v, a, b = np.log(v), np.log(a), np.log(b)
        tol = 0.01 * (b - a)
        out.append("low" if v <= a + tol else "high" if v >= b - tol else None)
    return out


# ----------------------------------------------------------------------------- the denoised dataset

def assemble(ds: Dataset, physical: np.ndarray, method: str, std: np.ndarray | None = None,
             info: dict | None = None) -> Dataset:
    """ds with vx, vy, omega replaced by `physical`; raw_*, noise_* (and std_*) extras added."""
    states = ds.states.copy()
    raw = {c: ds.extras.get(f"raw_{c}", ds.states[:, col]).copy() for c, col in zip(CHANNELS, VEL)}
    states[:, list(VEL)] = physical
    extras = dict(ds.extras)
    for j, c in enumerate(CHANNELS):
        extras[f"raw_{c}"] = raw[c]
        extras[f"noise_{c}"] = raw[c] - physical[:, j]
        if std is not None:
            extras[f"std_{c}"] = std[:, j]
    meta = dict(ds.metadata)
    meta["denoise_method"] = method
    units = {"vx": "m/s", "vy": "m/s", "omega": "rad/s"}
    added = [f"{p}_{c}={units[c]}" for p in ("raw", "noise") + (("std",) if std is not None else ()) for c in CHANNELS
             if f"{p}_{c}" not in ds.extras]
    if added:
        meta["extra_units"] = " ".join(filter(None, [meta.get("extra_units", "")] + added))
    if info:
        meta["denoise"] = json.dumps(_compact(info), separators=(",", ":"))
    src = f"ddyn denoise ({method}) of {ds.source}" if ds.source else f"ddyn denoise ({method})"
    return Dataset(ds.time.copy(), ds.segment.copy(), states, ds.inputs.copy(), ds.sample_time, ds.vehicle, src,
                   extras, meta)


def _compact(info: dict) -> dict:
    """What the output file's metadata records about the denoising (the full report is in OUT.denoise.json)."""
    keep = ("coefficients", "discretisation", "q", "r", "window", "coloured_phi", "coloured_var")
    return {k: info[k] for k in keep if info.get(k) is not None}


def denoise(ds: Dataset, method: str, source: CoefficientSource | None = None,
            settings: EKFSettings | None = None) -> tuple[Dataset, dict]:
    """Denoise ds with `method` ("ekf" needs a coefficient source); returns the new dataset and a report."""
    if method == "savgol":
        phys, info = savgol_denoise(ds)
        return assemble(ds, phys, "savgol", info=info), {"method": "savgol", **info}
    if method == "ekf":
        if source is None:
            raise DdynError("the ekf method needs a DDM checkpoint (--model) or a vehicle (--vehicle)")
        phys, std, info = ekf_denoise(ds, source, settings)
        return assemble(ds, phys, "ekf", std, info), {"method": "ekf", **info}
    raise DdynError(f"unknown denoising method {method!r}; expected one of {', '.join(METHODS)}")


# ----------------------------------------------------------------------------- suggested ranges

def ddm_estimates(model, ds: Dataset, tau: int) -> np.ndarray:
    """The DDM's coefficient estimates (n, 17) on every window of ds."""
    from ddyn.data.windows import make_windows
    from ddyn.learn.evaluate import predict

    w = make_windows(ds, tau)
    return predict(model, w.history, w.state, w.inputs)[1]


def suggest_ranges(estimates: np.ndarray, vehicle: Vehicle) -> dict:
    """Suggested coefficient ranges from the DDM's estimates on denoised data.

    Rule, per coefficient with vehicle range [lo, hi] and estimates' percentiles p1, p99:
      width w = max(p99 - p1, RANGE_MIN_WIDTH (hi - lo));  candidate [p1 - m w, p99 + m w], m = RANGE_MARGIN;
      intersect the candidate with [lo, hi] (the data never widen a range they do not press on),
      except on a side where the estimates are pinned at the guard (p1 within PINNED_TOL (hi - lo)
      of lo, or p99 of hi): the data want beyond the bound, so that side is extended past it
      (union): to lo / 2 or 2 hi for a positive bound (the papers' half-to-double convention),
      else by half the range width; a bound at zero is a sign constraint and stays. Estimates
      pinned at both ends fill the whole range (the coefficient is not identified, or serves as
      slack): the vehicle range is kept and the coefficient flagged "both".
    """
    lo, hi = vehicle.range_arrays()
    p_lo, p_hi = np.percentile(estimates, RANGE_PERCENTILES, axis=0)
    out = {}
    for i, name in enumerate(COEFF_NAMES):
        span = hi[i] - lo[i]
        w = max(p_hi[i] - p_lo[i], RANGE_MIN_WIDTH * span)
        a, b = max(lo[i], p_lo[i] - RANGE_MARGIN * w), min(hi[i], p_hi[i] + RANGE_MARGIN * w)
        pinned_low = p_lo[i] <= lo[i] + PINNED_TOL * span
        pinned_high = p_hi[i] >= hi[i] - PINNED_TOL * span
        if pinned_low and pinned_high:
            a, b = lo[i], hi[i]
        elif pinned_low:
            a = lo[i] / 2 if lo[i] > 0 else lo[i] if lo[i] == 0 else lo[i] - 0.5 * span
        elif pinned_high:
            b = hi[i] * 2 if hi[i] > 0 else hi[i] if hi[i] == 0 else hi[i] + 0.5 * span
        out[name] = {"vehicle": [float(lo[i]), float(hi[i])], "p01": float(p_lo[i]), "p99": float(p_hi[i]),
                     "suggested": [float(a), float(b)],
                     "pinned": "both" if pinned_low and pinned_high else "low" if pinned_low else
                     "high" if pinned_high else None}
    return {"rule": " ".join(suggest_ranges.__doc__.split("Rule, ")[1].split()),
            "parameters": {"RANGE_PERCENTILES": list(RANGE_PERCENTILES), "RANGE_MARGIN": RANGE_MARGIN,
                           "RANGE_MIN_WIDTH": RANGE_MIN_WIDTH, "PINNED_TOL": PINNED_TOL},
            "coefficients": out}


# ----------------------------------------------------------------------------- CLI

def _ranges_from_args(args, vehicle: Vehicle) -> NoiseRanges | None:
    if args.q_range is None and args.r_range is None and args.range_scale is None:
        return None
    d = default_ranges(vehicle)
    q = tuple(args.q_range) if args.q_range else None
    r = tuple(args.r_range) if args.r_range else None
    return NoiseRanges((q[0],) * 3 if q else d.q_lo, (q[1],) * 3 if q else d.q_hi,
                       (r[0],) * 3 if r else d.r_lo, (r[1],) * 3 if r else d.r_hi,
                       args.range_scale or d.scale)


def _run(args) -> int:
    from ddyn.data.importers import load_any

    torch.set_num_threads(max(1, args.threads))
    if args.model and args.vehicle:
        raise DdynError("give either --model or --vehicle, not both")
    source = None
    if args.model:
        source = source_from_checkpoint(args.model)
    elif args.vehicle and args.method == "ekf":
        source = source_from_vehicle(args.vehicle, args.integrator or "euler")
    ds = load_any(args.data, vehicle=source.vehicle if source else args.vehicle)   # a Vehicle, name or path
    if args.method == "ekf" and source is None:
        raise DdynError("the ekf method needs a DDM checkpoint (--model) or a vehicle (--vehicle)")
    if source is not None and args.integrator and args.model and args.integrator != source.method:
        source.method = args.integrator
        source.substeps = source.vehicle.rk4_substeps if args.integrator == "rk4" else 1
    settings = None
    if args.method == "ekf":
        settings = EKFSettings(ranges=_ranges_from_args(args, source.vehicle), chunk=args.chunk,
                               relinearisations=args.relinearisations, finetune=args.finetune,
                               coloured=args.coloured_noise)
    out_ds, report = denoise(ds, args.method, source, settings)
    out = write_canonical(out_ds, args.output)
    stem = out.with_suffix("")
    report_path = Path(f"{stem}.denoise.json")
    report_path.write_text(json.dumps({k: v for k, v in report.items() if not k.startswith("_")}, indent=2))
    noise = np.column_stack([out_ds.extras[f"noise_{c}"] for c in CHANNELS])
    print(f"wrote {out}: {len(out_ds)} rows, method {args.method}; noise part std "
          + ", ".join(f"{c} {s:.3g}" for c, s in zip(CHANNELS, noise.std(axis=0))))
    if args.method == "ekf":
        print("  Q " + " ".join(f"{x:.3g}" for x in report["q"]) + "   R " + " ".join(f"{x:.3g}" for x in report["r"])
              + f"   ({report['seconds']:.1f} s)")
        for name, flags in (("Q", report["q_at_bound"]), ("R", report["r_at_bound"])):
            hit = [f"{c} ({f})" for c, f in zip(CHANNELS, flags) if f]
            if hit:
                print(f"  note: {name} at its guard bound for {', '.join(hit)}" + (
                    "; the model's one-step error may exceed the range (check the model or widen --q-range)"
                    if name == "Q" and "high" in flags else ""))
    else:
        print("  windows " + ", ".join(f"{c} {w}" for c, w in report["window"].items()))
    print(f"wrote {report_path}")
    if source is not None and source.kind == "ddm":
        est = ddm_estimates(source.model, out_ds, source.tau)
        ranges = {"checkpoint": str(args.model), "data": str(out), **suggest_ranges(est, source.vehicle)}
        rp = Path(f"{stem}.ranges.json")
        rp.write_text(json.dumps(ranges, indent=2))
        print(f"wrote {rp}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("denoise", help="split a log into physical and noise parts (EKF-FTHD or Savitzky-Golay)",
                              description=__doc__.splitlines()[0])
    p.add_argument("data", help="dataset in any supported format")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--model", help="DDM checkpoint: the filter's coefficients per sample (and suggested ranges)")
    src.add_argument("--vehicle", help="vehicle name: its true coefficients (ekf), or the dataset's vehicle")
    p.add_argument("--method", choices=METHODS, default="ekf", help="(default: %(default)s)")
    p.add_argument("-o", "--output", required=True, help="output CSV (canonical dataset format)")
    p.add_argument("--integrator", choices=("euler", "rk4"), default=None,
                   help="the filter model's discretisation (default: the checkpoint's; euler with --vehicle)")
    p.add_argument("--q-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="process noise variance range for all channels (default: scaled to the vehicle's sensor noise)")
    p.add_argument("--r-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="measurement noise variance range (the paper's real car: --q-range 0.1 1 --r-range 0.01 1)")
    p.add_argument("--range-scale", choices=("log", "linear"), default=None, help="guard scaling (default log)")
    p.add_argument("--chunk", type=int, default=CHUNK, help="rows per chunk while learning Q, R (default %(default)s)")
    p.add_argument("--relinearisations", type=int, default=RELINEARISATIONS, help="(default %(default)s)")
    p.add_argument("--finetune", choices=FINETUNE, default=None,
                   help="also fine-tune the DDM's head (or all its weights) on the innovation NLL")
    p.add_argument("--coloured-noise", action="store_true",
                   help="model coloured (AR(1)) measurement noise with extra filter states")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.set_defaults(func=_run)
