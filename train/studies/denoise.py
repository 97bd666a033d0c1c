"""`ddyn study denoise`: does denoising the training data (Savitzky-Golay, EKF-FTHD) give a better DDM?

  sim   1:43 car, where the clean signal is known. Training data: 3 laps of ETHZ (seed 1) with
        two noise conditions on vx, vy, omega:
          white            the simulator's white noise, noise_scale 1 (std = the vehicle's
                           sensor_noise_std: 0.01 m/s, 0.005 m/s, 0.05 rad/s);
          white+coloured   the same plus first-order Gauss-Markov (AR(1)) noise added here,
                           n_{k+1} = phi n_k + sqrt(1 - phi^2) sigma e_k, stationary std sigma =
                           COLOURED_STD_FACTOR x sensor_noise_std per channel (0.01 m/s, 0.005 m/s,
                           0.05 rad/s) and correlation time COLOURED_TAU = 0.1 s (phi = 0.819 at 50 Hz):
                           slowly wandering errors such as a velocity estimate differentiated from
                           filtered positions, or IMU bias drift.
        Arms: raw; Savitzky-Golay; EKF-FTHD: round 1 runs `ddyn denoise --method ekf --finetune all`
        on the raw data with the DDM trained on the raw data (Q, R and all the DDM's weights fitted
        on the innovation NLL, then the iterated smoother) and trains a fresh DDM on the smoothed
        output; each further round (FTHD_ROUNDS in all) does the same starting from the previous
        round's DDM; EKF-FTHD + AR(1): the same with the filter's coloured-noise states. Each arm's signal is compared with the clean truth (RMSE per channel)
        and a DDM trained on it is evaluated on clean laps of ETHZMobil (seed 2) and, to check what a
        noisy test set says, on the same laps with the same kind of noise. References (not arms): a
        DDM trained on the clean signal, and the filters run with the vehicle's true coefficients.
  real  the Putnam log (AV-21): the first 80 % of rows train (each arm denoises them; DDMs as in
        sim; one more arm: one EKF-FTHD round with the paper's Q 0.1-1, R 0.01-1 ranges), the last
        20 % test, raw and denoised by each method (Savitzky-Golay with the windows
        chosen on the training part; EKF with the arm's final DDM and the Q, R learned on the
        training part, not refitted). Every DDM is evaluated on every version of the test block.

DDM budget, equal for every arm: TrainConfig defaults except epochs 100 and 500 L-BFGS iterations
(--quick: a smoke run on tiny data). Writes DIR/results.json and DIR/results.md (and per arm the
denoised training data, checkpoint and denoise report under DIR/sim, DIR/real).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ddyn.data import simulate
from ddyn.data.dataset import Dataset, write_canonical
from ddyn.errors import DdynError
from ddyn.learn import checkpoint
from ddyn.learn import denoise as dn
from ddyn.learn.ekf_layer import CHANNELS, PAPER_REAL_RANGES
from ddyn.learn.evaluate import evaluate, public
from ddyn.learn.training import TrainConfig, train
from ddyn.model import tracks
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.single_track import COEFF_NAMES
from ddyn.paths import shared_data_dir

COLOURED_TAU = 0.1          # s, correlation time of the added AR(1) noise
COLOURED_STD_FACTOR = 1.0   # stationary std as a multiple of the vehicle's sensor_noise_std
FTHD_ROUNDS = 2
REAL_LOG = ("real", "Putnam_park2023_run4_2.csv")


@dataclass(frozen=True)
class Budget:
    train_laps: float = 3
    test_laps: float = 2
    epochs: int = 100
    lbfgs_iterations: int = 500
    rounds: int = FTHD_ROUNDS
    ekf: dn.EKFSettings = field(default_factory=lambda: dn.EKFSettings(finetune="all"))
    real_train_rows: int | None = None
    real_test_rows: int | None = None

    def config(self) -> TrainConfig:
        return TrainConfig(epochs=self.epochs, lbfgs_iterations=self.lbfgs_iterations)


FULL = Budget()
QUICK = Budget(train_laps=0.2, test_laps=0.2, epochs=2, lbfgs_iterations=0, rounds=1,
               ekf=dn.EKFSettings(relinearisations=1, iterations=(1,), chunk=40, finetune="all",
                                  finetune_iterations=(2,)),
               real_train_rows=200, real_test_rows=80)


def add_coloured_noise(ds: Dataset, vehicle, seed: int, tau: float = COLOURED_TAU,
                       std_factor: float = COLOURED_STD_FACTOR) -> Dataset:
    """A copy of ds with stationary AR(1) noise added to vx, vy, omega, independently per segment
    and channel (std std_factor x sensor_noise_std, correlation time tau)."""
    rng = np.random.default_rng(seed)
    sigma = std_factor * np.array([vehicle.sensor_noise_std[c] for c in CHANNELS])
    phi = float(np.exp(-ds.sample_time / tau))
    noise = np.empty((len(ds), 3))
    for a, b in dn._segments(ds.segment):
        e = rng.standard_normal((b - a, 3)) * sigma
        noise[a] = e[0]
        for k in range(a + 1, b):
            noise[k] = phi * noise[k - 1] + np.sqrt(1 - phi ** 2) * e[k - a]
    states = ds.states.copy()
    states[:, list(dn.VEL)] += noise
    meta = dict(ds.metadata)
    meta["coloured_noise"] = f"AR(1) tau {tau} s, std {sigma.tolist()} on vx, vy, omega, seed {seed}"
    return Dataset(ds.time.copy(), ds.segment.copy(), states, ds.inputs.copy(), ds.sample_time, ds.vehicle,
                   ds.source, {k: v.copy() for k, v in ds.extras.items()}, meta)


def signal_rmse(ds: Dataset) -> dict | None:
    if not all(f"true_{c}" in ds.extras for c in CHANNELS):
        return None
    return {c: float(np.sqrt(np.mean((ds.states[:, col] - ds.extras[f"true_{c}"]) ** 2)))
            for c, col in zip(CHANNELS, dn.VEL)}


def _train_ddm(ds: Dataset, vehicle, cfg: TrainConfig, folder: Path) -> tuple[torch.nn.Module, dict, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    write_canonical(ds, folder / "train.csv")
    r = train(ds, vehicle, cfg, progress=False)
    ckpt = checkpoint.make(r, vehicle, ds.content_hash(), str(folder / "train.csv"), len(ds))
    path = checkpoint.save(ckpt, folder / "model.ckpt")
    return r.model, ckpt, path


def _metrics(model, ckpt, ds: Dataset) -> dict:
    m = public(evaluate(model, ckpt, ds))
    return {"rmse": m["rmse"], "ade": m["ade"], "fde": m["fde"], "samples": m["samples"]}


def _save_report(report: dict, path: Path) -> dict:
    clean = {k: v for k, v in report.items() if not k.startswith("_")}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean, indent=2))
    return clean


def _fthd(raw: Dataset, vehicle, budget: Budget, first_ckpt: Path, folder: Path, coloured: bool,
          label: str, rounds: int | None = None, **settings_override) -> list[dict]:
    """EKF-FTHD rounds: filter with the current DDM, train a DDM on the result, repeat."""
    ckpt_path, out = first_ckpt, []
    for r in range(budget.rounds if rounds is None else rounds):
        sub = folder / f"round{r + 1}"
        source = dn.source_from_checkpoint(ckpt_path)
        settings = replace(budget.ekf, coloured=coloured, **settings_override)
        t0 = time.perf_counter()
        den, report = dn.denoise(raw, "ekf", source, settings)
        seconds = time.perf_counter() - t0
        tuned = None
        if settings.finetune:   # the DDM as fine-tuned inside the filter (a by-product, saved beside)
            tuned_ckpt = dict(source.extra["ckpt"])
            tuned_ckpt["state_dict"] = {k: t.detach().clone() for k, t in source.model.state_dict().items()}
            checkpoint.save(tuned_ckpt, sub / "finetuned_in_filter.ckpt")
            tuned = (source.model, tuned_ckpt)
        model, ckpt, ckpt_path = _train_ddm(den, vehicle, budget.config(), sub)
        out.append({"label": f"{label} (round {r + 1})", "data": den, "model": model, "ckpt": ckpt,
                       "ckpt_path": ckpt_path, "report": _save_report(report, sub / "denoise.json"),
                       "layer_state": report["_layer_state"], "denoise_seconds": seconds, "tuned": tuned})
    return out


# ----------------------------------------------------------------------------- sim

def run_sim(out: Path, budget: Budget) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    v = vehicle_mod.load("orca_1_43")
    train_white = simulate.simulate(v, tracks.load_track("ethz"), laps=budget.train_laps, seed=1, noise_scale=1.0,
                                    progress=False)
    test_clean = simulate.simulate(v, tracks.load_track("ethzMobil"), laps=budget.test_laps, seed=2, progress=False)
    test_white = simulate.simulate(v, tracks.load_track("ethzMobil"), laps=budget.test_laps, seed=2,
                                   noise_scale=1.0, progress=False)
    conditions = {"white": (train_white, test_white),
                  "white+coloured": (add_coloured_noise(train_white, v, seed=11),
                                     add_coloured_noise(test_white, v, seed=12))}
    cfg = budget.config()
    result: dict = {"noise": {"white_std": {c: v.sensor_noise_std[c] for c in CHANNELS},
                              "coloured": {"tau_s": COLOURED_TAU, "std": {c: COLOURED_STD_FACTOR * v.sensor_noise_std[c]
                                                                           for c in CHANNELS}}},
                    "rows": {"train": len(train_white), "test": len(test_clean)}, "conditions": {}}
    clean = dn.assemble(train_white, np.column_stack([train_white.extras[f"true_{c}"] for c in CHANNELS]), "clean")
    model, ckpt, _ = _train_ddm(clean, v, cfg, out / "clean")
    result["reference_clean_ddm"] = {"clean_test": _metrics(model, ckpt, test_clean)}
    truth_source = dn.source_from_vehicle(v)
    for cond, (train_ds, test_noisy) in conditions.items():
        folder = out / cond.replace("+", "_")
        arms: list[dict] = []
        # raw
        model, ckpt, raw_ckpt = _train_ddm(train_ds, v, cfg, folder / "raw")
        arms.append({"label": "raw", "data": train_ds, "model": model, "ckpt": ckpt})
        # Savitzky-Golay
        sg, sg_report = dn.denoise(train_ds, "savgol")
        model, ckpt, _ = _train_ddm(sg, v, cfg, folder / "savgol")
        arms.append({"label": "Savitzky-Golay", "data": sg, "model": model, "ckpt": ckpt,
                     "report": _save_report(sg_report, folder / "savgol" / "denoise.json")})
        arms += _fthd(train_ds, v, budget, raw_ckpt, folder / "ekf", False, "EKF-FTHD")
        arms += _fthd(train_ds, v, budget, raw_ckpt, folder / "ekf_ar1", True, "EKF-FTHD + AR(1)")
        rows = []
        for arm in arms:
            row = {"label": arm["label"], "signal_rmse": signal_rmse(arm["data"]),
                   "clean_test": _metrics(arm["model"], arm["ckpt"], test_clean),
                   "noisy_test": _metrics(arm["model"], arm["ckpt"], test_noisy)}
            if "report" in arm:
                row["denoise"] = {k: arm["report"].get(k) for k in ("q", "r", "window", "coloured_phi",
                                                                     "coloured_var", "q_at_bound", "r_at_bound")
                                  if arm["report"].get(k) is not None}
            if "denoise_seconds" in arm:
                row["denoise_seconds"] = arm["denoise_seconds"]
            if arm.get("tuned"):
                row["finetuned_in_filter_clean_test"] = _metrics(*arm["tuned"], test_clean)
            rows.append(row)
        oracle = []
        for label, coloured in (("EKF, true coefficients", False), ("EKF + AR(1), true coefficients", True)):
            den, rep = dn.denoise(train_ds, "ekf", truth_source, replace(budget.ekf, coloured=coloured))
            oracle.append({"label": label, "signal_rmse": signal_rmse(den), "q": rep["q"], "r": rep["r"],
                           "coloured_phi": rep.get("coloured_phi")})
        result["conditions"][cond] = {"arms": rows, "oracle_filters": oracle}
    return result


# ----------------------------------------------------------------------------- real

def run_real(out: Path, budget: Budget) -> dict:
    from ddyn.data.importers import load_any

    out.mkdir(parents=True, exist_ok=True)
    src = shared_data_dir().joinpath(*REAL_LOG)
    if not src.is_file():
        raise DdynError(f"real log not found: {src} (set DDYN_SHARED_DATA)")
    ds = load_any(src)
    v = vehicle_mod.load(ds.vehicle)
    cut = int(len(ds) * 0.8)
    train_raw, test_raw = ds.subset(slice(0, cut)), ds.subset(slice(cut, None))
    if budget.real_train_rows:
        train_raw = train_raw.subset(slice(0, budget.real_train_rows))
    if budget.real_test_rows:
        test_raw = test_raw.subset(slice(0, budget.real_test_rows))
    cfg = budget.config()
    arms: list[dict] = []
    model, ckpt, raw_ckpt = _train_ddm(train_raw, v, cfg, out / "raw")
    arms.append({"label": "raw", "data": train_raw, "model": model, "ckpt": ckpt})
    sg, sg_report = dn.denoise(train_raw, "savgol")
    model, ckpt, _ = _train_ddm(sg, v, cfg, out / "savgol")
    arms.append({"label": "Savitzky-Golay", "data": sg, "model": model, "ckpt": ckpt,
                 "report": _save_report(sg_report, out / "savgol" / "denoise.json")})
    ekf_rounds = _fthd(train_raw, v, budget, raw_ckpt, out / "ekf", False, "EKF-FTHD")
    arms += ekf_rounds
    arms += _fthd(train_raw, v, budget, raw_ckpt, out / "ekf_paper_ranges", False, "EKF-FTHD, paper Q/R ranges",
                  rounds=1, ranges=PAPER_REAL_RANGES)
    # test versions: raw, Savitzky-Golay (training windows), EKF (final DDM, training Q and R)
    segs = dn._segments(test_raw.segment)
    sg_test = np.column_stack([dn.savgol_apply(test_raw.states[:, col], segs, sg_report["window"][c])
                               for c, col in zip(CHANNELS, dn.VEL)])
    final = ekf_rounds[-1]
    ekf_settings = replace(budget.ekf, learn=False, state=final["layer_state"])
    phys, std, ekf_test_report = dn.ekf_denoise(test_raw, dn.source_from_checkpoint(final["ckpt_path"]), ekf_settings)
    tests = {"raw": test_raw, "Savitzky-Golay": dn.assemble(test_raw, sg_test, "savgol"),
             "EKF-FTHD": dn.assemble(test_raw, phys, "ekf", std)}
    for name, t in tests.items():
        write_canonical(t, out / f"test_{name.split()[0].lower().replace('-', '_')}.csv")
    rows = []
    for arm in arms:
        noise = arm["data"].states[:, list(dn.VEL)] - train_raw.states[:, list(dn.VEL)]
        row = {"label": arm["label"], "tests": {n: _metrics(arm["model"], arm["ckpt"], t) for n, t in tests.items()},
               "removed_std": dict(zip(CHANNELS, noise.std(axis=0).tolist()))}
        if "report" in arm:
            row["denoise"] = {k: arm["report"].get(k) for k in ("q", "r", "window", "q_at_bound", "r_at_bound")
                              if arm["report"].get(k) is not None}
        if "denoise_seconds" in arm:
            row["denoise_seconds"] = arm["denoise_seconds"]
        if arm.get("tuned"):
            row["finetuned_in_filter_raw_test"] = _metrics(*arm["tuned"], tests["raw"])
        rows.append(row)
    # suggested coefficient ranges: the final EKF-FTHD DDM's estimates on its denoised training data
    est = dn.ddm_estimates(final["model"], final["data"], cfg.tau)
    ranges = dn.suggest_ranges(est, v)
    (out / "suggested_ranges.json").write_text(json.dumps(ranges, indent=2))
    return {"rows": {"train": len(train_raw), "test": len(test_raw)}, "arms": rows,
            "test_denoise": {"savgol_window": sg_report["window"], "ekf_q": ekf_test_report["q"],
                             "ekf_r": ekf_test_report["r"]},
            "suggested_ranges": ranges}


# ----------------------------------------------------------------------------- report

def _f(x) -> str:
    if x is None:
        return "-"
    return f"{x:.3g}" if abs(x) >= 1e-2 else f"{x:.2e}"


def _best(values: list[float]) -> int:
    return int(np.argmin(values))


def markdown(sim: dict | None, real: dict | None, seconds: float, quick: bool) -> str:
    L: list[str] = []
    if quick:
        L += ["*Quick smoke run (tiny data, a few epochs): the figures mean nothing.*", ""]
    if sim:
        n = sim["noise"]
        L += [f"### Simulated 1:43 car (train: {sim['rows']['train']} rows of ETHZ; test: {sim['rows']['test']} "
              "rows of ETHZMobil)", "",
              "Noise on vx, vy, omega: white std " + ", ".join(f"{c} {n['white_std'][c]:g}" for c in CHANNELS)
              + "; coloured AR(1) (condition white+coloured, added on top) std "
              + ", ".join(f"{c} {n['coloured']['std'][c]:g}" for c in CHANNELS)
              + f", correlation time {n['coloured']['tau_s']:g} s.", ""]
        ref = sim["reference_clean_ddm"]["clean_test"]
        for cond, block in sim["conditions"].items():
            arms = block["arms"]
            L += [f"**{cond}: the denoised training signal against the clean truth** (RMSE)", "",
                  "| signal | vx (m/s) | vy (m/s) | omega (rad/s) |", "|---|---|---|---|"]
            for a in arms:
                s = a["signal_rmse"]
                L.append(f"| {a['label']} | {_f(s['vx'])} | {_f(s['vy'])} | {_f(s['omega'])} |")
            for o in block["oracle_filters"]:
                s = o["signal_rmse"]
                L.append(f"| *reference: {o['label']}* | {_f(s['vx'])} | {_f(s['vy'])} | {_f(s['omega'])} |")
            L += ["", f"**{cond}: DDM trained on each signal, one-step RMSE and ADE/FDE (300 ms) on the clean test "
                  "laps** (last columns: the same models on the noisy test laps)", "",
                  "| DDM trained on | vx | vy | omega | ADE (m) | FDE (m) | noisy test: vx | vy | omega |",
                  "|---|---|---|---|---|---|---|---|---|"]
            for a in arms:
                c, t = a["clean_test"], a["noisy_test"]
                L.append(f"| {a['label']} | {_f(c['rmse']['vx'])} | {_f(c['rmse']['vy'])} | {_f(c['rmse']['omega'])} "
                         f"| {_f(c['ade'])} | {_f(c['fde'])} | {_f(t['rmse']['vx'])} | {_f(t['rmse']['vy'])} "
                         f"| {_f(t['rmse']['omega'])} |")
            L.append(f"| *reference: clean signal* | {_f(ref['rmse']['vx'])} | {_f(ref['rmse']['vy'])} "
                     f"| {_f(ref['rmse']['omega'])} | {_f(ref['ade'])} | {_f(ref['fde'])} | | | |")
            tuned = [a for a in arms if "finetuned_in_filter_clean_test" in a]
            if tuned:
                L += ["", "The DDM as fine-tuned inside the filter (innovation NLL; the raw DDM in round 1), on the "
                      "clean test laps: " + "; ".join(
                          f"{a['label']}: vx {_f(m['rmse']['vx'])}, vy {_f(m['rmse']['vy'])}, omega "
                          f"{_f(m['rmse']['omega'])}, ADE {_f(m['ade'])}"
                          for a in tuned for m in [a["finetuned_in_filter_clean_test"]]) + "."]
            L += ["", "Closest signal per channel: " + ", ".join(
                f"{c} {arms[_best([a['signal_rmse'][c] for a in arms])]['label']}" for c in CHANNELS)
                + ". Best DDM per metric (clean test): " + ", ".join(
                f"{c} {arms[_best([a['clean_test']['rmse'][c] for a in arms])]['label']}" for c in CHANNELS)
                + f", ADE {arms[_best([a['clean_test']['ade'] for a in arms])]['label']}."]
            learned = [a for a in arms if "denoise" in a and "q" in a["denoise"]]
            if learned:
                L += ["", "Learned noise (variances per sample, vx, vy, omega): " + "; ".join(
                    f"{a['label']}: Q {' '.join(_f(x) for x in a['denoise']['q'])}, R "
                    f"{' '.join(_f(x) for x in a['denoise']['r'])}"
                    + (f", AR(1) phi {' '.join(f'{x:.2f}' for x in a['denoise']['coloured_phi'])}"
                       if a["denoise"].get("coloured_phi") else "") for a in learned) + "."]
            L.append("")
    if real:
        arms = real["arms"]
        tests = list(arms[0]["tests"])
        L += [f"### Real AV-21, Putnam (train: first 80 %, {real['rows']['train']} rows; test: last 20 %, "
              f"{real['rows']['test']} rows)", "",
              "One-step RMSE (vx m/s, vy m/s, omega rad/s) and ADE (m, 600 ms) of each DDM on each version of the "
              "held-out block. Fair comparison: the raw column (the same measured targets for every model).", "",
              "| DDM trained on | " + " | ".join(f"{t} test: vx | vy | omega | ADE" for t in tests) + " |",
              "|---|" + "---|---|---|---|" * len(tests)]
        for a in arms:
            cells = []
            for t in tests:
                m = a["tests"][t]
                cells += [_f(m["rmse"]["vx"]), _f(m["rmse"]["vy"]), _f(m["rmse"]["omega"]), _f(m["ade"])]
            L.append(f"| {a['label']} | " + " | ".join(cells) + " |")
        tuned = [a for a in arms if "finetuned_in_filter_raw_test" in a]
        if tuned:
            L += ["", "The DDM as fine-tuned inside the filter, on the raw test block: " + "; ".join(
                f"{a['label']}: vx {_f(m['rmse']['vx'])}, vy {_f(m['rmse']['vy'])}, omega {_f(m['rmse']['omega'])}, "
                f"ADE {_f(m['ade'])}" for a in tuned for m in [a["finetuned_in_filter_raw_test"]]) + "."]
        L += ["", "Best DDM on the raw test block: " + ", ".join(
            f"{c} {arms[_best([a['tests']['raw']['rmse'][c] for a in arms])]['label']}" for c in CHANNELS)
            + f", ADE {arms[_best([a['tests']['raw']['ade'] for a in arms])]['label']}."]
        L += ["", "Removed from the training data (std of raw minus denoised): " + "; ".join(
            f"{a['label']}: " + ", ".join(f"{c} {_f(a['removed_std'][c])}" for c in CHANNELS)
            for a in arms if a["label"] != "raw") + "."]
        learned = [a for a in arms if "denoise" in a and "q" in a["denoise"]]
        if learned:
            L += ["", "Learned noise (variances per sample, vx, vy, omega): " + "; ".join(
                f"{a['label']}: Q {' '.join(_f(x) for x in a['denoise']['q'])}, R "
                f"{' '.join(_f(x) for x in a['denoise']['r'])}" for a in learned) + "."]
        sr = real["suggested_ranges"]["coefficients"]
        L += ["", "Suggested coefficient ranges (final EKF-FTHD DDM on its denoised training data; rule in "
              "`ddyn.learn.denoise.suggest_ranges`):", "",
              "| coefficient | vehicle range | DDM p1 - p99 | suggested | pinned |", "|---|---|---|---|---|"]
        for name in COEFF_NAMES:
            r = sr[name]
            L.append(f"| {name} | {_f(r['vehicle'][0])} .. {_f(r['vehicle'][1])} | {_f(r['p01'])} .. {_f(r['p99'])} "
                     f"| {_f(r['suggested'][0])} .. {_f(r['suggested'][1])} | {r['pinned'] or ''} |")
        L.append("")
    L.append(f"Study time {seconds / 60:.1f} min.")
    return "\n".join(L) + "\n"


def _run(args) -> int:
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    budget = QUICK if args.quick else FULL
    start = time.perf_counter()
    sim = run_sim(out / "sim", budget) if args.which in ("sim", "all") else None
    real = run_real(out / "real", budget) if args.which in ("real", "all") else None
    seconds = time.perf_counter() - start
    results = {"sim": sim, "real": real, "quick": args.quick, "seconds": seconds,
               "budget": {"epochs": budget.epochs, "lbfgs_iterations": budget.lbfgs_iterations,
                          "fthd_rounds": budget.rounds}}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    md = markdown(sim, real, seconds, args.quick)
    (out / "results.md").write_text(md)
    print(md)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("denoise", help="raw vs Savitzky-Golay vs EKF-FTHD training data (sim and real)",
                              description=__doc__.splitlines()[0])
    p.add_argument("which", nargs="?", choices=("sim", "real", "all"), default="all")
    p.add_argument("--out", default="out/denoise_study", help="output directory (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="tiny data and training: a smoke run, not the figures")
    p.set_defaults(func=_run)
