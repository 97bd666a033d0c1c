"""`ddyn study transfer`: does a DDM trained on one track carry to another, and does FTHD close the gap?

Issue 36, items 1 and 3, on an independent plant (not this project's model): an AV-21-class car of a plant family
(ddyn.gap.benchmark.families; default commonroad-mb, CommonRoad's multi-body model with its "av21" parameter
set; or mujoco, the physics-engine car, a 1500 kg saloon: not AV-21 class, trained with its own nominal vehicle
file) drives two effect-free logs with the families' own machinery (families.make_log, commonroad_st.LogSettings:
the DBW hold at the log rate, white sensor noise at the nominal's level, no effect):

  A  Putnam (the real log's track), seed LOG_SEEDS[0];
  B  a random road course: the seeded random track random:SEED (ddyn.model.track_random, default
     random:301) scaled by ROAD_SCALE to full size (random:301: 1.88 km, tightest radius 60 m) with a constant
     ROAD_WIDTH (Putnam's 9 m); seed LOG_SEEDS[1].

Both at the same speed cap (--speed, the gap study's 18-27 m/s band) and length (--duration). Then, per training
seed:

  transfer  the DDM trained with today's `ddyn train --vehicle av21` settings (the vehicle's training profile,
            train/vehicles/training/av21.json; --epochs and --lbfgs-iterations lower the budget and are recorded)
            on A's first 80 % (its last fifth validates, as `ddyn train` splits); RMSE vx, vy, omega and ADE, FDE
            on A's last 20 % (own track) and on B's last 20 % (other track), and their ratio other / own per
            channel (the issue's target: <= 1.5 on every channel). B's whole log is scored too (b_all).
  fractions the FTHD path: the A model fine-tuned (train/learn/finetune.py with `ddyn finetune`'s defaults:
            half the layers frozen, lambda1 = lambda2 = 0.5, 1500 Adam + 300 L-BFGS steps, lr 1e-3; --ft-*
            lower them) on 5, 10, 20 % of B's first 80 % (B's training part), taken as FRACTION_BLOCKS equal
            blocks spread evenly over it (--fraction-blocks 1: its first rows), beside a DDM trained on the same
            rows from scratch with the same settings as the A model. Each arm selects its weights on the last
            fifth of its own fraction's rows (as `ddyn finetune --data PART` and `ddyn train --data PART` split):
            B's last 20 % is only scored, never used to fit or select.

Selection by transfer (issue 36 item 1): --set KEY=VALUE (TrainConfig fields over the profile), --ranges FILE (guard
ranges) and --vehicle make a candidate setting; --no-finetune scores its A model alone. `python -m
ddyn.studies.transfer_compare BASE CAND --own` compares two such runs against the seed spread
(results/ddm_transfer_selection.json).

The A model never sees B before fine-tuning; no row of B's last 20 % enters any fit (the test checks both from the
datasets each fit receives). Writes DIR/results.json, DIR/results.md, the logs as canonical CSV (DIR/A.csv,
DIR/B.csv) and per seed the checkpoints (`ddyn evaluate` reads them).
"""
from __future__ import annotations

import json
import math
import pickle
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ddyn.data.dataset import Dataset, write_canonical
from ddyn.errors import DdynError
from ddyn.learn import checkpoint, training_profile
from ddyn.learn.evaluate import evaluate, public
from ddyn.learn.finetune import FinetuneConfig, FitConfig, finetune, fraction_of, split_by_time
from ddyn.learn.guard_ranges import read_ranges, with_ranges
from ddyn.learn.training import train
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.track_random import ROAD_SCALE, ROAD_WIDTH, road_course
from ddyn.studies.ddm import any_bound_share

FAMILIES = ("commonroad-mb", "mujoco")
PARAMS = {"commonroad-mb": "av21", "mujoco": "default"}      # the family's car: CommonRoad's AV-21 set
PROFILE_VEHICLE = "av21"           # whose training profile sets every training setting
TEST_FRACTION = 0.2                # the last 20 % of each log: A's own-track test, B's held-out part
FRACTIONS = (0.05, 0.10, 0.20)     # of B's training part (its first 80 %)
# the fine-tuning rows of a fraction: this many equal blocks spread evenly over B's training part, each its own
# segment (no window reads across a seam). Until 2026-12-01 a fraction was B's first rows (--fraction-blocks 1):
# Putnam's first 5-10 % is its start straight, so the rows the transferred model failed on (the slow corners) were
# not in the fraction and 27 of 36 fine-tunings kept the pre-trained weights. A user who fine-tunes on a new
# track logs some of every part of it, not one straight.
FRACTION_BLOCKS = 4
DEFAULT_ROAD_SEED = 301
LOG_SEEDS = (3601, 3602)           # plant seeds (excitation, noise) of A and B
RATIO_TARGET = 1.5
CHANNELS = ("vx", "vy", "omega", "ade", "fde")
UNITS = {"vx": "m/s", "vy": "m/s", "omega": "rad/s", "ade": "m", "fde": "m"}
DEFAULTS = dict(duration=180.0, speed=24.0, seeds=(0, 1, 2))
QUICK = dict(duration=16.0, epochs=2, lbfgs=20, ft_adam=20, ft_lbfgs=5)


# ---------------------------------------------------------------------------------------------
# data

def plant_log(family: str, track, seed: int, duration: float, speed: float, cache: Path | None = None,
              noise: float = 1.0) -> Dataset:
    """One effect-free log of the family (families.make_log), cached by its settings; noise: times the nominal's
    sensor noise (0: the plant's states as they are)."""
    from ddyn.gap.benchmark import families as F
    from ddyn.plants import commonroad_st as CP

    name = getattr(track, "name", str(track))
    tail = "" if noise == 1.0 else f"-noise{noise:g}"
    path = None if cache is None else cache / f"{family}-{name}-{seed}-{duration:g}s-{speed:g}{tail}.pkl"
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes())
    settings = CP.LogSettings(duration=duration, target_speed=speed, noise_scale=noise)
    ds = F.make_log(family, track, CP.PlantEffects(), seed, settings, PARAMS[family])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(ds))
    return ds


def for_vehicle(ds: Dataset, v) -> Dataset:
    """The log labelled as the training vehicle's (its sample time checked): the plant's nominal file only drove
    the driver; the model is the one a user trains."""
    if abs(ds.sample_time - v.sample_time) > 1e-9 * v.sample_time:
        raise DdynError(f"the log's sample time {ds.sample_time} s differs from vehicle {v.name}'s {v.sample_time} s")
    out = ds.subset(slice(None))
    out.vehicle = v.name
    return out


def default_vehicle(family: str) -> str:
    """av21 for the AV-21-class CommonRoad car; the MuJoCo saloon (1500 kg) only has its own nominal file."""
    if family == "mujoco":
        from ddyn.plants import mujoco_car

        return str(mujoco_car.NOMINAL_VEHICLE)
    return "av21"


def splits(a: Dataset, b: Dataset) -> dict:
    """A: first 80 % trains, last 20 % is the own-track test; B: first 80 % is the fine-tuning pool, last 20 %
    the held-out part every B figure is scored on. Row ranges recorded (end exclusive)."""
    a_train, a_test = split_by_time(a, TEST_FRACTION)
    b_pool, b_test = split_by_time(b, TEST_FRACTION)
    return {"a_train": a_train, "a_test": a_test, "b_pool": b_pool, "b_test": b_test,
            "rows": {"a_train": [0, len(a_train)], "a_test": [len(a_train), len(a)],
                     "b_pool": [0, len(b_pool)], "b_test": [len(b_pool), len(b)]}}


# ---------------------------------------------------------------------------------------------
# models

def parse_sets(items) -> dict:
    """--set KEY=VALUE ... as {TrainConfig field: value}, each value checked as a training profile's setting is
    (training_profile.check_setting: its type, then TrainConfig's own range check). A candidate setting for
    selection by transfer (issue 36 item 1); the seed and the budget have their own flags."""
    out = {}
    for item in items or ():
        key, sep, text = str(item).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise DdynError(f"--set: expected KEY=VALUE, got {item!r}")
        if key in ("seed", "epochs", "lbfgs_iterations"):
            raise DdynError(f"--set {key}: use --seeds, --epochs or --lbfgs-iterations")
        if key in out:
            raise DdynError(f"--set {key}: given twice")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out[key] = training_profile.check_setting("--set", key, value)
    return out


def train_config(seed: int, epochs: int | None, lbfgs: int | None, sets: dict | None = None):
    """Today's `ddyn train --vehicle av21` settings (its training profile), the --set values and the budget flags
    over them."""
    flags = {**(sets or {}), "seed": seed}
    if epochs is not None:
        flags["epochs"] = epochs
    if lbfgs is not None:
        flags["lbfgs_iterations"] = lbfgs
    return training_profile.resolve(PROFILE_VEHICLE, flags)


def fit_ddm(ds: Dataset, v, cfg, path: Path, what: str) -> tuple:
    """`ddyn train --data ds`: the last fifth of ds validates; saved as a checkpoint."""
    result = train(ds, v, cfg, progress=False)
    ckpt = checkpoint.make(result, v, ds.content_hash(), what, len(ds))
    checkpoint.save(ckpt, path)
    return result.model, ckpt


def scores(model, ckpt: dict, ds: Dataset) -> dict:
    m = evaluate(model, ckpt, ds)
    pub = public(m)
    worst = max(((n, c.get("at_lower_bound", 0.0) + c.get("at_upper_bound", 0.0))
                 for n, c in pub["coefficients"].items()), key=lambda t: t[1])
    return {"vx": pub["rmse"]["vx"], "vy": pub["rmse"]["vy"], "omega": pub["rmse"]["omega"], "ade": pub["ade"],
            "fde": pub["fde"], "samples": pub["samples"], "any_bound": any_bound_share(m, ckpt),
            "worst_bound": {"coefficient": worst[0], "share": worst[1]},
            "coefficients": {n: c["mean"] for n, c in pub["coefficients"].items()}}


def _steps(ckpt: dict) -> dict:
    t = ckpt["training"]
    if "optimizer_steps" in t:
        return dict(t["optimizer_steps"])
    epochs = ckpt["config"]["epochs"]      # the curve: one point per Adam epoch, then one per L-BFGS round (20 its)
    return {"adam_epochs": epochs, "lbfgs_rounds": t["epochs_run"] - epochs}


def kept_base(ckpt: dict) -> bool:
    """Whether a fine-tuning kept the A model's weights: no step validated below the start (the first point of the
    curve) on the fraction's own selection rows."""
    curve = ckpt["training"]["val_loss_curve"]
    return len(curve) < 2 or curve[0] <= min(curve[1:])


def fraction_blocks(pool: Dataset, fraction: float, blocks: int) -> tuple[Dataset, list[list[int]]]:
    """`fraction` of pool's rows as `blocks` equal blocks, block i starting at i/blocks of the way through it, each
    block its own segment (a model never steps from one into the next); with blocks 1 the first rows (as
    finetune.fraction_of). Returns the rows and their [start, end) ranges in pool."""
    if blocks == 1:
        part = fraction_of(pool, fraction)
        return part, [[0, len(part)]]
    n = len(pool)
    size = int(round(n * fraction / blocks))
    if size < 2:
        raise DdynError(f"fraction {fraction:g} in {blocks} blocks leaves {size} row(s) per block of {n}")
    ranges = [[int(round(i * n / blocks)), int(round(i * n / blocks)) + size] for i in range(blocks)]
    index = np.concatenate([np.arange(a, b) for a, b in ranges])
    part = pool.subset(index)
    span = int(pool.segment.max()) + 1
    part.segment = np.concatenate([pool.segment[a:b] + i * span for i, (a, b) in enumerate(ranges)])
    return part, ranges


def run_seed(seed: int, data: dict, v, opts: dict, out: Path, progress: bool = True) -> dict:
    torch.manual_seed(seed)
    d = out / f"seed{seed}"
    d.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cfg = train_config(seed, opts["epochs"], opts["lbfgs"], opts["sets"]).config
    base_path = d / "a_model.ckpt"
    model, ckpt = fit_ddm(data["a_train"], v, cfg, base_path, f"{out / 'A.csv'} rows {data['rows']['a_train']}")
    own, other = scores(model, ckpt, data["a_test"]), scores(model, ckpt, data["b_test"])
    row = {"seed": seed, "base": {"own": own, "other": other, "b_all": scores(model, ckpt, data["b"]),
                                  "ratio": {c: other[c] / own[c] for c in CHANNELS},
                                  "train_rows": len(data["a_train"]), "seconds": ckpt["training"]["seconds"],
                                  "best_val_loss": ckpt["training"]["best_val_loss"], "steps": _steps(ckpt)},
           "fractions": []}
    if progress:
        print(f"seed {seed}: A model ({time.perf_counter() - t0:.0f} s): own " + _fmt(own) + "; other "
              + _fmt(other), flush=True)
    fit = FitConfig(adam_steps=opts["ft_adam"], lbfgs_iterations=opts["ft_lbfgs"], seed=seed)
    for f in opts["fractions"]:
        part, ranges = fraction_blocks(data["b_pool"], f, opts["blocks"])
        ft_train, ft_val = split_by_time(part, cfg.val_fraction)
        fc = FinetuneConfig(fit=fit)
        rows_text = ", ".join(f"{a}-{b}" for a, b in ranges)
        ft_model, ft_ckpt = finetune(base_path, ft_train, ft_val, fc, source=f"{out / 'B.csv'} rows {rows_text}",
                                     split=f"{f:.0%} of B's training part in {len(ranges)} block(s); the last "
                                           "fifth of those rows validates")
        checkpoint.save(ft_ckpt, d / f"fthd_f{round(100 * f):02d}.ckpt")
        sc_model, sc_ckpt = fit_ddm(part, v, cfg, d / f"scratch_f{round(100 * f):02d}.ckpt",
                                    f"{out / 'B.csv'} rows {rows_text}")
        r = {"fraction": f, "rows": len(part), "blocks": ranges, "fit_rows": len(ft_train),
             "select_rows": len(ft_val),
             "fthd": scores(ft_model, ft_ckpt, data["b_test"]), "scratch": scores(sc_model, sc_ckpt, data["b_test"]),
             "fthd_steps": _steps(ft_ckpt), "scratch_steps": _steps(sc_ckpt), "fthd_kept_base": kept_base(ft_ckpt),
             "fthd_seconds": ft_ckpt["training"]["seconds"], "scratch_seconds": sc_ckpt["training"]["seconds"]}
        row["fractions"].append(r)
        if progress:
            print(f"seed {seed} {f:4.0%} of B ({time.perf_counter() - t0:.0f} s): FTHD " + _fmt(r["fthd"])
                  + "; scratch " + _fmt(r["scratch"]), flush=True)
    row["seconds"] = time.perf_counter() - t0
    return row


# ---------------------------------------------------------------------------------------------
# summary

def _stat(values) -> dict:
    a = np.asarray(values, float)
    return {"mean": float(a.mean()), "min": float(a.min()), "max": float(a.max()), "spread": float(a.max() - a.min())}


def summarise(runs: list[dict], fractions) -> dict:
    base = {k: {c: _stat([r["base"][k][c] for r in runs]) for c in CHANNELS} for k in ("own", "other", "b_all")}
    ratio = {c: _stat([r["base"]["ratio"][c] for r in runs]) for c in CHANNELS}
    per_ch = {c: ratio[c]["max"] <= RATIO_TARGET for c in CHANNELS}
    out = {"own": base["own"], "other": base["other"], "b_all": base["b_all"], "ratio": ratio,
           "ratio_target": {"target": RATIO_TARGET, "met": all(per_ch.values()), "per_channel": per_ch,
                            "reading": "every seed's other/own ratio <= the target"},
           "any_bound": {k: _stat([r["base"][k]["any_bound"] for r in runs]) for k in ("own", "other")},
           "fractions": []}
    for i, f in enumerate(fractions):
        rows = [r["fractions"][i] for r in runs]
        fr = {"fraction": f, "rows": rows[0]["rows"]}
        for arm in ("fthd", "scratch"):
            fr[arm] = {c: _stat([x[arm][c] for x in rows]) for c in CHANNELS}
            fr[arm]["any_bound"] = _stat([x[arm]["any_bound"] for x in rows])
        # FTHD better than the zero-shot A model, and than scratch, on a channel: on the seed mean
        fr["fthd_kept_base"] = sum(bool(x.get("fthd_kept_base")) for x in rows)
        fr["fthd_vs_zero_shot"] = {c: fr["fthd"][c]["mean"] / base["other"][c]["mean"] for c in CHANNELS}
        fr["fthd_vs_scratch"] = {c: fr["fthd"][c]["mean"] / fr["scratch"][c]["mean"] for c in CHANNELS}
        out["fractions"].append(fr)
    return out


def _noise_text(noise: float) -> str:
    if noise == 0:
        return "noise-free (the plant's states as logged)"
    return f"white sensor noise at {noise:g} x the nominal's level (vx 0.05 m/s, vy 0.02 m/s, omega 0.005 rad/s)"


def _g(x: float) -> str:
    return f"{x:.3g}" if 1e-3 <= abs(x) < 1e4 else f"{x:.2e}"


def _fmt(m: dict) -> str:
    return " ".join(f"{c} {_g(m[c])}" for c in CHANNELS)


def _cell(s: dict, n: int) -> str:
    return _g(s["mean"]) if n == 1 else f"{_g(s['mean'])} ({_g(s['min'])}-{_g(s['max'])})"


def markdown(res: dict) -> str:
    s, n = res["summary"], len(res["seeds"])
    st = res["settings"]
    lines = ["# Track transfer on an independent plant (issue 36)", ""]
    if res["quick"]:
        lines += ["**Quick mode: tiny logs and budgets; a smoke run, not the figures.**", ""]
    ta, tb = res["tracks"]["A"], res["tracks"]["B"]
    lines += [f"Plant: {res['family']} ({res['plant']}), effect-free, {res['duration']:g} s per log at a "
              f"{res['speed']:g} m/s cap, " + _noise_text(res.get("noise_scale", 1.0)) + ". " + "; ".join(
                  f"{k} = {t['name']} ({t['about']}, {t['length']:.0f} m, log seed {t['log_seed']}, {t['rows']} rows, "
                  f"vx {t['vx_range'][0]:.0f}-{t['vx_range'][1]:.0f} m/s, |vy| p95 {t['vy_p95']:.2f} max "
                  f"{t['vy_max']:.2f} m/s, |vx omega| p95 {t['ay_p95']:.1f} max {t['ay_max']:.1f} m/s^2)"
                  for k, t in (("A", ta), ("B", tb))) + f". Model vehicle "
              f"{res['vehicle']}; training settings: `ddyn train --vehicle av21`'s ({st['train']['origin_text']})"
              + (f"; guard ranges from {st['ranges']['file']}" if st.get("ranges") else "") + ". "
              f"FTHD: {st['finetune_text']}. Seeds {', '.join(map(str, res['seeds']))} (training seeds; the logs are "
              f"the same): each cell is the mean" + (" (min-max over the seeds)." if n > 1 else "."), "",
              "Trained on A's first 80 %, tested on A's last 20 % (own track) and on B's last 20 % (other track):", "",
              "| | " + " | ".join(f"{c} ({UNITS[c]})" for c in CHANNELS) + " |", "|---|" + "---|" * len(CHANNELS)]
    for key, label in (("own", "own track (A, last 20 %)"), ("other", "other track (B, last 20 %)"),
                       ("b_all", "other track (all of B)")):
        lines.append(f"| {label} | " + " | ".join(_cell(s[key][c], n) for c in CHANNELS) + " |")
    lines.append(f"| ratio other / own (target <= {RATIO_TARGET:g}) | "
                 + " | ".join(_cell(s["ratio"][c], n) for c in CHANNELS) + " |")
    t = s["ratio_target"]
    lines += ["", f"Ratio target (every seed, every channel <= {RATIO_TARGET:g}): **{'met' if t['met'] else 'NOT met'}**"
              f" (" + ", ".join(f"{c} {'yes' if ok else 'no'}" for c, ok in t["per_channel"].items()) + "). "
              f"Samples with a coefficient on a guard bound: own {100 * s['any_bound']['own']['mean']:.0f} %, other "
              f"{100 * s['any_bound']['other']['mean']:.0f} %.", ""]
    if not s["fractions"]:
        lines += ["No FTHD fractions (--no-finetune).", "", f"Study time {res['seconds']:.0f} s.", ""]
        return "\n".join(lines) + "\n"
    lines += ["FTHD path: the A model fine-tuned on "
              + ("the first rows of" if res["settings"].get("fraction_blocks", 1) == 1
                 else f"{res['settings']['fraction_blocks']} blocks spread over")
              + " B's training part, beside a DDM trained on the same rows from scratch (same settings as the A "
                "model); scored on B's last 20 % (never fitted or selected on):", "",
              "| fraction of B's training part | rows | model | " + " | ".join(CHANNELS) + " |",
              "|---|---|---|" + "---|" * len(CHANNELS),
              "| 0 | 0 | A model, zero-shot | " + " | ".join(_cell(s["other"][c], n) for c in CHANNELS) + " |"]
    for fr in s["fractions"]:
        for arm, label in (("fthd", "FTHD (A model fine-tuned)"), ("scratch", "DDM from scratch")):
            lines.append(f"| {fr['fraction']:.0%} | {fr['rows']} | {label} | "
                         + " | ".join(_cell(fr[arm][c], n) for c in CHANNELS) + " |")
    lines += ["", "Fine-tunings that kept the A model's weights (no step validated below the start on the fraction's "
              "own selection rows): " + ", ".join(f"{fr['fraction']:.0%} {fr['fthd_kept_base']} of {n}"
                                                  for fr in s["fractions"]) + ".",
              "", "FTHD / zero-shot and FTHD / scratch (seed means):", "",
              "| fraction | " + " | ".join(f"{c} vs zero-shot" for c in CHANNELS) + " | "
              + " | ".join(f"{c} vs scratch" for c in CHANNELS) + " |", "|---|" + "---|" * (2 * len(CHANNELS))]
    for fr in s["fractions"]:
        lines.append(f"| {fr['fraction']:.0%} | " + " | ".join(f"{fr['fthd_vs_zero_shot'][c]:.2f}" for c in CHANNELS)
                     + " | " + " | ".join(f"{fr['fthd_vs_scratch'][c]:.2f}" for c in CHANNELS) + " |")
    lines += ["", f"Study time {res['seconds']:.0f} s.", ""]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# command

def _positive(name: str, value, whole: bool = False):
    if value is None:
        return None
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0) or (whole and value != int(value)):
        raise DdynError(f"{name} must be a positive {'whole ' if whole else ''}number, got {value!r}")
    return int(value) if whole else float(value)


def options(args) -> dict:
    """Every option checked before any work; a DdynError names the option."""
    if args.family not in FAMILIES:
        raise DdynError(f"--family: unknown plant family {args.family!r}; expected one of {', '.join(FAMILIES)}")
    q = QUICK if args.quick else {}
    o = {"family": args.family, "quick": bool(args.quick),
         "duration": _positive("--duration", args.duration if args.duration is not None
                               else q.get("duration", DEFAULTS["duration"])),
         "speed": _positive("--speed", args.speed if args.speed is not None else DEFAULTS["speed"]),
         "epochs": _positive("--epochs", args.epochs if args.epochs is not None else q.get("epochs"), True),
         "lbfgs": (args.lbfgs_iterations if args.lbfgs_iterations is not None else q.get("lbfgs")),
         "ft_adam": (args.ft_adam_steps if args.ft_adam_steps is not None else q.get("ft_adam", FitConfig().adam_steps)),
         "ft_lbfgs": (args.ft_lbfgs_iterations if args.ft_lbfgs_iterations is not None
                      else q.get("ft_lbfgs", FitConfig().lbfgs_iterations)),
         "road_seed": args.road_seed, "road_scale": args.road_scale, "swap": bool(args.swap),
         "noise": args.noise_scale}
    for name, key in (("--lbfgs-iterations", "lbfgs"), ("--ft-adam-steps", "ft_adam"),
                      ("--ft-lbfgs-iterations", "ft_lbfgs")):
        v = o[key]
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise DdynError(f"{name} must be a whole number >= 0, got {v!r}")
    if o["ft_adam"] + o["ft_lbfgs"] < 1:
        raise DdynError("--ft-adam-steps plus --ft-lbfgs-iterations must be at least 1")
    if not 18.0 <= o["speed"] <= 30.0:
        raise DdynError(f"--speed must lie in 18-30 m/s (the AV-21-class logs of the gap study: 18-27), got {o['speed']}")
    fr = tuple(args.fractions) if args.fractions else FRACTIONS
    if args.no_finetune:
        if args.fractions:
            raise DdynError("--no-finetune and --fractions: give one of them")
        fr = ()
    for f in fr:
        if not (math.isfinite(f) and 0 < f <= 1):
            raise DdynError(f"--fractions: each must lie in (0, 1], got {f}")
    o["fractions"] = tuple(sorted(set(fr)))
    o["blocks"] = _positive("--fraction-blocks", args.fraction_blocks, True)
    seeds = tuple(args.seeds) if args.seeds else ((0,) if args.quick else DEFAULTS["seeds"])
    if len(set(seeds)) != len(seeds) or any(s < 0 for s in seeds):
        raise DdynError(f"--seeds: distinct non-negative integers, got {' '.join(map(str, seeds))}")
    o["seeds"] = seeds
    if o["road_seed"] < 0:
        raise DdynError(f"--road-seed must be >= 0, got {o['road_seed']}")
    if not (math.isfinite(o["noise"]) and 0.0 <= o["noise"] <= 5.0):
        raise DdynError(f"--noise-scale must lie in 0-5 (times the nominal's sensor noise), got {o['noise']}")
    if not (math.isfinite(o["road_scale"]) and 50.0 <= o["road_scale"] <= 500.0):
        raise DdynError(f"--road-scale must lie in 50-500 (random tracks are 8-18 m long), got {o['road_scale']}")
    o["sets"] = parse_sets(args.set)
    # the train settings themselves (epochs, lbfgs, --set) through TrainConfig's own checks, together
    try:
        train_config(0, o["epochs"], o["lbfgs"])
    except DdynError as e:
        raise DdynError(f"--epochs/--lbfgs-iterations: {e}") from None
    try:
        train_config(0, o["epochs"], o["lbfgs"], o["sets"])
    except DdynError as e:
        raise DdynError(f"--set: {e}") from None
    o["vehicle"] = args.vehicle or default_vehicle(args.family)
    try:
        vehicle_mod.load(o["vehicle"])
    except DdynError as e:
        raise DdynError(f"--vehicle: {e}") from None
    o["ranges"] = args.ranges
    if o["ranges"] is not None:
        if o["sets"].get("kind", "ddm") != "ddm":
            raise DdynError("--ranges sets the Physics Guard's ranges: DDM only (not with --set kind=dpm)")
        read_ranges(o["ranges"])        # a DdynError names the file and the key
    return o


def run(o: dict, out: Path, progress: bool = True) -> dict:
    torch.set_num_threads(1)
    from ddyn.gap.benchmark import families as F

    ok, why = F.available(o["family"])
    if not ok:
        raise DdynError(f"--family {o['family']}: the plant cannot run here: {why}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    v = vehicle_mod.load(o["vehicle"])
    ranges_record = None
    if o["ranges"] is not None:
        v, ranges_record = with_ranges(v, o["ranges"])
    road = road_course(o["road_seed"], o["road_scale"])
    cache = out / "logs"
    recs = []
    for track, seed in (("putnam", LOG_SEEDS[0]), (road, LOG_SEEDS[1])):
        name = getattr(track, "name", track)
        try:
            ds = for_vehicle(plant_log(o["family"], track, seed, o["duration"], o["speed"], cache, o["noise"]), v)
        except DdynError as e:
            raise DdynError(f"the {o['family']} log on {name} at --speed {o['speed']:g}: {e}") from None
        rec = {"name": "putnam", "track": "putnam", "length": _length("putnam"), "about": "the real log's track"} \
            if track == "putnam" else \
            {"name": f"random:{o['road_seed']}", "track": road.name, "length": road.length,
             "about": f"random:{o['road_seed']} x{o['road_scale']:g}, {ROAD_WIDTH:g} m wide",
             "scale": o["road_scale"], "width": ROAD_WIDTH}
        recs.append((ds, rec | {"log_seed": seed, "rows": len(ds), **envelope(ds)}))
    if o["swap"]:
        recs.reverse()
    (a, rec_a), (b, rec_b) = recs
    write_canonical(a, out / "A.csv")
    write_canonical(b, out / "B.csv")
    if progress:
        print(f"logs: A {rec_a['name']} {len(a)} rows, B {rec_b['name']} {len(b)} rows "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    data = {"a": a, "b": b, **splits(a, b)}
    runs = [run_seed(s, data, v, o, out, progress) for s in o["seeds"]]
    resolved = train_config(o["seeds"][0], o["epochs"], o["lbfgs"], o["sets"])
    cfg = asdict(resolved.config)
    cfg.pop("seed")
    origin = {k: src for k, src in resolved.origin.items() if k != "seed"}
    changed = {k: cfg[k] for k, src in origin.items() if src.startswith("--")}
    fc = FinetuneConfig(fit=FitConfig(adam_steps=o["ft_adam"], lbfgs_iterations=o["ft_lbfgs"]))
    from ddyn.learn.training_profile import profile_path

    res = {
        "family": o["family"], "plant": a.metadata.get("plant", ""), "vehicle": v.name, "quick": o["quick"],
        "duration": o["duration"], "speed": o["speed"], "seeds": list(o["seeds"]),
        "tracks": {"A": rec_a, "B": rec_b}, "swap": o["swap"], "noise_scale": o["noise"],
        "rows": data["rows"],
        "settings": {"train": {"config": cfg, "origin": origin, "profile": str(profile_path(PROFILE_VEHICLE)),
                               "origin_text": (", ".join(f"{k} {val}" for k, val in changed.items())
                                               + " given; the rest from the profile or the built-in defaults") if changed
                               else "all from the profile"},
                     "finetune": {"freeze_fraction": fc.freeze_fraction, "lambda1": fc.lambda1,
                                  "lambda2": fc.lambda2, "fit": asdict(fc.fit)},
                     "finetune_text": f"freeze fraction {fc.freeze_fraction}, lambda1 {fc.lambda1}, lambda2 "
                                      f"{fc.lambda2}, {fc.fit.adam_steps} Adam + {fc.fit.lbfgs_iterations} L-BFGS "
                                      f"steps, lr {fc.fit.lr}",
                     "fractions": list(o["fractions"]), "fraction_blocks": o["blocks"],
                     "sets": dict(o["sets"]), "ranges": ranges_record},
        "runs": runs,
        "summary": summarise(runs, o["fractions"]),
        "seconds": time.perf_counter() - t0,
    }
    (out / "results.json").write_text(json.dumps(res, indent=2, default=float))
    (out / "results.md").write_text(markdown(res))
    return res


def envelope(ds: Dataset) -> dict:
    """What the log drives: speed range, |vy| and |vx omega| (lateral acceleration) 95th percentile and max."""
    st = ds.states
    ay = np.abs(st[:, 3] * st[:, 5])
    return {"vx_range": [float(st[:, 3].min()), float(st[:, 3].max())],
            "vy_p95": float(np.percentile(np.abs(st[:, 4]), 95)), "vy_max": float(np.abs(st[:, 4]).max()),
            "ay_p95": float(np.percentile(ay, 95)), "ay_max": float(ay.max())}


def _length(name: str) -> float:
    from ddyn.model.tracks import load_track

    return float(load_track(name).length)


def _run(args) -> int:
    o = options(args)
    out = Path(args.out)
    res = run(o, out, progress=not args.quiet)
    print(markdown(res))
    print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("transfer", help="a DDM trained on one track tested on another, and FTHD on 5-20 per cent "
                              "of the other track, on an independent plant (issue 36)")
    p.add_argument("--family", default="commonroad-mb",
                   help=f"plant family: {', '.join(FAMILIES)} (default %(default)s)")
    p.add_argument("--vehicle", help="model vehicle (default: av21; the MuJoCo saloon's own nominal file for mujoco)")
    p.add_argument("--out", default="out/transfer", help="output directory (default: %(default)s)")
    p.add_argument("--duration", type=float, help=f"s per log (default {DEFAULTS['duration']:g}; quick "
                                                  f"{QUICK['duration']:g})")
    p.add_argument("--speed", type=float, help=f"m/s, the driver's speed cap on both tracks "
                                               f"(default {DEFAULTS['speed']:g})")
    p.add_argument("--road-seed", type=int, default=DEFAULT_ROAD_SEED,
                   help="track B: random:SEED scaled to a full-size road course (default %(default)s)")
    p.add_argument("--road-scale", type=float, default=ROAD_SCALE,
                   help="track B: the random track's scale factor to full size (default %(default)s)")
    p.add_argument("--noise-scale", type=float, default=1.0,
                   help="sensor noise of both logs, times the nominal vehicle's (0: noise-free; default %(default)s)")
    p.add_argument("--swap", action="store_true",
                   help="train on the road course (A) and test on Putnam (B): the other direction")
    p.add_argument("--seeds", type=int, nargs="+", help="training seeds (default 0 1 2; quick 0)")
    p.add_argument("--fractions", type=float, nargs="+", help="shares of B's training part for fine-tuning "
                                                              "(default 0.05 0.1 0.2)")
    p.add_argument("--no-finetune", action="store_true",
                   help="only the model trained on A, scored on both tracks (no FTHD fractions): a candidate "
                        "setting's transfer alone")
    p.add_argument("--fraction-blocks", type=int, default=FRACTION_BLOCKS,
                   help="each fine-tuning fraction as this many equal blocks spread evenly over B's training part "
                        "(1: its first rows; default %(default)s)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="a training setting over the av21 profile's (a TrainConfig field, e.g. guard_prior=0.01, "
                        "kind=dpm); repeatable; recorded in results.json (settings.sets)")
    p.add_argument("--ranges", help="guard ranges file in place of the model vehicle's, as `ddyn train --ranges` "
                                    "takes ({\"Df\": [lo, hi], ...}); recorded with its sha256")
    p.add_argument("--epochs", type=int, help="Adam epochs of every DDM training (default: the av21 profile's)")
    p.add_argument("--lbfgs-iterations", type=int, help="L-BFGS iterations of every DDM training (default: the "
                                                        "av21 profile's)")
    p.add_argument("--ft-adam-steps", type=int, help=f"FTHD Adam steps (default {FitConfig().adam_steps})")
    p.add_argument("--ft-lbfgs-iterations", type=int,
                   help=f"FTHD L-BFGS iterations (default {FitConfig().lbfgs_iterations})")
    p.add_argument("--quick", action="store_true", help="tiny logs and budgets: a smoke run, not the figures")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_run)
