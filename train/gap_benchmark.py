"""`ddyn gap-benchmark`: does `ddyn diagnose` find an effect it was not told about?

Each case: a nominal model identified on effect-free simulated data (per vehicle, once: the
17 coefficients fitted by least squares to one-step predictions of a separate noisy log,
starting from the vehicle file's values perturbed by up to 10 %), and a noisy simulated log
(sensor noise at the vehicle's sensor_noise_std) with one hidden effect of random magnitude
(log-uniform from 0.4 to 4 times the effect's stated detection threshold, capped where the
simulated driver would lose the car, random sign where the effect has one), on a random track and seed; a share of the cases has no effect at all.
The diagnosis runs without being told. Scores: top-1 identification (the first effect the
greedy selection adds, "none" when it adds none) with a confusion matrix; relative error of
the estimated parameter; gap closed against the oracle (the true plant with its true effect):
(E_nominal - E_diagnosed) / (E_nominal - E_oracle) on the held-out normalised one-step MSE;
false alarms (anything selected on an effect-free log); and, per effect, the smallest
magnitude above which it is identified in at least 95 % of the cases.

Targets (the issue's): top-1 >= 95 % above the thresholds, false alarms <= 5 %, median
parameter error <= 15 %, median gap closed >= 90 % of the oracle's.

--real: the Putnam log of the AV-21, split by time: the first part identifies the nominal
coefficients (or a given checkpoint is the nominal), the rest is diagnosed.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from . import diagnose as D
from . import effects as E
from .errors import DdynError
from .model import COEFF_NAMES
from .vehicle import Vehicle, load as load_vehicle

NOISE = 1.0
TRACKS = {"orca_1_43": ("ethz", "ethzMobil"), "av21": ("putnam",)}
LAPS = {"orca_1_43": 3.0, "av21": 1.0}
# stated detection thresholds (|main parameter|) per vehicle: set beforehand from a development sweep
# (magnitudes 0.15-6 x a first guess, other seeds than the benchmark's): the smallest magnitude from which
# the effect was identified in (nearly) every development case
THRESHOLDS = {
    "orca_1_43": {"steer_delay": 0.012, "throttle_delay": 0.02, "steer_lag": 0.01, "bank_angle": 0.008,
                  "grade": 0.02, "downforce": 0.012, "combined_slip": 0.5, "tire_relaxation": 0.015,
                  "tire_wear": 0.002, "yaw_rate_bias": 0.03, "mass_offset": 0.04},
    "av21": {"steer_delay": 0.025, "throttle_delay": 0.12, "steer_lag": 0.01, "bank_angle": 0.01,
             "grade": 0.025, "downforce": 1e-4, "combined_slip": 0.8, "tire_relaxation": 0.6,
             "tire_wear": 0.001, "yaw_rate_bias": 0.004, "mass_offset": 0.15},
}
# largest magnitudes drawn: beyond these the simulator's driver loses the car (or the delay leaves the fit's range)
MAX_MAGNITUDE = {
    "orca_1_43": {"combined_slip": 1.0, "tire_relaxation": 0.04, "tire_wear": 0.008},
    "av21": {"throttle_delay": 0.45, "combined_slip": 1.8, "tire_wear": 0.0025, "mass_offset": 0.5},
}
SIGNED = ("bank_angle", "grade", "yaw_rate_bias", "mass_offset")
NONE = "none"
IDENT_SEED = 9000


# ----------------------------------------------------------------------------------------------- nominal

def identify(vehicle: Vehicle, ds, start: np.ndarray, fit_fraction: float = 0.95) -> np.ndarray:
    """The 17 coefficients fitted (as factors within +-50 % of `start`) to one-step predictions of ds."""
    nominal = D.nominal_from_vehicle(vehicle, ds, start)
    prob = D.Problem(ds, nominal, fit_fraction, refit=COEFF_NAMES)
    f = D.fit(prob, ())
    return start * (1.0 + f.rho)


def identified_nominal(vehicle: Vehicle) -> tuple[np.ndarray, dict]:
    from .simulate import simulate

    track = TRACKS[vehicle.name][0]
    ds = simulate(vehicle, track, laps=LAPS[vehicle.name], seed=IDENT_SEED, noise_scale=NOISE, progress=False)
    rng = np.random.default_rng(IDENT_SEED)
    truth = vehicle.true_vector()
    start = truth * (1.0 + 0.1 * rng.uniform(-1, 1, len(truth)))
    t0 = time.perf_counter()
    c = identify(vehicle, ds, start)
    rel = {n: float((c[i] - truth[i]) / truth[i]) for i, n in enumerate(COEFF_NAMES)}
    return c, {"track": track, "seed": IDENT_SEED, "rows": len(ds), "seconds": time.perf_counter() - t0,
               "relative_error": rel}


# ----------------------------------------------------------------------------------------------- cases

def plan(n: int, seed: int = 0, vehicles=("orca_1_43", "av21")) -> list[dict]:
    """n cases: effects cycled (two 'none' slots in 13), magnitudes log-uniform over 0.4-4 x threshold."""
    rng = np.random.default_rng(seed)
    slots = list(E.EFFECT_NAMES) + [NONE, NONE]
    cases = []
    for i in range(n):
        v = vehicles[0] if i % 3 != 2 else vehicles[-1]    # two of three cases on the first vehicle
        eff = slots[i % len(slots)]
        track = str(rng.choice(TRACKS[v]))
        mag = 0.0
        if eff != NONE:
            lo = 0.4 * THRESHOLDS[v][eff]
            hi = min(4.0 * THRESHOLDS[v][eff], MAX_MAGNITUDE[v].get(eff, math.inf))
            mag = math.exp(rng.uniform(math.log(lo), math.log(hi)))
            if eff in SIGNED and rng.uniform() < 0.5:
                mag = -mag
        cases.append({"case": i, "vehicle": v, "track": track, "effect": eff, "magnitude": mag,
                      "seed": int(1000 + seed * 100000 + i)})
    return cases


def _normalised_mse(rmse: dict, scale: dict) -> float:
    return float(np.mean([(rmse[c] / scale[c]) ** 2 for c in D.CHANNELS]))


def oracle_error(ds, vehicle: Vehicle, case: dict, diag: dict) -> dict:
    """Held-out one-step RMSE and ADE of the true plant (true coefficients and the true effect)."""
    nominal = D.nominal_from_vehicle(vehicle, ds)
    prob = D.Problem(ds, nominal, diag["split"]["fit_fraction"], refit=())
    values = {} if case["effect"] == NONE else {case["effect"]: case["magnitude"]}
    steps = max(1, int(round(vehicle.evaluation_horizon / ds.sample_time)))
    starts = D._starts(prob, prob.rows_held, steps, 400)
    h = D.heldout_summary(prob, values, np.zeros(0), starts, steps)
    return {"rmse": D._chan(h["rmse"]), "ade": h["ade"]}


def run_case(case: dict, vehicle: Vehicle, nominal_coeffs: np.ndarray, tries: int = 3) -> dict:
    from .simulate import simulate

    eff = None if case["effect"] == NONE else {case["effect"]: case["magnitude"]}
    ds, err = None, None
    seed = case["seed"]
    for k in range(tries):
        try:
            ds = simulate(vehicle, case["track"], laps=LAPS[vehicle.name], seed=seed, noise_scale=NOISE,
                          progress=False, effects=eff)
            break
        except DdynError as e:   # the hidden effect made the driver lose the car: another seed
            err, seed = str(e), seed + 7919
    out = dict(case)
    if ds is None:
        return out | {"status": "simulation failed", "error": err}
    t0 = time.perf_counter()
    diag = D.diagnose(ds, D.nominal_from_vehicle(vehicle, ds, nominal_coeffs))
    seconds = time.perf_counter() - t0
    top1 = diag["selected"][0] if diag["selected"] else NONE
    est = None
    if case["effect"] != NONE:
        chosen = [e for e in diag["model"]["effects"] if e["effect"] == case["effect"]]
        pick = chosen[0] if chosen else next(c for c in diag["candidates"] if c["effect"] == case["effect"])
        est = next(iter(pick["params"].values()))
    orc = oracle_error(ds, vehicle, case, diag)
    scale = diag["method"]["channel_scale"]
    h = diag["model"]["heldout"]
    e_nom, e_diag, e_orc = (_normalised_mse(h["rmse_before"], scale), _normalised_mse(h["rmse_after"], scale),
                            _normalised_mse(orc["rmse"], scale))
    gap = (e_nom - e_diag) / (e_nom - e_orc) if e_nom - e_orc > 1e-12 * e_nom else None
    return out | {
        "status": "ok", "seed_used": seed, "rows": len(ds), "selected": diag["selected"], "top1": top1,
        "correct": top1 == case["effect"], "estimate": est,
        "param_error": abs(est - case["magnitude"]) / abs(case["magnitude"]) if est is not None else None,
        "gap_vs_oracle": gap, "e_nominal": e_nom, "e_diagnosed": e_diag, "e_oracle": e_orc,
        "ade": {"nominal": h["ade_before"], "diagnosed": h["ade_after"], "oracle": orc["ade"]},
        "delta_bic_top": diag["candidates"][0]["delta_bic"], "top_candidate": diag["candidates"][0]["effect"],
        "diagnose_seconds": seconds,
    }


# ----------------------------------------------------------------------------------------------- scoring

def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def reliable_threshold(rows: list[dict], rate: float = 0.95, min_cases: int = 3) -> float | None:
    """Smallest |magnitude| m such that cases with |magnitude| >= m are identified at >= rate (>= min_cases)."""
    rows = sorted(rows, key=lambda r: abs(r["magnitude"]))
    best = None
    for i in range(len(rows) - min_cases, -1, -1):
        tail = rows[i:]
        if np.mean([r["correct"] for r in tail]) >= rate:
            best = abs(rows[i]["magnitude"])
        else:
            break
    return best


def score(results: list[dict]) -> dict:
    ok = [r for r in results if r["status"] == "ok"]
    none = [r for r in ok if r["effect"] == NONE]
    eff = [r for r in ok if r["effect"] != NONE]
    above = [r for r in eff if abs(r["magnitude"]) >= THRESHOLDS[r["vehicle"]][r["effect"]]]
    good = [r for r in above if r["correct"]]
    labels = list(E.EFFECT_NAMES) + [NONE]
    conf = {t: {p: 0 for p in labels} for t in labels}
    for r in above + none:
        conf[r["effect"]][r["top1"] if r["top1"] in labels else NONE] += 1
    per = {}
    for v in THRESHOLDS:
        for e in E.EFFECT_NAMES:
            rows = [r for r in eff if r["vehicle"] == v and r["effect"] == e]
            if not rows:
                continue
            ab = [r for r in rows if abs(r["magnitude"]) >= THRESHOLDS[v][e]]
            per[f"{v}/{e}"] = {
                "vehicle": v, "effect": e, "stated_threshold": THRESHOLDS[v][e], "cases": len(rows),
                "above": len(ab), "top1_above": float(np.mean([r["correct"] for r in ab])) if ab else None,
                "top1_all": float(np.mean([r["correct"] for r in rows])),
                "reliable_from": reliable_threshold(rows),
                "median_param_error": _median([r["param_error"] for r in ab if r["correct"]]),
                "median_gap_vs_oracle": _median([r["gap_vs_oracle"] for r in ab if r["correct"]]),
            }
    s = {
        "cases": len(results), "simulated": len(ok), "simulation_failed": len(results) - len(ok),
        "effect_cases": len(eff), "above_threshold": len(above), "none_cases": len(none),
        "top1_above_threshold": len(good) / len(above) if above else None,
        "top1_all_effect_cases": float(np.mean([r["correct"] for r in eff])) if eff else None,
        "false_alarm_rate": float(np.mean([bool(r["selected"]) for r in none])) if none else None,
        "median_param_error": _median([r["param_error"] for r in good]),
        "median_gap_vs_oracle": _median([r["gap_vs_oracle"] for r in good]),
        "mean_diagnose_seconds": _median([r["diagnose_seconds"] for r in ok]),
    }
    s["targets"] = {
        "top1_above_threshold >= 0.95": s["top1_above_threshold"] is not None and s["top1_above_threshold"] >= 0.95,
        "false_alarm_rate <= 0.05": s["false_alarm_rate"] is not None and s["false_alarm_rate"] <= 0.05,
        "median_param_error <= 0.15": s["median_param_error"] is not None and s["median_param_error"] <= 0.15,
        "median_gap_vs_oracle >= 0.90": s["median_gap_vs_oracle"] is not None and s["median_gap_vs_oracle"] >= 0.9,
    }
    return {"summary": s, "per_effect": per, "confusion": conf}


def _f(x, pct=False) -> str:
    if x is None:
        return "-"
    if pct:
        return f"{100 * x:.0f} %"
    return f"{x:.3g}"


def markdown(sc: dict, nominal_info: dict, seconds: float) -> str:
    s = sc["summary"]
    t = s["targets"]
    yes = lambda k: "**met**" if t[k] else "**not met**"  # noqa: E731
    lines = [
        f"{s['cases']} cases ({s['simulation_failed']} could not be simulated), {s['effect_cases']} with a hidden "
        f"effect ({s['above_threshold']} at or above the stated threshold), {s['none_cases']} effect-free; "
        f"{seconds / 60:.1f} min.", "",
        "| metric | result | target | |", "|---|---|---|---|",
        f"| top-1 identification above the thresholds | {_f(s['top1_above_threshold'], True)} | >= 95 % | "
        f"{yes('top1_above_threshold >= 0.95')} |",
        f"| top-1 over all effect cases (incl. below threshold) | {_f(s['top1_all_effect_cases'], True)} | | |",
        f"| false alarms on effect-free logs | {_f(s['false_alarm_rate'], True)} | <= 5 % | "
        f"{yes('false_alarm_rate <= 0.05')} |",
        f"| median parameter error (identified, above threshold) | {_f(s['median_param_error'], True)} | <= 15 % | "
        f"{yes('median_param_error <= 0.15')} |",
        f"| median gap closed vs the oracle | {_f(s['median_gap_vs_oracle'], True)} | >= 90 % | "
        f"{yes('median_gap_vs_oracle >= 0.90')} |", "",
        "| vehicle | effect | stated threshold | cases (above) | top-1 above | top-1 all | reliable from | "
        "param error | gap vs oracle |", "|---|---|---|---|---|---|---|---|---|"]
    for k, p in sc["per_effect"].items():
        lines.append(f"| {p['vehicle']} | {p['effect']} | {p['stated_threshold']:.3g} {E.UNITS[p['effect']]} | "
                     f"{p['cases']} ({p['above']}) | {_f(p['top1_above'], True)} | {_f(p['top1_all'], True)} | "
                     f"{_f(p['reliable_from'])} | {_f(p['median_param_error'], True)} | "
                     f"{_f(p['median_gap_vs_oracle'], True)} |")
    labels = list(E.EFFECT_NAMES) + [NONE]
    short = {n: "".join(w[0] for w in n.split("_")) for n in labels}
    short[NONE] = "none"
    lines += ["", "Confusion (rows: hidden effect, cases at or above threshold and effect-free; columns: top-1 "
              "found; " + ", ".join(f"{short[n]} = {n}" for n in labels[:-1]) + ")", "",
              "| hidden \\ found | " + " | ".join(short[n] for n in labels) + " |",
              "|---|" + "---|" * len(labels)]
    for a in labels:
        row = sc["confusion"][a]
        if sum(row.values()) == 0:
            continue
        lines.append(f"| {a} | " + " | ".join(str(row[b]) if row[b] else "." for b in labels) + " |")
    lines += ["", "Nominal models identified on effect-free logs: " + "; ".join(
        f"{v}: {i['rows']} rows of {i['track']}, median |coefficient error| "
        f"{100 * float(np.median(np.abs(list(i['relative_error'].values())))):.2g} %"
        for v, i in nominal_info.items())]
    return "\n".join(lines) + "\n"


def detection_plot(results: list[dict], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 4, figsize=(14, 9))
    for ax, e in zip(axes.ravel(), E.EFFECT_NAMES):
        for v, mk in (("orca_1_43", "o"), ("av21", "s")):
            rows = [r for r in results if r["status"] == "ok" and r["effect"] == e and r["vehicle"] == v]
            if not rows:
                continue
            x = np.array([abs(r["magnitude"]) / THRESHOLDS[v][e] for r in rows])
            y = np.array([1.0 if r["correct"] else 0.0 for r in rows]) + (0.03 if v == "av21" else -0.03)
            ax.scatter(x, y, marker=mk, c=["C2" if r["correct"] else "C3" for r in rows], s=18, label=v)
        ax.axvline(1.0, color="0.5", ls="--")
        ax.set_xscale("log")
        ax.set_yticks([0, 1], ["missed", "found"])
        ax.set_title(e, fontsize=9)
    axes.ravel()[-1].axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.supxlabel("magnitude / stated threshold")
    fig.tight_layout()
    path = out / "detection.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run(n_cases: int, out: Path, seed: int = 0, progress: bool = True) -> dict:
    import torch

    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    vehicles = {name: load_vehicle(name) for name in THRESHOLDS}
    nominal, info = {}, {}
    for name, v in vehicles.items():
        nominal[name], info[name] = identified_nominal(v)
    cases = plan(n_cases, seed)
    results = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(cases), desc="gap-benchmark")
    for c in cases:
        results.append(run_case(c, vehicles[c["vehicle"]], nominal[c["vehicle"]]))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    sc = score(results)
    md = markdown(sc, info, seconds)
    detection_plot(results, out)
    doc = {"settings": {"cases": n_cases, "seed": seed, "noise_scale": NOISE, "laps": LAPS, "tracks": TRACKS,
                        "thresholds": THRESHOLDS, "max_magnitude": MAX_MAGNITUDE}, "nominal": info, **sc, "results": results, "seconds": seconds}
    (out / "results.json").write_text(json.dumps(doc, indent=2, default=float))
    (out / "results.md").write_text(md + "\n![detection](detection.png)\n")
    return doc | {"markdown": md}


# ----------------------------------------------------------------------------------------------- real data

def run_real(out: Path, model: str | None = None, ident_fraction: float = 0.5) -> dict:
    """Nominal from the first part of the Putnam log (or a checkpoint); diagnose the rest."""
    from .importers import load_any
    from .paths import shared_data_dir

    src = shared_data_dir() / "real" / "Putnam_park2023_run4_2.csv"
    if not src.is_file():
        raise DdynError(f"real log not found: {src}")
    out.mkdir(parents=True, exist_ok=True)
    ds = load_any(src)
    cut = int(len(ds) * ident_fraction)
    first, rest = ds.subset(slice(0, cut)), ds.subset(slice(cut, None))
    v = load_vehicle("av21")
    reports = {}
    if model:
        nominal = D.nominal_from_checkpoint(model, rest)
        label = f"checkpoint {Path(model).name}"
    else:
        t0 = time.perf_counter()
        c = identify(v, first, v.true_vector())
        nominal = D.nominal_from_vehicle(v, rest, c)
        nominal.label = f"av21 coefficients identified on the first {100 * ident_fraction:.0f} % of the log " \
                        f"({time.perf_counter() - t0:.1f} s)"
        label = "identified"
        reports["vehicle_file"] = D.diagnose(rest, D.nominal_from_vehicle(v, rest), track=D._track("putnam", rest))
        D.write_report(reports["vehicle_file"], out / "vehicle_file")
    d = D.diagnose(rest, nominal, track=D._track("putnam", rest))
    D.write_report(d, out / label)
    reports[label] = d
    summary = {k: {"selected": r["selected"], "verdict": r["verdict"], "model": r["model"],
                   "where": r["where"]["summary"], "candidates": [
                       {"effect": c["effect"], "params": c["params"], "uncertainty": c["uncertainty"],
                        "delta_bic": c["delta_bic"], "gap_closed_pct": c["gap_closed_pct"]} for c in r["candidates"]]}
               for k, r in reports.items()}
    (out / "real.json").write_text(json.dumps(summary, indent=2, default=float))
    return summary


def real_markdown(summary: dict) -> str:
    lines = []
    for k, r in summary.items():
        h = r["model"]["heldout"]
        lines += [f"**Nominal: {k}** — selected: {', '.join(r['selected']) or 'none'} ({r['verdict']})", "",
                  f"held-out one-step RMSE vx {h['rmse_before']['vx']:.3g} -> {h['rmse_after']['vx']:.3g} m/s, "
                  f"vy {h['rmse_before']['vy']:.3g} -> {h['rmse_after']['vy']:.3g} m/s, omega "
                  f"{h['rmse_before']['omega']:.3g} -> {h['rmse_after']['omega']:.3g} rad/s; ADE "
                  f"{h['ade_before']:.3g} -> {h['ade_after']:.3g} m; gap closed {_f(r['model']['gap_closed_pct'])} %",
                  ""] + [f"- where: {s}" for s in r["where"]] + [""]
        lines += ["| effect | estimate | +- | dBIC | gap closed % |", "|---|---|---|---|---|"]
        for c in r["candidates"][:6]:
            (pn, pv), = c["params"].items()
            lines.append(f"| {c['effect']} | {pn} = {pv:.4g} | {c['uncertainty'][pn]:.2g} | {c['delta_bic']:.1f} | "
                         f"{_f(c['gap_closed_pct'])} |")
        lines.append("")
    return "\n".join(lines)


def _run(args) -> int:
    out = Path(args.out)
    if args.real:
        summary = run_real(out, args.model)
        md = real_markdown(summary)
        (out / "real.md").write_text(md)
        print(md)
        print(f"wrote {out / 'real.json'} and {out / 'real.md'}")
        return 0
    n = args.cases or (26 if args.quick else 390)
    doc = run(n, out, args.seed, progress=not args.no_progress)
    print(doc["markdown"])
    print(f"wrote {out / 'results.json'}, {out / 'results.md'} and {out / 'detection.png'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("gap-benchmark", help="hidden-effect benchmark of ddyn diagnose (and --real: the "
                                                    "Putnam log)", description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=None, help="number of cases (default 390; --quick 26)")
    p.add_argument("--out", default="runs/gap_benchmark", help="output directory")
    p.add_argument("--quick", action="store_true", help="a small run (26 cases)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--real", action="store_true", help="diagnose the Putnam log: nominal from its first half "
                                                       "(or --model), diagnosis on the rest")
    p.add_argument("--model", default=None, help="with --real: a DDM checkpoint as the nominal model")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run)
