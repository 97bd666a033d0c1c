"""`ddyn sil tracks`: the SIL's first lap on seeded random tracks over several sensor-noise seeds.

Why: `ddyn mpc tracks` scores the C MPC in the host loop, where the controller sees the true state.
In the SIL the EKF estimates it from noisy sensors (the vehicle file's noise, drawn from --seed) sent
as CAN frames at their own rates. The same held-out tracks, repeated over noise seeds, say whether
the set-up holds with estimation in the loop. Scored per (track, noise seed): the first lap
completed without a violation, and its time within 5 % of the track's computed optimum (the same
standing start). In process by default (frames through memory, ~5 s a lap); --where guest for the
qemu vcan path.

    ddyn sil tracks --seeds 200-219 --noise-seeds 1-3
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddyn.control.mpc_tracks import WITHIN, optimum, parse_seeds
from ddyn.model.track_files import open_track
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil.run import SilSpec, run_sil


def evaluate(vehicle_name: str, seeds: list[int], noise_seeds: list[int], out: Path, where: str = "inprocess",
             noise: float = 1.0, line: str | None = None) -> list[dict]:
    v = load_vehicle(vehicle_name)
    rows = []
    for seed in seeds:
        track = open_track(f"random:{seed}", vehicle_name)
        best = optimum(vehicle_name, track)
        for ns in noise_seeds:
            spec = SilSpec(vehicle=v, track=track, coeffs_plant=v.true_vector(), coeffs_controller=v.true_vector(),
                           nominal=v.true_vector(), laps=1, noise_scale=noise, seed=ns, line=line,
                           max_time=1.5 * best + 1.0)
            m = run_sil(spec, out / f"random{seed}_noise{ns}", None, where=where)
            lap = m["lap_times"][0] if m["lap_times"] else None
            rows.append({"seed": seed, "noise_seed": ns, "optimal_lap_s": best, "lap_s": lap,
                         "ratio": None if lap is None else lap / best, "violations": m["violations"],
                         "worst_clearance_m": m["worst_clearance"], "end_reason": m["end_reason"],
                         "safe_periods": (m["controller"] or {}).get("safe_periods")})
    return rows


def summary(rows: list[dict]) -> dict:
    clean = [r for r in rows if r["violations"] == 0 and r["lap_s"] is not None]
    ratios = [r["ratio"] for r in clean]
    per_noise = {}
    for r in rows:
        d = per_noise.setdefault(r["noise_seed"], {"runs": 0, "clean": 0, "within_5pct": 0})
        d["runs"] += 1
        ok = r["violations"] == 0 and r["lap_s"] is not None
        d["clean"] += ok
        d["within_5pct"] += ok and r["ratio"] <= 1 + WITHIN
    return {"runs": len(rows), "clean": len(clean), "clean_share": len(clean) / len(rows) if rows else 0.0,
            "within_5pct": sum(1 for x in ratios if x <= 1 + WITHIN),
            "ratio_median": float(np.median(ratios)) if ratios else None,
            "ratio_max": float(np.max(ratios)) if ratios else None, "per_noise_seed": per_noise}


def _run(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = evaluate(args.vehicle, parse_seeds(args.seeds), parse_seeds(args.noise_seeds), out, args.where,
                    args.noise, args.line)
    print("| seed | noise seed | optimal lap (s) | SIL lap (s) | ratio | violations | worst clearance (mm) | end |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        lap = f"{r['lap_s']:.3f}" if r["lap_s"] is not None else "-"
        ratio = f"{r['ratio']:.3f}" if r["ratio"] is not None else "-"
        print(f"| {r['seed']} | {r['noise_seed']} | {r['optimal_lap_s']:.3f} | {lap} | {ratio} | {r['violations']} "
              f"| {1000 * r['worst_clearance_m']:.1f} | {r['end_reason']} |")
    s = summary(rows)
    print(f"{s['clean']}/{s['runs']} first laps clean, {s['within_5pct']}/{s['runs']} clean and within 5 % of the "
          f"optimum (lap/optimum median {s['ratio_median']:.3f}, max {s['ratio_max']:.3f}); per noise seed: "
          + "; ".join(f"{k}: {d['clean']}/{d['runs']} clean, {d['within_5pct']} within 5 %"
                      for k, d in s["per_noise_seed"].items()))
    (out / "sil_tracks.json").write_text(json.dumps({"rows": rows, "summary": s}, indent=1))
    print(f"wrote {out / 'sil_tracks.json'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("tracks", help="first SIL laps on seeded random tracks over sensor-noise seeds",
                              description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", default="orca_1_43")
    p.add_argument("--seeds", default="200-219", help="random track seeds (default: %(default)s, held out)")
    p.add_argument("--noise-seeds", default="1-3", help="sensor noise seeds (default: %(default)s)")
    p.add_argument("--noise", type=float, default=1.0, help="sensor noise scale (default: %(default)s)")
    p.add_argument("--line", choices=("default", "flying", "standing"), default=None)
    p.add_argument("--where", choices=("inprocess", "guest", "host", "auto"), default="inprocess",
                   help="in process (default: frames through memory) or the vcan paths of ddyn sil run")
    p.add_argument("--out", default="out/sil_tracks")
    p.set_defaults(func=_run)
