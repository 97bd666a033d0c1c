"""`ddyn mpc tracks`: the C MPC's first lap on many seeded random tracks, against each track's optimum.

Why: the MPC's weights, speed margin and racing line were chosen on ETHZMobil alone. One set-up
should hold on any track, and a choice made on some tracks must be judged on others: tuning seeds
choose (with --grid), held-out seeds that no choice has seen report.

For each seed: the random track (ddyn.model.track_random), the vehicle's time-optimal line on it
(computed once by ddyn.control.raceline and kept in out/racelines/), then the C MPC's closed loop
from vx0 = 0.1 m/s with the true coefficients on the plant's RK4 (as `ddyn mpc lap`), for
1.5 x the optimal lap + 1 s. Scored per track: violation steps (a footprint corner outside the
bounds) in the first lap and over the whole run, the first lap's time and its ratio to the line's
optimal lap (the same standing start).

    ddyn mpc tracks --seeds 0-5 --grid speed_scale=0.95,1.0 --grid r_dsteering=0.1,0.3   # tuning
    ddyn mpc tracks --seeds 100-119                                                     # held out
"""
from __future__ import annotations

import itertools
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from ddyn.control import raceline as R
from ddyn.control.mpc_lap import DEFAULT_TOOL, _parse_assignments, _summary, run_c, score
from ddyn.control.mpc_setup import MpcSettings
from ddyn.errors import DdynError
from ddyn.model.track_files import open_track
from ddyn.model.vehicle import load as load_vehicle

WITHIN = 0.05  # the target: laps within 5 % of each track's optimum


def parse_seeds(text: str) -> list[int]:
    """`0-5,9,100-119` -> [0, 1, ..., 5, 9, 100, ..., 119]."""
    out = []
    try:
        for part in text.split(","):
            a, _, b = part.partition("-")
            out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    except ValueError:
        raise DdynError(f"--seeds {text!r}: expected integers and ranges like 0-5,9") from None
    return out


def optimum(vehicle_name: str, track, flying: bool = False) -> float:
    """The vehicle's optimal standing-start (or flying) lap on the track: its line, computed once if missing."""
    path = R.default_path(vehicle_name, track, flying)
    if R.load_for(vehicle_name, track, flying) is None:
        v = load_vehicle(vehicle_name)
        settings = R.resolved(replace(R.settings_for(vehicle_name), flying=flying), track)
        R.save(path, R.raceline_arrays(v, track, R.solve(v, track, settings), settings))
    return float(R.meta_of(path)["lap_time_s"])


def evaluate(vehicle_name: str, seeds: list[int], settings: MpcSettings, tool: Path = DEFAULT_TOOL,
             laps: int = 1) -> list[dict]:
    """Per seed, the first lap (and with laps > 1 the next ones, scored against the flying-lap optimum)."""
    dt = load_vehicle(vehicle_name).sample_time
    rows = []
    for seed in seeds:
        track = open_track(f"random:{seed}", vehicle_name)
        best = optimum(vehicle_name, track)
        fly = optimum(vehicle_name, track, True) if laps > 1 or settings.line == "flying" else None
        steps = int(np.ceil((1.5 * best + 1.0) / dt)) if laps == 1 else \
            int(np.ceil((1.2 * best + 1.2 * (laps - 1) * fly + 1.0) / dt))
        run = run_c(vehicle_name, track, settings, steps, tool=tool)
        m = _summary(run, track, vehicle_name)
        lap = m["lap_time_s"]
        # the first lap is what is scored (as a one-lap SIL run); the rest of the run is reported:
        # the line is a standing-start lap, so the next lap starts fast into a table made for vx0
        k = steps if lap is None else min(steps, int(np.ceil(lap / dt)) + 1)
        first = score(track, run["x"][: k + 1], dt, vehicle_name)
        rows.append({"seed": seed, "length_m": track.length, "width_m": track.properties["width"],
                     "optimal_lap_s": best, "lap_s": lap, "ratio": None if lap is None else lap / best,
                     "violation_steps": first["violation_steps"],
                     "closest_corner_mm": 1000 * first["min_boundary_distance_m"],
                     "violation_steps_run": m["violation_steps"], "run_s": steps * dt,
                     "qp_iterations_max": m["qp_iterations_max"], "status_counts": m["status_counts"]})
        if laps > 1:
            later = m["lap_times_s"][1:laps]
            rows[-1].update({"flying_optimal_lap_s": fly, "lap_times_s": m["lap_times_s"][:laps],
                             "violation_steps_per_lap": m["violation_steps_per_lap"][:laps],
                             "flying_ratios": [t / fly for t in later], "laps_completed": len(m["lap_times_s"][:laps])})
    return rows


def summary(rows: list[dict]) -> dict:
    """Counts over the tracks: clean first laps, clean and within 5 % of the optimum, whole runs clean."""
    n = len(rows)
    clean = [r for r in rows if r["violation_steps"] == 0 and r["lap_s"] is not None]
    ratios = [r["ratio"] for r in rows if r["ratio"] is not None]
    out = {}
    multi = [r for r in rows if "lap_times_s" in r]
    if multi:  # the laps after the first: all completed and clean, within 5 % of the flying optimum
        laps = max(len(r["violation_steps_per_lap"]) for r in multi)
        ok = [r for r in multi if r["laps_completed"] == laps and sum(r["violation_steps_per_lap"]) == 0]
        fr = [x for r in multi for x in r["flying_ratios"]]
        out = {"laps": laps, "all_laps_clean": len(ok),
               "later_laps_within_5pct": sum(1 for r in ok if all(x <= 1 + WITHIN for x in r["flying_ratios"])),
               "flying_ratio_median": float(np.median(fr)) if fr else None,
               "flying_ratio_max": float(np.max(fr)) if fr else None}
    return {**out, "tracks": n, "clean": len(clean), "clean_share": len(clean) / n if n else 0.0,
            "within_5pct": sum(1 for r in clean if r["ratio"] <= 1 + WITHIN),
            "runs_clean": sum(1 for r in rows if r.get("violation_steps_run", 0) == 0),
            "ratio_median": float(np.median(ratios)) if ratios else None,
            "ratio_max": float(np.max(ratios)) if ratios else None}


def _print_rows(rows: list[dict]) -> None:
    print("| seed | length (m) | width (m) | optimal lap (s) | MPC lap (s) | ratio | violation steps (lap) "
          "| closest corner (mm) | violation steps (whole run) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        lap = f"{r['lap_s']:.3f}" if r["lap_s"] is not None else "-"
        ratio = f"{r['ratio']:.3f}" if r["ratio"] is not None else "-"
        extra = ""
        if "lap_times_s" in r:
            extra = (f" flying optimum {r['flying_optimal_lap_s']:.3f}; laps " + ", ".join(f"{t:.3f}" for t in r["lap_times_s"])
                     + "; per lap violation steps " + ", ".join(str(v) for v in r["violation_steps_per_lap"]) + " |")
        print(f"| {r['seed']} | {r['length_m']:.2f} | {r['width_m']:.3f} | {r['optimal_lap_s']:.3f} | {lap} | {ratio} "
              f"| {r['violation_steps']} | {r['closest_corner_mm']:.1f} | {r['violation_steps_run']} |{extra}")


def _line(s: dict) -> str:
    text = (f"{s['clean']}/{s['tracks']} clean, {s['within_5pct']}/{s['tracks']} clean and within 5 %, "
            f"lap/optimum median {s['ratio_median']:.3f} max {s['ratio_max']:.3f}; whole runs clean "
            f"{s['runs_clean']}/{s['tracks']}")
    if "laps" in s:
        text += (f"; {s['laps']} laps: all clean {s['all_laps_clean']}/{s['tracks']}, and laps 2-{s['laps']} "
                 f"within 5 % of the flying optimum {s['later_laps_within_5pct']}/{s['tracks']} (lap/flying optimum "
                 f"median {s['flying_ratio_median']:.3f} max {s['flying_ratio_max']:.3f})")
    return text


def _run(args) -> int:
    seeds = parse_seeds(args.seeds)
    base = replace(MpcSettings(), line=args.line, **_parse_assignments(args.set, multi=False))
    grid = _parse_assignments(args.grid, multi=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    keys = list(grid)
    for values in itertools.product(*(grid[k] for k in keys)) if keys else [()]:
        st = replace(base, **dict(zip(keys, values)))
        rows = evaluate(args.vehicle, seeds, st, Path(args.tool), laps=args.laps)
        s = summary(rows)
        results.append({"settings": st.as_dict(), "grid_point": dict(zip(keys, values)), "summary": s, "rows": rows})
        if keys:
            print(" ".join(f"{k}={v:g}" for k, v in zip(keys, values)) + ": " + _line(s))
        else:
            _print_rows(rows)
            print(_line(s))
    (out / "mpc_tracks.json").write_text(json.dumps({"seeds": seeds, "results": results}, indent=1))
    print(f"wrote {out / 'mpc_tracks.json'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("tracks", help="the C MPC's first lap on seeded random tracks against each optimum",
                              description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", default="orca_1_43")
    p.add_argument("--seeds", default="100-119", help="random track seeds, e.g. 0-5,9 (default: %(default)s, held out)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override an MpcSettings value (repeatable)")
    p.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                   help="evaluate every combination of these values (tuning seeds only)")
    p.add_argument("--laps", type=int, default=1,
                   help="laps to drive; with more than one the later laps are scored against the flying-lap optimum")
    p.add_argument("--line", choices=("default", "flying", "standing"), default="default",
                   help="the MPC's table: the vehicle's own line (default), or its flying-lap line")
    p.add_argument("--out", default="out/mpc_tracks")
    p.add_argument("--tool", default=str(DEFAULT_TOOL))
    p.set_defaults(func=_run)
