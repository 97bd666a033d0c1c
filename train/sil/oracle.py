"""`ddyn study sil-oracle`: the controller told the true effect, over tracks, effects and noise seeds.

The oracle of `ddyn study sil-loop` on its own: how many of its laps are clean and within 2 % of the car without the
effect.

What it is for: the runtime's compensation alone, without a diagnosis in between, over many cases at once. The loop's
settings that are not the diagnosis's (the racing line every run drives, how the MPC plans with a delay) are chosen
with it on tracks the loop does not score (ETHZMobil is the loop's own; random:303-305 are held out of it), so the
loop's held-out tracks (random:301, :302) stay held out. Each run is the loop's: in process, emulated time, four laps
from rest, scored on the median of the three flying laps (ddyn.sil.loop._row); `--line` as the loop's.

Output: oracle.json (every run, a summary per line of cases) and oracle.md."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from ddyn.control.raceline import LINES
from ddyn.errors import DdynError
from ddyn.sil import loop

WITHIN_PCT = 2.0   # the loop's target: the flying lap within 2 % of the car without the effect


def run_track(vehicle, tname: str, cases: list[tuple[str, float]], seed: int, line: str, out: Path) -> list[dict]:
    """The reference (no effect) and one oracle run per case on one track at one noise seed."""
    track = loop.open_track_for_line(vehicle, tname, line)
    tdir = out / f"seed{seed}" / tname.replace(":", "_")
    ref = loop._row(loop._drive(vehicle, track, tdir / "reference", effects={}, seed=seed, line=line),
                    tdir / "reference")
    rows = []
    for effect, size in cases:
        what, key = loop.ORACLE[effect]
        told = {"delays": {"delays": {key: size}}, "lag": {"lag": {key: size}}, "mass": {"mass_offset": size},
                "downforce": {"downforce": size}, "grade": {"controller_grade": True}}[what]
        d = tdir / f"{effect}_{size:g}"
        if effect == loop.ROAD_GRADE:   # the road's hills (the world's): the graded track, no plant effect
            from ddyn.model.road_grade import graded
            r = loop._row(loop._drive(vehicle, graded(track, size), d, effects={}, seed=seed, line=line, **told), d)
        else:
            r = loop._row(loop._drive(vehicle, track, d, effects={effect: size}, seed=seed, line=line, **told), d)
        clean = bool(r["lap_completed"] and r["violations"] == 0)
        vs = 100.0 * (r["lap_s"] / ref["lap_s"] - 1.0) if clean and ref["lap_completed"] and ref["lap_s"] else None
        rows.append({"track": track.name, "seed": seed, "effect": effect, "size": size, "reference": ref,
                     "oracle": r, "clean": clean, "vs_reference_pct": vs,
                     "clean_within": bool(clean and vs is not None and vs <= WITHIN_PCT)})
    return rows


def summarise(rows: list[dict]) -> dict:
    """Per effect and over all: runs, clean, clean and within WITHIN_PCT of no effect, the worst and best clean lap
    against no effect (%)."""
    groups: dict[str, list[dict]] = {"all": rows}
    for r in rows:
        groups.setdefault(r["effect"], []).append(r)
    out = {}
    for name, rs in groups.items():
        vs = [r["vs_reference_pct"] for r in rs if r["vs_reference_pct"] is not None]
        out[name] = {"runs": len(rs), "clean": sum(r["clean"] for r in rs),
                     "clean_within": sum(r["clean_within"] for r in rs),
                     "worst_vs_reference_pct": max(vs) if vs else None,
                     "best_vs_reference_pct": min(vs) if vs else None}
    return out


def markdown(rows: list[dict], summary: dict) -> str:
    lines = ["| track | seed | plant effect (told) | oracle: flying lap / violations | vs no effect |", "|---|---|---|---|---|"]
    for r in rows:
        o = r["oracle"]
        lap = f"{o['lap_s']:.3f} s" if o["lap_completed"] and o["lap_s"] else f"no lap ({o['end']})"
        vs = f"{r['vs_reference_pct']:+.2f} %" if r["vs_reference_pct"] is not None else "-"
        lines.append(f"| {r['track']} | {r['seed']} | {r['effect']} {r['size']:g} | {lap} / {o['violations']} | {vs} |")
    a = summary["all"]
    lines.append(f"\n{a['clean_within']} of {a['runs']} runs clean and within {WITHIN_PCT:g} % of the car without the "
                 f"effect ({a['clean']} clean)")
    return "\n".join(lines) + "\n"


def _run(args: argparse.Namespace) -> int:
    from ddyn.model.vehicle import load as load_vehicle

    vehicle = load_vehicle(args.vehicle)
    cases = loop.parse_cases(args.cases)
    told = [k for k in loop.ORACLE if k != loop.ROAD_BANK]
    bad = [e for e, _ in cases if e not in told]
    if bad:
        raise DdynError(f"--cases {bad[0]}: no oracle for it here (one of {', '.join(told)})")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s]
    except ValueError:
        raise DdynError(f"--seeds: expected comma-separated integers, got {args.seeds!r}") from None
    out = Path(args.out)
    rows: list[dict] = []
    for seed in seeds:
        for tname in args.tracks.split(","):
            rows += run_track(vehicle, tname, cases, seed, args.line, out)
            print(f"seed {seed} {tname}: " + ", ".join(
                f"{r['effect']}={r['size']:g} {'clean' if r['clean'] else 'not clean'}"
                + (f" {r['vs_reference_pct']:+.2f} %" if r["vs_reference_pct"] is not None else "")
                for r in rows if r["seed"] == seed and r["track"] == rows[-1]["track"]), flush=True)
    summary = summarise(rows)
    doc = {"vehicle": vehicle.name, "line": args.line, "seeds": seeds, "tracks": args.tracks.split(","),
           "within_pct": WITHIN_PCT, "scored_laps": loop.SCORED_LAPS, "summary": summary, "runs": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "oracle.json").write_text(json.dumps(doc, indent=2) + "\n")
    md = markdown(rows, summary)
    (out / "oracle.md").write_text(md)
    print(md + f"wrote {out / 'oracle.json'} and oracle.md")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sil-oracle", help="the controller told the true effect on tracks x effects x seeds: clean laps within 2 %% "
                           "of no effect (chooses the loop's settings on tracks it does not score)",
        description=__doc__.splitlines()[0])
    p.add_argument("--vehicle", default="orca_1_43", help="vehicle file name (default: %(default)s)")
    p.add_argument("--tracks", default="ethzMobil,random:303,random:304,random:305",
                   help="comma-separated tracks (default: %(default)s, not the loop's held-out ones)")
    p.add_argument("--cases", default="steer_delay=0.04,steer_delay=0.06,steer_delay=0.08,throttle_delay=0.06,"
                                      "throttle_delay=0.1,throttle_delay=0.12,steer_lag=0.05,steer_lag=0.1",
                   help="plant effects and sizes, effect=SIZE,..., each told to the controller (default: %(default)s)")
    p.add_argument("--seeds", default="1,2", help="sensor noise seeds, comma-separated (default: %(default)s)")
    p.add_argument("--line", choices=tuple(k for k in LINES if k != "standing"), default=loop.LINE,
                   help="the racing line of every run, as `ddyn study sil-loop --line` (default: %(default)s)")
    p.add_argument("--out", default="out/sil_oracle", help="output folder (default: %(default)s)")
    p.set_defaults(func=_run)
