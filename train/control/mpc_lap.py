"""`ddyn mpc lap`: the C MPC drives the simulated car around a track from near standstill.

The closed loop runs in the host tool ddyn_mpc_lap (plant: the generated RK4 step with the true
coefficients; controller: ddyn_mpc with the coefficients given, by default the true ones). This
module writes its setup, parses its per-step output and scores the run: track violations of the
car's footprint (its four corners against the bounds, every step), lap time (first crossing of one
centre-line length of progress, interpolated), QP iterations and the solver status counts. With
--reference it also drives the same lap with the CasADi + IPOPT MPC (train/control/mpc_reference.py) and
compares lap times.
"""
from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np

from ddyn.control.mpc_setup import MpcSettings, perturbed_start, raceline_table, settings_for, start_state
from ddyn.control.raceline import is_flying, line_for
from ddyn.errors import DdynError
from ddyn.model import vehicle as vehicle_mod
from ddyn.model.track_files import open_track
from ddyn.model.tracks import Track
from ddyn.model.vehicle import footprint
from ddyn.paths import BUILD

DEFAULT_TOOL = BUILD / "c_src" / "ddyn_mpc_lap"
STATUS_NAMES = {0: "ok", 2: "nonfinite_input", 3: "nonfinite_output", 4: "evaluation", 6: "qp_not_converged",
                7: "not_ready"}


SWEEP_SPEEDS = (0.1, 0.2, 0.3, 0.5, 1.0)  # m/s at the start
SWEEP_OFFSETS = ((0.0, 0.0), (0.03, 0.0), (-0.03, 0.0), (0.0, 0.15), (0.0, -0.15))  # (lateral m, heading rad)


def sweep(vehicle_name: str = "orca_1_43", track_name: str = "ethzMobil", steps: int = 10000,
          settings: MpcSettings | None = None, speeds=SWEEP_SPEEDS, offsets=SWEEP_OFFSETS,
          tool: Path = DEFAULT_TOOL) -> list[dict]:
    """Robustness: the long closed loop from every start speed x start perturbation, scored each."""
    settings = settings or settings_for(vehicle_name)
    track = open_track(track_name, vehicle_name)
    table = raceline_table(track, vehicle_name, settings)
    rows = []
    for v0 in speeds:
        for lateral, heading in offsets:
            run = run_c(vehicle_name, track, settings, steps, tool=tool,
                        x0=perturbed_start(table, v0, lateral, heading))
            m = _summary(run, track, vehicle_name)
            rows.append({"start_speed": v0, "lateral_m": lateral, "heading_rad": heading,
                         "violation_steps": m["violation_steps"],
                         "min_boundary_distance_m": m["min_boundary_distance_m"],
                         "lap_time_s": m["lap_time_s"], "laps": m["progress_m"] / track.length,
                         "qp_iterations_max": m["qp_iterations_max"], "status_counts": m["status_counts"],
                         "max_slack_m": m["max_slack_m"]})
    return rows


def setup_text(vehicle_name: str, table: dict, settings: MpcSettings, coeffs: np.ndarray, plant_coeffs: np.ndarray,
               x0: np.ndarray, steps: int) -> str:
    s = settings
    lines = [f"vehicle {vehicle_name}", f"disc {s.disc}", f"horizon {s.horizon}", f"steps {steps}",
             "weights " + " ".join(repr(float(v)) for v in (s.q_x, s.q_y, s.q_terminal, s.r_dthrottle,
                                                             s.r_dsteering, s.slack_l1, s.slack_l2)),
             f"qp {s.qp_max_iterations} {s.qp_tolerance!r}",
             "coeffs " + " ".join(repr(float(v)) for v in coeffs),
             "plant_coeffs " + " ".join(repr(float(v)) for v in plant_coeffs),
             "x0 " + " ".join(repr(float(v)) for v in x0),
             f"track {len(table['x'])}"]
    cols = [table[k] for k in ("x", "y", "speed", "room_left", "room_right")]
    lines += [" ".join(repr(float(c[i])) for c in cols) for i in range(len(cols[0]))]
    return "\n".join(lines) + "\n"


def run_c(vehicle_name: str, track: Track, settings: MpcSettings, steps: int, coeffs: np.ndarray | None = None,
          tool: Path = DEFAULT_TOOL, x0: np.ndarray | None = None) -> dict:
    """Run the C closed loop; per-step arrays: status, qp_iterations, converged, residual, slack, solve_us, u, x."""
    if not Path(tool).is_file():
        raise DdynError(f"{tool} not found: build with scripts/build.sh build")
    v = vehicle_mod.load(vehicle_name)
    table = raceline_table(track, vehicle_name, settings)
    true = v.true_vector()
    if x0 is None:  # a flying line: a rolling start at the reference's speed; else from near standstill
        x0 = start_state(table, float(table["speed"][0]) if is_flying(track, vehicle_name) else 0.1)
    x0 = np.asarray(x0, float)
    text = setup_text(vehicle_name, table, settings, true if coeffs is None else coeffs, true, x0, steps)
    proc = subprocess.run([str(tool)], input=text, capture_output=True, text=True)
    if proc.returncode != 0 or not proc.stdout.rstrip().endswith("done"):
        raise DdynError(f"{tool}: {proc.stderr.strip() or 'incomplete output'}")
    rows = np.array([[float(t) for t in line.split()] for line in proc.stdout.splitlines()[:-1]])
    return {"status": rows[:, 1].astype(int), "qp_iterations": rows[:, 2].astype(int),
            "converged": rows[:, 3].astype(int), "residual": rows[:, 4], "slack": rows[:, 5],
            "solve_us": rows[:, 6], "u": rows[:, 7:9], "x": np.vstack([x0, rows[:, 9:17]]),
            "table": table, "dt": v.sample_time}


def footprint_corners(x: np.ndarray, vehicle_name: str) -> np.ndarray:
    """(N, 4, 2) corners of the car's rectangle centred on the centre of gravity."""
    length, width = footprint(vehicle_name)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * np.array([length / 2, width / 2])
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    cx = x[:, 0, None] + c[:, None] * local[:, 0] - s[:, None] * local[:, 1]
    cy = x[:, 1, None] + s[:, None] * local[:, 0] + c[:, None] * local[:, 1]
    return np.stack([cx, cy], axis=-1)


def score(track: Track, x: np.ndarray, dt: float, vehicle_name: str) -> dict:
    """Violations (steps with any footprint corner outside the bounds, and the worst depth) and lap time."""
    s, _ = track.project(x[:, 0], x[:, 1])
    progress = np.concatenate(([0.0], np.cumsum((np.diff(s) + track.length / 2) % track.length - track.length / 2)))
    corners = footprint_corners(x, vehicle_name)
    s_hint = np.repeat(s[:, None], 4, axis=1)
    depth = track.boundary_distance(corners[..., 0], corners[..., 1], s_hint=s_hint, window=1.0)
    worst = depth.min(axis=1)
    crossings = []  # times at which the progress passes 1, 2, ... lengths (interpolated)
    for lap in range(1, int(progress[-1] // track.length) + 1):
        k = int(np.nonzero(progress >= lap * track.length)[0][0])
        frac = (lap * track.length - progress[k - 1]) / (progress[k] - progress[k - 1])
        crossings.append(float((k - 1 + frac) * dt))
    lap_times = list(np.diff([0.0] + crossings))
    # violation steps per lap (a step belongs to the lap its time falls in; the last entry: the unfinished rest)
    bounds = np.concatenate(([0.0], crossings, [np.inf]))
    t = np.arange(len(x)) * dt
    per_lap = [int(np.sum((worst < 0.0) & (t >= a) & (t < b))) for a, b in zip(bounds[:-1], bounds[1:])]
    return {"violation_steps": int(np.sum(worst < 0.0)), "min_boundary_distance_m": float(worst.min()),
            "lap_time_s": lap_times[0] if lap_times else None, "lap_times_s": [float(v) for v in lap_times],
            "violation_steps_per_lap": per_lap, "progress_m": float(progress[-1]), "steps": int(len(x) - 1)}


def _summary(run: dict, track: Track, vehicle_name: str) -> dict:
    m = score(track, run["x"], run["dt"], vehicle_name)
    it = run["qp_iterations"]
    us = np.sort(run["solve_us"])
    m.update({"qp_iterations_median": float(np.median(it)), "qp_iterations_max": int(it.max()),
              "status_counts": {STATUS_NAMES.get(int(k), str(k)): int(c)
                                for k, c in zip(*np.unique(run["status"], return_counts=True))},
              "max_slack_m": float(run["slack"].max()),
              "solve_us": {"median": float(us[len(us) // 2]), "p99": float(us[int(0.99 * (len(us) - 1))]),
                           "max": float(us[-1])}})
    return m


def plot_lap(track: Track, runs: dict[str, np.ndarray], path: Path, vehicle_name: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 7))
    for b in (track.inner, track.outer):
        loop = np.vstack([b, b[:1]])
        ax.plot(loop[:, 0], loop[:, 1], "k-", lw=1)
    rl = line_for(track, vehicle_name)
    ax.plot(rl.x, rl.y, "--", color="0.6", lw=1, label="raceline")
    for name, x in runs.items():
        ax.plot(x[:, 0], x[:, 1], lw=1.2, label=name)
        c = footprint_corners(x[::10], vehicle_name)
        for quad in c[:: max(1, len(c) // 60)]:
            q = np.vstack([quad, quad[:1]])
            ax.plot(q[:, 0], q[:, 1], lw=0.5, alpha=0.5)
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{track.name}: MPC lap from near standstill")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def lap(vehicle_name: str = "orca_1_43", track_name: str = "ethzMobil", seconds: float = 7.0,
        settings: MpcSettings | None = None, reference: bool = True, out: Path | None = None,
        tool: Path = DEFAULT_TOOL) -> dict:
    settings = settings or settings_for(vehicle_name)
    track = open_track(track_name, vehicle_name)
    v = vehicle_mod.load(vehicle_name)
    steps = int(round(seconds / v.sample_time))
    c_run = run_c(vehicle_name, track, settings, steps, tool=tool)
    result = {"vehicle": vehicle_name, "track": track_name, "settings": settings.as_dict(),
              "c_mpc": _summary(c_run, track, vehicle_name)}
    runs = {"C MPC (RTI)": c_run["x"]}
    if reference:
        from ddyn.control.mpc_reference import closed_loop

        ref = closed_loop(vehicle_name, track, settings, steps)
        result["ipopt_mpc"] = score(track, ref["x"], v.sample_time, vehicle_name)
        result["ipopt_mpc"]["solve_ms_median"] = float(np.median(ref["solve_ms"]))
        runs["CasADi + IPOPT MPC"] = ref["x"]
        a, b = result["c_mpc"]["lap_time_s"], result["ipopt_mpc"]["lap_time_s"]
        result["lap_time_ratio_c_over_ipopt"] = a / b if a and b else None
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        result["plot"] = str(plot_lap(track, runs, out / "mpc_lap.png", vehicle_name))
        (out / "mpc_lap.json").write_text(json.dumps(result, indent=2))
    return result


def _run_sweep(args, settings: MpcSettings) -> int:
    rows = sweep(args.vehicle, args.track, args.sweep_steps, settings, tool=Path(args.tool))
    print("| start speed (m/s) | lateral (m) | heading (rad) | violation steps | closest corner (mm) "
          "| first lap (s) | laps | QP iterations max | status |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        lap_s = f"{r['lap_time_s']:.3f}" if r["lap_time_s"] else "-"
        print(f"| {r['start_speed']} | {r['lateral_m']:+.2f} | {r['heading_rad']:+.2f} | {r['violation_steps']} "
              f"| {r['min_boundary_distance_m'] * 1000:.1f} | {lap_s} | {r['laps']:.1f} "
              f"| {r['qp_iterations_max']} | {r['status_counts']} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mpc_sweep.json").write_text(json.dumps({"steps": args.sweep_steps, "settings": settings.as_dict(),
                                                    "runs": rows}, indent=2))
    bad = sum(r["violation_steps"] > 0 for r in rows)
    print(f"{len(rows) - bad} of {len(rows)} runs without a footprint violation; wrote {out}/mpc_sweep.json")
    return 0 if bad == 0 else 1


def _parse_assignments(items: list[str], multi: bool) -> dict:
    """KEY=VALUE (or KEY=V1,V2,... when multi) for float fields of MpcSettings."""
    fields = {k for k, v in MpcSettings().as_dict().items() if isinstance(v, float)}
    out = {}
    for item in items or []:
        key, _, value = item.partition("=")
        if key not in fields or not value:
            raise DdynError(f"--set/--grid {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(fields))}")
        values = [float(v) for v in value.split(",")]
        if not multi and len(values) != 1:
            raise DdynError(f"--set {item!r}: one value")
        out[key] = values if multi else values[0]
    return out


def _run_grid(args, settings: MpcSettings) -> int:
    """First lap (C MPC, --seconds) at every combination of the --grid values: how the defaults were chosen."""
    import itertools
    grid = _parse_assignments(args.grid, multi=True)
    track = open_track(args.track, args.vehicle)
    steps = int(round(args.seconds / vehicle_mod.load(args.vehicle).sample_time))
    keys = list(grid)
    print("| " + " | ".join(keys) + " | lap (s) | violation steps | closest corner (mm) | QP iterations max |")
    print("|" + "---|" * (len(keys) + 4))
    rows = []
    for values in itertools.product(*(grid[k] for k in keys)):
        st = replace(settings, **dict(zip(keys, values)))
        m = _summary(run_c(args.vehicle, track, st, steps, tool=Path(args.tool)), track, args.vehicle)
        rows.append({**dict(zip(keys, values)), **m})
        lap_s = f"{m['lap_time_s']:.3f}" if m["lap_time_s"] else "-"
        print("| " + " | ".join(f"{v:g}" for v in values) + f" | {lap_s} | {m['violation_steps']} | "
              f"{m['min_boundary_distance_m'] * 1000:.1f} | {m['qp_iterations_max']} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mpc_grid.json").write_text(json.dumps({"settings": settings.as_dict(), "grid": grid, "runs": rows},
                                                  indent=2))
    return 0


def _run(args) -> int:
    settings = settings_for(args.vehicle, horizon=args.horizon, disc=args.disc, line=args.line)
    if args.speed_scale is not None:
        settings = replace(settings, speed_scale=args.speed_scale)
    settings = replace(settings, **_parse_assignments(args.set, multi=False))
    if args.grid:
        return _run_grid(args, settings)
    if args.sweep:
        return _run_sweep(args, settings)
    r = lap(args.vehicle, args.track, args.seconds, settings, not args.no_reference, Path(args.out), Path(args.tool))
    c = r["c_mpc"]
    laps = ", ".join(f"{v:.3f}" for v in c["lap_times_s"]) or "none"
    print(f"C MPC: laps {laps} s, violations {c['violation_steps']} steps "
          f"(min distance to bounds {c['min_boundary_distance_m'] * 1000:.1f} mm), QP iterations median "
          f"{c['qp_iterations_median']:.0f} max {c['qp_iterations_max']}, status {c['status_counts']}")
    if "ipopt_mpc" in r:
        i = r["ipopt_mpc"]
        print(f"IPOPT MPC: lap {i['lap_time_s']} s, violations {i['violation_steps']} steps; "
              f"lap-time ratio C/IPOPT {r['lap_time_ratio_c_over_ipopt']}")
    print(f"wrote {args.out}/mpc_lap.json, {args.out}/mpc_lap.png")
    ok = c["violation_steps"] == 0 and c["lap_time_s"] is not None
    return 0 if ok else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("lap", help="closed-loop lap of the C MPC (and the IPOPT reference MPC)")
    p.add_argument("--vehicle", default="orca_1_43")
    p.add_argument("--track", default="ethzMobil")
    p.add_argument("--seconds", type=float, default=7.0, help="simulated time (default %(default)s)")
    p.add_argument("--horizon", type=int, default=20)
    p.add_argument("--disc", default="rk4_single", choices=("rk4_single", "euler", "rk4"),
                   help="prediction model (default %(default)s)")
    p.add_argument("--no-reference", action="store_true", help="skip the CasADi + IPOPT reference lap")
    p.add_argument("--line", choices=("default", "flying", "standing"), default=None,
                   help="the racing line the table is made of: the vehicle's own (default), or its flying-lap or "
                        "standing-start line (computed with ddyn mpc raceline [--flying])")
    p.add_argument("--out", default="out/mpc_lap", help="directory for mpc_lap.json and mpc_lap.png")
    p.add_argument("--tool", default=str(DEFAULT_TOOL), help="ddyn_mpc_lap binary (default: %(default)s)")
    p.add_argument("--speed-scale", type=float, default=None,
                   help="reference speed = raceline speed * this (default: MpcSettings, %s)" % MpcSettings().speed_scale)
    p.add_argument("--sweep", action="store_true",
                   help="robustness sweep instead of the lap: start speeds x start perturbations, --sweep-steps "
                        "each, C MPC only; exit 1 if any run has a footprint violation")
    p.add_argument("--sweep-steps", type=int, default=10000, help="steps per sweep run (default %(default)s)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override an MpcSettings weight or limit, e.g. --set r_dsteering=0.1 (repeatable)")
    p.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                   help="first-lap table (C MPC) over every combination of these values (repeatable), "
                        "written to OUT/mpc_grid.json")
    p.set_defaults(func=_run)
