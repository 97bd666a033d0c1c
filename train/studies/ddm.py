"""`ddyn study ddm`: the paper-table reproduction, as a command whose output goes into docs/learning.md.

  sim   1:43 ORCA car, explicit-Euler data as in the papers: train on laps of ETHZ
        (`ddyn simulate`, seed 1), test on laps of ETHZMobil (seed 2), validation the
        last 20 % of the training laps. DDM, and DPM with Iz at truth, +20 % and -20 %.
        The harder case: a DDM (Euler physics step) trained and tested on RK4 data.
  real  the Putnam log of the AV-21, split by time into contiguous blocks: the first
        80 % trains (its last fifth validates), the last 20 % tests. Three DDMs on that
        split: the papers' drivetrain with the papers' ranges (av21), the papers' drivetrain
        with drivetrain ranges from the training part (`ddyn study drivetrain`, via
        `--ranges`), and the powertrain drivetrain of av21_powertrain (its ranges come from
        the same study, committed in the vehicle file).
        `--holdout laps` (issue 36) leaves whole laps out instead: the laps are found from x, y
        (ddyn.data.laps), the named laps test (default HOLDOUT_LAPS) and the others train (their
        last fifth validates); `--holdout speed` trains on the rows below a speed and tests on those
        at or above it. Either way the training part's rows are renumbered into segments wherever a
        held-out row was taken out (split_rows), so no window reads across the cut; each run is
        also evaluated on its own training part (in_sample) beside the held-out one, and
        `--seeds` trains several seeds into one results.json with their mean and spread
        (holdout_summary).

Writes DIR/results.json, DIR/results.md, and per model a checkpoint, metrics.json and
plots; `--update-doc` replaces the block between the study markers in docs/learning.md.
"""
from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ddyn.data import simulate
from ddyn.data.dataset import Dataset, write_canonical
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn.evaluate import evaluate, public
from ddyn.learn.networks import SATURATION_TOL
from ddyn.learn.plots import plot_evaluation
from ddyn.learn.train_cmd import train_to_checkpoint
from ddyn.learn.training import TrainConfig
from ddyn.model import tracks
from ddyn.model import vehicle as vehicle_mod
from ddyn.paths import REPO, putnam_log

PAPER_SIM_DDM = {"vx": 1.506e-5, "vy": 1.839e-4, "omega": 9.6e-3, "ade": 3.77e-5, "fde": 1.15e-4}
PAPER_REAL_DDM = {"vx": 0.0312, "vy": 0.0730, "omega": 0.0187, "ade": 0.1827, "fde": 0.3840}
TARGET_COEFFS = ("Bf", "Cf", "Df", "Br", "Cr", "Dr", "Cm1", "Cm2", "Cr0", "Iz")
POWERTRAIN_VEHICLE = "av21_powertrain"
# TrainConfig.guard_prior of the last real rows, chosen on the training part's validation fifth only: the smallest
# of 1e-3, 1e-2, 1e-1 with no coefficient at a bound in over 5 % of the validation samples on seeds 0, 1, 2
# (Gf 21-22 %, 14-19 %, at most 1.8 %; docs/learning.md)
REAL_GUARD_PRIOR = 0.1
# TrainConfig.tau of the last row, chosen the same way: the lowest mean validation loss of tau 1, 3, 5 on seeds
# 0, 1, 2 with the prior (docs/learning.md)
REAL_TAU = 5
# (run name, vehicle file, table label, drivetrain ranges from the training part via --ranges, TrainConfig fields)
REAL_RUNS = (("ddm_putnam", "av21", "DDM, papers' drivetrain, papers' ranges", False, {}),
             ("ddm_putnam_ranges", "av21", "DDM, papers' drivetrain, ranges from data", True, {}),
             ("ddm_putnam_powertrain", "av21_powertrain", "DDM, powertrain drivetrain (av21_powertrain)", False, {}),
             ("ddm_putnam_powertrain_prior", "av21_powertrain",
              f"DDM, powertrain drivetrain, guard prior {REAL_GUARD_PRIOR:g}", False, {"guard_prior": REAL_GUARD_PRIOR}),
             ("ddm_putnam_powertrain_prior_tau", "av21_powertrain",
              f"DDM, powertrain drivetrain, guard prior {REAL_GUARD_PRIOR:g}, history {REAL_TAU}", False,
              {"guard_prior": REAL_GUARD_PRIOR, "tau": REAL_TAU}),
             ("ddm_putnam_powertrain_prior_tau_iz", "av21_powertrain",
              f"DDM, powertrain drivetrain, guard prior {REAL_GUARD_PRIOR:g}, history {REAL_TAU}, Iz in the papers' "
              f"[500, 2000] kg m2", False, {"guard_prior": REAL_GUARD_PRIOR, "tau": REAL_TAU}),
             # issue 36 item 2: the power-limited drivetrain, every drivetrain range and Iz from the car's physics
             # (train/vehicles/av21_power.json), TrainConfig's built-in defaults as the ddm_putnam row
             ("ddm_putnam_power", "av21_power",
              "DDM, power-limited drivetrain, physical ranges (av21_power)", False, {}),
             # the same with the guard prior: does pulling the coefficients the log cannot tell apart (Cr0 against
             # Cd, the tyres' scale against Iz) toward the middle of their physical ranges keep them off the bounds
             # without costing held-out error
             ("ddm_putnam_power_prior", "av21_power",
              f"DDM, power-limited drivetrain, physical ranges, guard prior {REAL_GUARD_PRIOR:g}", False,
              {"guard_prior": REAL_GUARD_PRIOR}))
# runs trained without --only (the papers' table in docs/learning.md); the others only when named
REAL_DEFAULT_RUNS = tuple(r[0] for r in REAL_RUNS[:5])
# guard ranges a run takes in place of its vehicle file's (through the `ddyn train --ranges` path): the papers'
# nominal Iz range for this car (shared/data/README.md), fixed before any selection (issue 36)
REAL_RANGE_OVERRIDES = {"ddm_putnam_powertrain_prior_tau_iz": {"Iz": [500.0, 2000.0]}}
# how the real log is split into training and held-out parts (--holdout)
HOLDOUTS = ("time", "laps", "speed")
# --holdout laps: the laps that test by default. The Putnam log holds 2.6 laps (ddyn.data.laps: lap 0 from the
# first row, slow, 5,726 rows; lap 1 the one whole lap after it, 4,012 rows; lap 2 the fastest, partial, 1,768
# rows); lap 1 is the whole lap with training data on both sides of it in time
HOLDOUT_LAPS = (1,)
# --holdout speed: rows at or above this vx (m/s) test, those below train (about the log's 80th percentile)
HOLDOUT_SPEED = 20.0
STUDY_BEGIN, STUDY_END = "<!-- study:begin -->", "<!-- study:end -->"
STUDY_DOC = REPO / "docs" / "learning.md"


def _simulated_sets(out: Path, method: str, train_laps: int, test_laps: int) -> tuple[Path, Path]:
    v = vehicle_mod.load("orca_1_43")
    paths = []
    for track, laps, seed, role in (("ethz", train_laps, 1, "train"), ("ethzMobil", test_laps, 2, "test")):
        p = out / f"{role}_{track}_{method}.csv"
        if not p.is_file():
            write_canonical(simulate.simulate(v, tracks.load_track(track), laps=laps, method=method, seed=seed,
                                              progress=False), p)
        paths.append(p)
    return paths[0], paths[1]


def _saturation_max_pct(coefficients: dict | None) -> float | None:
    """The largest share (%) of samples any one coefficient spends on a guard bound (lower or upper)."""
    shares = [100.0 * (float(c.get("at_lower_bound", 0.0)) + float(c.get("at_upper_bound", 0.0)))
              for c in (coefficients or {}).values() if isinstance(c, dict)]
    return max(shares) if shares else None


def _run_model(name: str, train_path: Path, test_path: Path | None, test_ds, cfg: TrainConfig, out: Path,
               ranges_file: Path | None = None) -> dict:
    from ddyn.data.importers import load_any

    ckpt_path = out / name / "model.ckpt"
    ckpt = train_to_checkpoint(str(train_path), cfg, str(ckpt_path), progress=False,
                               ranges_file=str(ranges_file) if ranges_file else None)
    model, ckpt = checkpoint.load(ckpt_path)
    ds = test_ds if test_ds is not None else load_any(test_path)
    m = evaluate(model, ckpt, ds)
    plot_evaluation(m, ckpt, out / name)
    result = {"name": name, "kind": cfg.kind, "train_seconds": ckpt["training"]["seconds"],
              "validation_loss": ckpt["training"]["best_val_loss"], "seed_kept": ckpt["training"]["seed"],
              "restarts": ckpt["training"]["restarts"], **public(m),
              # the figure "no coefficient at a bound in over X % of the samples" (results/ddm_real_putnam.json)
              "saturation_max_pct": _saturation_max_pct(public(m).get("coefficients"))}
    (out / name / "metrics.json").write_text(json.dumps(result, indent=2))
    return result


def run_sim(out: Path, quick: bool = False) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    laps = (1, 1) if quick else (3, 2)
    base = TrainConfig(epochs=5, lbfgs_iterations=40) if quick else TrainConfig()
    euler = _simulated_sets(out, "euler", *laps)
    rk4 = _simulated_sets(out, "rk4", *laps)
    runs = [("DDM", euler, dict(kind="ddm"))]
    runs += [(f"DPM Iz {label}", euler, dict(kind="dpm", dpm_iz_scale=s))
             for label, s in (("true", 1.0), ("+20%", 1.2), ("-20%", 0.8))]
    runs += [("DDM (RK4 data)", rk4, dict(kind="ddm"))]
    results = []
    for name, (tr, te), over in tqdm(runs, desc="sim study"):
        cfg = TrainConfig(**{**base.__dict__, **over})
        results.append(_run_model(_slug(name), tr, te, None, cfg, out) | {"label": name})
    return results


def split_rows(ds: Dataset, keep: np.ndarray) -> Dataset:
    """The rows of ds where `keep` (a boolean mask), in order, with segments renumbered: a new segment starts
    wherever ds's segment changes or rows were taken out in between, so no window of the part reads across a
    row that is not in it (the time between the kept rows would otherwise pass as one sample time)."""
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (len(ds),):
        raise DdynError(f"row mask of {keep.shape} for a dataset of {len(ds)} rows")
    idx = np.flatnonzero(keep)
    part = ds.subset(idx)
    if len(idx):
        part.segment = np.r_[0, np.cumsum((np.diff(idx) != 1) | (np.diff(ds.segment[idx]) != 0))].astype(np.int64)
    return part


def split_real(ds: Dataset, holdout: str = "time", test_laps: tuple[int, ...] = HOLDOUT_LAPS,
               speed: float = HOLDOUT_SPEED) -> tuple[Dataset, Dataset, dict]:
    """(training part, held-out part, what was held out) of a real log.
    time: the first TRAIN_FRACTION of the rows train, the rest test (the study's split before issue 36);
    laps: the laps numbered in test_laps (ddyn.data.laps, from x, y) test, the other laps train;
    speed: rows with vx >= speed test, the rows below train."""
    from ddyn.data import laps as laps_mod
    from ddyn.studies import drivetrain

    if holdout == "time":
        cut = int(len(ds) * drivetrain.TRAIN_FRACTION)
        return (ds.subset(slice(0, cut)), ds.subset(slice(cut, None)),
                {"holdout": "time", "train_rows": cut, "test_rows": len(ds) - cut,
                 "what": f"first {drivetrain.TRAIN_FRACTION:.0%} of the rows train, the rest test"})
    if holdout == "laps":
        lp = laps_mod.from_dataset(ds)
        if not lp.circuit:
            raise DdynError(f"--holdout laps: the log has no laps ({lp.reason})")
        present = sorted(int(x) for x in np.unique(lp.lap))
        bad = sorted(set(test_laps) - set(present))
        if bad or not test_laps:
            raise DdynError(f"--holdout-laps {' '.join(map(str, test_laps)) or '(none)'}: the log's laps are "
                            f"{', '.join(map(str, present))} ({lp.source}); {', '.join(map(str, bad))} not among them")
        test = np.isin(lp.lap, list(test_laps))
        if test.all():
            raise DdynError(f"--holdout-laps {' '.join(map(str, test_laps))}: every lap of the log would test; "
                            f"keep at least one of {', '.join(map(str, present))} for training")
        info = {"holdout": "laps", "test_laps": sorted(test_laps),
                "train_laps": [x for x in present if x not in test_laps], "laps_source": lp.source,
                "what": f"laps {', '.join(map(str, sorted(test_laps)))} test, laps "
                        f"{', '.join(str(x) for x in present if x not in test_laps)} train ({lp.source})"}
    elif holdout == "speed":
        if not np.isfinite(speed) or speed <= 0:
            raise DdynError(f"--holdout-speed must be a positive speed in m/s, got {speed}")
        test = ds.states[:, 3] >= speed
        if test.all() or not test.any():
            raise DdynError(f"--holdout-speed {speed:g}: no rows on one side (vx spans "
                            f"{ds.states[:, 3].min():.1f}-{ds.states[:, 3].max():.1f} m/s)")
        info = {"holdout": "speed", "speed": speed,
                "what": f"rows with vx >= {speed:g} m/s test, those below train"}
    else:
        raise DdynError(f"holdout must be one of {', '.join(HOLDOUTS)}, got {holdout!r}")
    train_part, test_part = split_rows(ds, ~test), split_rows(ds, test)
    return train_part, test_part, {**info, "train_rows": len(train_part), "test_rows": len(test_part)}


def any_bound_share(m: dict, ckpt: dict) -> float | None:
    """Share of the evaluated samples with at least one coefficient within SATURATION_TOL of the range width of a
    guard bound (None for a model without a guard)."""
    r = ckpt.get("ranges")
    if not r:
        return None
    c = np.asarray(m["_series"]["coeffs"])
    lo, hi = np.asarray(r["lo"]), np.asarray(r["hi"])
    tol = SATURATION_TOL * (hi - lo)
    return float(((c <= lo + tol) | (c >= hi - tol)).any(axis=1).mean())


def run_real(out: Path, quick: bool = False, seed: int = 0, only: tuple[str, ...] = (), restarts: int = 1,
             guard_prior: float | None = None, method: str = "euler", tau: int | None = None,
             holdout: str = "time", test_laps: tuple[int, ...] = HOLDOUT_LAPS, speed: float = HOLDOUT_SPEED,
             epochs: int | None = None, lbfgs_iterations: int | None = None) -> list[dict]:
    """seed: the training seed of every run (TrainConfig.seed); only: run names of REAL_RUNS to run
    (REAL_DEFAULT_RUNS if empty); restarts: TrainConfig.restarts (seeds seed..seed+restarts-1, the lowest
    validation loss kept); guard_prior, tau: TrainConfig.guard_prior, TrainConfig.tau of every run (None: each
    run's own in REAL_RUNS); method: the physics step of the model (TrainConfig.method); holdout, test_laps,
    speed: the split (split_real); epochs, lbfgs_iterations: the training budget (None: TrainConfig's)."""
    from ddyn.data.importers import load_any

    out.mkdir(parents=True, exist_ok=True)
    src = putnam_log()
    if not src.is_file():
        raise DdynError(f"real log not found: {src}")
    from ddyn.studies import drivetrain

    unknown = set(only) - {r[0] for r in REAL_RUNS}
    if unknown:
        raise DdynError(f"unknown real run(s) {', '.join(sorted(unknown))}; expected {', '.join(r[0] for r in REAL_RUNS)}")
    base = (TrainConfig(epochs=5, lbfgs_iterations=40, seed=seed, restarts=restarts, method=method) if quick
            else TrainConfig(seed=seed, restarts=restarts, method=method))
    budget = {k: v for k, v in (("epochs", epochs), ("lbfgs_iterations", lbfgs_iterations)) if v is not None}
    base = replace(base, **budget)
    results = []
    for name, vehicle_name, label, data_ranges, fields in REAL_RUNS:
        if name not in (only or REAL_DEFAULT_RUNS):
            continue
        run_prior, run_tau = fields.get("guard_prior", 0.0), fields.get("tau", base.tau)
        prior = run_prior if guard_prior is None else guard_prior
        history = run_tau if tau is None else tau
        cfg = replace(base, **{**fields, "guard_prior": prior, "tau": history})
        ds = load_any(src, vehicle=vehicle_name)
        train_part, test_part, split = split_real(ds, holdout, test_laps, speed)
        ranges_file = None
        if data_ranges:
            # the papers' form with ranges from the training part: its own drivetrain fit's, and
            # the other coefficients' from av21_powertrain (derived from the same part), so that
            # the two rows differ in the drivetrain only
            fit = drivetrain.run(train_part, vehicle_mod.load(vehicle_name), fraction=1.0)
            other = {k: list(r) for k, r in vehicle_mod.load(POWERTRAIN_VEHICLE).ranges.items()
                     if k not in drivetrain.DRIVE}
            ranges_file = out / f"ranges_{name}.json"
            ranges_file.write_text(json.dumps({**other, **fit["forms"]["papers"]["ranges"]}, indent=2))
        elif name in REAL_RANGE_OVERRIDES:
            ranges_file = out / f"ranges_{name}.json"
            ranges_file.write_text(json.dumps(REAL_RANGE_OVERRIDES[name], indent=2))
        if quick:
            train_part = train_part.subset(slice(0, 1500))
        train_path = out / f"putnam_train_{vehicle_name}.csv"
        write_canonical(train_part, train_path)
        r = _run_model(name, train_path, None, test_part, cfg, out, ranges_file)
        extra = {}
        if holdout != "time":
            # the same model on the rows it was fitted on (its validation fifth included) beside the held-out part
            model, ckpt = checkpoint.load(out / name / "model.ckpt")
            m_test, m_train = evaluate(model, ckpt, test_part), evaluate(model, ckpt, train_part)
            extra = {"test_any_bound": any_bound_share(m_test, ckpt),
                     "in_sample": {**public(m_train), "any_bound": any_bound_share(m_train, ckpt)}}
        results.append(r | extra
                       | {"label": label + (f" (seed {seed})" if seed and restarts == 1 else "")
                          + (f" (seeds {seed}-{seed + restarts - 1}, best validation kept)" if restarts > 1 else "")
                          + (f" (guard prior {prior:g})" if prior != run_prior else "")
                          + (f" (history {history})" if history != run_tau else "")
                          + (f" ({method} step)" if method != "euler" else ""),
                          "seed": seed, "restarts_requested": restarts, "guard_prior": prior, "tau": history,
                          "vehicle": vehicle_name, "epochs": cfg.epochs, "lbfgs_iterations": cfg.lbfgs_iterations,
                          "split": split})
    return results


HOLDOUT_FIGURES = ("vx", "vy", "omega", "ade", "fde", "any_bound", "worst_bound")


def _figures(m: dict, any_bound: float | None) -> dict:
    worst = max((c.get("at_lower_bound", 0) + c.get("at_upper_bound", 0) for c in m["coefficients"].values()),
                default=0.0)
    return {"vx": m["rmse"]["vx"], "vy": m["rmse"]["vy"], "omega": m["rmse"]["omega"], "ade": m["ade"],
            "fde": m["fde"], "any_bound": any_bound, "worst_bound": worst,
            "Iz_mean": m["coefficients"].get("Iz", {}).get("mean")}


def holdout_summary(real: list[dict]) -> list[dict]:
    """Per run name over its seeds: mean, min, max and spread (max - min) of the held-out (test) and in-sample
    figures (RMSE vx, vy, omega; ADE, FDE; any_bound: share of samples with some coefficient at a guard bound;
    worst_bound: the largest share of one coefficient; Iz_mean: the mean Iz estimate)."""
    out = []
    for name in dict.fromkeys(r["name"] for r in real):
        runs = [r for r in real if r["name"] == name and "in_sample" in r]
        if not runs:
            continue
        row = {"name": name, "label": re.sub(r" \(seed \d+\)", "", runs[0]["label"]),
               "seeds": [r["seed"] for r in runs]}
        for part, get in (("test", lambda r: _figures(r, r.get("test_any_bound"))),
                          ("in_sample", lambda r: _figures(r["in_sample"], r["in_sample"].get("any_bound")))):
            vals = [get(r) for r in runs]
            row[part] = {}
            for k in vals[0]:
                xs = [v[k] for v in vals if v[k] is not None]
                if xs:
                    row[part][k] = {"mean": float(np.mean(xs)), "min": float(np.min(xs)), "max": float(np.max(xs)),
                                    "spread": float(np.max(xs) - np.min(xs))}
        # "nothing changes" on the same windows (ddyn.learn.reference): no seed, so one value per part
        refs = (runs[0].get("reference"), runs[0]["in_sample"].get("reference"))
        if all(r and "rmse" in r for r in refs):
            row["reference"] = {part: {**r["rmse"], "ade": r["ade"], "fde": r["fde"]}
                                for part, r in zip(("test", "in_sample"), refs)}
        out.append(row)
    return out


def holdout_markdown(summary: list[dict], split: dict) -> str:
    def cell(f: dict | None, pct: bool = False) -> str:
        if f is None:
            return "-"
        if pct:
            return f"{100 * f['mean']:.1f} ({100 * f['min']:.1f}-{100 * f['max']:.1f}) %"
        return f"{_fmt(f['mean'])} ({_fmt(f['min'])}-{_fmt(f['max'])})"

    lines = ["", f"**Held out: {split['what']}** ({split['train_rows']} training rows, {split['test_rows']} held-out "
             "rows). Mean (min-max) over the seeds; held-out figures first, in-sample (the training part, its "
             "validation fifth included) below.", "",
             "| model | part | seeds | vx (m/s) | vy (m/s) | omega (rad/s) | ADE (m) | FDE (m) | samples with a coefficient at a bound | worst coefficient at a bound | mean Iz (kg m2) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    ref = next((row["reference"] for row in summary if row.get("reference")), None)
    for row in summary:
        for part in ("test", "in_sample"):
            f = row[part]
            lines.append(f"| {row['label']} | {'held out' if part == 'test' else 'in sample'} | {len(row['seeds'])} | "
                         + " | ".join(cell(f.get(k)) for k in ("vx", "vy", "omega", "ade", "fde")) + " | "
                         + cell(f.get("any_bound"), True) + " | " + cell(f.get("worst_bound"), True) + " | "
                         + (f"{f['Iz_mean']['mean']:.0f} ({f['Iz_mean']['min']:.0f}-{f['Iz_mean']['max']:.0f})"
                            if "Iz_mean" in f else "-") + " |")
    if ref:
        for part in ("test", "in_sample"):
            lines.append(f"| reference: nothing changes (constant vx, vy, yaw rate) | "
                         f"{'held out' if part == 'test' else 'in sample'} | - | "
                         + " | ".join(_fmt(ref[part][k]) for k in ("vx", "vy", "omega", "ade", "fde")) + " | - | - | - |")
    return "\n".join(lines) + "\n"


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower().replace("+", "plus").replace("-20", "minus20")).strip("_")


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) >= 1e-2 else f"{x:.3e}"


def markdown(sim: list[dict] | None, real: list[dict] | None) -> str:
    lines = []
    if sim:
        lines += ["**Simulated 1:43 car** (train ETHZ, test ETHZMobil; RMSE of the next state; ADE/FDE over 300 ms)", "",
                  "| model | vx (m/s) | vy (m/s) | omega (rad/s) | ADE (m) | FDE (m) | train time (s) |",
                  "|---|---|---|---|---|---|---|"]
        p = PAPER_SIM_DDM
        lines.append(f"| paper: DDM | {_fmt(p['vx'])} | {_fmt(p['vy'])} | {_fmt(p['omega'])} | {_fmt(p['ade'])} "
                     f"| {_fmt(p['fde'])} | |")
        for r in sim:
            lines.append(f"| {r['label']} | {_fmt(r['rmse']['vx'])} | {_fmt(r['rmse']['vy'])} | "
                         f"{_fmt(r['rmse']['omega'])} | {_fmt(r['ade'])} | {_fmt(r['fde'])} | {r['train_seconds']:.0f} |")
        ddm = next(r for r in sim if r["label"] == "DDM")
        lines += ["", "DDM coefficient estimates on the test track (mean over samples) against the simulator's truth:", "",
                  "| " + " | ".join(TARGET_COEFFS) + " |", "|" + "---|" * len(TARGET_COEFFS),
                  "| " + " | ".join(f"{100 * ddm['coefficients'][c]['rel_error']:+.1f} %" for c in TARGET_COEFFS) + " |"]
        pinned = sorted({f"{r['label']}: {n}" for r in sim for n, c in r["coefficients"].items()
                         if c.get("at_lower_bound", 0) + c.get("at_upper_bound", 0) > 0.01})
        lines += ["", "Guard saturation (over 1 % of samples within 1 % of a bound): "
                  + ("; ".join(pinned) if pinned else "none") + "."]
    if real:
        p = PAPER_REAL_DDM
        lines += ["", "**Real AV-21, Putnam Park** (the same time split for every row: first 80 % trains, its last fifth "
                  "validates, the held-out last 20 % tests; ADE/FDE over 600 ms). The paper's figures are from another "
                  "track and split, so they are a reference point, not a like-for-like comparison.", "",
                  "| model | vx (m/s) | vy (m/s) | omega (rad/s) | ADE (m) | FDE (m) | train time (s) | coefficients at a guard bound in over 5 % of samples |",
                  "|---|---|---|---|---|---|---|---|",
                  f"| paper: DDM (real data) | {p['vx']} | {p['vy']} | {p['omega']} | {p['ade']} | {p['fde']} | | |"]
        for r in real:
            lines.append(f"| {r['label']} | {_fmt(r['rmse']['vx'])} | {_fmt(r['rmse']['vy'])} | "
                         f"{_fmt(r['rmse']['omega'])} | {_fmt(r['ade'])} | {_fmt(r['fde'])} | {r['train_seconds']:.0f} | "
                         f"{_saturation(r, 0.05) or 'none'} |")
        lines += ["", "Guard saturation on the real log (share of held-out samples within 1 % of the range width of a "
                  "bound, over 1 %):"]
        lines += [f"- {r['label']}: {_saturation(r, 0.01) or 'none'}" for r in real]
    return "\n".join(lines) + "\n"


def _saturation(r: dict, above: float) -> str:
    share = {n: c.get("at_lower_bound", 0) + c.get("at_upper_bound", 0) for n, c in r["coefficients"].items()}
    return ", ".join(f"{n} ({100 * s:.0f} %)" for n, s in share.items() if s > above)


def update_doc(block: str, doc: Path = STUDY_DOC) -> None:
    text = doc.read_text()
    if STUDY_BEGIN not in text or STUDY_END not in text:
        raise DdynError(f"{doc} has no {STUDY_BEGIN} ... {STUDY_END} block")
    head, rest = text.split(STUDY_BEGIN, 1)
    _, tail = rest.split(STUDY_END, 1)
    doc.write_text(f"{head}{STUDY_BEGIN}\n{block}{STUDY_END}{tail}")


def _run(args) -> int:
    out = Path(args.out)
    sim = run_sim(out / "sim", args.quick) if args.which in ("sim", "all") else None
    seeds = tuple(dict.fromkeys(args.seeds)) if args.seeds else (args.seed,)
    if args.holdout_laps and args.holdout != "laps":
        raise DdynError("--holdout-laps needs --holdout laps")
    if args.holdout_speed is not None and args.holdout != "speed":
        raise DdynError("--holdout-speed needs --holdout speed")
    real = None
    if args.which in ("real", "all"):
        real = []
        for s in seeds:
            # one folder per seed when there are several (each run's checkpoint, metrics and plots)
            real += run_real(out / "real" / (f"seed{s}" if len(seeds) > 1 else ""), args.quick, s,
                             tuple(args.only or ()), args.restarts, args.guard_prior, args.method, args.tau,
                             args.holdout, tuple(args.holdout_laps or HOLDOUT_LAPS),
                             HOLDOUT_SPEED if args.holdout_speed is None else args.holdout_speed,
                             args.epochs, args.lbfgs_iterations)
    results = {"sim": sim, "real": real, "quick": args.quick}
    md = markdown(sim, real)
    if real and args.holdout != "time":
        results["holdout"] = real[0]["split"]
        results["holdout_summary"] = holdout_summary(real)
        md += holdout_markdown(results["holdout_summary"], real[0]["split"])
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(md)
    print(md)
    if args.update_doc:
        if (args.quick or args.which != "all" or args.only or args.seed or args.restarts != 1
                or args.guard_prior is not None or args.tau is not None or args.method != "euler"
                or args.seeds or args.holdout != "time" or args.epochs is not None
                or args.lbfgs_iterations is not None):
            raise DdynError("--update-doc needs the full study: `ddyn study ddm all` without --quick")
        update_doc(md)
        print(f"{STUDY_DOC.relative_to(REPO)} results block updated")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("ddm", help="reproduce the papers' DDM/DPM table (simulated and real)")
    p.add_argument("which", nargs="?", choices=("sim", "real", "all"), default="all")
    p.add_argument("--out", default="out/study", help="output directory (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="tiny data and training: a smoke run, not the figures")
    p.add_argument("--update-doc", action="store_true", help="write the results table into docs/learning.md")
    p.add_argument("--seed", type=int, default=0, help="training seed of the real runs (default: %(default)s)")
    p.add_argument("--restarts", type=int, default=1, help="real runs: train seeds SEED..SEED+N-1 and keep the "
                   "lowest validation loss (TrainConfig.restarts; default: %(default)s)")
    p.add_argument("--guard-prior", type=float, help="real runs: TrainConfig.guard_prior of every run, the weight "
                   f"of the mean squared guard logit (default: each run's own: {REAL_GUARD_PRIOR:g} for the runs with "
                   "'prior' in their name, 0 for the others)")
    p.add_argument("--tau", type=int, help="real runs: TrainConfig.tau of every run, the rows of history the "
                   f"network reads (default: each run's own: {REAL_TAU} for those with 'tau' in it, 1 for the others)")
    p.add_argument("--method", choices=("euler", "rk4"), default="euler", help="real runs: the model's physics "
                   "step (TrainConfig.method; default: %(default)s, as in the papers)")
    p.add_argument("--only", nargs="+", metavar="RUN", help="real runs to train, by name (default: "
                   + ", ".join(REAL_DEFAULT_RUNS) + "; by name only: "
                   + ", ".join(r[0] for r in REAL_RUNS if r[0] not in REAL_DEFAULT_RUNS) + ")")
    p.add_argument("--seeds", nargs="+", type=int, metavar="SEED", help="real runs: train each run once per seed "
                   "(in place of --seed; one folder per seed) and summarise mean and spread over them")
    p.add_argument("--holdout", choices=HOLDOUTS, default="time", help="real runs: what the test part is: time "
                   "(the last 20 %% of the rows, default), laps (whole laps found from x, y: --holdout-laps), speed "
                   "(the rows at or above --holdout-speed); laps and speed also report in-sample figures")
    p.add_argument("--holdout-laps", nargs="+", type=int, metavar="LAP", help="--holdout laps: the laps (0 = the "
                   f"log's first) that test (default: {' '.join(map(str, HOLDOUT_LAPS))})")
    p.add_argument("--holdout-speed", type=float, metavar="M_S", help="--holdout speed: rows with vx at or above "
                   f"this test (default: {HOLDOUT_SPEED:g} m/s)")
    p.add_argument("--epochs", type=int, help="real runs: Adam epochs (TrainConfig.epochs; default: its default, "
                   "5 with --quick)")
    p.add_argument("--lbfgs-iterations", type=int, help="real runs: L-BFGS iterations after Adam "
                   "(TrainConfig.lbfgs_iterations; default: its default, 40 with --quick)")
    p.set_defaults(func=_run)
