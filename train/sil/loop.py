"""`ddyn study sil-loop`: closed-loop "how far it shrinks" (issue 34, item 3), in process on emulated time.

Per case (an effect and its size in the SIL plant, on a track):

1. reference: the car without the effect, full speed, one lap (the nominal controller);
2. before: the effect in the plant, the nominal controller, full speed, one lap;
3. log drive: the effect in the plant, the nominal controller, at the fastest of --log-speeds (speed scales of
   the car's line) whose drive completes at least --log-seconds of driving (several laps) without a violation
   (else the fastest that completes it at all);
4. the controller's own log (controller_log.csv: its state estimates and the set-points it commanded) as a
   user's log (`user_log`, a canonical dataset; no plant truth in it), diagnosed with `ddyn gap diagnose
   --vehicle V --data LOG --out D` and nothing else;
5. rebuilt: full speed, one lap, the controller configured from D (`--effects-from D`, ddyn.sil.effects);
6. oracle: full speed, one lap, the controller told the true effect (`--controller-delays`).

This scores the loop, not the diagnosis (the plant is the project's own model with the effect). Every run is
`ddyn sil run --where inprocess` (deterministic); each run's folder keeps its lap.png (the SIL's plot).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import time
from pathlib import Path

import numpy as np

from ddyn.errors import DdynError
from ddyn.model.single_track import INPUT_NAMES, STATE_NAMES
from ddyn.sil.effects import controller_effects

LOG_SPEEDS = (0.6, 0.5, 0.4, 0.3, 0.2)
LOG_SECONDS = 60.0
MIN_VX = 0.3        # m/s: rows slower than this (the standing start) are left out of the user's log
# the plant effect -> (the controller's compensation: delays or lag, its key) that is its oracle
ORACLE = {"steer_delay": ("delays", "steer"), "throttle_delay": ("delays", "throttle"), "steer_lag": ("lag", "steer")}


# ---------------------------------------------------------------------------------------------- the user's log

def user_log(controller_log: Path, vehicle_name: str, sample_time: float, min_vx: float = MIN_VX):
    """The controller's own log as a user's log (a canonical Dataset): per control period, the state estimate
    (x .. omega) and, as throttle and steering, the set-points the controller had commanded, i.e. what a
    drive-by-wire car's log records as its inputs. Row k's throttle/steering is the set-point sent in period
    k - 1 (the one the actuator reaches at the start of period k: the DBW unit's actuator reaches each set-point
    within a period), its rate (dthrottle, dsteering) the step to period k's set-point. With no effect in the
    plant, `ddyn gap diagnose` finds no delay on it (with row k's own set-point it finds one period).
    Rows with the safe command or slower than min_vx are dropped; each gap starts a segment."""
    from ddyn.data.dataset import Dataset
    from ddyn.sil.run import read_csv

    if not controller_log.is_file():
        raise DdynError(f"{controller_log}: no such file (the controller's log of a SIL run)")
    c = read_csv(controller_log)
    need = ("step", "safe", "throttle_cmd", "steering_cmd") + STATE_NAMES[:6]
    missing = [k for k in need if k not in c]
    if missing:
        raise DdynError(f"{controller_log}: not a controller log: no column {missing[0]!r}")
    if len(c["step"]) < 3:
        raise DdynError(f"{controller_log}: {len(c['step'])} rows; need at least 3")
    thr = np.r_[c["throttle_cmd"][0], c["throttle_cmd"][:-1]]
    ste = np.r_[c["steering_cmd"][0], c["steering_cmd"][:-1]]
    states = np.column_stack([c[k] for k in STATE_NAMES[:6]] + [thr, ste])
    rates = np.column_stack([np.r_[np.diff(thr), 0.0], np.r_[np.diff(ste), 0.0]]) / sample_time
    keep = np.flatnonzero((c["vx"] >= min_vx) & (c["safe"] == 0))
    if len(keep) < 3:
        raise DdynError(f"{controller_log}: {len(keep)} rows at vx >= {min_vx} m/s without the safe command")
    step = c["step"][keep].astype(np.int64)
    brk = np.r_[False, np.diff(step) != 1]
    segment = np.cumsum(brk)
    # the last row of a segment has no successor in it: repeat the previous rate (as the LCM importer)
    inputs = rates[keep].copy()
    last = np.flatnonzero(np.r_[brk[1:], True])
    for i in last:
        if i > 0 and segment[i - 1] == segment[i]:
            inputs[i] = inputs[i - 1]
    ds = Dataset(time=step * sample_time, segment=segment, states=states[keep], inputs=inputs,
                 sample_time=sample_time, vehicle=vehicle_name, source=f"{controller_log.parent.name}/controller_log.csv")
    ds.metadata = {"import_format": "ddyn study sil-loop user_log (the controller's own log)",
                   "input_mapping": "throttle, steering = the set-points commanded the period before; "
                                    "dthrottle, dsteering = their steps per period / sample time",
                   "rows": f"{len(keep)} of {len(c['step'])} periods kept (vx >= {min_vx} m/s, no safe command) "
                           f"in {segment[-1] + 1} segment(s)"}
    assert ds.states.shape[1] == len(STATE_NAMES) and ds.inputs.shape[1] == len(INPUT_NAMES)
    return ds


def write_user_log(controller_log: Path, out: Path, vehicle_name: str, sample_time: float) -> Path:
    from ddyn.data.dataset import write_canonical
    return write_canonical(user_log(controller_log, vehicle_name, sample_time), out)


# ---------------------------------------------------------------------------------------------- runs

def _drive(vehicle, track, out: Path, *, effects: dict, delays: dict | None = None, lag: dict | None = None,
           effects_from: dict | None = None, speed_scale: float | None = None, laps: int = 1, seed: int = 1) -> dict:
    from ddyn.sil.run import SilSpec, run_sil

    spec = SilSpec.true_car(vehicle, track, laps=laps, effects=dict(effects), speed_scale=speed_scale, seed=seed,
                            controller_delays=dict(delays or {}), controller_lag=dict(lag or {}),
                            effects_from=effects_from)
    with contextlib.redirect_stdout(io.StringIO()):
        m = run_sil(spec, out, None, where="inprocess")
    return m


def _row(m: dict, out: Path) -> dict:
    laps = m["lap_times"]
    return {"lap_completed": bool(m["lap_completed"]), "lap_s": laps[0] if laps else None,
            "lap_times": laps, "violations": int(m["violations"]), "end": m["end_reason"],
            "tracking_error_mean_m": m["tracking_error"]["mean"], "worst_clearance_m": m["worst_clearance"],
            "plot": str(out / "lap.png")}


def log_drive(vehicle, track, out: Path, effects: dict, ref_lap: float, speeds=LOG_SPEEDS,
              seconds: float = LOG_SECONDS, seed: int = 1) -> tuple[dict, Path]:
    """The nominal controller's drive for the log: the fastest speed scale that drives `seconds` (several
    laps) without a violation, else the one that completes them with the fewest violations (the faster of
    equals)."""
    tried = []
    fallback = None
    for s in speeds:
        laps = max(2, math.ceil(seconds / (ref_lap / s)) + 1)
        d = out / f"log_speed{s:g}"
        m = _drive(vehicle, track, d, effects=effects, speed_scale=s, laps=laps, seed=seed)
        driven = float(sum(m["lap_times"]))
        r = {"speed_scale": s, "laps": laps, "lap_completed": bool(m["lap_completed"]), "driven_s": driven,
             "violations": int(m["violations"]), "end": m["end_reason"],
             "tracking_error_mean_m": m["tracking_error"]["mean"]}
        tried.append(r)
        ok = m["lap_completed"] and driven >= seconds
        if ok and m["violations"] == 0:
            return {"chosen": r, "tried": tried}, d
        if ok and (fallback is None or r["violations"] < fallback[0]["violations"]):
            fallback = (r, d)
    if fallback is None:
        raise DdynError(f"{track.name}, plant effects {effects}: no speed of {list(speeds)} drives {seconds:g} s with "
                        "the nominal controller (tried: " + "; ".join(f"{t['speed_scale']:g}: {t['end']}, "
                                                                      f"{t['violations']} violations" for t in tried) + ")")
    return {"chosen": fallback[0], "tried": tried}, fallback[1]


def diagnose(log: Path, vehicle_name: str, out: Path) -> dict:
    """`ddyn gap diagnose --vehicle V --data LOG --out D`, its defaults (no other option)."""
    from ddyn.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["gap", "diagnose", "--vehicle", vehicle_name, "--data", str(log), "--out", str(out)])
    if rc != 0:
        raise DdynError(f"ddyn gap diagnose on {log} exited {rc}:\n{buf.getvalue()[-2000:]}")
    return json.loads((out / "diagnosis.json").read_text())


def _first(d: dict) -> dict:
    """The diagnosis's first selected effect and its estimate; the steering delay's own candidate too."""
    eff = (d["model"].get("effects") or [])
    first = eff[0] if eff else None
    cand = {c["effect"]: c for c in d.get("candidates", [])}
    sd = cand.get("steer_delay")
    return {"selected": d["selected"], "first": first["effect"] if first else None,
            "first_estimate": next(iter(first["params"].values())) if first else None,
            "runner_up": (d.get("runner_up") or {}).get("effect"),
            "steer_delay_candidate_s": sd["params"]["delay"] if sd else None,
            "steer_delay_candidate_rank": list(cand).index("steer_delay") + 1 if sd else None,
            "calibration": (d.get("calibration") or {}).get("name")}


def run_case(vehicle, track, effect: str, size: float, out: Path, ref: dict, seed: int = 1,
             speeds=LOG_SPEEDS, seconds: float = LOG_SECONDS) -> dict:
    fx = {} if effect == "none" else {effect: size}
    case = {"track": track.name, "effect": effect, "size": size, "reference": ref}
    t0 = time.time()
    m = _drive(vehicle, track, out / "before", effects=fx, seed=seed)
    case["before"] = _row(m, out / "before")
    drive, d = log_drive(vehicle, track, out, fx, ref["lap_s"], speeds, seconds, seed)
    case["log_drive"] = drive
    log = write_user_log(d / "controller_log.csv", out / "user_log.csv", vehicle.name, vehicle.sample_time)
    diag = diagnose(log, vehicle.name, out / "diagnosis")
    case["diagnosis"] = _first(diag) | {"path": str(out / "diagnosis"), "truth": size,
                                        "first_is_the_effect": (not diag["selected"]) if effect == "none" else
                                        (bool(diag["selected"]) and diag["selected"][0] == effect)}
    if case["diagnosis"]["first_is_the_effect"] and effect != "none":
        case["diagnosis"]["error_pct"] = 100.0 * (case["diagnosis"]["first_estimate"] - size) / size
    if effect == "steer_delay" and case["diagnosis"]["steer_delay_candidate_s"] is not None:
        case["diagnosis"]["steer_delay_candidate_error_pct"] = \
            100.0 * (case["diagnosis"]["steer_delay_candidate_s"] - size) / size
    cfx = controller_effects(out / "diagnosis", vehicle.sample_time)
    case["rebuilt_effects"] = cfx.summary()
    m = _drive(vehicle, track, out / "rebuilt", effects=fx, delays=cfx.delays, lag=cfx.lag, effects_from=cfx.summary(),
               seed=seed)
    case["rebuilt"] = _row(m, out / "rebuilt")
    if effect in ORACLE:
        what, key = ORACLE[effect]
        m = _drive(vehicle, track, out / "oracle", effects=fx, seed=seed,
                   **({"delays": {key: size}} if what == "delays" else {"lag": {key: size}}))
        case["oracle"] = _row(m, out / "oracle")
    sd = case["diagnosis"]["steer_delay_candidate_s"]
    if effect == "steer_delay" and "steer_delay" not in cfx.applied and sd is not None and 0.0 <= sd <= 0.1:
        # not the loop's answer: what the diagnosis's own steering-delay estimate (a candidate it did not claim
        # first) would give the controller, to tell a wrong claim from a wrong size
        sdw = round(sd / vehicle.sample_time) * vehicle.sample_time     # as ddyn.sil.effects writes it
        m = _drive(vehicle, track, out / "steer_delay_candidate", effects=fx, delays={"steer": sdw}, seed=seed)
        case["steer_delay_candidate"] = _row(m, out / "steer_delay_candidate") | {"delay_s": sd, "written_s": sdw}
    ref_lap = ref["lap_s"]
    for k in ("before", "rebuilt", "oracle", "steer_delay_candidate"):
        r = case.get(k)
        if r and r["lap_s"] is not None and r["lap_completed"]:
            r["vs_reference_pct"] = 100.0 * (r["lap_s"] / ref_lap - 1.0)
    o, b = case.get("oracle"), case["rebuilt"]
    if o and o.get("lap_s") and b.get("lap_s") and o["lap_completed"] and b["lap_completed"]:
        b["vs_oracle_pct"] = 100.0 * (b["lap_s"] / o["lap_s"] - 1.0)
    b["targets"] = {"clean_within_2pct_of_reference": bool(b["lap_completed"] and b["violations"] == 0
                                                          and b.get("vs_reference_pct", 1e9) <= 2.0),
                    "diagnosis_first_within_15pct": bool(case["diagnosis"]["first_is_the_effect"]
                                                         and abs(case["diagnosis"].get("error_pct", 0.0)) <= 15.0),
                    "diagnosis_first_within_15pct_alone": bool(
                        case["diagnosis"]["first_is_the_effect"] and
                        abs(case["diagnosis"].get("steer_delay_candidate_error_pct", 0.0)) <= 15.0),
                    "within_1pct_of_oracle": bool(b.get("vs_oracle_pct") is not None
                                                  and abs(b["vs_oracle_pct"]) <= 1.0)}
    case["seconds"] = time.time() - t0
    return case


def parse_cases(text: str) -> list[tuple[str, float]]:
    from ddyn.sil.run import PLANT_EFFECTS

    out = []
    for item in text.replace(" ", ",").split(","):
        if not item:
            continue
        if "=" not in item:
            raise DdynError(f"--cases: expected effect=SIZE, got {item!r}")
        k, v = item.split("=", 1)
        if k not in PLANT_EFFECTS + ("none",):
            raise DdynError(f"--cases: unknown effect {k!r}; expected one of {', '.join(PLANT_EFFECTS)}")
        try:
            out.append((k, float(v)))
        except ValueError:
            raise DdynError(f"--cases: {k} needs a number, got {v!r}") from None
    return out


def _fmt_run(r: dict | None) -> str:
    if not r:
        return "-"
    lap = f"{r['lap_s']:.3f} s" if r["lap_completed"] and r["lap_s"] is not None else "no lap (" + r["end"] + ")"
    te = r["tracking_error_mean_m"]
    return f"{lap} / {r['violations']} / {te:.3f}" if te is not None else f"{lap} / {r['violations']} / -"


def markdown(cases: list[dict]) -> str:
    lines = ["| track | plant effect | log drive (speed scale, s) | diagnosis: selected first (joint estimate) | "
             "steer_delay fitted alone (rank) | control.delay / lag written | before | rebuilt | oracle | "
             "reference (no effect) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        dg = c["diagnosis"]
        first = (f"{dg['first']} {dg['first_estimate']:.4g}" if dg["first"] else "none")
        sd = f"{dg['steer_delay_candidate_s']:.4g} s (rank {dg['steer_delay_candidate_rank']})" \
            if dg["steer_delay_candidate_s"] is not None else "-"
        ld = c["log_drive"]["chosen"]
        written = ", ".join([f"{k} {v:.4g} s" for k, v in c["rebuilt_effects"]["controller_delays"].items()] +
                            [f"lag {k} {v:.4g} s" for k, v in c["rebuilt_effects"].get("controller_lag", {}).items()])
        applied = written or ("nothing (" + "; ".join(c["rebuilt_effects"]["not_applied"]) + ")"
                              if c["rebuilt_effects"]["not_applied"] else "nothing")
        lines.append(f"| {c['track']} | {c['effect']} {c['size']:g} | {ld['speed_scale']:g}, {ld['driven_s']:.1f} s, "
                     f"{ld['violations']} viol. | {first} | {sd} | {applied} | {_fmt_run(c['before'])} | "
                     f"{_fmt_run(c['rebuilt'])} | {_fmt_run(c.get('oracle'))} | {_fmt_run(c['reference'])} |")
    return "\n".join(lines) + "\n\n(lap / violations / mean tracking error, m)\n"


def _run(args: argparse.Namespace) -> int:
    from ddyn.model.track_files import open_track
    from ddyn.model.vehicle import load as load_vehicle

    vehicle = load_vehicle(args.vehicle)
    cases = parse_cases(args.cases)
    speeds = tuple(float(s) for s in args.log_speeds.split(","))
    out = Path(args.out)
    results = []
    for tname in args.tracks.split(","):
        track = open_track(tname, vehicle.name)
        if tname.startswith("random:"):
            from ddyn.control.mpc_tracks import optimum
            optimum(vehicle.name, track)    # the car's line on a random track, computed once (out/racelines)
        tdir = out / tname.replace(":", "_")
        m = _drive(vehicle, track, tdir / "reference", effects={}, seed=args.seed)
        ref = _row(m, tdir / "reference")
        if not ref["lap_completed"]:
            raise DdynError(f"{tname}: the car without any effect does not complete the lap ({ref['end']})")
        for effect, size in cases:
            c = run_case(vehicle, track, effect, size, tdir / f"{effect}_{size:g}", ref, args.seed, speeds,
                         args.log_seconds)
            results.append(c)
            print(f"{tname} {effect}={size:g}: "
                  f"diagnosis {c['diagnosis']['selected']}; before {_fmt_run(c['before'])}; rebuilt "
                  f"{_fmt_run(c['rebuilt'])}; oracle {_fmt_run(c.get('oracle'))} ({c['seconds']:.0f} s)", flush=True)
    doc = {"vehicle": vehicle.name, "seed": args.seed, "log_speeds": list(speeds), "log_seconds": args.log_seconds,
           "cases": results, "markdown": markdown(results)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "loop.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    (out / "loop.md").write_text(doc["markdown"])
    print(doc["markdown"])
    print(f"wrote {out / 'loop.json'} and loop.md")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sil-loop", help="closed loop: effect in the plant, the controller's own log diagnosed, the controller rebuilt "
                     "from the diagnosis, against the oracle (issue 34)",
        description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", default="orca_1_43", help="vehicle file name (default: %(default)s)")
    p.add_argument("--tracks", default="ethzMobil", help="comma-separated tracks (e.g. ethzMobil,random:301)")
    p.add_argument("--cases", default="steer_delay=0.04,steer_delay=0.08",
                   help="plant effects and sizes, effect=SIZE,...; none=0: no effect (what the diagnosis claims on "
                        "an effect-free log) (default: %(default)s)")
    p.add_argument("--log-speeds", default=",".join(f"{s:g}" for s in LOG_SPEEDS),
                   help="speed scales tried for the log drive, fastest first (default: %(default)s)")
    p.add_argument("--log-seconds", type=float, default=LOG_SECONDS,
                   help="driving time of the log drive, s (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="sensor noise seed")
    p.add_argument("--out", default="out/sil_loop",
                   help="output folder: loop.json, loop.md, a folder per track and case (default: %(default)s)")
    p.set_defaults(func=_run)
