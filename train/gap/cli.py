"""`ddyn gap diagnose | calibrate | benchmark | rescore`: the gap diagnosis's commands (`ddyn diagnose` is an alias
of `ddyn gap diagnose`). Every setting beyond the inputs and outputs lives in a config file (ddyn.gap.config)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.gap import calibration as CAL
from ddyn.gap.config import DiagnosisConfig, load_config
from ddyn.gap.problem import CHANNELS, nominal_from_checkpoint, nominal_from_vehicle, track_for
from ddyn.gap.report import _fmt, write_report
from ddyn.gap.selection import diagnose
from ddyn.model.single_track import COEFF_NAMES


def diagnose_log(ds, nominal, config: DiagnosisConfig | None = None, calibration: str | None = None, track=None,
                 progress=None) -> dict:
    """The diagnosis as `ddyn gap diagnose` runs it: under the calibration that covers the log (calibration None:
    a shipped one that covers it, if any; a name or file: that one; "none": uncalibrated), its choice and why
    recorded under "calibration"."""
    length = float(ds.time[-1] - ds.time[0]) + ds.sample_time if len(ds) else 0.0
    cal, cfg, why = CAL.choose(length, ds.sample_time, config, calibration)
    d = diagnose(ds, nominal, cfg, track=track, progress=progress)
    d["calibration"] = (cal.summary() if cal else {"name": None}) | {"why": why}
    return d


# ----------------------------------------------------------------------------------------------- diagnose

def _coefficients_arg(text: str | None):
    if not text:
        return None
    p = Path(text)
    try:
        raw = json.loads(p.read_text()) if p.is_file() else json.loads(text)
        if isinstance(raw, dict):
            raw = raw.get("coefficients", raw)
            return np.array([float(raw[k]) for k in COEFF_NAMES])
        return np.array(raw, float)
    except (json.JSONDecodeError, KeyError, ValueError, TypeError, OSError) as e:
        raise DdynError(f"--coefficients: {e}") from None


def load_inputs(args):
    """(log, nominal) of --data and --model or --vehicle (with --coefficients, --method, --substeps)."""
    from ddyn.data.importers import load_any
    from ddyn.model.vehicle import load as load_vehicle

    if args.model:
        from ddyn.learn import checkpoint

        # the checkpoint's embedded vehicle file, not its name: the file may live outside train/vehicles
        ds = load_any(args.data, vehicle=checkpoint.vehicle_of(checkpoint.read(args.model)))
        return ds, nominal_from_checkpoint(args.model, ds)
    vehicle = load_vehicle(args.vehicle)
    ds = load_any(args.data, vehicle=vehicle)   # the loaded file, not a second look-up by name
    return ds, nominal_from_vehicle(vehicle, ds, _coefficients_arg(args.coefficients), args.method, args.substeps)


def _run_diagnose(args) -> int:
    config = load_config(args.config)[0] if args.config else None
    ds, nominal = load_inputs(args)
    d = diagnose_log(ds, nominal, config, args.calibration, track_for(args.track, ds))
    paths = write_report(d, args.out, not args.no_plots)
    c = d["calibration"]
    print(f"calibration: {c['name'] or 'none'} ({c['why']})")
    print(f"selected: {', '.join(d['selected']) if d['selected'] else 'none'} ({d['verdict']})")
    h = d["model"]["heldout"]
    print("held-out one-step RMSE " + ", ".join(f"{ch} {h['rmse_before'][ch]:.3e} -> {h['rmse_after'][ch]:.3e}"
                                                for ch in CHANNELS)
          + f"; ADE {h['ade_before']:.3e} -> {h['ade_after']:.3e} m; gap closed {_fmt(d['model']['gap_closed_pct'])} % "
          f"of the error above the noise floor, {_fmt(d['model']['error_reduction_pct'])} % of the whole error "
          f"(nominal {d['gate']['ratio']:.3g}x the noise floor)")
    for s in d["where"]["summary"]:
        print(f"  where: {s}")
    for v in (d.get("limits") or {}).values():
        print(f"  limit: {v['sentence']}")
    print(f"wrote {paths['json']}, {paths['markdown']} and {len(paths['figures'])} figures in {d['seconds']:.1f} s")
    return 0


def _add_diagnose(sub, name: str = "diagnose", aliases_help: str = "") -> None:
    p = sub.add_parser(name, help="where a model's error lies, which unmodelled effect causes it, how far it "
                                  "shrinks" + aliases_help,
                       description="Diagnose a log against a nominal model (a vehicle file's coefficients or a "
                                   "checkpoint's per-window estimates). Settings: --config (docs/gap.md).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--vehicle", help="vehicle name or JSON file: its true_coefficients are the nominal model")
    src.add_argument("--model", help="a DDM/DPM checkpoint: its per-window coefficients are the nominal model")
    p.add_argument("--data", required=True, help="log in any supported format (canonical, DDM .npz, RACECAR csv)")
    p.add_argument("--out", required=True, help="output directory (diagnosis.json, diagnosis.md, PNGs)")
    p.add_argument("--config", default=None, metavar="NAME|FILE",
                   help="the diagnosis's settings: a TOML/JSON file or a shipped config's name (e.g. 'dbw' for "
                        "drive-by-wire logs); default: the built-in defaults, or a covering calibration's")
    p.add_argument("--calibration", default=None, metavar="NAME|FILE|none",
                   help="the calibration to claim under (`ddyn gap calibrate` writes one; shipped ones load by name); "
                        "default: a shipped one that covers the log, else uncalibrated; 'none': uncalibrated")
    p.add_argument("--coefficients", help="with --vehicle: nominal coefficients, JSON {name: value} or list, "
                                          "or a file holding it")
    p.add_argument("--method", choices=("euler", "rk4"), default=None,
                   help="discretisation (default: the log's, else euler)")
    p.add_argument("--substeps", type=int, default=None, help="integrator substeps (default: the log's)")
    p.add_argument("--track", default=None, help="track for the by-position breakdown (default: the log's)")
    p.add_argument("--no-plots", action="store_true", help="write no PNG plots")
    p.set_defaults(func=_run_diagnose)


# ----------------------------------------------------------------------------------------------- benchmark

def _seed_note(plant: str, seed: int | None) -> None:
    import sys

    from ddyn.gap.benchmark.seeds import calibration_seeds, seen_seeds

    if seed is None:
        return
    if seed in calibration_seeds():
        print(f"note: seed {seed} is a calibration seed: not a blind test", file=sys.stderr)
    elif seed in seen_seeds():
        print(f"note: seed {seed} was scored before (seen_seeds.json): not a blind test", file=sys.stderr)


def _write_run(doc: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    if doc.get("markdown") is not None:
        (out / "results.md").write_text(doc["markdown"])
        print(doc["markdown"])
    (out / "results.json").write_text(json.dumps(doc, indent=2, default=float))
    print(f"wrote {out / 'results.json'}")


def _with_scheduler(args, fn):
    if not args.scheduler:
        return fn()
    from ddyn.gap.benchmark.parallel import use_scheduler

    use_scheduler(args.scheduler)
    try:
        return fn()
    finally:
        use_scheduler(None)


def _run_benchmark(args) -> int:
    from ddyn.gap.benchmark import base

    config, bench = load_config(args.config) if args.config else (None, load_config(None)[1])
    cal = CAL.load(args.calibration) if args.calibration else None
    _seed_note(args.plant, args.seed)
    out = Path(args.out)
    doc = _with_scheduler(args, lambda: base.run(args.plant, args.case_set, out, args.seed, args.cases, config, bench,
                                                 cal, args.duration, args.jobs, not args.no_progress))
    _write_run(doc, out)
    s = doc.get("settings", {})
    if s.get("calibration_seed") and "results" in doc:
        print(f"leaving <= {100 * CAL.TARGET_FALSE_ALARMS:.0f} % of these effect-free logs with a selection: "
              f"evidence margin {CAL.calibrate_margin(doc['results']):.4g}")
    return 0


def _add_benchmark(sub) -> None:
    from ddyn.gap.benchmark.base import PLANTS

    p = sub.add_parser("benchmark", help="the diagnosis scored on logs with a hidden effect (own model, CommonRoad "
                                         "plants, the real Putnam log)",
                       description="Run a benchmark of the diagnosis: plan cases with hidden effects, diagnose each "
                                   "log blind, score. Settings: --config ([diagnosis], [benchmark]; docs/gap.md).")
    p.add_argument("--plant", choices=tuple(PLANTS), default="commonroad",
                   help="; ".join(f"{k}: {v.about}" for k, v in PLANTS.items()) + " (default commonroad)")
    p.add_argument("--case-set", default="putnam", metavar="SET",
                   help="putnam (every effect on the road course, default), sweep (one effect per log at eight "
                        "magnitudes: what a calibration is made of), above (only effects with a threshold, drawn "
                        "above it; needs --calibration), oval (the banked oval), drivetrain, eiv-check, mass-check")
    p.add_argument("--seed", type=int, default=None,
                   help="benchmark seed (seen and calibration seeds: train/gap/benchmark/seen_seeds.json)")
    p.add_argument("--cases", type=int, default=None, help="number of cases (default: the plant's)")
    p.add_argument("--config", default=None, metavar="NAME|FILE", help="settings file or shipped config name")
    p.add_argument("--calibration", default=None, metavar="NAME|FILE",
                   help="diagnose and score under this calibration: its settings, margin and decision levels; "
                        "its thresholds scored against")
    p.add_argument("--duration", type=float, default=None, metavar="SECONDS",
                   help="seconds of log per case (CommonRoad putnam, sweep, above; default 60, or the calibration's)")
    p.add_argument("--jobs", type=int, default=1, help="cases run in this many processes (default 1)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the cases on this Dask distributed scheduler instead of local processes")
    p.add_argument("--out", default="runs/gap_benchmark", help="output directory (results.json, results.md)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_benchmark)


# ----------------------------------------------------------------------------------------------- calibrate

def _seeds_arg(text: str) -> list[int]:
    try:
        return [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise DdynError(f"--seeds {text!r}: expected comma-separated integers") from None


def _run_calibrate(args) -> int:
    import shlex
    import sys

    from ddyn.gap.benchmark import base

    if args.from_runs:
        docs = []
        for p in [q for q in args.from_runs.split(",") if q]:
            try:
                docs.append(json.loads(Path(p).read_text()))
            except (OSError, json.JSONDecodeError) as e:
                raise DdynError(f"--from-runs {p}: {e}") from None
    else:
        config, bench = load_config(args.config)
        if config.min_evidence or config.detection_limits:
            raise DdynError("calibrate: the sweeps are diagnosed with margin 0 and no limits (the calibration "
                            "measures them): leave min_evidence and detection_limits out of the config")
        docs = []
        for seed in _seeds_arg(args.seeds):
            out = Path(args.runs_dir or Path(args.out).with_suffix("")) / f"sweep_{seed}"
            print(f"== sweep seed {seed} -> {out}")
            doc = _with_scheduler(args, lambda: base.run(args.plant, "sweep", out, seed, args.cases, config, bench,
                                                         None, args.duration, args.jobs, not args.no_progress))
            _write_run(doc, out)
            docs.append(doc)
    name = args.name or Path(args.out).stem
    # the command that made it, as typed (not when called through ddyn.cli.main from Python, e.g. a test)
    typed = sys.argv[1:3] == ["gap", "calibrate"]
    cal = CAL.from_runs(name, docs, "ddyn gap calibrate " + shlex.join(sys.argv[3:]) if typed else "")
    path = CAL.write(cal, args.out)
    lim = ", ".join(f"{e} {v:.4g}" for e, v in cal.decision_levels.items() if v is not None) or "none"
    print(f"calibration {name}: {cal.cases} cases of {cal.duration:g} s logs, seeds {list(cal.seeds)}; margin "
          f"{cal.margin:.4g}; thresholds {cal.thresholds}; decision levels {lim}; withdrawn "
          f"{cal.claim_record.get('withdrawn') or 'none'}")
    print(f"wrote {path}")
    return 0


def _add_calibrate(sub) -> None:
    p = sub.add_parser("calibrate", help="make a calibration: sweeps of one-effect logs -> margin, thresholds, "
                                         "decision levels (one JSON file)",
                       description="Run one-effect sweeps of a plant (or read recorded ones) and write the "
                                   "calibration a diagnosis claims under (docs/gap.md).")
    p.add_argument("--plant", choices=("commonroad", "commonroad-mb"), default="commonroad",
                   help="the plant the sweeps run on (default commonroad)")
    p.add_argument("--config", default=None, metavar="NAME|FILE",
                   help="the diagnosis's settings the sweeps use (margin 0, no limits)")
    p.add_argument("--seeds", default="11,13,15,17", help="sweep seeds, comma-separated (default the calibration "
                                                          "seeds 11,13,15,17)")
    p.add_argument("--cases", type=int, default=64, help="cases per sweep (default 64: 8 magnitudes of 7 effects "
                                                         "and effect-free logs)")
    p.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="seconds of log per case "
                                                                                   "(default 60)")
    p.add_argument("--jobs", type=int, default=1, help="cases run in this many processes")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="a Dask distributed scheduler")
    p.add_argument("--out", required=True, help="the calibration file to write (NAME.json)")
    p.add_argument("--name", default=None, help="the calibration's name (default the file's stem)")
    p.add_argument("--runs-dir", default=None, help="where the sweeps' results.json go (default OUT without .json)")
    p.add_argument("--from-runs", default=None, metavar="RESULTS_JSON,...",
                   help="make it from recorded sweep runs instead of running them")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_calibrate)


# ----------------------------------------------------------------------------------------------- rescore

def _run_rescore(args) -> int:
    from ddyn.gap.benchmark import base

    out = Path(args.out)
    cal = CAL.load(args.calibration) if args.calibration else None
    doc = base.rescore(out, cal, args.cases, args.min_evidence)
    _write_run(doc, out)
    return 0


def _add_rescore(sub) -> None:
    p = sub.add_parser("rescore", help="score a recorded benchmark run again (another margin, a calibration's "
                                       "thresholds, its first N cases)")
    p.add_argument("--out", required=True, help="the run's directory (its results.json is rewritten)")
    p.add_argument("--calibration", default=None, metavar="NAME|FILE",
                   help="score against this calibration's thresholds at its margin")
    p.add_argument("--min-evidence", type=float, default=None, metavar="DBIC",
                   help="the evidence margin (only raises the run's own)")
    p.add_argument("--cases", type=int, default=None, help="only the first N cases (the same cases a run with "
                                                           "--cases N makes)")
    p.set_defaults(func=_run_rescore)


# ----------------------------------------------------------------------------------------------- lofo

def _run_lofo(args) -> int:
    from ddyn.gap.benchmark import families as F
    from ddyn.gap.benchmark import lofo

    fams = [f.strip() for f in args.families.split(",") if f.strip()]
    bad = [f for f in fams if f not in F.FAMILIES]
    if bad:
        raise DdynError(f"--families: unknown {', '.join(bad)}; expected some of {', '.join(F.FAMILIES)}")
    if args.logs < 4:
        raise DdynError(f"--logs {args.logs}: at least 4 logs per family")
    if args.calibration_out:     # checked before the hours of work, not after
        _writable(Path(args.calibration_out))
    out = Path(args.out)
    if args.from_results:        # a recorded study: its calibration again, nothing re-run
        if not args.calibration_out:
            raise DdynError("--from-results: give --calibration-out (what to make of the recorded study)")
        if args.folds_from:
            raise DdynError("--from-results re-reads the study in --out; --folds-from scores a new one: not both")
        path = out / "results.json"
        try:
            doc = json.loads(path.read_text())
            doc["all_families_calibration"], doc["pass1"], doc["settings"]["seed"]
        except FileNotFoundError:
            raise DdynError(f"{path}: not found (a `ddyn gap lofo --out {out}` run writes it)") from None
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise DdynError(f"{path}: not a leave-one-family-out study's results.json ({e})") from None
        cal_doc = lofo.calibrate(doc["pass1"])
        if cal_doc != json.loads(json.dumps(doc["all_families_calibration"], default=float)):
            raise DdynError(f"{path}: its recorded calibration differs from what the current rules make of its "
                            "pass 1: run the study again")
        _summarised(doc)
        _write_run(doc, out)
        return _write_travelling(args, doc)
    folds_from = None
    if args.folds_from:          # another campaign scored under a recorded study's fold calibrations
        if args.calibration_out:
            raise DdynError("--folds-from scores under a recorded study's calibrations; it makes none "
                            "(drop --calibration-out)")
        src = Path(args.folds_from)
        folds_from = {"doc": _read_study(src), "path": src}
        lofo.recorded_folds(folds_from["doc"], src, fams, args.seed)    # checked before the work, not after
    durations = lofo.DURATIONS
    if args.durations:
        try:
            durations = tuple((float(d), 1.0) for d in args.durations.split(",") if d.strip())
        except ValueError:
            raise DdynError(f"--durations {args.durations!r}: expected seconds, comma-separated") from None
        if not durations or any(not 10.0 <= d <= 900.0 for d, _ in durations):
            raise DdynError(f"--durations {args.durations!r}: each between 10 and 900 s")
    doc = _with_scheduler(args, lambda: lofo.run(fams, args.logs, args.seed, out, args.jobs, not args.no_progress,
                                                 durations, folds_from, args.tracks))
    _summarised(doc)
    _write_run(doc, out)
    return _write_travelling(args, doc) if args.calibration_out else 0


def _run_pool(args) -> int:
    """Blind campaigns under the same recorded folds, scored together (nothing is run or calibrated)."""
    from ddyn.gap.benchmark import lofo

    doc = lofo.pooled([(_read_study(Path(p)), Path(p)) for p in args.results])
    _summarised(doc)
    _write_run(doc, Path(args.out))
    return 0


def _add_pool(sub) -> None:
    p = sub.add_parser("pool", help="score several `ddyn gap lofo --folds-from` campaigns together",
                       description="Joins campaigns that were each scored blind with `ddyn gap lofo --folds-from` "
                                   "under the same recorded study (other seeds), and that study itself if given "
                                   "(each of its families was scored under the fold of the others), and scores "
                                   "every family again on the union of their logs: nothing is run or calibrated "
                                   "(docs/gap.md).")
    p.add_argument("results", nargs="+", metavar="RESULTS",
                   help="the campaigns' results.json (two or more; the recorded study's may be one of them)")
    p.add_argument("--out", required=True, help="the pooled study's folder (results.json, results.md)")
    p.set_defaults(func=_run_pool)


def _read_study(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DdynError(f"{path}: not found (a `ddyn gap lofo --out DIR` run writes DIR/results.json)") from None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DdynError(f"{path}: not a leave-one-family-out study's results.json ({e})") from None


def _summarised(doc: dict) -> None:
    """The study's headline against the targets (the worst family on each) added to its document and table."""
    from ddyn.gap.benchmark import lofo, lofo_summary

    doc["summary"] = lofo_summary.summary(doc)
    doc["markdown"] = lofo.markdown(doc) + "\n" + lofo_summary.markdown(doc["summary"])


def _write_travelling(args, doc: dict) -> int:
    import shlex
    import sys

    path = Path(args.calibration_out)
    typed = sys.argv[1:3] == ["gap", "lofo"]
    from ddyn.gap.benchmark import lofo

    cal = CAL.travelling_from_study(path.stem, doc,     # named as its file: a shipped name is its file stem
                                    lofo.applied_config(doc["all_families_calibration"]).to_dict(),
                                    "ddyn gap lofo " + shlex.join(sys.argv[3:]) if typed else "")
    CAL.write(cal, path)
    print(f"wrote the calibration of all {len(cal.families)} families: {path}")
    return 0


def _writable(path: Path) -> None:
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir() or (parent.exists() and not parent.is_dir()):
        raise DdynError(f"{path}: cannot write a file there")


def _add_lofo(sub) -> None:
    from ddyn.gap.benchmark import families as F
    from ddyn.gap.benchmark import lofo

    p = sub.add_parser("lofo", help="leave one plant family out: calibrate on the others, score blind on it, every "
                                    "family in turn; optionally write the calibration of all families",
                       description="The diagnosis's generalisation study (docs/gap.md): logs of every plant family "
                                   "(cars, lengths, DBW rates, noise, tracks, channels varied), each family scored "
                                   "under the calibration of the others. Offline: hours on 2 cores at the default "
                                   "size; a Dask cluster (--scheduler) shares the work.")
    p.add_argument("--families", default=",".join(F.FAMILIES), help=f"comma-separated (default all: "
                                                                      f"{', '.join(F.FAMILIES)})")
    p.add_argument("--logs", type=int, default=lofo.DEFAULT_LOGS, help="logs per family (default %(default)s)")
    p.add_argument("--seed", type=int, default=lofo.DEFAULT_SEED, help="the campaign's seed (default %(default)s)")
    p.add_argument("--durations", default=None, help="log lengths in s, comma-separated, drawn equally often "
                                                     "(default 60, 120, 300 s in shares 45, 35, 20 %%)")
    p.add_argument("--tracks", choices=lofo.TRACK_SETS, default="putnam",
                   help="the track of every log not on the banked oval: putnam (every rule was chosen there), or "
                        "road (a full-size random road course per log: with --folds-from, the held-out-track "
                        "check; default %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes")
    p.add_argument("--scheduler", default=None, help="a Dask scheduler address (tcp://HOST:8786) instead of --jobs")
    p.add_argument("--out", required=True, help="the study's folder (results.json, results.md, the logs' cache)")
    p.add_argument("--calibration-out", default=None, metavar="FILE",
                   help="also write the calibration of all families (a travelling calibration) to FILE")
    p.add_argument("--from-results", action="store_true",
                   help="make --calibration-out from the study already recorded in --out (nothing re-run)")
    p.add_argument("--folds-from", default=None, metavar="RESULTS",
                   help="no calibration of its own: score this campaign (use another --seed) with each family under "
                        "the fold calibration of a recorded study (its results.json): logs that neither the "
                        "calibrations nor the choices behind their rules saw")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_lofo)


def register(subparsers) -> None:
    """`ddyn gap` subcommands (the group's parser)."""
    _add_diagnose(subparsers)
    _add_calibrate(subparsers)
    _add_lofo(subparsers)
    _add_pool(subparsers)
    _add_benchmark(subparsers)
    _add_rescore(subparsers)


def register_alias(subparsers) -> None:
    """`ddyn diagnose`: the same as `ddyn gap diagnose`."""
    _add_diagnose(subparsers, "diagnose", " (the same as `ddyn gap diagnose`)")
